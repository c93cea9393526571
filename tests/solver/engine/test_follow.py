"""A ball that follows the state (``[domain] follow``, solver/engine/follow.py), against exact truth.

Truth: the exact Kalman filter of the sampled linear model (KalmanBucyFilter(kind="discrete"): the
engine's own time discretisation, so what is left is the space error and the moves) and Kalman–Bucy (the
continuous-time filter, O(dt) away).  The random walk with a trend travels ~100 units on a ball of
radius 6: a fixed ball loses it (tested), the following one stays within 1e-3 of Kalman.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from helpers.loop_moves import assert_loop_moves_as_blocks
from yauyau.service.cli import main
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter, build
from yauyau.solver.engine.follow import FollowingFilter
from yauyau.solver.errors import SpecError
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.methods import make_filter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

import yauyau

TREND = {"name": "random walk with trend", "state": ["x"], "drift": ["1.0"], "observation": ["x"],
         "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
         "domain": {"radius": 6.0, "follow": True}, "discretization": {"dt": 0.01, "basis": 48}}
STEPS = 10_000  # t in [0, 100]


def _spec(**domain):
    doc = json.loads(json.dumps(TREND))
    doc["domain"].update(domain)
    return spec_from_dict(doc)


@pytest.fixture(scope="module")
def trend():
    model = compile_model(_spec())
    return model, precompute(model)


def _run(flt, rows, chunk):
    state, parts = flt.initial_state(), []
    for start in range(0, len(rows), chunk):
        state, part = flt.run_arrays(state, rows[start:start + chunk])
        parts.append(part)
    from yauyau.solver.filtering import concat_results

    return state, concat_results(parts)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4])
def test_random_walk_with_trend_matches_the_exact_kalman_filter_over_100_units(trend, seed):
    model, offline = trend
    flt = build(model, offline)
    assert isinstance(flt, FollowingFilter) and flt.directions == (0,)
    sim = simulate(model, STEPS, np.random.default_rng(seed))
    assert sim.states[-1, 0] - sim.states[0, 0] > 80  # the state leaves the ball many times over
    _, result = _run(flt, sim.increments, 500)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), sim.increments)
    mean_gap = np.abs(result.mean[:, 0] - exact.mean[:, 0]).max()
    var_error = np.abs(result.cov[:, 0, 0] / exact.cov[:, 0, 0] - 1).max()
    print(f"seed {seed}: {int(result.recentred.sum())} moves, mean gap {mean_gap:.2e}, "
          f"variance error {var_error:.2e}, loglik gap {abs(result.loglik[-1] - exact.loglik[-1]):.2e}")
    assert not result.degenerate.any(), result.reason
    assert mean_gap <= 1e-3 and var_error <= 0.01
    assert result.recentred.sum() > 50
    assert abs(result.loglik[-1] - exact.loglik[-1]) < 1e-3  # no move changes the log-likelihood
    # the centre follows the state: never more than the trigger distance + stray from the mean
    assert np.abs(result.mean[:, 0] - result.center[:, 0]).max() < 0.3 * 6.0
    # the continuous-time Kalman–Bucy filter is O(dt) away (tests/solver/exact/test_exact_vs_engine.py:
    # ≤ 0.01)
    bucy = KalmanBucyFilter(model)
    _, continuous = bucy.run_arrays(bucy.initial_state(), sim.increments)
    assert np.abs(result.mean[:, 0] - continuous.mean[:, 0]).max() <= 0.01


@pytest.mark.slow
def test_a_fixed_ball_loses_the_same_state(trend):
    model = compile_model(_spec(follow=False))
    flt = make_filter(model, precompute(model), "yau-yau")
    assert type(flt) is YauYauFilter
    sim = simulate(model, 1500, np.random.default_rng(3))
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    assert result.degenerate.any() and "boundary" in result.reason
    assert result.center is None and not result.recentred.any()


def test_a_move_carries_the_density_and_keeps_the_log_likelihood(trend):
    """Moved by whole elements, the carried nodal values are the old ones where the balls overlap: the
    moments of a density well inside both balls are unchanged up to the projection onto the basis
    (measured: mean 4e-7, variance 2.3e-6 for N(0, 1) moved by 0.72 with 48 functions)."""
    model, offline = trend
    flt = build(model, offline)
    state = flt.initial_state()
    before = flt.estimate(state)
    target = flt.snapped(state.center, np.array([0.7]))
    assert target[0] == pytest.approx(3 * flt._lattice)  # 0.72: three elements of 0.24
    assert flt.moved_mass(state, target) < 1e-6
    moved = flt.recentre(state, target)
    assert np.array_equal(moved.center, target) and moved.loglik == state.loglik
    nodes, weights = flt.engine(target).nodes[:, 0], flt.weights
    sigma = flt.engine(target).nodal_density(moved)
    mass = weights @ sigma
    mean = weights @ (sigma * nodes) / mass
    var = weights @ (sigma * nodes ** 2) / mass - mean ** 2
    assert abs(mean - before.mean[0]) < 1e-5 and abs(var - before.cov[0, 0]) < 1e-5


@pytest.mark.slow
def test_a_state_round_trips_through_json_with_its_centre(trend):
    model, offline = trend
    flt = build(model, offline)
    sim = simulate(model, 600, np.random.default_rng(5))
    state, first = flt.run_arrays(flt.initial_state(), sim.increments[:300])
    assert first.recentred.any() and state.center[0] != 0.0
    restored = flt.state_from_dict(json.loads(json.dumps(state.to_dict())))
    assert np.array_equal(restored.center, state.center)
    a = flt.run_arrays(state, sim.increments[300:])[1]
    b = flt.run_arrays(restored, sim.increments[300:])[1]
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.center, b.center)
    bad = state.to_dict()
    bad["center"] = ["far"]
    with pytest.raises(Exception, match="state.center"):
        flt.state_from_dict(bad)


def test_the_ball_starts_around_the_prior_and_the_density_is_where_the_state_is(trend):
    model, offline = trend
    flt = build(model, offline)
    state = flt.initial_state({"kind": "gaussian", "mean": [40.0], "cov": [[1.0]]})
    assert abs(state.center[0] - 40.0) <= flt._lattice / 2
    assert flt.density(state, np.array([[40.0]]))[0] == pytest.approx(1 / np.sqrt(2 * np.pi), rel=1e-3)
    assert flt.density(state, np.array([[0.0]]))[0] == 0.0
    from yauyau.solver import summaries

    q = summaries.quantiles(flt, state, [0.5])
    assert q[0][0] == pytest.approx(40.0, abs=1e-3)


@pytest.mark.slow
def test_the_mode_of_a_following_ball_is_where_the_ball_is(trend):
    """The posterior is Gaussian (Kalman), so its mode is its mean.  The mode is read off the nodes of
    the ball where the state is (before 2026-11-24 it was read off the home ball's nodes: 0.456 for a
    mean of 7.84 on a ball centred at 7.38)."""
    from yauyau.solver import summaries

    model, offline = trend
    flt = build(model, offline)
    rows = simulate(model, 1500, np.random.default_rng(5)).increments
    state, result = flt.run_arrays(flt.initial_state(), rows)
    assert result.recentred.sum() > 3 and abs(state.center[0]) > 8  # the ball has travelled
    mean = flt.estimate(state).mean[0]
    assert summaries.mode(flt, state)[0] == pytest.approx(mean, abs=0.02)


def test_without_follow_the_spec_and_its_model_id_are_unchanged():
    doc = json.loads(json.dumps(TREND))
    doc["domain"] = {"radius": 6.0}
    plain = spec_from_dict(doc)
    assert "follow" not in plain.canonical_json()
    doc["domain"] = {"radius": 6.0, "follow": False}
    assert spec_from_dict(doc).canonical_json() == plain.canonical_json()
    assert "follow" in _spec().canonical_json()


def test_follow_options_are_checked(tmp_path):
    with pytest.raises(SpecError, match="domain.follow"):
        _spec(follow=False, follow_distance=0.2)
    with pytest.raises(SpecError, match="domain.follow_distance"):
        _spec(follow_distance=0.9)
    doc = json.loads(json.dumps(TREND))
    doc["drift"] = ["0.8 + 0.3*sin(x)"]  # depends on x: the operator changes with the ball
    model = compile_model(spec_from_dict(doc))
    with pytest.raises(SpecError, match="domain.follow") as err:
        make_filter(model, precompute(model), "yau-yau")
    assert "depends on every state variable" in str(err.value)
    with pytest.raises(SpecError, match="domain.follow"):
        yauyau.precompute(spec_from_dict(doc), tmp_path)
    model = compile_model(_spec())
    with pytest.raises(SpecError, match="form"):
        make_filter(model, precompute(model), "yau-yau", form="literal")


def test_constant_velocity_moves_only_the_position():
    """f = (v, −0.2v): the operator is invariant in p, not in v (SymPy decides)."""
    doc = {"name": "cv", "state": ["p", "v"], "drift": ["v", "-0.2*v"], "observation": ["p"],
           "diffusion": [[0.05, 0.0], [0.0, 1.0]], "method": "yau-yau",
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
           "domain": {"radius": 6.0, "follow": True}, "discretization": {"dt": 0.05, "basis": 40}}
    model = compile_model(spec_from_dict(doc))
    assert model.shift_directions == (0,)
    doc["drift"] = ["v + 0*p", "-0.2*v + p - p"]  # zero derivatives that only simplify to 0
    assert compile_model(spec_from_dict(doc)).shift_directions == (0,)


@pytest.mark.slow
def test_the_cli_writes_the_centre_and_the_moves(tmp_path):
    store = tmp_path / "store"
    spec = _spec()
    model_id = yauyau.precompute(spec, store)
    sim = simulate(compile_model(spec), 400, np.random.default_rng(2))
    inc = tmp_path / "inc.csv"
    inc.write_text("dy\n" + "\n".join(repr(float(v)) for v in sim.increments[:, 0]) + "\n")
    out = tmp_path / "out.csv"
    assert main(["filter", model_id, "--store", str(store), "--increments", str(inc), "--out", str(out)]) == 0
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[-2:] == ["center_x", "recentred"]
    moves = [r for r in rows if r["recentred"] == "1"]
    assert moves and float(rows[-1]["center_x"]) > 1.0
    assert main(["filter", model_id, "--store", str(store), "--increments", str(inc), "--out",
                 str(tmp_path / "o2.csv"), "--density", str(tmp_path / "d.h5")]) == 2


@pytest.mark.slow
def test_a_restart_row_has_the_ball_centre_and_the_csv_keeps_its_columns(tmp_path):
    """on_degenerate = "reinitialise" on a following ball: the restart row carries the new ball's centre
    (the broadened prior's, flagged recentred), so the result keeps its centre column and every CSV row
    has the header's fields (before, the restart row had none and the rows after it lost two columns)."""
    doc = json.loads(json.dumps(TREND))
    doc["measurement"] = {"gate": 0}
    spec = spec_from_dict(doc)
    store = tmp_path / "store"
    model_id = yauyau.precompute(spec, store)
    sim = simulate(compile_model(spec), 400, np.random.default_rng(2))
    rows = sim.increments[:, 0].copy()
    rows[250] = 1e5  # no density survives this row: the filter degenerates there and restarts
    inc = tmp_path / "inc.csv"
    inc.write_text("dy\n" + "\n".join(repr(float(v)) for v in rows) + "\n")
    out = tmp_path / "out.csv"
    assert main(["filter", model_id, "--store", str(store), "--increments", str(inc), "--out", str(out),
                 "--on-degenerate", "reinitialise", "--chunk", "100"]) == 0
    with out.open() as fh:
        table = list(csv.reader(fh))
    header, body = table[0], table[1:]
    assert len(body) == 400 and {len(r) for r in body} == {len(header)}
    rows_by = [dict(zip(header, r, strict=True)) for r in body]
    again = [k for k, r in enumerate(rows_by) if r["reinitialised"] == "1"]
    assert again == [250]
    restart = rows_by[250]
    assert restart["recentred"] == "1"
    assert abs(float(restart["center_x"]) - float(restart["mean_x"])) < 0.2  # the ball sits on the prior
    assert abs(float(rows_by[-1]["mean_x"]) - sim.states[-1, 0]) < 4.0  # and follows the state on


def _moments(flt, state):
    """Mean and covariance of the state's nodal density on its ball (lumped quadrature)."""
    engine = flt.engine(state.center)
    w = engine.weights * engine.nodal_density(state)
    mean = w @ engine.nodes / w.sum()
    d = engine.nodes - mean
    return mean, (w[:, None] * d).T @ d / w.sum()


def test_in_2d_a_following_ball_has_a_lattice_mesh_and_its_moves_do_not_blur():
    """Truth: the prior N(0, I).  Moves by whole lattice steps read the density off (6 moves: the
    moments stay to 1e-5); a move off the lattice interpolates and projects, and the variance grows
    (why follow snaps to the lattice)."""
    from yauyau.solver.engine.atlas import lattice_step

    doc = json.loads(json.dumps(TREND))
    doc.update(state=["x", "y"], drift=["1.0", "0.5"], observation=["x", "y"],
               initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]})
    doc["discretization"]["basis"] = 300
    model = compile_model(spec_from_dict(doc))
    offline = precompute(model)
    flt = build(model, offline)
    step = lattice_step(offline.mesh_points, model.center, model.radius)
    assert step is not None and flt._lattice == step  # the interior vertices are c + step·(i, j)
    start = flt.initial_state()
    state, move = start, np.array([2 * step, step])
    for _ in range(3):
        state = flt.recentre(flt.recentre(state, state.center + move), state.center)
    mean, cov = _moments(flt, state)
    assert np.abs(mean).max() < 1e-5 and np.abs(cov - np.eye(2)).max() < 1e-5
    off = start
    for _ in range(3):
        off = flt.recentre(flt.recentre(off, off.center + [0.3, 0.2]), off.center)
    assert _moments(flt, off)[1][0, 0] > 1.05  # interpolated: blurred
    assert np.allclose(flt.snapped(start.center, [0.3, 0.2]), [step, 0.0])  # follow snaps to the lattice


