"""An atlas of propagators (``[domain] region``, solver/engine/atlas.py): a following ball for a drift that is
not shift-invariant, against a fine-grid reference.

Truth: the point-mass filter of tests/helpers/atlas.py (finite volumes, zero flux) on a box that holds
the whole path, [-17.5, 72.5] with 2400 cells, exact in time (the dense exp(dt L), computed once) and
with the same continuous-increment likelihood exp(h dy - h^2 dt / 2).  Its own error, from halving its
cells, is ~1e-3 on these paths.  The model is f = 0.8 + 0.3 sin x, h = x, unit noises: the issue's
"drift that is not shift-invariant"; the ball has radius 6, the path travels 30-55 units.
"""

from __future__ import annotations

import csv
import json

import h5py
import numpy as np
import pytest
from helpers.atlas import SIN, reference_means
from helpers.irregular_refs import GridReference, simulate_irregular
from helpers.loop_moves import assert_loop_moves_as_blocks
from yauyau.service.cli import main
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.atlas import MAX_CENTERS, lattice, lattice_step
from yauyau.solver.engine.filter import YauYauFilter, build
from yauyau.solver.engine.follow import FollowingFilter
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.filtering import concat_results
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate
from yauyau.storage.errors import StoreError

import yauyau
from yauyau.api import solve

STEPS = 3000  # t in [0, 60]


def _spec(**domain):
    doc = json.loads(json.dumps(SIN))
    doc["domain"].update(domain)
    return spec_from_dict(doc)


@pytest.fixture(scope="module")
def sin():
    model = compile_model(_spec())
    return model, precompute(model)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_a_drift_that_is_not_shift_invariant_matches_the_fine_grid_over_the_whole_path(sin, seed):
    model, offline = sin
    flt = build(model, offline)
    assert isinstance(flt, FollowingFilter) and flt.atlas is not None
    sim = simulate(model, STEPS, np.random.default_rng(seed))
    assert sim.states[-1, 0] > 25  # four radii and more beyond the start
    state, result = flt.run_arrays(flt.initial_state(), sim.increments)
    gap = np.abs(result.mean[:, 0] - reference_means(model, sim.increments)).max()
    print(f"seed {seed}: x(60) = {sim.states[-1, 0]:.1f}, {int(result.recentred.sum())} moves, "
          f"{offline.atlas.loads} of {offline.atlas.size} centres read, gap {gap:.2e}")
    assert not result.degenerate.any(), result.reason
    assert gap <= 0.01
    assert result.recentred.sum() > 30
    # every centre is a lattice centre, and the ball stays near the mean
    spacing = offline.atlas.lattice.spacing
    assert np.allclose(np.round(result.center[:, 0] / spacing) * spacing, result.center[:, 0])
    assert np.abs(result.mean[:, 0] - result.center[:, 0]).max() < 0.3 * 6.0


@pytest.mark.slow
def test_the_fixed_ball_of_the_same_radius_cannot_follow(sin):
    model, _ = sin
    fixed = compile_model(spec_from_dict({**SIN, "domain": {"radius": 6.0}}))
    flt = build(fixed, precompute(fixed))
    sim = simulate(model, STEPS, np.random.default_rng(1))
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    assert result.degenerate.any() and "boundary" in result.reason


def test_the_lattice_covers_the_region_in_whole_elements(sin):
    model, offline = sin
    grid = offline.atlas.lattice
    element = float(np.diff(np.sort(offline.mesh_points.ravel()))[0])
    centers = grid.centers()[:, 0]
    assert grid.axes == (0,) and len(centers) == offline.atlas.size
    assert abs(grid.spacing / element - round(grid.spacing / element)) < 1e-9  # nodes meet nodes
    assert abs(grid.spacing - 0.15 * 6.0) <= element / 2  # follow_distance x radius, rounded
    assert np.any(np.isclose(centers, 0.0))  # anchored at the spec's centre
    probe = np.linspace(-5.0, 60.0, 2001)  # every point of the region is within s/2 of a centre
    assert np.abs(probe[:, None] - centers[None, :]).min(axis=1).max() <= grid.spacing / 2 + 1e-12
    # each centre's ball is its own: the drift at its nodes differs, the basis is shared
    a, b = offline.atlas.offline(0), offline.atlas.offline(offline.atlas.size - 1)
    assert not np.allclose(a.propagator_fp, b.propagator_fp)
    assert a.basis is b.basis and np.allclose(b.nodes - a.nodes, centers[-1] - centers[0])


