"""Kalman–Bucy's Rauch–Tung–Striebel smoother (solver/exact/kalman_smoother.py) against an RTS smoother
written here, scalar, on the same discretised models (measured: 1e-15 .. 1e-13; asserted 1e-8)."""

from __future__ import annotations

import math

import numpy as np
from helpers.smoothing_refs import DT, THETA, A, R, rts_sampled, sample_ou
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.smoothing import smooth

OU = {"name": "ou", "state": ["x"], "drift": [f"-{THETA}*x"], "observation": ["x"],
      "diffusion": [[A]], "observation_noise": [[R]],
      "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]},
      "domain": {"radius": 6.0}, "discretization": {"dt": DT, "basis": 32}}


def test_sampled_model_equals_rts():
    """Continuous increments, the time-sampled model: 1000 rows."""
    _, dy = sample_ou(1000, seed=3)
    flt = KalmanBucyFilter(compile_model(spec_from_dict(OU)), kind="discrete")
    _, result = smooth(flt, flt.initial_state(), dy[:, None])
    _, _, ms, Ps = rts_sampled(dy, 1.0, 0.5)
    gaps = np.abs(result.mean[:, 0] - ms).max(), np.abs(result.cov[:, 0, 0] - Ps).max()
    print("sampled", gaps)
    assert max(gaps) < 1e-8


def test_discrete_readings_irregular_missing_equal_rts():
    """Discrete readings z = x + N(0, R) at irregular times, 5% missing, against a scalar RTS."""
    doc = dict(OU, measurement={"kind": "discrete"})
    flt = KalmanBucyFilter(compile_model(spec_from_dict(doc)))
    rng = np.random.default_rng(7)
    K = 300
    taus = rng.exponential(0.1, K) + 1e-3
    x, z = rng.normal(1.0, math.sqrt(0.5)), np.empty(K)
    for k, tau in enumerate(taus):
        phi = math.exp(-THETA * tau)
        x = phi * x + rng.normal(0, math.sqrt(A * (1 - phi * phi) / (2 * THETA)))
        z[k] = x + rng.normal(0, math.sqrt(R))
    z[rng.random(K) < 0.05] = np.nan
    _, result = smooth(flt, flt.initial_state(), z[:, None], np.cumsum(taus))
    # the scalar RTS with H τ = 1 and R τ = R: dy = z, taus as given
    _, _, ms, Ps = rts_sampled(z, 1.0, 0.5, taus=taus, r=R / taus, H=1 / taus)
    gaps = np.abs(result.mean[:, 0] - ms).max(), np.abs(result.cov[:, 0, 0] - Ps).max()
    print("discrete", gaps)
    assert max(gaps) < 1e-8