@pytest.mark.slow
def test_in_2d_with_the_bubble_element_the_following_ball_stays_near_kalman():
    """A 2-D random walk with trend (1, 0.5) over t = 0..50 (50 and 25 units: 8 and 4 radii) on the
    lattice mesh with element = "bubble", basis 600: measured 3.1e-3 in the mean and 0.45% in the
    variance from the exact Kalman filter (P1 at basis 300: 0.16, bench/results/follow.md)."""
    doc = json.loads(json.dumps(TREND))
    doc.update(state=["x", "y"], drift=["1.0", "0.5"], observation=["x", "y"],
               initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]})
    doc["discretization"].update(basis=600, element="bubble")
    model = compile_model(spec_from_dict(doc))
    flt = build(model, precompute(model))
    sim = simulate(model, 5000, np.random.default_rng(3))
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), sim.increments)
    gap = float(np.abs(result.mean - exact.mean).max())
    var = float(np.max(np.abs(np.diagonal(result.cov, axis1=1, axis2=2)
                              / np.diagonal(exact.cov, axis1=1, axis2=2) - 1)))
    print(f"2-D bubble: {int(result.recentred.sum())} moves, gap {gap:.2e}, variance error {var:.2e}")
    assert not result.degenerate.any() and result.recentred.sum() > 50
    assert gap <= 5e-3 and var <= 0.01


