"""The Yau–Jia filter's compiled pieces (solver/exact/yau_jia_fast.py) against its numpy path.

``YAUYAU_KERNEL`` = numpy is the tested reference; the compiled kernels (the sensor inside them as a
tape, solver/exact/sensor_tape.py) must give its means,
covariances, log-likelihoods, predictive log-likelihoods and gate decisions to 1e-10 relative on the
bundled yau-jia examples: regular rows, irregular times (long gaps in pieces), missing rows
(prediction), gated outliers and a state round-trip.  The counts of pieces taken by the kernels make
sure the comparison is not numpy against numpy.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import EXAMPLES
from yauyau.solver.exact import yau_jia_fast
from yauyau.solver.exact.yau_jia import YauJiaFilter
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec, spec_from_dict

RTOL = 1e-10


@pytest.fixture
def fast_pieces(monkeypatch):
    """Counts of pieces the kernels took (done) and declined (None)."""
    counts = {"done": 0, "declined": 0}
    original = yau_jia_fast.FastPieces.piece

    def counted(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        counts["done" if out is not None else "declined"] += 1
        return out

    monkeypatch.setattr(yau_jia_fast.FastPieces, "piece", counted)
    return counts


def _model(name):
    return compile_model(load_spec(EXAMPLES / name))


def _run(monkeypatch, kernel, flt, rows, times=None, state=None):
    monkeypatch.setenv("YAUYAU_KERNEL", kernel)
    return flt.run_arrays(flt.initial_state() if state is None else state, rows, times)


def _close(a, b, what):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert np.array_equal(np.isnan(a), np.isnan(b)), what
    ok = ~np.isnan(a)
    err = np.abs(a[ok] - b[ok]) / (1.0 + np.abs(b[ok]))
    assert err.max(initial=0.0) < RTOL, (what, float(err.max()))


def _same(fast, slow):
    (s1, r1), (s0, r0) = fast, slow
    for field in ("mean", "cov", "loglik", "loglik_increment", "predictive_loglik", "gate_score"):
        _close(getattr(r1, field), getattr(r0, field), field)
    assert np.array_equal(r1.gated, r0.gated) and np.array_equal(r1.degenerate, r0.degenerate)
    assert s1.splits == s0.splits and s1.clipped == s0.clipped and len(s1.C) == len(s0.C)
    _close(s1.loglik, s0.loglik, "state loglik")


@pytest.mark.parametrize("name, steps", [("range_only_4d.toml", 120), ("yau_jia_1d.toml", 300)])
def test_regular_rows_match_the_numpy_path(monkeypatch, fast_pieces, name, steps):
    model = _model(name)
    rows = simulate(model, steps, np.random.default_rng(3)).increments
    flt = YauJiaFilter(model)
    _same(_run(monkeypatch, "compiled", flt, rows), _run(monkeypatch, "numpy", flt, rows))
    assert fast_pieces["done"] >= steps - 2  # a rare piece may be declined (damping)


@pytest.mark.parametrize("cap", [None, 4])
def test_two_sensors_and_a_small_cap_match_the_numpy_path(monkeypatch, fast_pieces, cap):
    doc = {"name": "t", "state": ["x", "y"], "drift": ["-x", "-y"], "method": "yau-jia",
           "observation": ["sqrt(1 + x**2)", "sqrt(1 + y**2)"], "observation_noise": [[0.5, 0.0], [0.0, 0.4]],
           "initial": {"kind": "gaussian", "mean": [0.5, -0.3], "cov": [[1.0, 0.2], [0.2, 0.8]]},
           "domain": {"radius": 8.0}, "discretization": {"dt": 0.01, "basis": 64}}
    model = compile_model(spec_from_dict(doc))
    rows = simulate(model, 120, np.random.default_rng(1)).increments
    flt = YauJiaFilter(model, max_components=cap)
    _same(_run(monkeypatch, "compiled", flt, rows), _run(monkeypatch, "numpy", flt, rows))
    assert fast_pieces["done"] >= 118


def test_a_sqrt_atan2_exp_sin_cos_sensor_with_missing_rows_matches_the_numpy_path(monkeypatch, fast_pieces):
    """Two sensors whose squares sum to 1 + x² (seed 001's class), built of sqrt, atan2, exp, sin and
    cos: the compiled tape (solver/exact/sensor_tape.py) inside the kernels, a fifth of the rows
    missing.  libm's sin, cos and exp (the kernels) and numpy's vectorised ones differ in the last
    bit, so an exact tie — mirror-image split children after a prediction, as in the test of a long
    gap below — goes either way: with these rows none occurs (with seeds 4, 6, 7 and 9 one does,
    before row 35, and the paths then part by ~1e-3 in the mean, the filter's own error)."""
    angle = "atan2(y, 2) + exp(-x**2)"
    doc = {"name": "t", "state": ["x", "y"], "drift": ["-x", "-0.5*y"], "method": "yau-jia",
           "observation": [f"sqrt(1 + x**2)*sin({angle})", f"sqrt(1 + x**2)*cos({angle})"],
           "observation_noise": [[0.5, 0.0], [0.0, 0.5]],
           "initial": {"kind": "gaussian", "mean": [0.5, -0.3], "cov": [[1.0, 0.2], [0.2, 0.8]]},
           "domain": {"radius": 8.0}, "discretization": {"dt": 0.01, "basis": 64}}
    model = compile_model(spec_from_dict(doc))
    rng = np.random.default_rng(5)
    rows = simulate(model, 150, rng).increments.copy()
    rows[rng.choice(150, 30, replace=False)] = np.nan
    flt = YauJiaFilter(model)
    assert flt.sensor.tapes() is not None
    _same(_run(monkeypatch, "compiled", flt, rows), _run(monkeypatch, "numpy", flt, rows))
    assert fast_pieces["done"] >= 148


def test_a_sensor_without_a_tape_takes_the_numpy_path_with_one_warning(monkeypatch, fast_pieces):
    import sympy as sp
    from yauyau.solver.exact import yau_jia

    model = _model("range_only_4d.toml")
    rows = simulate(model, 20, np.random.default_rng(6)).increments
    flt = YauJiaFilter(model)
    x = model.symbols[0]
    monkeypatch.setattr(flt.sensor, "h", [sp.gamma(2 + x**2)])  # no instruction: gamma
    monkeypatch.setattr(yau_jia, "_UNCOMPILED", set())
    with pytest.warns(RuntimeWarning, match="numpy path.*gamma"):
        fast = _run(monkeypatch, "compiled", flt, rows)
    _same(fast, _run(monkeypatch, "numpy", flt, rows))
    assert fast_pieces == {"done": 0, "declined": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        YauJiaFilter(model)._fast_pieces()  # another filter, same sensor: compiles, no warning


def test_irregular_times_missing_and_gated_rows_match_the_numpy_path(monkeypatch, fast_pieces):
    model = _model("range_only_4d.toml")
    gaps = np.tile([0.02, 0.05, 0.013, 0.3, 0.02, 0.9, 0.04], 12)
    times = np.cumsum(gaps)
    rng = np.random.default_rng(5)
    rows = simulate(model, len(gaps), rng, times=times).increments.copy()
    rows[[4, 9, 30, 58]] = np.nan  # prediction only (single-piece gaps: see the next test)
    rows[[15, 44]] += 3.0  # outliers: gated at the spec's 6 sd
    flt = YauJiaFilter(model)
    fast = _run(monkeypatch, "compiled", flt, rows, times)
    slow = _run(monkeypatch, "numpy", flt, rows, times)
    _same(fast, slow)
    assert slow[1].gated[[15, 44]].all() and np.isnan(rows[:, 0]).sum() == 4
    assert fast_pieces["done"] > len(gaps), fast_pieces  # the long observed gaps go in pieces


def test_prediction_over_a_long_gap_agrees_up_to_a_mirror_tie(monkeypatch, fast_pieces):
    """Over a gap in pieces without data the flow is linear: the three children of a split stay
    mirror images, so the next pieces' merge and split choices meet exact ties, which rounding
    decides — in the numpy path as in the kernels (whose eigenvectors' signs order the children
    the other way).  Both then hold mirror-image mixtures: the moments agree closely, not to 1e-10."""
    model = _model("range_only_4d.toml")
    times = np.array([0.02, 0.04, 0.06, 0.36, 1.26, 1.28])
    rows = simulate(model, len(times), np.random.default_rng(5), times=times).increments.copy()
    rows[[3, 4]] = np.nan
    flt = YauJiaFilter(model)
    (_, fast), (_, slow) = (_run(monkeypatch, k, flt, rows, times) for k in ("compiled", "numpy"))
    _close(fast.mean[:4], slow.mean[:4], "before the tie")
    np.testing.assert_allclose(fast.mean, slow.mean, rtol=0.05, atol=0.05)
    np.testing.assert_allclose(fast.cov, slow.cov, rtol=0.1, atol=0.05)


def test_a_state_round_trip_continues_as_the_numpy_path(monkeypatch, fast_pieces):
    model = _model("range_only_4d.toml")
    rows = simulate(model, 80, np.random.default_rng(8)).increments
    flt = YauJiaFilter(model)
    half = {}
    for kernel in ("compiled", "numpy"):
        state, _ = _run(monkeypatch, kernel, flt, rows[:40])
        state = flt.state_from_dict(state.to_dict())
        half[kernel] = _run(monkeypatch, kernel, flt, rows[40:], state=state)
    _same(half["compiled"], half["numpy"])
    whole = _run(monkeypatch, "compiled", flt, rows)
    _close(half["compiled"][1].mean, whole[1].mean[40:], "restarted vs whole")
    assert fast_pieces["done"] >= 150


def test_benes_phi_not_zero_takes_the_numpy_path(monkeypatch, fast_pieces):
    model = _model("benes.toml")
    rows = simulate(model, 60, np.random.default_rng(2)).increments
    flt = YauJiaFilter(model)
    _same(_run(monkeypatch, "compiled", flt, rows), _run(monkeypatch, "numpy", flt, rows))
    assert fast_pieces == {"done": 0, "declined": 0}  # φ = log cosh x: the kernels are not asked


def test_the_kernels_linear_algebra():
    from yauyau.solver.exact import mixture_kernels as mk

    rng = np.random.default_rng(0)
    for n in (1, 2, 4, 6):
        X = rng.normal(size=(n, n))
        M = X @ X.T + 0.1 * np.eye(n)
        lam, U, scratch = np.empty(n), np.empty((n, n)), mk.lapack_workspace(n)
        assert mk.eigh(M, lam, U, scratch) == 0
        np.testing.assert_allclose(lam, np.linalg.eigvalsh(M), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(U @ np.diag(lam) @ U.T, M, atol=1e-12)
        L, inv, tmp = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
        assert mk.cholesky(M, L)
        log_det = mk.spd_inverse(L, inv, tmp)
        np.testing.assert_allclose(inv, np.linalg.inv(M), rtol=1e-10)
        assert log_det == pytest.approx(np.linalg.slogdet(M)[1], rel=1e-12)
        b, out, work = rng.normal(size=n), np.empty(n), np.empty((n, 2 * n))
        mk.solve_transposed(X, b, out, work)
        np.testing.assert_allclose(out, np.linalg.solve(X.T, b), rtol=1e-9)
        sign, ld = mk.lu_inverse(X, inv, work)
        np.testing.assert_allclose(inv, np.linalg.inv(X), rtol=1e-9, atol=1e-12)
        assert (sign, ld) == pytest.approx(tuple(np.linalg.slogdet(X)), rel=1e-12)
    assert not mk.cholesky(-np.eye(3), np.empty((3, 3)))
