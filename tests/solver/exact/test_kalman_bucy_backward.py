"""Kalman–Bucy's smoother of continuous increments (solver/exact/kalman_bucy_backward.py, the two-filter form
with the adjoint flow) against a Rauch–Tung–Striebel smoother written here on the exact discrete model of
each gap: the joint Gaussian of (x_(k−1), x_k) given the rows up to k, from the Kalman–Bucy equations of
the augmented state (x(t), x_(k−1)) integrated by solve_ivp (covariance form, no exponentials), with the
observation path linear over the gap as the filter takes it; and the issue's OU case against RTS on the
time-sampled model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.smoothing_refs import DT, THETA, A, R, rts_exact_gaps, rts_sampled, sample_ou
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.smoothing import smooth, smooth_lag

OU = {"name": "ou", "state": ["x"], "drift": [f"-{THETA}*x"], "observation": ["x"],
      "diffusion": [[A]], "observation_noise": [[R]],
      "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]},
      "domain": {"radius": 6.0}, "discretization": {"dt": DT, "basis": 32}}
OSCILLATOR = {"name": "osc", "state": ["x", "v"], "drift": ["v + 0.2", "-x - 0.5*v"],
              "observation": ["x", "v - 0.1"], "diffusion": [[0.2, 0.05], [0.05, 0.5]],
              "observation_noise": [[0.3, 0.1], [0.1, 0.4]],
              "initial": {"kind": "gaussian", "mean": [1.0, 0.0], "cov": [[0.5, 0.1], [0.1, 0.3]]},
              "domain": {"radius": 6.0}, "discretization": {"dt": 0.05, "basis": 16}}


def _reference(flt, rows, taus, gated):
    model = flt.model
    state = flt.initial_state()
    return rts_exact_gaps(np.asarray(flt.F, float), np.asarray(flt.f0, float), np.asarray(model.a, float),
                          np.asarray(flt.H, float), np.asarray(flt.h0, float), np.asarray(model.R, float),
                          state.mean, state.cov, rows, taus, gated)


def _gaps(result, mf, Pf, ms, Ps, filtered):
    return (np.abs(filtered.mean - mf).max(), np.abs(filtered.cov - Pf).max(),
            np.abs(result.mean - ms).max(), np.abs(result.cov - Ps).max())


def test_ou_irregular_missing_gated_equals_rts_of_the_exact_gaps():
    """1-D OU, 300 rows at irregular times (gaps 1e-3 … ~1), 5% missing, one outlier row the gate rejects
    (the reference takes it as missing).  Asserted 1e-8 (filter and smoother)."""
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OU)), gate=5.0)
    rng = np.random.default_rng(21)
    K = 300
    taus = rng.exponential(0.1, K) + 1e-3
    x, dy = 1.0, np.empty(K)
    for k, tau in enumerate(taus):
        phi = math.exp(-THETA * tau)
        x = phi * x + rng.normal(0, math.sqrt(A * (1 - phi * phi) / (2 * THETA)))
        dy[k] = x * tau + rng.normal(0, math.sqrt(R * tau))
    dy[rng.random(K) < 0.05] = np.nan
    dy[150] = 40.0  # an outlier
    rows = dy[:, None]
    _, result = smooth(flt, flt.initial_state(), rows, np.cumsum(taus))
    _, filtered = flt.run_arrays(flt.initial_state(), rows, np.cumsum(taus))
    assert result.gated[150] and result.gated.sum() == 1
    ref = _reference(flt, rows, taus, result.gated)
    gaps = _gaps(result, *ref, filtered)
    print("ou irregular", gaps)
    assert max(gaps) < 1e-8


def test_ou_regular_chunk_with_missing_rows_equals_rts_of_the_exact_gaps():
    """The regular chunk path (one flow pair over dt, the backward A path data-free): 1000 rows one dt
    apart, 5% missing.  Asserted 1e-8."""
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OU)))
    _, dy = sample_ou(1000, seed=5)
    dy[np.random.default_rng(6).random(1000) < 0.05] = np.nan
    rows = dy[:, None]
    _, result = smooth(flt, flt.initial_state(), rows)
    _, filtered = flt.run_arrays(flt.initial_state(), rows)
    ref = _reference(flt, rows, np.full(1000, DT), np.zeros(1000, bool))
    gaps = _gaps(result, *ref, filtered)
    print("ou regular", gaps)
    assert max(gaps) < 1e-8


def test_two_dimensional_partly_missing_equals_rts_of_the_exact_gaps():
    """2-D damped oscillator with affine terms, two correlated increments, irregular times, rows with one
    component missing and whole rows missing.  Asserted 1e-8."""
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OSCILLATOR)))
    rng = np.random.default_rng(31)
    K = 200
    taus = rng.uniform(0.01, 0.3, K)
    rows = rng.normal(0, 0.3, (K, 2)) * np.sqrt(taus)[:, None] + 0.1 * taus[:, None]
    rows[rng.random(K) < 0.1, 0] = np.nan
    rows[rng.random(K) < 0.1, 1] = np.nan
    rows[rng.random(K) < 0.05] = np.nan
    _, result = smooth(flt, flt.initial_state(), rows, np.cumsum(taus))
    _, filtered = flt.run_arrays(flt.initial_state(), rows, np.cumsum(taus))
    ref = _reference(flt, rows, taus, result.gated)
    gaps = _gaps(result, *ref, filtered)
    print("2-D", gaps)
    assert max(gaps) < 1e-8


def test_ou_within_the_issue_bounds_of_rts_on_the_sampled_model():
    """Issue 38's OU case: 1000 steps, smoothed mean within 0.01 and variance within 3% of RTS on the
    time-sampled model (they differ at O(dt): the sampled model updates with x_k alone)."""
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OU)))
    _, dy = sample_ou(1000, seed=3)
    _, result = smooth(flt, flt.initial_state(), dy[:, None])
    _, _, ms, Ps = rts_sampled(dy, 1.0, 0.5)
    mean_gap, var_gap = np.abs(result.mean[:, 0] - ms).max(), np.abs(result.cov[:, 0, 0] / Ps - 1).max()
    print(f"vs sampled RTS: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03


@pytest.mark.parametrize("lag", [1, 7])
def test_fixed_lag_equals_fixed_interval_where_the_window_reaches_the_end(lag):
    """smooth_lag over a chunk: the rows whose window reaches the end are the fixed-interval smoother's
    (1e-10), and row k is the fixed-interval smoother's first row over rows k … k + lag from the filter's
    state after row k − 1 (1e-12)."""
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OU)))
    _, dy = sample_ou(60, seed=9)
    rows = dy[:, None]
    _, whole = smooth(flt, flt.initial_state(), rows)
    _, lagged = smooth_lag(flt, flt.initial_state(), rows, lag=lag)
    tail = slice(60 - lag - 1, 60)
    assert np.abs(lagged.mean[tail] - whole.mean[tail]).max() < 1e-10
    state, _ = flt.run_arrays(flt.initial_state(), rows[:10])
    _, window = smooth(flt, state, rows[10:11 + lag])
    assert np.abs(lagged.mean[10] - window.mean[0]).max() < 1e-12