@pytest.mark.slow
def test_a_stream_of_single_rows_moves_as_often_as_one_chunk(trend):
    """Rows posted one at a time (a live stream) must not move the ball on the noise of a one-row
    velocity: about as many moves as one chunk of the same rows, and the same estimates to within the
    filter's accuracy (moves happen between blocks, so chunking shifts when they happen)."""
    model, offline = trend
    flt = build(model, offline)
    rows = simulate(model, 3000, np.random.default_rng(5)).increments
    _, whole = flt.run_arrays(flt.initial_state(), rows)
    _, single = _run(flt, rows, 1)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), rows)
    print(f"moves: one chunk {int(whole.recentred.sum())}, single rows {int(single.recentred.sum())}")
    assert single.recentred.sum() <= 1.5 * whole.recentred.sum() + 2
    assert np.abs(single.mean - exact.mean).max() <= 1e-3 and not single.degenerate.any()


@pytest.mark.slow
def test_an_engine_told_to_stop_ends_its_chunk_there_as_a_shorter_chunk_would(trend):
    """``run_until(..., rule)`` (what a following ball uses instead of running a strayed block
    again): the chunk ends after the rows the rule keeps; result and state are those of the shorter
    chunk, bit for bit, and the run goes on from there as it would have.  A following filter that
    moves between blocks gives the same estimates with and without the rule, running fewer rows."""
    model, offline = trend
    flt = build(model, offline)
    engine = flt.runner(flt.initial_state().center)
    rows = simulate(model, 120, np.random.default_rng(9)).increments
    start = flt.initial_state()
    seen = []
    state, part = engine.run_until(start, rows, None, lambda mean, centers: seen.append(len(mean)) or 40)
    short_state, short = engine.run_arrays(start, rows[:40])
    assert seen == [120] and len(part.step) == 40 and not part.degenerate.any()
    for name in ("step", "t", "mean", "cov", "loglik", "loglik_increment"):
        np.testing.assert_array_equal(getattr(part, name), getattr(short, name))
    np.testing.assert_array_equal(state.coefficients, short_state.coefficients)
    assert (state.step, state.t, state.mass, state.loglik) == (40, short_state.t, short_state.mass,
                                                              short_state.loglik)
    _, rest = engine.run_arrays(state, rows[40:])
    _, whole = engine.run_arrays(start, rows)
    np.testing.assert_array_equal(rest.mean, whole.mean[40:])
    _, kept_all = engine.run_until(start, rows, None, lambda mean, centers: None)
    np.testing.assert_array_equal(kept_all.mean, whole.mean)

    counted = {"rows": 0}
    original = YauYauFilter.run_until

    def counting(self, *args, **kwargs):
        counted["rows"] += len(args[1])
        return original(self, *args, **kwargs)

    long_rows = simulate(model, 2000, np.random.default_rng(10)).increments
    runs = {}
    for mode in ("rule", "again"):
        follower = build(model, offline)
        follower.moves_in_loop = False  # the block logic (a moving frame, gaps filtered in pieces)
        if mode == "again":  # the rule keeps every row: a strayed block runs again, shorter
            follower._keep_until = lambda center: (lambda mean, centers: None)
        counted["rows"] = 0
        YauYauFilter.run_until = counting
        try:
            runs[mode] = (_run(follower, long_rows, 1000)[1], counted["rows"])
        finally:
            YauYauFilter.run_until = original
    np.testing.assert_array_equal(runs["rule"][0].mean, runs["again"][0].mean)
    np.testing.assert_array_equal(runs["rule"][0].loglik, runs["again"][0].loglik)
    assert runs["rule"][1] < runs["again"][1], (runs["rule"][1], runs["again"][1])


