"""Simulated truth for the filters: sample paths of the signal and the observation increments.

    dx = f(x) dt + G dv,   dy = h(x) dt + dw,   a = G Q Gᵀ,  E[dw dwᵀ] = R dt,

by Euler–Maruyama with ``substeps`` steps of length δ = dt/substeps inside each observation
interval: x ← x + f(x) δ + a^{1/2} √δ ξ, and Δy_k = Σ h(x) δ + R^{1/2} √dt ζ_k over
[τ_{k−1}, τ_k] (left-point rule, Itô).  The initial state is drawn from the model's prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .model import Model
from .spec import GaussianPrior, MixturePrior

_GRID_CELLS = {1: 20000, 2: 400, 3: 80}  # cells per axis for sampling a density prior


@dataclass(frozen=True)
class Simulation:
    """One simulated path: ``times`` (K+1,), ``states`` (K+1, n), ``increments`` (K, m)."""

    times: np.ndarray
    states: np.ndarray
    increments: np.ndarray


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
    width = 2.0 * model.radius / cells
    axis = -model.radius + width * (np.arange(cells) + 0.5)
    grids = np.meshgrid(*([axis] * n), indexing="ij")
    offsets = np.stack([g.ravel() for g in grids], axis=1)
    points = model.center + offsets
    log_p = model.log_prior(points)
    log_p[np.linalg.norm(offsets, axis=1) > model.radius] = -np.inf
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
                   paths: int = 1) -> Simulation:
    """``paths`` independent paths at once: states (paths, K+1, n), increments (paths, K, m)."""
    _check_counts(steps, substeps, paths)
    dt = model.dt
    delta = dt / substeps
    chol_a = noise_factor(model.a)
    chol_r = np.linalg.cholesky(model.R)
    x = sample_prior(model, paths, rng)
    states = np.empty((paths, steps + 1, model.n))
    increments = np.empty((paths, steps, model.m))
    states[:, 0] = x
    for k in range(steps):
        integral = np.zeros((paths, model.m))
        for _ in range(substeps):
            integral += model.h(x) * delta  # left point: Itô
            x = x + model.f(x) * delta + np.sqrt(delta) * rng.standard_normal((paths, model.n)) @ chol_a.T
        states[:, k + 1] = x
        increments[:, k] = integral + np.sqrt(dt) * rng.standard_normal((paths, model.m)) @ chol_r.T
    if not (np.all(np.isfinite(states)) and np.all(np.isfinite(increments))):
        raise InputError("steps", "the simulated path left the floating-point range (explosive drift?)")
    times = dt * np.arange(steps + 1)
    return Simulation(times=times, states=states, increments=increments)


def simulate(model: Model, steps: int, rng: np.random.Generator, substeps: int = 10) -> Simulation:
    """One path of K = ``steps`` observation intervals of length ``model.dt``."""
    batch = simulate_paths(model, steps, rng, substeps=substeps, paths=1)
    return Simulation(times=batch.times, states=batch.states[0], increments=batch.increments[0])