@pytest.mark.slow
def test_leaving_the_region_is_a_degenerate_step_with_its_reason(sin):
    model = compile_model(_spec(region=[[-5.0, 20.0]]))
    flt = build(model, precompute(model))
    sim = simulate(model, STEPS, np.random.default_rng(2))  # x reaches ~54
    state, result = flt.run_arrays(flt.initial_state(), sim.increments)
    first = int(np.argmax(result.degenerate))
    assert result.degenerate.any() and state.degenerate
    assert "left domain.region ([-5, 20])" in result.reason and "widen the region" in result.reason
    assert result.mean[first - 1, 0] > 19 and not result.degenerate[:first].any()
    # the flagged row is the one whose mean left (its estimate, on the ball, is the last good one) and the
    # rows after it repeat that estimate
    assert result.mean[first, 0] > 20 >= result.mean[first - 1, 0]
    assert np.all(result.mean[first:] == result.mean[first])
    assert np.all(result.cov[first:] == result.cov[first])
    assert np.all(np.isfinite(result.mean)) and np.all(np.isfinite(result.cov))


@pytest.mark.slow
def test_a_state_that_left_the_region_is_not_re_initialised_at_the_model_prior(sin):
    """on_degenerate = "reinitialise" cannot restart a ball that left its region (a prior around the last
    estimate lies outside it too, and the model's prior describes t = 0, ~20 units behind): the rows stay
    degenerate, with the reason, as under "stop" (before, they restarted at x = 0 and ran on garbage)."""
    from yauyau.solver.recovery import restart_from_last, run_with_policy

    model = compile_model(_spec(region=[[-5.0, 20.0]]))
    flt = build(model, precompute(model))
    sim = simulate(model, STEPS, np.random.default_rng(2))
    _, stopped = flt.run_arrays(flt.initial_state(), sim.increments)
    state, result = run_with_policy(flt, flt.initial_state(), sim.increments, policy="reinitialise")
    first = int(np.argmax(stopped.degenerate))
    assert not result.reinitialised.any() and state.degenerate
    assert result.degenerate[first:].all() and not result.degenerate[:first].any()
    assert "left domain.region" in result.reason and "not re-initialised" in result.reason
    assert "not re-initialised" in state.reason
    assert np.array_equal(result.mean, stopped.mean)  # the last good estimate, never the prior at 0
    assert result.center is not None and np.isfinite(result.center).all()
    again, more = run_with_policy(flt, state, sim.increments[:5], policy="reinitialise")  # a later chunk
    assert again.degenerate and more.degenerate.all() and not more.reinitialised.any()
    with pytest.raises(InputError, match="send a prior where the state is now") as info:
        restart_from_last(flt, state)  # a reset "from last" (library, HTTP) says so too: a 4xx, not a restart
    assert info.value.field == "from"


@pytest.mark.slow
def test_a_stored_atlas_is_read_one_centre_at_a_time_and_checked(tmp_path):
    spec = _spec()
    model_id = yauyau.precompute(spec, tmp_path)
    flt = yauyau.open_filter(tmp_path, model_id)
    atlas = flt.filter.atlas
    sim = simulate(compile_model(spec), 500, np.random.default_rng(1))  # x travels ~8: a few centres
    result = flt.run(sim.increments)
    assert 1 <= atlas.loads <= 12 < atlas.size and result.recentred.any()
    memory = build(compile_model(spec), precompute(compile_model(spec)))
    _, same = memory.run_arrays(memory.initial_state(), sim.increments)
    assert np.abs(result.mean - same.mean).max() < 1e-10  # the file holds the arrays solved in memory
    # a row altered on disk is caught when (and only when) it is read
    with h5py.File(tmp_path / f"{model_id}.h5", "r+") as h5:
        row = h5["lazy"]["atlas_propagator_fp"]
        row[atlas.size - 1, 0, 0] += 1e-3
    flt = yauyau.open_filter(tmp_path, model_id)
    flt.run(sim.increments[:10])
    with pytest.raises(StoreError, match="checksum"):
        flt.filter.atlas.offline(flt.filter.atlas.size - 1)