@pytest.mark.slow
@pytest.mark.parametrize("window", [None, 3])
def test_a_move_inside_the_loop_is_the_move_between_blocks(trend, window, monkeypatch):
    """The engine's loop re-centres the ball itself (solver/engine/recentring.py): the same as a block that
    ends after that row, FollowingFilter.recentre onto the centre the loop chose, and the next block
    from there (the issue's carry: the old expansion at the new nodes, zero outside, projected) — to
    rounding, with a missing row and an outlier the gate rejects among the rows, and the update
    factors a window at a time (``window``: 3 rows at a time, so most windows end without a move)."""
    if window:
        from yauyau.solver.engine import recentring

        for name in ("FIRST_WINDOW", "MIN_WINDOW", "MAX_WINDOW"):
            monkeypatch.setattr(recentring, name, window)
    model, offline = trend
    assert_loop_moves_as_blocks(build(model, offline), simulate(model, 600, np.random.default_rng(11)))


def test_irregular_rows_move_the_ball_inside_the_loop_and_match_the_exact_kalman_filter(trend, monkeypatch):
    """Gaps drawn in [0.5, 1.5]·dt (the modal flow e^{τA}, none filtered in pieces), three missing rows,
    chunks of 500: the ball moves inside the engine's loop (no block runs), against the exact discrete
    Kalman filter at the same times.  Measured: mean 3.5e-4, variance 6.6e-4 relative, log-likelihood
    8.6e-5, 46 moves (the block logic, before: 1.1e-3, 2.6e-3, 6.0e-4)."""
    model, offline = trend
    rng = np.random.default_rng(4)
    gaps = rng.uniform(0.5, 1.5, 3000) * model.dt
    x, rows = rng.normal(0.0, 1.0), np.empty((3000, 1))
    for k, tau in enumerate(gaps):  # the exact transition of dx = dt + dv, dy = x dt + dw (x frozen)
        x += tau + np.sqrt(tau) * rng.standard_normal()
        rows[k, 0] = x * tau + np.sqrt(tau) * rng.standard_normal()
    rows[[100, 101, 2000]] = np.nan
    times = np.cumsum(gaps)
    blocks = []
    original = YauYauFilter.run_until
    monkeypatch.setattr(YauYauFilter, "run_until", lambda *args: blocks.append(1) or original(*args))
    flt = build(model, offline)
    state, parts = flt.initial_state(), []
    for start in range(0, len(rows), 500):
        state, part = flt.run_arrays(state, rows[start:start + 500], times[start:start + 500])
        parts.append(part)
    from yauyau.solver.filtering import concat_results

    result = concat_results(parts)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), rows, times)
    mean_gap = np.abs(result.mean[:, 0] - exact.mean[:, 0]).max()
    var_error = np.abs(result.cov[:, 0, 0] / exact.cov[:, 0, 0] - 1).max()
    print(f"{int(result.recentred.sum())} moves, mean gap {mean_gap:.2e}, variance error {var_error:.2e}")
    assert not blocks and not result.degenerate.any() and result.recentred.sum() > 30
    assert mean_gap <= 1e-3 and var_error <= 5e-3
    assert abs(result.loglik[-1] - exact.loglik[-1]) < 1e-3
    np.testing.assert_array_equal(np.isnan(result.predictive_loglik), np.isnan(rows[:, 0]))


