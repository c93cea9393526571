"""A ball that rides a frame moving with the mean's ODE (solver/engine/frame.py): an affine drift f = Ax + b.

Truth: the exact Kalman filter of the sampled linear model (KalmanBucyFilter(kind="discrete"): the
engine's own time discretisation), and the closed-form flow of ċ = ac + b.  The model f = 0.1x + 0.2
depends on x, so a plain translation of the ball is wrong (the operator changes with the centre); in
the frame it is the operator of the drift 0.1ξ, whatever the centre.  The state grows from 2 to ~15
over t = 0..30, two radii and more.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers.loop_moves import assert_loop_moves_as_blocks
from helpers.specs import modified
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.engine.follow import FollowingFilter
from yauyau.solver.engine.frame import AffineFrame, affine_frame
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.pipeline import OfflineModel, precompute
from yauyau.solver.simulate import simulate

import yauyau

GROWTH = {"name": "linear growth", "state": ["x"], "drift": ["0.1*x + 0.2"], "observation": ["x"],
          "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [2.0], "cov": [[0.5]]},
          "domain": {"radius": 6.0, "follow": True}, "discretization": {"dt": 0.01, "basis": 120}}
STEPS = 3000  # t in [0, 30]


def _doc(**changes):
    return modified(GROWTH, **changes)


@pytest.fixture(scope="module")
def growth():
    model = compile_model(spec_from_dict(GROWTH))
    return model, precompute(model)


def _exact(model, rows, times=None):
    kalman = KalmanBucyFilter(model, kind="discrete")
    return kalman.run_arrays(kalman.initial_state(), rows, times)[1]


def test_an_affine_drift_is_found_symbolically():
    model = compile_model(spec_from_dict(_doc(drift=["0.1*x + 0.2 + 0*sin(x)"])))
    A, b = model.affine_drift
    assert A.tolist() == [[0.1]] and b.tolist() == [0.2]
    assert compile_model(spec_from_dict(_doc(drift=["0.1*x + 0.1*sin(x)"]))).affine_drift is None
    doc = _doc(state=["p", "v"], drift=["v", "-0.2*v + 0.5"], observation=["p"],
               initial={"mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]})
    A, b = compile_model(spec_from_dict(doc)).affine_drift
    assert A.tolist() == [[0.0, 1.0], [0.0, -0.2]] and b.tolist() == [0.0, 0.5]
    doc["drift"] = ["v", "-p*v"]
    assert compile_model(spec_from_dict(doc)).affine_drift is None
    # a drift invariant along every coordinate needs no frame (a plain translation); no follow, none
    assert affine_frame(compile_model(spec_from_dict(_doc(drift=["1.0"])))) is None
    assert affine_frame(compile_model(spec_from_dict(_doc(domain={"follow": False})))) is None


def test_the_frame_flow_is_the_closed_form_of_the_ode():
    """ċ = ac + b: c(t) = (c₀ + b/a)e^{at} − b/a; and a rotation, e^{Aτ} = [[cos, sin], [−sin, cos]]."""
    frame = AffineFrame(A=np.array([[0.1]]), b=np.array([0.2]), origin=np.zeros(1))
    gaps = np.array([0.01, 0.5, 0.01, 2.0])
    path = frame.path(np.array([2.0]), gaps)
    t = np.cumsum(gaps)
    assert path[:, 0] == pytest.approx((2.0 + 2.0) * np.exp(0.1 * t) - 2.0, rel=1e-13)
    rotation = AffineFrame(A=np.array([[0.0, 1.0], [-1.0, 0.0]]), b=np.zeros(2), origin=np.zeros(2))
    end = rotation.path(np.array([1.0, 0.0]), np.full(100, np.pi / 200))[-1]
    assert end == pytest.approx([0.0, -1.0], abs=1e-12)
    # regular gaps over more than one segment of kept powers (frame.SEGMENT rows from one start)
    regular = frame.path(np.array([2.0]), np.full(1000, 0.01))
    t = 0.01 * np.arange(1, 1001)
    assert regular[:, 0] == pytest.approx(4.0 * np.exp(0.1 * t) - 2.0, rel=1e-13)
    turns = rotation.path(np.array([1.0, 0.0]), np.full(700, np.pi / 200))
    angle = np.pi / 200 * np.arange(1, 701)
    np.testing.assert_allclose(turns, np.column_stack([np.cos(angle), -np.sin(angle)]), rtol=0, atol=1e-12)


@pytest.mark.slow
def test_linear_growth_rides_the_frame_and_matches_the_exact_kalman_filter(growth):
    """Measured: mean gap 2.4e-4, variance error 0.09%, ~36 moves over 3000 steps."""
    model, offline = growth
    flt = build(model, offline)
    assert isinstance(flt, FollowingFilter) and flt.frame is not None and flt.directions == (0,)
    sim = simulate(model, STEPS, np.random.default_rng(1))
    assert sim.states[-1, 0] - sim.states[0, 0] > 2 * model.radius
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    exact = _exact(model, sim.increments)
    gap = np.abs(result.mean[:, 0] - exact.mean[:, 0])
    var = np.abs(result.cov[:, 0, 0] / exact.cov[:, 0, 0] - 1)
    print(f"linear growth: {int(result.recentred.sum())} moves, gap {gap.max():.2e}, "
          f"variance {var.max():.2e}")
    assert not result.degenerate.any(), result.reason
    assert gap.max() <= 1e-3 and var.max() <= 0.01
    assert abs(result.loglik[-1] - exact.loglik[-1]) < 1e-3
    # between moves the centre rides the ODE: c_{k+1} = e^{a dt}c_k + (e^{a dt} − 1)b/a
    quiet = ~result.recentred[1:]  # row k did not move the ball: c_k is c_(k−1) carried by the ODE
    ride = (result.center[:-1, 0] + 2.0) * np.exp(0.1 * model.dt) - 2.0
    assert np.abs(result.center[1:, 0] - ride)[quiet].max() < 1e-12
    assert np.abs(result.mean[:, 0] - result.center[:, 0]).max() < 0.5 * model.radius


@pytest.mark.slow
def test_without_the_frame_a_plain_translation_would_be_wrong(growth):
    """The stored propagator is the frame's (drift 0.1(x − c₀)): moving the ball without the frame's
    ODE loses the state: the independent check that the frame is what makes the run right."""
    model, offline = growth
    flt = build(model, offline)
    flt.frame = None
    flt._framed.clear()
    sim = simulate(model, 1500, np.random.default_rng(1))
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    exact = _exact(model, sim.increments)
    good = ~result.degenerate
    assert result.degenerate.any() or np.abs(result.mean[good, 0] - exact.mean[good, 0]).max() > 0.05


@pytest.mark.slow
def test_irregular_times_and_missing_rows_ride_the_same_frame(growth):
    """Gaps drawn in [0.5, 2.2]·dt (not multiples of dt: the frame's flow and the propagator over each
    gap, no pieces) and missing rows, against the exact discrete Kalman filter at the same times.
    Measured: gap 1.7e-4, variance 0.06%, 19 moves."""
    model, offline = growth
    flt = build(model, offline)
    rng = np.random.default_rng(7)
    gaps = rng.uniform(0.5, 2.2, 1500) * model.dt
    times = np.cumsum(gaps)
    x, rows = 2.0 + np.sqrt(0.5) * rng.standard_normal(), np.empty((1500, 1))
    for k, tau in enumerate(gaps):  # Euler–Maruyama on the drawn gaps, dy = x dt + dw
        x += (0.1 * x + 0.2) * tau + np.sqrt(tau) * rng.standard_normal()
        rows[k, 0] = x * tau + np.sqrt(tau) * rng.standard_normal()
    assert x > 2.0 + model.radius
    rows[[50, 51, 300]] = np.nan
    _, result = flt.run_arrays(flt.initial_state(), rows, times)
    exact = _exact(model, rows, times)
    gap = np.abs(result.mean[:, 0] - exact.mean[:, 0]).max()
    var = np.abs(result.cov[:, 0, 0] / exact.cov[:, 0, 0] - 1).max()
    print(f"irregular: gap {gap:.2e}, variance {var:.2e}, {int(result.recentred.sum())} moves")
    assert not result.degenerate.any(), result.reason
    assert gap <= 1e-3 and var <= 0.01


@pytest.mark.slow
def test_chunks_and_the_stored_file_give_the_same_run(growth, tmp_path):
    model, offline = growth
    spec = spec_from_dict(GROWTH)
    model_id = yauyau.precompute(spec, tmp_path)
    stored = yauyau.load_model(tmp_path, model_id)
    assert float(stored.offline.to_arrays()["frame"][0]) == pytest.approx(0.1 * 0.0 + 0.2)
    sim = simulate(model, 600, np.random.default_rng(2))
    opened = yauyau.open_filter(tmp_path, model_id)
    parts = [opened.run(sim.increments[k:k + 97]) for k in range(0, 600, 97)]
    flt = build(model, offline)  # in process, the same chunks: the file holds the same frame
    state, mine = flt.initial_state(), []
    for k in range(0, 600, 97):
        state, part = flt.run_arrays(state, sim.increments[k:k + 97])
        mine.append(part.mean)
    stored_means = np.concatenate([p.mean for p in parts])
    assert np.abs(stored_means - np.concatenate(mine)).max() < 1e-9
    assert opened.state_dict()["center"][0] == pytest.approx(float(state.center[0]), abs=1e-9)
    # the chunks decide when the ball moves (a chunk does not look past its end), not the answer
    exact = _exact(model, sim.increments)
    assert np.abs(stored_means[:, 0] - exact.mean[:, 0]).max() <= 1e-3


def test_arrays_solved_without_the_frame_are_refused():
    """A file written before frames holds the propagator of f itself, which differs from the frame's
    where f(c₀) ≠ 0: opening it says to precompute again."""
    doc = _doc(discretization={"basis": 20})
    model = compile_model(spec_from_dict(doc))
    arrays = precompute(model).to_arrays()
    arrays.pop("frame")
    with pytest.raises(InputError, match="arrays.frame"):
        OfflineModel.from_arrays(model, arrays)
    # where f(c₀) = 0 the two propagators are the same arrays: accepted
    doc = _doc(drift=["0.1*x"], discretization={"basis": 20}, domain={"center": [0.0]})
    model = compile_model(spec_from_dict(doc))
    arrays = precompute(model).to_arrays()
    arrays.pop("frame")
    OfflineModel.from_arrays(model, arrays)


def test_a_nonlinear_drift_without_region_is_still_refused():
    model = compile_model(spec_from_dict(_doc(drift=["0.1*x + 0.1*sin(x)"], discretization={"basis": 20})))
    with pytest.raises(SpecError, match="domain.follow") as err:
        build(model, precompute(model))
    assert "not affine" in str(err.value)


def test_a_degenerate_frame_says_why_keeps_its_centre_and_restarts():
    """An impossible increment (gate off) stops the filter with a reason; later chunks stay degenerate
    without error, with the frame's centre where it stopped; a fresh state from the prior recovers."""
    model = compile_model(spec_from_dict(_doc(measurement={"gate": 0}, discretization={"basis": 60})))
    flt = build(model, precompute(model))
    rows = simulate(model, 300, np.random.default_rng(3)).increments
    rows[120, 0] = 1e6
    state, result = flt.run_arrays(flt.initial_state(), rows[:200])
    assert state.degenerate and result.degenerate[120:].all() and not result.degenerate[:120].any()
    assert result.reason and np.all(np.isfinite(result.mean)) and np.all(np.isfinite(result.center))
    later, tail = flt.run_arrays(state, rows[200:], np.arange(201, 301) * model.dt)
    assert later.degenerate and tail.degenerate.all() and np.array_equal(later.center, state.center)
    fresh, again = flt.run_arrays(flt.initial_state(), rows[:100])
    assert not again.degenerate.any() and not fresh.degenerate
    # a 50σ glitch: the reason names it, its size read off the row's moved nodes (Kalman: the one-step
    # prediction m + f(m)dt of E[h] = E[x], in standard deviations √(R dt))
    rows[120, 0] = 5.0
    _, hit = flt.run_arrays(flt.initial_state(), rows[:200])
    m = _exact(model, rows[:120]).mean[-1, 0]
    sigmas = abs(5.0 - (m + (0.1 * m + 0.2) * model.dt) * model.dt) / np.sqrt(model.dt)
    assert hit.degenerate[120] and f"is {sigmas:.3g} standard deviations" in hit.reason, (sigmas, hit.reason)


@pytest.mark.slow
def test_in_the_frame_a_move_inside_the_loop_is_the_move_between_blocks(growth):
    """The loop's moves (solver/engine/recentring.py) ride the frame too: the same estimates and state, to
    rounding, as blocks that end where the loop moved, FollowingFilter.recentre and the next block
    (the frame's path restarted from the new centre)."""
    model, offline = growth
    flt = build(model, offline)
    assert flt.frame is not None
    assert_loop_moves_as_blocks(flt, simulate(model, 900, np.random.default_rng(4)))
