"""Simulated truth for the filters: sample paths of the signal and its observations.

    dx = f(x) dt + G dv,   a = G Q Gᵀ,

by Euler–Maruyama with ``substeps`` steps of length δ = dt/substeps per observation interval
(irregular ``times``: each gap τ_k in ⌈τ_k/δ⌉ equal steps): x ← x + f(x) δ + a^{1/2} √δ ξ.  The
observations are those of the spec's ``[measurement]``:

* continuous: Δy_k = Σ h(x) δ + R^{1/2} √τ_k ζ_k over [t_(k−1), t_k] (left-point rule, Itô);
* discrete: z_k = h(x(t_k)) + v_k, v_k ~ N(0, R), or R^{1/2} ζ √(ν/χ²_ν) for a Student-t sensor.

The initial state is drawn from the model's prior at t = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .model import Model
from .spec import GaussianPrior, MixturePrior

_GRID_CELLS = {1: 20000, 2: 400, 3: 80}  # cells per axis for sampling a density prior


@dataclass(frozen=True)
class Simulation:
    """One simulated path: ``times`` (K+1,) from t = 0, ``states`` (K+1, n) and the rows the filter
    reads (K, m): ``increments`` (continuous kind) or ``observations`` (discrete kind); ``rows`` is
    whichever the model has."""

    times: np.ndarray
    states: np.ndarray
    increments: np.ndarray | None = None
    observations: np.ndarray | None = None

    @property
    def rows(self) -> np.ndarray:
        return self.increments if self.observations is None else self.observations


def _check_counts(steps: int, substeps: int, paths: int) -> None:
    for name, value, low in (("steps", steps, 1), ("substeps", substeps, 1), ("paths", paths, 1)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise InputError(name, f"must be an integer >= {low}")


def sample_prior(model: Model, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` draws (count, n) from the model's prior (gaussian, mixture or density)."""
    prior = model.spec.initial
    if isinstance(prior, GaussianPrior):
        return _sample_gaussian(np.asarray(prior.mean, float), np.asarray(prior.cov, float), count, rng)
    if isinstance(prior, MixturePrior):
        w = np.asarray(prior.weights, float) / np.sum(prior.weights)
        which = rng.choice(len(w), size=count, p=w)
        out = np.empty((count, model.n))
        for k in range(len(w)):
            sel = which == k
            out[sel] = _sample_gaussian(np.asarray(prior.means[k], float),
                                        np.asarray(prior.covs[k], float), int(sel.sum()), rng)
        return out
    return _sample_density_on_grid(model, count, rng)