def _trend_2d(element: str):
    """The 2-D trend f = (1, 0.5), h = (x, y) on the lattice mesh, basis 300: (model, filter)."""
    doc = json.loads(json.dumps(TREND))
    doc.update(state=["x", "y"], drift=["1.0", "0.5"], observation=["x", "y"],
               initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]})
    doc["discretization"].update(basis=300, element=element)
    model = compile_model(spec_from_dict(doc))
    return model, build(model, precompute(model))


@pytest.mark.parametrize("element, degree", [("lagrange", 1), ("bubble", 2)])
def test_a_move_by_whole_lattice_steps_carries_polynomials_exactly_and_is_kept_per_offset(element, degree):
    """Truth: the element reproduces polynomials of its degree (P1: linear, P2 + bubble: quadratic), so
    the carry of g's nodal values from a ball away from home onto the ball moved by whole lattice
    steps is g at the new nodes inside the old ball and 0 outside it.  The carry is kept per offset
    and serves every centre (every ball is the home ball translated)."""
    model, flt = _trend_2d(element)
    step = flt._lattice

    def g(points):
        x, y = points[:, 0], points[:, 1]
        return 1.0 + 0.3 * x - 0.7 * y + (0.05 * x * x - 0.02 * x * y if degree == 2 else 0.0)

    for old_center in (np.array([3 * step, -2 * step]), np.array([40 * step, 17 * step])):
        old = flt.engine(old_center)
        for offset in (np.array([step, 0.0]), np.array([2 * step, step]), np.array([-4 * step, 3 * step])):
            carry = flt.carry(offset)
            assert carry is flt.carry(offset + 1e-13)  # kept: one per offset in lattice steps
            new_nodes = old.nodes + offset
            carried = carry.apply(g(old.nodes))
            distance = np.linalg.norm(new_nodes - old_center, axis=1)
            inside = distance < model.radius - 2 * step  # well inside the old (polygonal) ball
            assert inside.sum() > 20
            assert np.abs(carried[inside] - g(new_nodes[inside])).max() < 1e-12
            assert np.all(carried[distance >= model.radius] == 0.0)
            assert 0 < len(carry.rest) < 0.5 * len(carried)  # a rim is interpolated, the rest read off
    assert flt.carry(np.array([0.5 * step, 0.0])) is None  # off the lattice: the direct carry