def test_a_restored_state_must_sit_on_the_lattice(sin):
    model, offline = sin
    flt = yauyau.OnlineFilter(build(model, offline))
    flt.run(simulate(model, 300, np.random.default_rng(1)).increments)
    data = flt.state_dict()
    yauyau.OnlineFilter(build(model, offline)).restore(data)  # as saved: fine
    data["center"] = [data["center"][0] + 0.1]
    with pytest.raises(InputError, match="not a centre of this model's atlas"):
        yauyau.OnlineFilter(build(model, offline)).restore(data)


@pytest.mark.parametrize(("domain", "field", "words"), [
    ({"follow": False, "region": [[0, 1]]}, "domain.region", "only applies with follow"),
    ({"region": [[0, 1], [2, 3]]}, "domain.region", "one [lo, hi] pair per state variable"),
    ({"region": [[3, 1]]}, "domain.region[0]", "finite lo < hi"),
    ({"region": [[0, 1e6]]}, "domain.region", f"more than {MAX_CENTERS}"),
])
def test_a_bad_region_names_the_field_and_the_fix(domain, field, words):
    with pytest.raises(SpecError) as caught:
        lattice(compile_model(_spec(**domain)))
    assert caught.value.field == field and words in caught.value.message


@pytest.mark.slow
def test_follow_without_a_region_says_to_declare_one_and_a_prior_outside_is_refused():
    doc = json.loads(json.dumps(SIN))
    del doc["domain"]["region"]
    with pytest.raises(SpecError, match="domain.region") as caught:
        solve(spec_from_dict(doc))
    assert caught.value.field == "domain.follow"
    with pytest.raises(SpecError, match="prior mean \\(0\\) lies outside domain.region") as caught:
        _spec(region=[[5.0, 60.0]])  # refused with the spec, before any precompute
    assert caught.value.field == "initial.mean" and "move the prior into the region" in caught.value.message
    mixture = {"kind": "mixture", "weights": [1.0, 3.0], "means": [[0.0], [8.0]], "covs": [[[1.0]], [[1.0]]]}
    spec_from_dict({**SIN, "initial": mixture, "domain": {**SIN["domain"], "region": [[5.0, 60.0]]}})
    with pytest.raises(SpecError, match="prior mean \\(2\\) lies outside") as caught:
        spec_from_dict({**SIN, "initial": {**mixture, "weights": [3.0, 1.0]},
                        "domain": {**SIN["domain"], "region": [[5.0, 60.0]]}})
    assert caught.value.field == "initial.means"
    model = compile_model(_spec(region=[[-5.0, 60.0]]))
    flt = build(model, precompute(model))
    with pytest.raises(SpecError, match="prior mean \\(70\\) lies outside domain.region"):
        flt.initial_state({"kind": "gaussian", "mean": [70.0], "cov": [[1.0]]})  # a prior sent later
    # without a region the spec's id is what it was before regions existed
    assert "region" not in spec_from_dict({**SIN, "domain": {"radius": 6.0}}).canonical_json()


def test_a_spec_whose_prior_is_outside_the_region_is_refused_and_nothing_is_stored(tmp_path, capsys):
    spec_file = tmp_path / "outside.json"
    doc = json.loads(_spec().canonical_json())
    doc["domain"]["region"] = [[20.0, 30.0]]
    spec_file.write_text(json.dumps(doc))
    store = tmp_path / "store"
    assert main(["precompute", str(spec_file), "--store", str(store)]) == 2
    err = capsys.readouterr().err
    assert "initial.mean: the prior mean (0) lies outside domain.region ([20, 30])" in err
    assert "Traceback" not in err and not list(store.glob("*.h5"))


