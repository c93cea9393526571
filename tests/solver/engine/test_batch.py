"""Many states stepped together (solver/engine/batch.py).

* Truth: a batch of OU streams (linear Gaussian) against the exact sampled-time Kalman filter, each
  stream on its own data and its own length.
* The batch is the engine stepped alone, to rounding (``BATCH_RTOL``): unequal lengths, missing rows,
  an outlier the gate rejects, a degenerate state, irregular times, single precision, a 2-D model.
* A refused item names itself and leaves the others alone.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers.irregular_refs import kalman_irregular
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.batch import BATCH_RTOL, MAX_BATCH_BYTES
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.errors import InputError
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate


@pytest.fixture(scope="module")
def plane():
    doc = {"name": "damped-rotation", "state": ["x1", "x2"], "drift": ["-0.5*x1 + x2", "-x1 - 0.5*x2"],
           "observation": ["x1", "x2**3/4"], "initial": {"kind": "gaussian", "mean": [0.5, 0.0],
                                                          "cov": [[1.0, 0.0], [0.0, 1.0]]},
           "domain": {"radius": 4.0}, "discretization": {"dt": 0.02, "basis": 120}}
    model = compile_model(spec_from_dict(doc))
    return model, precompute(model)


def _chunks(model, lengths, seed=0):
    return [simulate(model, K, np.random.default_rng(seed + i)).increments if K else np.empty((0, model.m))
            for i, K in enumerate(lengths)]


def _assert_same(alone, together, precision="double"):
    """Every field of every item equal to rounding: the tolerance documented in solver/engine/batch.py."""
    rtol = BATCH_RTOL[precision]
    for (s1, r1), (s2, r2) in zip(alone, together, strict=True):
        np.testing.assert_array_equal(r1.step, r2.step)
        np.testing.assert_array_equal(r1.t, r2.t)
        np.testing.assert_array_equal(r1.degenerate, r2.degenerate)
        np.testing.assert_array_equal(r1.gated, r2.gated)
        assert r1.reason == r2.reason
        for name in ("mean", "cov", "loglik", "loglik_increment", "predictive_loglik"):
            a, b = getattr(r1, name), getattr(r2, name)
            np.testing.assert_allclose(b, a, rtol=rtol, atol=rtol, equal_nan=True, err_msg=name)
        np.testing.assert_allclose(s2.coefficients / s2.mass, s1.coefficients / s1.mass, rtol=rtol,
                                   atol=rtol * np.abs(s1.coefficients / s1.mass).max())
        assert (s1.step, s1.t, s1.degenerate) == (s2.step, s2.t, s2.degenerate)
        np.testing.assert_allclose(s2.loglik, s1.loglik, rtol=rtol, atol=rtol)


@pytest.mark.slow
def test_a_batch_of_ou_streams_matches_the_exact_kalman_filter(ou):
    model, offline = ou
    engine = YauYauFilter(model, offline)
    kalman = DiscreteKalmanFilter(model)
    lengths = [400, 250, 399, 37, 1, 400, 180, 300]
    chunks = _chunks(model, lengths, seed=30)
    chunks[1][[3, 4, 90]] = np.nan  # missing rows only predict
    results = engine.run_batch([engine.initial_state() for _ in chunks], chunks)
    for chunk, (state, result) in zip(chunks, results, strict=True):
        _, ref = kalman.run(kalman.initial_state(), chunk)
        mean = np.array([e.mean[0] for e in ref])
        var = np.array([e.cov[0, 0] for e in ref])
        assert np.max(np.abs(result.mean[:, 0] - mean)) < 1e-3
        assert np.max(np.abs(result.cov[:, 0, 0] / var - 1.0)) < 0.01
        assert abs(result.loglik[-1] - ref[-1].loglik) < 1e-3
        assert state.step == len(chunk) and not result.degenerate.any()


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["double", "single"])
def test_the_batch_is_each_state_stepped_alone(cubic, precision):
    model, offline = cubic
    engine = YauYauFilter(model, offline, precision=precision)
    assert len(engine.nodes) + 1 < 2 * (engine.N + 1)  # the batch's fused operator P Π (engine/batch.py)
    lengths = [100, 100, 64, 100, 3, 99, 100, 250, 17, 100, 0, 100]
    chunks = _chunks(model, lengths, seed=7)
    chunks[2][10:20] = np.nan
    chunks[5][50] = 40.0  # an outlier: near the gate the state leaves the fast path
    # states at different points of their streams
    starts = [engine.initial_state() for _ in chunks]
    warm = _chunks(model, [30] * len(chunks), seed=100)
    starts = [engine.run_arrays(s, w)[0] if i % 3 else s
              for i, (s, w) in enumerate(zip(starts, warm, strict=True))]
    alone = [engine.run_arrays(s, c) for s, c in zip(starts, chunks, strict=True)]
    together = engine.run_batch(starts, chunks)
    assert alone[5][1].gated[50]  # the outlier was rejected in both
    _assert_same(alone, together, precision)
    # and chunk by chunk the batch goes on as the single engine does
    again = engine.run_batch([s for s, _ in together], chunks)
    _assert_same([engine.run_arrays(s, c) for (s, _), c in zip(alone, chunks, strict=True)], again, precision)


@pytest.mark.slow
def test_degenerate_states_and_irregular_times_run_alone_with_the_same_answer(cubic):
    model, offline = cubic
    engine = YauYauFilter(model, offline, gate=0)  # no gate: an impossible row degenerates
    paths = _chunks(model, [60, 60, 60, 60], seed=3)
    chunks, next_chunks = [p[:50] for p in paths], [p[50:] for p in paths]
    states = [engine.initial_state() for _ in chunks]
    chunks[1][20] = 1e6  # impossible under the model: the state degenerates at row 20
    times = [None, None, list(0.013 * np.arange(1, 51)), None]
    alone = [engine.run_arrays(s, c, t) for s, c, t in zip(states, chunks, times, strict=True)]
    together = engine.run_batch(states, chunks, times)
    assert alone[1][1].degenerate[20] and not alone[1][1].degenerate[19]
    _assert_same(alone, together)
    # a degenerate state stays so, and the others go on
    _assert_same([engine.run_arrays(s, c) for (s, _), c in zip(alone, next_chunks, strict=True)],
                 engine.run_batch([s for s, _ in together], next_chunks))


@pytest.mark.slow
def test_a_2d_batch_is_each_state_stepped_alone(plane, monkeypatch):
    from yauyau.solver import jit

    model, offline = plane
    engine = YauYauFilter(model, offline)
    assert len(engine.nodes) + 1 >= 2 * (engine.N + 1)  # the batch's two products (not fused)
    sizes = _spy_batches(monkeypatch)
    chunks = _chunks(model, [60, 40, 60, 60, 59, 60], seed=21)
    chunks[3][5:9, 1] = np.nan  # partly missing rows: with the other such chunk, the numpy loop's
    chunks[5][30, 0] = np.nan
    states = [engine.initial_state() for _ in chunks]
    _assert_same([engine.run_arrays(s, c) for s, c in zip(states, chunks, strict=True)],
                 engine.run_batch(states, chunks))
    assert sizes == ([4] if jit.enabled() else [])  # every row observed: the compiled kernel's


def test_a_batch_larger_than_memory_allows_runs_in_groups(cubic, monkeypatch):
    import yauyau.solver.engine.batch as batch

    model, offline = cubic
    engine = YauYauFilter(model, offline)
    chunks = _chunks(model, [40] * 7, seed=50)
    states = [engine.initial_state() for _ in chunks]
    whole = engine.run_batch(states, chunks)
    monkeypatch.setattr(batch, "MAX_BATCH_BYTES", 2 * 40 * len(engine.nodes) * 8)  # two states a group
    assert batch.MAX_BATCH_BYTES < MAX_BATCH_BYTES
    _assert_same(whole, engine.run_batch(states, chunks))


def test_a_refused_item_names_itself_and_leaves_the_others(cubic):
    model, offline = cubic
    engine = YauYauFilter(model, offline)
    chunks = _chunks(model, [20, 20, 20], seed=1)
    chunks[1] = np.ones((20, 2))  # two columns for a one-component sensor
    states = [engine.initial_state() for _ in chunks]
    with pytest.raises(InputError) as caught:
        engine.run_batch(states, chunks)
    assert caught.value.field.startswith("chunks[1].")
    out = engine.run_batch(states, chunks, return_exceptions=True)
    assert isinstance(out[1], InputError) and out[1].field == "increments"
    _assert_same([engine.run_arrays(states[i], chunks[i]) for i in (0, 2)], [out[0], out[2]])
    with pytest.raises(InputError, match="one chunk per state"):
        engine.run_batch(states, chunks[:2])


def test_other_filters_take_a_batch_one_by_one(ou):
    from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter

    model, _ = ou
    kalman = KalmanBucyFilter(model)
    chunks = _chunks(model, [30, 10], seed=2)
    states = [kalman.initial_state() for _ in chunks]
    for (_, r1), (_, r2) in zip([kalman.run_arrays(s, c) for s, c in zip(states, chunks, strict=True)],
                                  kalman.run_batch(states, chunks), strict=True):
        np.testing.assert_array_equal(r1.mean, r2.mean)


@pytest.fixture(scope="module", params=[("continuous", 44), ("discrete", 44), ("continuous", None),
                                        ("discrete", None)], ids=lambda p: f"{p[0]}-mesh{p[1]}")
def ou_batched(request, ou_doc):
    """The OU model on a mesh of ~1.8 nodes per basis function (mesh 44: Q = 175 < 2(N + 1)), whose
    regular rows take one product PΠ a row, and on the default mesh (Q = 195: two products a row)."""
    kind, mesh = request.param
    doc = dict(ou_doc)
    if mesh is not None:
        doc["discretization"] = {**doc["discretization"], "mesh": mesh}
    if kind == "discrete":
        doc["measurement"] = {"kind": "discrete"}
    model = compile_model(spec_from_dict(doc))
    return model, precompute(model)


def _spy_batches(monkeypatch) -> list[int]:
    """The sizes of the groups the compiled batched kernel stepped (solver/engine/fused.py)."""
    import yauyau.solver.engine.fused as fused

    sizes: list[int] = []
    kernel = fused.run_fused_batch

    def spy(engine, items, gating=True):
        sizes.append(len(items))
        return kernel(engine, items, gating)

    monkeypatch.setattr(fused, "run_fused_batch", spy)
    return sizes


def test_compiled_batches_match_the_exact_kalman_filter(ou_batched, monkeypatch):
    """Streams of unequal lengths stepped by the compiled batched kernel (one product a row, or two),
    chunk after chunk, against the exact sampled-time Kalman filter on each stream's whole data."""
    from yauyau.solver import jit

    if not jit.enabled():
        pytest.skip("the compiled kernels are off (YAUYAU_KERNEL=numpy or no numba)")
    model, offline = ou_batched
    engine = YauYauFilter(model, offline)
    sizes = _spy_batches(monkeypatch)
    lengths = [300, 120, 299, 37, 1, 300]
    paths = [simulate(model, K, np.random.default_rng(80 + i)).rows for i, K in enumerate(lengths)]
    states = [engine.initial_state() for _ in paths]
    means: list[list[np.ndarray]] = [[] for _ in paths]
    variances: list[list[np.ndarray]] = [[] for _ in paths]
    for start in range(0, 300, 100):  # three rounds: the second and third continue from the states' σ
        pieces = [(i, p[start:start + 100]) for i, p in enumerate(paths) if len(p) > start]
        results = engine.run_batch([states[i] for i, _ in pieces], [c for _, c in pieces])
        for (i, _), (state, result) in zip(pieces, results, strict=True):
            states[i] = state
            means[i].append(result.mean[:, 0])
            variances[i].append(result.cov[:, 0, 0])
            assert not result.degenerate.any()
    assert sizes == [6, 4, 3]  # every round's chunks in the kernel (the 1-row one too)
    kind = "discrete" if engine.observation.discrete else "continuous"
    for i, path in enumerate(paths):
        exact = kalman_irregular([[-0.5]], [0.0], model.a, [[1.0]], [0.0], model.R, [1.0], [[0.5]], path,
                                 model.dt * np.arange(1, len(path) + 1), kind)
        assert np.max(np.abs(np.concatenate(means[i]) - exact.mean[:, 0])) < 1e-3
        assert np.max(np.abs(np.concatenate(variances[i]) / exact.cov[:, 0, 0] - 1.0)) < 0.01
        if kind == "discrete":  # the cumulative log-likelihood is log p(z_1..k)
            assert abs(states[i].loglik - exact.loglik[-1]) < 1e-2


