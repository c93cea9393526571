"""The spec the fitting tests share: an Ornstein–Uhlenbeck rate θ read through x with discrete readings,
and its records simulated exactly (the OU transition over each gap)."""

import math

import numpy as np

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


# the x**2/2 sensor of an OU state, on the general engine (a nonlinear model: the grid reference's)
SQUARE = '''
name = "square-sensor-fit"
state = ["x"]
drift = ["-theta*x"]
observation = ["x**2/2"]
observation_noise = [[0.05]]
parameters = { theta = 0.6 }
method = "yau-yau"
[measurement]
kind = "discrete"
[initial]
kind = "gaussian"
mean = [1.0]
cov = [[0.25]]
[domain]
radius = 6.0
[discretization]
dt = 0.01
basis = 40
'''

def irregular_times(rng: np.random.Generator, K: int, dyadic: bool = False) -> np.ndarray:
    """K increasing times at random gaps of mean about 0.1: exponential, or with ``dyadic`` whole
    multiples of 1/16 (geometric counts, mean 1/0.6), exact in binary, so that the few distinct gaps hit
    the exact filters' per-gap caches (irregular rows at a fraction of the cost)."""
    if dyadic:
        return np.cumsum(rng.geometric(0.6, K)) / 16.0
    return np.cumsum(rng.exponential(0.1, K))


def ou_record(K: int, seed: int, theta: float = 1.0, r: float = 0.09, dyadic: bool = False):
    """K readings z = x + N(0, r) of dx = −θx dt + dv, x(0) ~ N(0, 1) (the spec's prior at t0 = 0), at
    :func:`irregular_times`: the exact OU transition over each gap.  Returns (z, t)."""
    rng = np.random.default_rng(seed)
    t = irregular_times(rng, K, dyadic)
    xs = ou_path(rng, t, theta, rng.normal(0.0, 1.0))
    return xs + rng.normal(0.0, math.sqrt(r), K), t


def ou_path(rng: np.random.Generator, t: np.ndarray, theta: float, x: float) -> np.ndarray:
    """x(t_k) of dx = −θx dt + dv from x(0) = ``x``: the exact OU transition over each gap."""
    prev, xs = 0.0, []
    for tk in t:
        a = math.exp(-theta * (tk - prev))
        x = a * x + rng.normal(0.0, math.sqrt((1 - a * a) / (2 * theta)))
        xs.append(x)
        prev = tk
    return np.array(xs)
