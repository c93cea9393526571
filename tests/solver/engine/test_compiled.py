"""The compiled row loops (solver/engine/compiled.py) and the fused chunks (solver/engine/fused.py: factor
and moments inside the row) give the numpy path's σ, ∫σ, log-likelihoods, moments and states to
rounding (their exponential is a polynomial within 2 ulp of libm's, their sums BLAS's).

Every bundled example through the general engine (small bases), in double and single precision:
regular rows, irregular times (modal, and the nodal flow of an ill-conditioned generator), missing
and partly missing rows, a gated outlier, a row that takes the slow path in the middle (log-scale
rescue) and one that makes the filter degenerate, a ball that moves inside the loop (an atlas's too).
``YAUYAU_KERNEL`` picks the path on each chunk.
A read-only ``YAUYAU_CACHE_DIR`` warns once and compiles in memory.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import EXAMPLES, ROOT
from helpers.irregular_refs import random_times, simulate_irregular
from yauyau.solver import compile_model, jit, load_spec, spec_from_dict
from yauyau.solver.engine import compiled as compiled_loops
from yauyau.solver.engine import filter as engine_filter
from yauyau.solver.engine import loops, powers, semigroup
from yauyau.solver.methods import make_filter
from yauyau.solver.offline.pipeline import precompute

pytest.importorskip("numba")

# the examples the general engine runs (the others' methods forced to it), with a small basis each
BASES = {"benes": 32, "constant_velocity": 60, "cubic_sensor": 32, "ou": 32, "power_meter": 32,
         "random_walk_trend": 32, "range_2d": 60, "sin_drift_atlas": 32, "yau_jia_1d": 32}
TWO_SENSORS = {"name": "two-sensors", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x**2", "x"],
               "observation_noise": [[0.5, 0.1], [0.1, 1.0]],
               "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]},
               "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 32}}
# at these bases the gate rejects the 30-sd outlier of these models (the others accept it in the slow
# path, degenerate on it or pass it under the cheap bound: the same on both paths)
GATED = {"benes", "constant_velocity", "random_walk_trend", "sin_drift_atlas", "two_sensors"}
K = 120
_OFFLINE: dict = {}


def _model(name: str):
    if name == "two_sensors":
        return compile_model(spec_from_dict(TWO_SENSORS))
    spec = load_spec(EXAMPLES / f"{name}.toml")
    small = spec.discretization.model_copy(update={"basis": BASES[name]})
    return compile_model(spec.model_copy(update={"discretization": small}))


def _offline(name: str):
    if name not in _OFFLINE:
        model = _model(name)
        _OFFLINE[name] = model, precompute(model)
    return _OFFLINE[name]


def _rows(model, times: np.ndarray, seed: int) -> np.ndarray:
    kind = model.spec.measurement.kind
    _, rows = simulate_irregular(model, times, kind, np.random.default_rng(seed))
    rows[10] = np.nan  # a missing row
    if model.m > 1:
        rows[20:40:3, 0] = np.nan  # partly missing rows
    gap = times[K // 3] - times[K // 3 - 1] if kind == "continuous" else 1.0
    rows[K // 3] = rows[K // 3] + 30.0 * np.sqrt(gap)  # an outlier: ~30 noise sd
    return rows


def _run(monkeypatch, kernel: str, model, offline, precision: str, rows, times, gate=None, tiny=None):
    monkeypatch.setenv("YAUYAU_KERNEL", kernel)
    flt = make_filter(model, offline, "yau-yau", precision=precision, gate=gate)
    if tiny is not None:  # more rows through the log-scale rescue
        flt.arith = dataclasses.replace(flt.arith, tiny=tiny)
    return flt.run_arrays(flt.initial_state(), rows, times)


@pytest.fixture(autouse=True)
def _fused_chunks(monkeypatch):
    """The fused chunks that ran to the end (row counts), for the tests that expect them or not."""
    done: list[int] = []
    original = compiled_loops.run_fused

    def counted(*args):
        stop = original(*args)
        done.append(stop if stop == args[1] else -1)
        return stop

    monkeypatch.setattr(compiled_loops, "run_fused", counted)
    monkeypatch.setattr(sys.modules[__name__], "_FUSED", done)
    return done


_FUSED: list[int] = []


def _both(monkeypatch, model, offline, precision, rows, times, gate=None, tiny=None, rtol=None) -> tuple:
    """Both paths on the same rows: the same results and state (within ``rtol`` where given), the same rows
    through the slow path.
    Returns (the result, the slow path's (row, reason or None), the rows given to the compiled loops,
    fused chunks' included)."""
    slow: list = []
    original = loops.slow_step

    def counted(*args, **kwargs):
        new_mass, reason = original(*args, **kwargs)
        slow.append((args[1], reason))
        return new_mass, reason

    monkeypatch.setattr(loops, "slow_step", counted)
    compiled_rows, run_compiled = [], loops.run_compiled

    def run_counted(rows, start, stop, *args, **kwargs):
        compiled_rows.append(stop - start)
        return run_compiled(rows, start, stop, *args, **kwargs)

    monkeypatch.setattr(loops, "run_compiled", run_counted)
    moving_compiled = loops.moving_compiled

    def moving_counted(rows, *args, **kwargs):
        compiled_rows.append(len(rows.factor))
        return moving_compiled(rows, *args, **kwargs)

    monkeypatch.setattr(loops, "moving_compiled", moving_counted)
    numpy_run = _run(monkeypatch, "numpy", model, offline, precision, rows, times, gate, tiny)
    numpy_slow = list(slow)
    slow.clear()
    assert not compiled_rows
    compiled_run = _run(monkeypatch, "compiled", model, offline, precision, rows, times, gate, tiny)
    _close(numpy_run, compiled_run, precision, rtol)
    assert slow == numpy_slow
    return numpy_run[1], slow, sum(compiled_rows) + sum(done for done in _FUSED if done > 0)


# compiled chunks against the numpy path: each column of each array within RTOL of its largest value
# (moments' sums by BLAS, not einsum; the factor's exp compiled.exp_shifted's): double, single.  The
# per-row rounding (~1e-15) accumulates through the recursion over the K rows: 1.5e-11 of the mean's
# scale measured on an AVX-512 machine (OpenBLAS's AVX-512 kernels and numba's FMAs round differently
# from numpy's einsum), < 1e-12 on AVX2 ones
RTOL = {"double": 1e-10, "single": 1e-5}
# the outlier row's predictive log-likelihood (about -416) reads the predicted density ~30 sd out, where
# the basis expansion's O(1) terms cancel to a tiny density: its relative rounding is amplified
# there whichever kernel runs (1.0e-7 measured on the AVX-512 machine); absolute, for that row only (and
# for the gate's score, the same predictive density)
OUTLIER_LOGLIK_ATOL = {"double": 1e-6, "single": 1e-2}
# the Schur form's products sum in another order on the two paths (numba's column loop, BLAS's tpmv on
# the numpy path): to rounding, with a wider tolerance in single.  In single precision each path's
# moments are 3–5e-5 of their scale from the double-precision run's (measured on two_sensors and
# yau_jia_1d, 120 rows), the two paths 1.2e-5 from each other
RTOL_SCHUR = {"double": 1e-10, "single": 1e-4}


def _close_array(a, b, precision: str, name: str, rtol: float | None = None) -> None:
    if isinstance(a, np.ndarray) and a.dtype.kind == "f":
        assert a.dtype == b.dtype and np.array_equal(np.isnan(a), np.isnan(b)), name
        a2, b2 = np.nan_to_num(a).reshape(len(a), -1), np.nan_to_num(b).reshape(len(b), -1)
        scale = np.maximum(np.abs(a2).max(axis=0, initial=0.0), 1e-300)
        within = np.abs(a2 - b2) <= (rtol or RTOL[precision]) * scale
        if name in ("predictive_loglik", "gate_score") and len(a2) == K:
            within[K // 3] = np.abs(a2[K // 3] - b2[K // 3]) <= OUTLIER_LOGLIK_ATOL[precision]
        assert np.all(within), name
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), name
    else:
        assert a == b, name


def _close(numpy_run, fused_run, precision: str, rtol: float | None = None) -> None:
    (state_a, result_a), (state_b, result_b) = numpy_run, fused_run
    for field in dataclasses.fields(result_a):
        _close_array(getattr(result_a, field.name), getattr(result_b, field.name), precision, field.name,
                     rtol)
    a, b, rtol = state_a.coefficients, state_b.coefficients, rtol or RTOL[precision]
    assert np.all(np.abs(a - b) <= rtol * np.abs(a).max())
    assert state_a.mass == pytest.approx(state_b.mass, rel=rtol)


def test_the_factors_exponential_against_libm():
    """compiled.exp_shifted (the update factors' exponential, a polynomial LLVM vectorises): within 2 ulp
    of libm's exp over [−708, 0] and its shift, exactly 1 at the shift, 0 below −708 (and at −inf), inf
    above 709 and NaN kept."""
    x = np.concatenate([np.random.default_rng(0).uniform(-708.0, 0.0, 20_000), -np.logspace(-17, 0, 200),
                        [0.0, -708.0, -0.5 * math.log(2.0), -1.5 * math.log(2.0), -745.0, -np.inf, 720.0,
                         np.nan]])
    for shift in (0.0, 3.25):
        out, bits = np.empty_like(x), np.empty(len(x), dtype=np.int64)
        compiled_loops.exp_shifted(x + shift, shift, out, bits)
        inside = (x >= -708.0) & (x <= 0.0)
        exact = np.array([math.exp(v) for v in (x + shift)[inside] - shift])
        assert np.all(np.abs(out[inside] - exact) <= 2 * np.spacing(exact))
        assert out[x == 0.0][0] == 1.0
        assert np.all(out[(x < -708.0)] == 0.0) and out[x == 720.0][0] == np.inf and np.isnan(out[-1])


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", [*BASES, "two_sensors"])
def test_fused_chunks_are_the_numpy_rows(monkeypatch, _fused_chunks, name, precision):
    """Every row observed, no outlier: regular and irregular (modal) chunks run fused where the model
    allows it (no moving ball or frame), within RTOL of the numpy path."""
    model, offline = _offline(name)
    regular = model.dt * np.arange(1, K + 1)
    irregular = random_times(np.random.default_rng(2), K, model.dt)
    kind = model.spec.measurement.kind
    for times, given in ((regular, None), (irregular, irregular)):
        _, rows = simulate_irregular(model, times, kind, np.random.default_rng(11))
        numpy_run = _run(monkeypatch, "numpy", model, offline, precision, rows, given)
        assert not _fused_chunks
        fused_run = _run(monkeypatch, "compiled", model, offline, precision, rows, given)
        _close(numpy_run, fused_run, precision)
        if name in ("cubic_sensor", "power_meter", "two_sensors") and given is None:
            assert _fused_chunks == [K]
        _fused_chunks.clear()


def test_fused_chunks_with_one_product_a_row(monkeypatch, _fused_chunks):
    """examples/cubic_sensor.toml as bundled (Q = 159 nodes, N = 128): fewer nodes than 2(N + 1), so the
    fused rows take s_{k+1} = PΠσ_k/∫σ_k in one product (fused.py ``_operator``), Πσ after the last row
    only: within RTOL of the numpy path's two products a row, over 600 rows in one chunk and in chunks
    of 7: the chunks continue from the state's nodal σ, bit for bit the uninterrupted run (a state whose
    coefficients were changed since does not)."""
    from yauyau.solver.engine import fused

    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    offline = precompute(model)
    flt = make_filter(model, offline, "yau-yau")
    assert fused._operator(flt) is not None
    assert fused._operator(make_filter(model, offline, "yau-yau", precision="single")) is None
    times = model.dt * np.arange(1, 601)
    _, rows = simulate_irregular(model, times, "continuous", np.random.default_rng(21))
    numpy_run = _run(monkeypatch, "numpy", model, offline, "double", rows, None)
    fused_run = _run(monkeypatch, "compiled", model, offline, "double", rows, None)
    assert _fused_chunks == [600]
    _close(numpy_run, fused_run, "double")
    monkeypatch.setenv("YAUYAU_KERNEL", "compiled")
    state = flt.initial_state()
    means = []
    for start in range(0, 600, 7):
        state, result = flt.run_arrays(state, rows[start:start + 7])
        means.append(result.mean)
    _close_array(numpy_run[1].mean, np.concatenate(means), "double", "mean")
    assert np.array_equal(np.concatenate(means), fused_run[1].mean) and state.loglik == fused_run[0].loglik
    assert state.to_dict() == fused_run[0].to_dict() and len(state.to_dict()["nodal"]) == 159
    moved = dataclasses.replace(state, coefficients=state.coefficients * (1.0 + 1e-9))
    assert fused._continues(state, *_fixed_projection(flt), np.append(state.coefficients, state.mass))
    assert not fused._continues(moved, *_fixed_projection(flt), np.append(moved.coefficients, moved.mass))


def _fixed_projection(flt):
    return np.asfortranarray(flt.projection), np.ascontiguousarray(flt.weights, dtype=float)


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", ["cubic_sensor", "two_sensors", "yau_jia_1d"])
def test_fused_chunks_in_the_schur_form(monkeypatch, _fused_chunks, name, precision):
    """Irregular rows of an ill-conditioned generator (all forced there: yau_jia_1d's is at cond(V) ≈
    9e9 at its default basis, under double precision's cap) run fused too, each row's flow e^{τT} by the
    Schur tables inside the row: the whole chunk in one compiled loop, within RTOL_SCHUR of the numpy
    path (which applies the same tables)."""
    model, offline = _offline(name)
    monkeypatch.setattr(semigroup, "MAX_CONDITION", 1.0)
    times = random_times(np.random.default_rng(5), K, model.dt)
    times[60:] += 40.0 * model.dt  # one long gap: several digit positions of the tables
    _, rows = simulate_irregular(model, times, model.spec.measurement.kind, np.random.default_rng(13))
    numpy_run = _run(monkeypatch, "numpy", model, offline, precision, rows, times)
    assert not _fused_chunks
    flt = make_filter(model, offline, "yau-yau", precision=precision)
    assert flt.flow.powers is not None  # the Schur form
    fused_run = _run(monkeypatch, "compiled", model, offline, precision, rows, times)
    assert _fused_chunks and min(_fused_chunks) > 0  # every chunk fused to its end (a long gap: pieces)
    _close(numpy_run, fused_run, precision, RTOL_SCHUR[precision])


@pytest.mark.parametrize("precision", ["double", "single"])
def test_a_fused_chunk_that_meets_the_slow_path_runs_again_keeping_sigma(monkeypatch, _fused_chunks,
                                                                          precision):
    """A gated outlier (the gate's exact score needs s) and a rescued row: the fused loop stops there
    and the whole chunk runs on the path that keeps σ, the numpy path's to rounding."""
    model, offline = _offline("two_sensors")
    times = model.dt * np.arange(1, K + 1)
    _, rows = simulate_irregular(model, times, "continuous", np.random.default_rng(12))
    rows[K // 2] += 30.0 * np.sqrt(model.dt)
    result, slow, compiled = _both(monkeypatch, model, offline, precision, rows, None)
    assert _fused_chunks == [-1] and compiled >= K and (K // 2, None) in slow and result.gated[K // 2]


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", [*BASES, "two_sensors"])
def test_compiled_rows_are_the_numpy_rows(monkeypatch, name, precision):
    """Regular and irregular (modal) rows with a missing row, partly missing rows and a gated outlier
    (the examples with a ball that follows the state: regular rows on a ball that moves in the loop)."""
    model, offline = _offline(name)
    regular = model.dt * np.arange(1, K + 1)
    result, slow, compiled = _both(monkeypatch, model, offline, precision, _rows(model, regular, 1), None)
    assert compiled >= K
    if name in GATED:
        assert (K // 3, None) in slow and result.gated is not None and result.gated[K // 3], slow
    irregular = random_times(np.random.default_rng(2), K, model.dt)
    rows = _rows(model, irregular, 3)
    result, slow, compiled = _both(monkeypatch, model, offline, precision, rows, irregular)
    assert compiled >= K
    if name in GATED:  # long gaps run in pieces: the outlier's row is another row of the loop
        assert slow and result.gated is not None and result.gated.any(), slow


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", ["random_walk_trend", "sin_drift_atlas", "constant_velocity"])
def test_a_ball_that_moves_inside_the_compiled_loop(monkeypatch, name, precision):
    """A state that travels: the compiled loop stops where the trigger fires, the ball moves in Python
    (an atlas: onto another centre's propagator) and the loop goes on, as the numpy loop does."""
    model, offline = _offline(name)
    times = model.dt * np.arange(1, 6 * K + 1)
    _, rows = simulate_irregular(model, times, model.spec.measurement.kind, np.random.default_rng(8))
    result, _, compiled = _both(monkeypatch, model, offline, precision, rows, None)
    assert compiled >= len(rows) and result.recentred is not None and result.recentred.any()


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", ["random_walk_trend", "sin_drift_atlas"])
def test_irregular_rows_on_a_ball_that_moves_inside_the_compiled_loop(monkeypatch, _fused_chunks, name,
                                                                       precision):
    """Gaps of 0.5–1.5 dt (none filtered in pieces), a missing row and a gated outlier: the rows run in
    the moving loop in the ball's modal coordinates (an atlas: each centre's own flow), the compiled
    loop scaling by e^{τΛ} with libm's exp as the fused rows do: within RTOL of the numpy loop."""
    model, offline = _offline(name)
    times = np.cumsum(np.random.default_rng(9).uniform(0.5, 1.5, 6 * K) * model.dt)
    rows = _rows(model, times, 8)
    moved, original = [], loops.loop_moving

    def counted(*args):  # (..., moving, taus): whether the moving loop ran irregular rows
        moved.append(args[-1] is not None)
        return original(*args)

    monkeypatch.setattr(engine_filter, "loop_moving", counted)
    numpy_run = _run(monkeypatch, "numpy", model, offline, precision, rows, times)
    compiled_run = _run(monkeypatch, "compiled", model, offline, precision, rows, times)
    assert moved and all(moved) and not _fused_chunks  # irregular rows, in the moving loop only
    _close(numpy_run, compiled_run, precision)
    result = compiled_run[1]
    assert result.recentred.sum() >= 3 and result.gated[K // 3] and not result.degenerate.any()
    np.testing.assert_array_equal(result.center, numpy_run[1].center)


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("name", ["cubic_sensor", "power_meter", "two_sensors"])
@pytest.mark.parametrize("form", ["schur", "expm"])
def test_the_flow_of_an_ill_conditioned_generator(monkeypatch, name, precision, form):
    """Above MAX_CONDITION the rows run in the Schur form (tables and a Taylor polynomial per gap); where
    the tables would not fit, each gap's flow is a nodal matrix: runs of equal gaps and single gaps."""
    model, offline = _offline(name)
    monkeypatch.setattr(semigroup, "MAX_CONDITION", 1.0)
    if form == "expm":
        monkeypatch.setattr(powers, "MAX_TABLE_BYTES", 0)
    gaps = np.random.default_rng(4).choice([1.0, 2.0, 3.5], size=K) * model.dt
    gaps[50:70] = 1.5 * model.dt  # a longer run of equal gaps
    times = np.cumsum(gaps)
    _, slow, compiled = _both(monkeypatch, model, offline, precision, _rows(model, times, 5), times,
                              rtol=RTOL_SCHUR[precision] if form == "schur" else None)
    assert compiled and slow  # the outlier's row: rejected, accepted or degenerate, the same on both paths


@pytest.mark.parametrize("precision", ["double", "single"])
@pytest.mark.parametrize("irregular", [False, True])
def test_rescued_rows_in_the_middle_and_a_degenerate_row(monkeypatch, precision, irregular):
    """Gate off.  With ``tiny`` raised to 0.5, every row whose ∫σ is under it takes the log-scale rescue
    and succeeds: the compiled loop stops there and re-enters at the next row.  An impossible
    increment later makes the rest of the chunk degenerate, the same on both paths."""
    model, offline = _offline("cubic_sensor")
    regular = model.dt * np.arange(1, K + 1)
    times = random_times(np.random.default_rng(6), K, model.dt) if irregular else regular
    rows, given = _rows(model, times, 7), times if irregular else None
    rows[K // 3] = 0.0
    result, slow, compiled = _both(monkeypatch, model, offline, precision, rows, given, gate=0.0, tiny=0.5)
    assert compiled >= K and len(slow) >= 5 and all(reason is None for _, reason in slow)
    assert not result.degenerate.any()
    rows[90] = 1e6
    result, slow, _ = _both(monkeypatch, model, offline, precision, rows, given, gate=0.0)
    assert slow[-1][1] is not None and result.degenerate[90:].all() and not result.degenerate[:90].any()


def test_the_kernel_switch(monkeypatch):
    monkeypatch.setenv("YAUYAU_KERNEL", "numpy")
    assert not jit.enabled()
    monkeypatch.setenv("YAUYAU_KERNEL", "compiled")
    assert jit.enabled()
    monkeypatch.delenv("YAUYAU_KERNEL")
    assert jit.enabled()  # numba is installed
    monkeypatch.setenv("YAUYAU_KERNEL", "fortran")
    with pytest.raises(ValueError, match="YAUYAU_KERNEL"):
        jit.enabled()
    monkeypatch.setenv("YAUYAU_CACHE_DIR", "/somewhere/numba")
    assert str(jit.cache_dir()) == "/somewhere/numba"


def test_the_cache_lives_under_a_digest_of_every_kernel_source(monkeypatch, tmp_path):
    """numba checks only the file that defines a function; a kernel inlining another module's (the
    batched kernel's fused_row from compiled.py) must not load stale code after only that one changed."""
    root = Path(jit.__file__).resolve().parent
    sources = jit.kernel_sources()
    names = {path.relative_to(root).as_posix() for path, _ in sources}
    assert {"engine/compiled.py", "engine/compiled_batch.py", "engine/compiled_backward.py", "qmc/kernels.py",
            "exact/mixture_kernels.py", "exact/sensor_kernel.py", "exact/mixture_piece.py"} <= names
    monkeypatch.setenv("YAUYAU_CACHE_DIR", str(tmp_path))
    assert jit.writable_cache_dir() == tmp_path / jit.kernels_digest()
    changed = [(path, text + b"\n# edited") if path.name == "compiled.py" else (path, text)
               for path, text in sources]
    monkeypatch.setattr(jit, "kernel_sources", lambda: changed)
    assert jit.kernels_digest.__wrapped__() != jit.kernels_digest()


SCRIPT = """
import warnings
import numpy as np
from yauyau.solver import compile_model, load_spec
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.engine.filter import YauYauFilter
import sys
assert "numba" not in sys.modules  # imported by the first chunk only
spec = load_spec({path!r})
spec = spec.model_copy(update={{"discretization": spec.discretization.model_copy(update={{"basis": 24}})}})
model = compile_model(spec)
flt = YauYauFilter(model, precompute(model))
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for _ in range(3):
        _, result = flt.run_arrays(flt.initial_state(), np.zeros((20, 1)))
assert "numba" in sys.modules and not result.degenerate.any()
messages = [str(w.message) for w in caught if "cache directory" in str(w.message)]
print(len(messages), messages[0] if messages else "")
"""


def test_an_unwritable_cache_directory_warns_once_and_compiles_in_memory(tmp_path):
    """A cache directory that cannot be made (under a file: read-only even for root)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    cache = blocker / "numba"
    env = dict(os.environ, YAUYAU_CACHE_DIR=str(cache), YAUYAU_KERNEL="compiled", OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", SCRIPT.format(path=str(EXAMPLES / "cubic_sensor.toml"))],
                          env=env, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr
    count, message = done.stdout.strip().split(" ", 1)
    assert count == "1" and str(cache) in message and "in memory" in message