def test_compiled_batches_are_each_state_stepped_alone(cubic, monkeypatch):
    """The compiled batched kernel against each state stepped alone, by the compiled fused rows and by
    the numpy reference path: states at different points of their streams (some continuing from their
    last σ), unequal lengths, an outlier the gate rejects (that state leaves the kernel and runs alone)."""
    from yauyau.solver import jit

    if not jit.enabled():
        pytest.skip("the compiled kernels are off (YAUYAU_KERNEL=numpy or no numba)")
    model, offline = cubic
    engine = YauYauFilter(model, offline)
    sizes = _spy_batches(monkeypatch)
    chunks = _chunks(model, [100, 100, 64, 250, 3, 99, 100, 17], seed=9)
    chunks[5][50] = 40.0
    warm = _chunks(model, [30] * len(chunks), seed=200)
    starts = [engine.run_arrays(engine.initial_state(), w)[0] if i % 3 else engine.initial_state()
              for i, w in enumerate(warm)]
    together = engine.run_batch(starts, chunks)
    assert sizes == [len(chunks)] and together[5][1].gated[50]
    _assert_same([engine.run_arrays(s, c) for s, c in zip(starts, chunks, strict=True)], together)
    monkeypatch.setenv("YAUYAU_KERNEL", "numpy")
    _assert_same([engine.run_arrays(s, c) for s, c in zip(starts, chunks, strict=True)], together)
    # the driver called in any order (the kernel steps them longest first): each item its own answer
    from yauyau.solver.engine import fused
    from yauyau.solver.filtering import chunk_clock

    monkeypatch.delenv("YAUYAU_KERNEL")
    picked = [0, 2, 3, 4]  # 100, 64, 250 and 3 rows, every row observed and ungated
    items = [(starts[i], chunks[i], *chunk_clock(starts[i], len(chunks[i]), model.dt, None, None))
             for i in picked]
    _assert_same([together[i] for i in picked], fused.run_fused_batch(engine, items))
