"""yauyau.fit (solver/fitting.py, issue 39) against independent truth: the exact Kalman
maximum-likelihood estimate of an OU rate (the test's own recursion and scipy), a point-mass grid
likelihood of a nonlinear model, and bad input naming the field."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers.fit_specs import OU, SQUARE, ou_path, ou_record
from scipy.optimize import minimize_scalar
from yauyau.solver.errors import InputError

import yauyau


def kalman_loglik(theta: float, z: np.ndarray, t: np.ndarray, r: float = 0.09) -> float:
    """The exact log-likelihood of discrete readings of dx = -θx dt + dv, prior N(0, 1) at t = 0."""
    m, p, prev, total = 0.0, 1.0, 0.0, 0.0
    for zk, tk in zip(z, t, strict=True):
        a = math.exp(-theta * (tk - prev))
        m, p = a * m, a * a * p + (1 - a * a) / (2 * theta)
        s = p + r
        total += -0.5 * (math.log(2 * math.pi * s) + (zk - m) ** 2 / s)
        k = p / s
        m, p = m + k * (zk - m), (1 - k) * p
        prev = tk
    return total


def exact_mle(z, t, lo=0.05, hi=5.0):
    found = minimize_scalar(lambda th: -kalman_loglik(th, z, t), bounds=(lo, hi), method="bounded",
                            options={"xatol": 1e-7})
    th = found.x
    h = 1e-3 * th
    curv = (kalman_loglik(th + h, z, t) - 2 * kalman_loglik(th, z, t) + kalman_loglik(th - h, z, t)) / h**2
    return th, 1 / math.sqrt(-curv)


def check_ou(K: int, seed: int):
    spec = yauyau.parse_spec_text(OU, "toml")
    z, t = ou_record(K, seed)
    theta, se = exact_mle(z, t)
    found = yauyau.fit(spec, z[:, None], t, free={"theta": (0.05, 5.0)})
    assert found.converged, found.reason
    assert found.method == "kalman-bucy"
    assert abs(found.estimates["theta"] - theta) < 0.25 * se, (found.estimates, theta, se)
    assert 0.5 < found.stderr["theta"] / se < 2.0, (found.stderr, se)
    assert abs(found.loglik - kalman_loglik(theta, z, t)) < 1e-3 * abs(found.loglik)
    return found, theta, se


def test_ou_rate_from_1000_irregular_readings_is_the_exact_kalman_mle():
    check_ou(1000, 3)


def test_ou_rate_from_300_irregular_readings_is_the_exact_kalman_mle():
    check_ou(300, 4)


def test_bad_input_names_the_field():
    spec = yauyau.parse_spec_text(OU, "toml")
    z, t = ou_record(50, 1)
    cases = [({"nope": (0.1, 1.0)}, "free.nope"),
             ({"theta": (1.0, 0.1)}, "free.theta"),
             ({"theta": (0.6, 2.0)}, "free.theta"),  # the start 0.5 is outside
             ({"observation_noise[0][0]": (-1.0, 1.0)}, "free.observation_noise[0][0]"),
             ({"diffusion[0][1]": (0.1, 1.0)}, "free.diffusion[0][1]")]
    for free, field in cases:
        with pytest.raises(InputError) as err:
            yauyau.fit(spec, z[:, None], t, free=free)
        assert err.value.field == field
    # continuous increments: the quadratic variation fixes R, the likelihood is unbounded as R → 0
    doc = spec.model_dump(mode="json")
    doc["measurement"] = {"kind": "continuous"}
    continuous = yauyau.parse_spec_text(json.dumps(doc), "json")
    with pytest.raises(InputError) as err:
        yauyau.fit(continuous, 0.1 * z[:, None], t, free={"observation_noise[0][0]": (0.01, 1.0)})
    assert err.value.field == "free.observation_noise[0][0]" and "Σ dy² / T" in err.value.message
    with pytest.raises(InputError) as err:
        yauyau.fit(spec, z[:2, None], t[:2], free={"theta": (0.1, 1.0)})
    assert err.value.field == "rows"


def grid_loglik(theta: float, z: np.ndarray, t: np.ndarray, r: float = 0.05, half: float = 6.0,
                points: int = 241) -> float:
    """A point-mass likelihood: the grid's Markov chain (upwind rates of drift -θx, diffusion 1) carries
    the prior between readings (scipy.sparse.linalg.expm_multiply), each reading weighs the masses."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import expm_multiply

    x = np.linspace(-half, half, points)
    h = x[1] - x[0]
    f = -theta * x
    up = np.maximum(f, 0) / h + 0.5 / h**2
    down = np.maximum(-f, 0) / h + 0.5 / h**2
    up[-1] = down[0] = 0.0
    Q = diags([-(up + down), up[:-1], down[1:]], [0, 1, -1]).tocsc()  # rows: from, columns: to
    A = Q.T.tocsc()
    p = np.exp(-0.5 * (x - 1.0) ** 2 / 0.25)
    p /= p.sum()
    prev, total = 0.0, 0.0
    for zk, tk in zip(z, t, strict=True):
        p = np.maximum(expm_multiply(A * (tk - prev), p), 0.0)
        w = p * np.exp(-0.5 * (zk - x**2 / 2) ** 2 / r) / math.sqrt(2 * math.pi * r)
        total += math.log(w.sum())
        p = w / w.sum()
        prev = tk
    return total