@pytest.mark.parametrize("element", ["lagrange", "bubble"])
def test_the_carries_built_with_the_filter_are_those_built_one_at_a_time(element):
    """The table of carries built at once with the filter (every offset a move usually takes: within
    (1.5·follow_distance + 0.1)·R) holds, for each offset, the arrays and interpolated rows that the
    carry built alone has; an offset beyond it is built when a move first takes it."""
    from yauyau.solver.engine.carry import Carry

    model, flt = _trend_2d(element)
    step, reach = flt._lattice, (1.5 * flt.distance + 0.1 * model.radius)
    assert len(flt._table) >= 8 and all(0 < np.hypot(*k) * step <= reach for k in flt._table)
    for key, tabled in flt._table.items():
        alone = Carry.build(flt.home.offline, flt.home_center, flt.radius, np.array(key) * step,
                             flt.home.node_tree)
        for name in ("size", "matched", "source", "rest", "others"):
            assert np.array_equal(getattr(tabled, name), getattr(alone, name)), (key, name)
        assert (tabled.rows is None) == (alone.rows is None)
        if alone.rows is not None:
            assert abs(tabled.rows - alone.rows).max() == 0.0
        assert flt.carry(np.array(key) * step) is tabled
    far = (int(reach / step) + 2, 0)
    assert far not in flt._table and flt.carry(np.array(far) * step) is flt.carry(np.array(far) * step)