def _sample_gaussian(mean: np.ndarray, cov: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    chol = np.linalg.cholesky(cov)
    return mean + rng.standard_normal((count, len(mean))) @ chol.T


def _sample_density_on_grid(model: Model, count: int, rng: np.random.Generator) -> np.ndarray:
    """Inverse CDF of the prior tabulated on cells of the ball's bounding box, uniform within a cell.

    In 1-D this is the inverse-CDF method on a fine grid; in 2-D/3-D the same idea over the
    flattened cells (a piecewise-constant approximation of the density, cells outside the ball
    get probability zero).
    """
    n, cells = model.n, _GRID_CELLS[model.n]
    half = model.half_widths  # the box around the domain (an ellipsoid's too)
    width = 2.0 * half / cells
    grids = np.meshgrid(*[-half[i] + width[i] * (np.arange(cells) + 0.5) for i in range(n)], indexing="ij")
    offsets = np.stack([g.ravel() for g in grids], axis=1)
    points = model.center + offsets
    log_p = model.log_prior(points)
    log_p[model.ball_distance(offsets) > model.radius] = -np.inf
    top = np.max(log_p)
    p = np.exp(log_p - top)
    cdf = np.cumsum(p)
    cdf /= cdf[-1]
    idx = np.searchsorted(cdf, rng.uniform(size=count), side="right").clip(0, len(cdf) - 1)
    return points[idx] + width * (rng.uniform(size=(count, n)) - 0.5)


def noise_factor(a: np.ndarray) -> np.ndarray:
    """G with GGᵀ = a: the Cholesky factor, or for a semi-definite a (noise on some coordinates only)
    the symmetric square root U√ΛUᵀ."""
    try:
        return np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        lam, U = np.linalg.eigh(a)
        return U * np.sqrt(np.clip(lam, 0.0, None))


def simulate_paths(model: Model, steps: int, rng: np.random.Generator, substeps: int = 10,
                   paths: int = 1, times: np.ndarray | None = None) -> Simulation:
    """``paths`` independent paths at once: states (paths, K+1, n), rows (paths, K, m); at ``times``
    (K,) (strictly increasing, > 0) if given, else every dt."""
    _check_counts(steps, substeps, paths)
    dt = model.dt
    delta = dt / substeps
    gaps = np.full(steps, dt) if times is None else _gaps(times, steps)
    chol_a = noise_factor(model.a)
    chol_r = np.linalg.cholesky(model.R)
    measurement = model.spec.measurement
    discrete = measurement.kind == "discrete"
    x = sample_prior(model, paths, rng)
    states = np.empty((paths, steps + 1, model.n))
    rows = np.empty((paths, steps, model.m))
    states[:, 0] = x
    for k, gap in enumerate(gaps.tolist()):
        count = substeps if times is None else max(1, int(math.ceil(gap / delta - 1e-9)))
        small = gap / count
        integral = np.zeros((paths, model.m))
        for _ in range(count):
            if not discrete:
                integral += model.h(x) * small  # left point: Itô
            x = x + model.f(x) * small + np.sqrt(small) * rng.standard_normal((paths, model.n)) @ chol_a.T
        states[:, k + 1] = x
        if not discrete:
            rows[:, k] = integral + np.sqrt(gap) * rng.standard_normal((paths, model.m)) @ chol_r.T
            continue
        noise = rng.standard_normal((paths, model.m)) @ chol_r.T
        if measurement.likelihood == "student-t":
            scale = np.sqrt(measurement.dof / rng.chisquare(measurement.dof, (paths, 1)))
            rows[:, k] = model.h(x) + noise * scale
        else:
            rows[:, k] = model.h(x) + noise
    if not (np.all(np.isfinite(states)) and np.all(np.isfinite(rows))):
        raise InputError("steps", "the simulated path left the floating-point range (explosive drift?)")
    t = np.concatenate([[0.0], dt * np.arange(1, steps + 1) if times is None else np.cumsum(gaps)])
    if discrete:
        return Simulation(times=t, states=states, observations=rows)
    return Simulation(times=t, states=states, increments=rows)


def _gaps(times, steps: int) -> np.ndarray:
    t = np.asarray(times, dtype=float).reshape(-1)
    if len(t) != steps:
        raise InputError("times", f"needs {steps} time(s), one per step, got {len(t)}")
    if not np.all(np.isfinite(t)):
        raise InputError("times", "must be finite")
    gaps = np.diff(t, prepend=0.0)
    if np.any(gaps <= 0):
        row = int(np.argmax(gaps <= 0))
        raise InputError(f"times[{row}]", "times must start after 0 and increase strictly")
    from .measurement import resolve_times

    resolve_times(0.0, True, steps, 0.0, t)  # each gap keeps its precision (the filters refuse others)
    return gaps


def random_times(steps: int, mean_gap: float, rng: np.random.Generator) -> np.ndarray:
    """Irregular times from 0: exponential gaps of mean ``mean_gap`` (a Poisson stream of readings)."""
    _check_counts(steps, 1, 1)
    if not (math.isfinite(mean_gap) and mean_gap > 0):
        raise InputError("mean_gap", "must be a positive number")
    return np.cumsum(np.maximum(rng.exponential(mean_gap, steps), 1e-9 * mean_gap))


def simulate(model: Model, steps: int, rng: np.random.Generator, substeps: int = 10,
             times: np.ndarray | None = None) -> Simulation:
    """One path of K = ``steps`` observations, every ``model.dt`` or at ``times``."""
    batch = simulate_paths(model, steps, rng, substeps=substeps, paths=1, times=times)
    first = (lambda a: None if a is None else a[0])
    return Simulation(times=batch.times, states=batch.states[0], increments=first(batch.increments),
                      observations=first(batch.observations))