def test_square_sensor_drift_rate_is_the_grid_likelihood_maximiser():
    spec = yauyau.parse_spec_text(SQUARE, "toml")
    rng = np.random.default_rng(7)
    K, theta = 300, 1.0
    t = np.cumsum(rng.exponential(0.1, K))
    xs = ou_path(rng, t, theta, rng.normal(1.0, 0.5))
    z = xs**2 / 2 + rng.normal(0.0, math.sqrt(0.05), K)
    ref = minimize_scalar(lambda th: -grid_loglik(th, z, t), bounds=(0.2, 3.0), method="bounded",
                          options={"xatol": 1e-4}).x
    found = yauyau.fit(spec, z[:, None], t, free={"theta": (0.2, 3.0)})
    assert found.converged, found.reason
    assert found.method == "yau-yau"
    assert abs(found.estimates["theta"] - ref) < 0.02 + 0.05 * ref, (found.estimates, ref)
    assert math.isfinite(found.stderr["theta"]) and found.stderr["theta"] > 0


def test_offline_stage_is_keyed_by_what_it_depends_on():
    """A name entering only h, the observation noise or the prior keeps the offline stage's content hash
    (reused, no precompute); one entering the drift or the diffusion changes it (recomputed)."""
    from yauyau.solver.fitting import offline_key, with_values

    spec = yauyau.parse_spec_text(SQUARE.replace("parameters = { theta = 0.6 }",
                                                 "parameters = { theta = 0.6, c = 0.5 }")
                                  .replace('["x**2/2"]', '["c*x**2"]'), "toml")
    key = offline_key(spec)
    assert offline_key(with_values(spec, {"c": 0.7})) == key
    assert offline_key(with_values(spec, {"observation_noise[0][0]": 0.2})) == key
    assert offline_key(with_values(spec, {"theta": 0.7})) != key
    assert offline_key(with_values(spec, {"diffusion[0][0]": 2.0})) != key


def test_profile_peaks_at_the_estimate():
    spec = yauyau.parse_spec_text(OU, "toml")
    z, t = ou_record(300, 4)
    found = yauyau.fit(spec, z[:, None], t, free={"theta": (0.05, 2.0)}, profile="theta")
    grid, ll = np.array(found.profile["grid"]), np.array(found.profile["loglik"])
    assert np.all(ll <= found.loglik + 1e-9)
    assert abs(grid[np.argmax(ll)] - found.estimates["theta"]) <= grid[1] - grid[0]


def test_a_likelihood_not_finite_in_the_box_is_reported_not_optimised(monkeypatch):
    """Where the record's log-likelihood is NaN (here: made so on 0.54 < θ < 0.57, around the
    maximum, where the optimiser or the Hessian's steps go), the fit stops with
    converged False and the reason naming the values, instead of optimising through it."""
    import dataclasses

    from yauyau.solver import methods

    real = methods.make_filter

    def broken(model, offline=None, method=None, **kw):
        flt = real(model, offline, method, **kw)
        if not 0.54 < model.spec.parameters["theta"] < 0.57:
            return flt
        run = flt.run_arrays

        def nan_run(state, rows, times=None):
            state, result = run(state, rows, times)
            return state, dataclasses.replace(result, loglik=np.full_like(result.loglik, np.nan))
        flt.run_arrays = nan_run
        return flt

    monkeypatch.setattr(methods, "make_filter", broken)
    spec = yauyau.parse_spec_text(OU, "toml")
    z, t = ou_record(300, 4)  # its maximum is near 0.553
    found = yauyau.fit(spec, z[:, None], t, free={"theta": (0.05, 5.0)})
    assert not found.converged
    assert "not finite" in found.reason and "theta" in found.reason