def test_the_nearest_node_on_a_line_is_the_kd_trees():
    """carry.nearest_1d (a binary search, for 1-D carries) against scipy's cKDTree: the same
    distances and nodes, for points between, beyond and on the nodes."""
    from scipy.spatial import cKDTree
    from yauyau.solver.engine.carry import nearest_1d

    rng = np.random.default_rng(0)
    nodes = rng.uniform(-5.0, 5.0, (99, 1))
    points = np.vstack([rng.uniform(-7.0, 7.0, (300, 1)), nodes + 1e-13, nodes[:5]])
    gap, index = nearest_1d(nodes, points)
    tree_gap, tree_index = cKDTree(nodes).query(points)
    np.testing.assert_array_equal(gap, tree_gap)
    np.testing.assert_array_equal(index, tree_index)


def test_h_read_off_a_move_is_h_at_the_new_nodes():
    """A move's h (FollowingFilter.h_at with the carry: read off the old ball's nodes where a new node is
    an old one, evaluated at the others) against the observation function evaluated at every new node,
    for a nonlinear h on the 2-D lattice, moves of several offsets."""
    doc = json.loads(json.dumps(TREND))
    doc.update(state=["x", "y"], drift=["1.0", "0.5"], observation=["sin(x) + y**2", "atan(y/5) * x"],
               initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]})
    doc["discretization"].update(basis=120)
    model = compile_model(spec_from_dict(doc))
    flt = build(model, precompute(model))
    step = flt._lattice
    old_center = np.array([3 * step, -2 * step])
    before = model.h(flt.home.nodes + old_center)
    for offset in (np.array([2 * step, step]), np.array([-4 * step, 3 * step]), np.array([0.0, step])):
        target = old_center + offset
        carry = flt.carry(offset)
        assert 0 < len(carry.others) < 0.5 * len(before)  # most read off, the rest evaluated
        flt._h.clear()
        h, _ = flt.h_at(target, carry, before)
        np.testing.assert_allclose(h, model.h(flt.home.nodes + target), rtol=0, atol=1e-13)


@pytest.mark.slow
def test_precompute_says_when_follow_has_no_effect(tmp_path, capsys):
    """method auto on a linear-Gaussian model chooses the exact Kalman–Bucy filter, which has no ball:
    precompute says follow does nothing there and how to get it (before, it was silently ignored)."""
    doc = json.loads(json.dumps(TREND))
    del doc["method"]
    spec_file = tmp_path / "trend.json"
    spec_file.write_text(json.dumps(doc))
    assert main(["precompute", str(spec_file), "--store", str(tmp_path / "store")]) == 0
    err = capsys.readouterr().err
    assert "method kalman-bucy" in err
    assert "domain.follow has no effect here" in err and 'method = "yau-yau"' in err


def test_a_translated_engine_updates_with_h_at_its_own_nodes(trend):
    """The engine on a translated ball (``centred_at``, a move of the following ball) must weigh each row
    by h at its own nodes, also after the home engine has stepped: it used to share the home engine's
    cache of h R⁻¹ per observation pattern (h at the home nodes; 0.115 off in log e here).  Truth: the
    stable form's log e = h dy − ½ h² dt (R = 1, h = x) at the translated nodes, minus its maximum."""
    model, offline = trend
    home = build(model, offline)
    rows, gaps = np.array([[0.01], [-0.02], [0.05]]), np.full(3, model.dt)
    home.factors(rows, gaps)  # fills the home engine's cache
    moved = home.centred_at(np.array([2.0]))
    log_factor = moved.factors(rows, gaps)[2]
    x = moved.nodes[:, 0]
    expected = rows * x[None, :] - 0.5 * x[None, :] ** 2 * gaps[:, None]
    expected -= expected.max(axis=1, keepdims=True)
    np.testing.assert_allclose(log_factor, expected, rtol=0, atol=1e-12)