@pytest.mark.slow
def test_the_cli_precomputes_and_filters_an_atlas(tmp_path, capsys):
    spec_file = tmp_path / "sin.json"
    spec_file.write_text(_spec().canonical_json())
    assert main(["precompute", str(spec_file), "--store", str(tmp_path / "store"), "--quiet"]) == 0
    model_id = capsys.readouterr().out.strip()
    assert main(["models", "--store", str(tmp_path / "store")]) == 0
    header, line = capsys.readouterr().out.splitlines()
    at = header.index("follow")  # the name has a space: read the column where its header starts
    assert line[at:].split()[0] == "region"
    assert main(["models", "--store", str(tmp_path / "store"), "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert (listed[0]["follow"], listed[0]["region"]) == (True, _spec().domain.region)
    sim = simulate(compile_model(_spec()), 1000, np.random.default_rng(1))
    inc = tmp_path / "inc.csv"
    inc.write_text("dy\n" + "\n".join(repr(float(v)) for v in sim.increments[:, 0]) + "\n")
    out = tmp_path / "out.csv"
    assert main(["filter", model_id, "--store", str(tmp_path / "store"), "--increments", str(inc),
                 "--out", str(out)]) == 0
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[-2:] == ["center_x", "recentred"] and len(rows) == 1000
    assert any(r["recentred"] == "1" for r in rows)
    assert abs(float(rows[-1]["mean_x"]) - float(rows[-1]["center_x"])) < 1.8
    assert float(rows[-1]["center_x"]) > 5


@pytest.mark.slow
def test_in_2d_the_lattice_runs_along_the_coordinates_the_drift_depends_on_only():
    """f = (0.8 + 0.3 sin x, 0.5): a lattice along x; along y the centre's ball moves by translation and
    shares that centre's stored propagator (SymPy finds y shift-invariant)."""
    doc = {**SIN, "state": ["x", "y"], "drift": ["0.8 + 0.3*sin(x)", "0.5"], "observation": ["x", "y"],
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
           "domain": {"radius": 6.0, "follow": True, "region": [[-5.0, 20.0], [-5.0, 20.0]]},
           "discretization": {"dt": 0.02, "basis": 150}}
    model = compile_model(spec_from_dict(doc))
    offline = precompute(model)
    grid = offline.atlas.lattice
    step = lattice_step(offline.mesh_points, model.center, model.radius)  # the lattice mesh of a follow ball
    assert model.shift_directions == (1,) and grid.axes == (0,) and step is not None
    assert abs(grid.spacing / step - round(grid.spacing / step)) < 1e-9 and offline.atlas.size == 23
    flt = build(model, offline)
    sim = simulate(model, 1000, np.random.default_rng(1))  # x travels ~14, y ~5
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    assert not result.degenerate.any() and result.recentred.sum() > 10
    assert np.abs(result.mean - result.center).max() < 0.3 * 6.0
    xs = result.center[:, 0]
    assert np.allclose(np.round(xs / grid.spacing) * grid.spacing, xs)  # x on the lattice ...
    assert len(np.unique(result.center[:, 1])) > 3  # ... y anywhere
    center = result.center[-1]
    engine = flt.engine(center)
    k = grid.index(center)
    assert engine.offline.home is offline.atlas.offline(k)  # the centre's arrays, translated along y
    assert np.allclose(engine.nodes, offline.atlas.offline(k).nodes + [0.0, center[1]])


@pytest.mark.slow
def test_a_session_over_http_carries_the_centre_and_ends_at_the_region_with_its_reason(tmp_path):
    """The service: rows carry "center" (and "recentred": true where the ball moved), the stored state
    keeps the centre between chunks (the same means as one run in this process), and a path that
    leaves the region gives degenerate rows with the reason, not an error."""
    from fastapi.testclient import TestClient
    from yauyau.service.http.app import create_app
    from yauyau.service.settings import Settings

    spec = _spec(region=[[-5.0, 20.0]])
    model_id = yauyau.precompute(spec, tmp_path / "store")
    model = compile_model(spec)
    increments = simulate(model, STEPS, np.random.default_rng(2)).increments  # x reaches ~54
    flt = build(model, precompute(model))
    state, parts = flt.initial_state(), []
    for start in range(0, STEPS, 500):  # the same chunks (a move happens between blocks of a chunk)
        state, part = flt.run_arrays(state, increments[start:start + 500])
        parts.append(part)
    local = concat_results(parts)
    settings = Settings(store=tmp_path / "store", session_db=tmp_path / "s.sqlite3")
    with TestClient(create_app(settings), raise_server_exceptions=False) as api:
        listed = {m["id"]: m for m in api.get("/v1/models").json()}[model_id]
        assert (listed["follow"], listed["region"]) == (True, [[-5.0, 20.0]])
        detail = api.get(f"/v1/models/{model_id}").json()
        assert (detail["follow"], detail["region"]) == (True, [[-5.0, 20.0]])
        sid = api.post("/v1/sessions", json={"model": model_id}).json()["id"]
        assert api.get(f"/v1/sessions/{sid}").json()["center"] == [0.0]  # the prior's mean, on the lattice
        rows = []
        for seq, start in enumerate(range(0, STEPS, 500)):
            r = api.post(f"/v1/sessions/{sid}/observations",
                         json={"seq": seq, "increments": increments[start:start + 500].tolist()})
            assert r.status_code == 200, r.text
            rows += r.json()["estimates"]
            assert api.get(f"/v1/sessions/{sid}").json()["center"] == rows[-1]["center"]
    means = np.array([row["mean"][0] for row in rows])
    assert np.abs(means - local.mean[:, 0]).max() < 1e-9  # the state (and its centre) kept between chunks
    assert all(len(row["center"]) == 1 for row in rows)
    assert sum(bool(row.get("recentred")) for row in rows) == int(local.recentred.sum()) > 10
    first = next(i for i, row in enumerate(rows) if row.get("degenerate"))
    assert first == int(np.argmax(local.degenerate)) and "left domain.region" in rows[first]["reason"]


def test_with_an_atlas_a_move_inside_the_loop_is_the_move_between_blocks(sin):
    """The loop's moves (solver/engine/recentring.py) switch to the new centre's stored propagator: the same
    estimates and state, to rounding, as blocks that end where the loop moved, FollowingFilter.recentre
    and the next block on the new centre's engine."""
    model, offline = sin
    flt = build(model, offline)
    assert flt.atlas is not None
    assert_loop_moves_as_blocks(flt, simulate(model, 900, np.random.default_rng(6)))


def test_irregular_rows_move_onto_each_centres_flow_inside_the_loop_and_match_the_fine_grid(sin, monkeypatch):
    """Gaps drawn in [0.5, 1.5]·dt and two missing rows: the loop moves the ball and switches to the new
    centre's modal flow (its own generator's eigenbasis), no block runs; truth: the fine-grid filter at
    the same times (helpers/irregular_refs.py, exact in time).  Measured: mean 2.2e-3, variance 0.29%,
    43 moves (the block logic, before: 5.2e-3, 0.94%, 29 moves)."""
    model, offline = sin
    times = np.cumsum(np.random.default_rng(4).uniform(0.5, 1.5, 1500) * model.dt)
    _, rows = simulate_irregular(model, times, "continuous", np.random.default_rng(5))
    rows[[40, 41]] = np.nan
    blocks = []
    original = YauYauFilter.run_until
    monkeypatch.setattr(YauYauFilter, "run_until", lambda *args: blocks.append(1) or original(*args))
    flt = build(model, offline)
    _, result = flt.run_arrays(flt.initial_state(), rows, times)
    doc = json.loads(json.dumps(SIN))
    doc["domain"] = {"radius": 45.0, "center": [27.5]}  # [-17.5, 72.5]: the whole path
    exact = GridReference(compile_model(spec_from_dict(doc)), cells=2400, method="expm_multiply").run(
        rows, times, "continuous")
    gap = np.abs(result.mean[:, 0] - exact.mean[:, 0]).max()
    var = np.abs(result.cov[:, 0, 0] / exact.cov[:, 0, 0] - 1).max()
    print(f"{int(result.recentred.sum())} moves, mean {gap:.2e}, variance {var:.2e}")
    assert not blocks and not result.degenerate.any() and result.recentred.sum() > 20
    assert gap <= 0.005 and var <= 0.01
    assert len(np.unique(result.center[:, 0])) > 5  # several centres of the atlas, each its own flow


def test_the_loops_propagator_at_a_centre_is_the_one_stored_for_it(sin):
    """Truth: the atlas's stored arrays.  What a move in the loop multiplies by at a centre
    (FollowingFilter.propagator_at, made without the centre's engine) is that centre's stored
    propagator with the engine's zero column, for centres met in either order and in single precision."""
    model, offline = sin
    for precision in ("double", "single"):
        flt = build(model, offline, precision=precision)
        solved = offline.atlas.solved
        for k in (3, 40, 3):
            center = offline.atlas.center(k)
            found = flt.propagator_at(center)
            assert found.dtype == np.dtype(np.float64 if precision == "double" else np.float32)
            assert found.flags.f_contiguous and found.shape == (len(offline.nodes), offline.size + 1)
            np.testing.assert_array_equal(found[:, :-1], solved.propagator_fp[k].astype(found.dtype))
            assert not found[:, -1].any()
        flt.engine(offline.atlas.center(7))  # the block path's engine there: its matrix is the one used
        assert flt.propagator_at(offline.atlas.center(7)) is flt._atlas_engine(7).propagator


@pytest.mark.slow
def test_a_precomputed_atlas_goes_to_the_store_centre_by_centre_and_is_never_all_in_memory(sin, tmp_path):
    """Truth: the atlas solved in memory (the fixture).  Streamed, each centre reaches the sink once,
    bit for bit the same, and the solve keeps none of them: its peak of traced memory is below the
    in-memory solve's by most of the atlas's size (K centres of (Q, N) + (N, N) doubles)."""
    import tracemalloc

    model, kept = sin
    solved = kept.atlas.solved
    K = kept.atlas.size
    seen = {}

    def sink(k, count, rows):  # compared as it arrives, kept by no one
        assert count == K and k not in seen and sorted(rows) == ["atlas_generator", "atlas_propagator_fp"]
        seen[k] = (np.array_equal(rows["atlas_propagator_fp"], solved.propagator_fp[k])
                   and np.array_equal(rows["atlas_generator"], solved.generator[k]))

    peaks = {}
    for name, kwargs in (("kept", {}), ("streamed", {"atlas_sink": sink})):
        tracemalloc.start()
        offline = precompute(model, **kwargs)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert sorted(seen) == list(range(K)) and all(seen.values())
    assert offline.atlas.solved is None and offline.lazy_arrays() == {}
    with pytest.raises(InputError, match="open the model from the store"):
        offline.atlas.offline(0)
    atlas_bytes = solved.propagator_fp.nbytes + solved.generator.nbytes
    print(f"atlas {atlas_bytes / 1e6:.1f} MB: peak {peaks['kept'] / 1e6:.1f} MB kept, "
          f"{peaks['streamed'] / 1e6:.1f} MB streamed")
    assert peaks["kept"] - peaks["streamed"] > 0.7 * atlas_bytes
    # through the store: the file written centre by centre holds the rows solved in memory
    model_id = yauyau.precompute(_spec(), tmp_path)
    stored = yauyau.storage.model_store.ModelStore(tmp_path).load(model_id)
    for k in (0, K // 2, K - 1):
        assert np.array_equal(stored.lazy.read("atlas_propagator_fp", k), solved.propagator_fp[k])
        assert np.array_equal(stored.lazy.read("atlas_generator", k), solved.generator[k])
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left
