"""yauyau.fit (solver/fitting.py, issue 39) against independent truth: the exact Kalman
maximum-likelihood estimate of an OU rate (the test's own recursion and scipy), a point-mass grid
likelihood of a nonlinear model, and bad input naming the field."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from yauyau.solver.errors import InputError

import yauyau

OU = '''
name = "ou-fit"
state = ["x"]
drift = ["-theta*x"]
observation = ["x"]
observation_noise = [[0.09]]
parameters = { theta = 0.5 }
[measurement]
kind = "discrete"
[initial]
kind = "gaussian"
mean = [0.0]
cov = [[1.0]]
[domain]
radius = 8.0
[discretization]
dt = 0.01
basis = 32
'''


def ou_record(K: int, seed: int, theta: float = 1.0, r: float = 0.09):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.exponential(0.1, K))
    x, prev, xs = rng.normal(0.0, 1.0), 0.0, []
    for tk in t:
        a = math.exp(-theta * (tk - prev))
        x = a * x + rng.normal(0.0, math.sqrt((1 - a * a) / (2 * theta)))
        xs.append(x)
        prev = tk
    return np.array(xs) + rng.normal(0.0, math.sqrt(r), K), t


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


@pytest.mark.slow
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
    with pytest.raises(InputError) as err:
        yauyau.fit(spec, z[:2, None], t[:2], free={"theta": (0.1, 1.0)})
    assert err.value.field == "rows"
