"""Bootstrap particle filter: the signal by Euler–Maruyama, weights by the update factor.

Particles move by x ← x + f(x) δ + a^{1/2} √δ ξ over ``substeps`` substeps of dt; the log
weights gain hᵀR⁻¹Δy − ½hᵀR⁻¹h dt (the engine's update, in log scale) and the log
normaliser ratio log Σ w_i e^{…} is the step's log-likelihood.  Systematic resampling when the
effective sample size 1/Σw² falls below N/2.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ..filtering import Estimate
from ..model import Model
from ..simulate import noise_factor, sample_prior
from ._base import ReferenceFilter, StepState, advance, log_sum_exp, log_update_factor


@dataclass(frozen=True)
class ParticleState(StepState):
    particles: np.ndarray = field(default_factory=lambda: np.zeros((0, 1)))
    log_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))  # normalised: logsumexp = 0

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["particles"] = self.particles.tolist()
        out["log_weights"] = self.log_weights.tolist()
        return out


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of N particles by systematic resampling of normalised ``weights``."""
    count = len(weights)
    positions = (rng.uniform() + np.arange(count)) / count
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right").clip(0, count - 1)


class BootstrapParticleFilter(ReferenceFilter):
    method = "particle"

    def __init__(self, model: Model, n_particles: int, rng: np.random.Generator, substeps: int = 10):
        super().__init__(model)
        if not isinstance(n_particles, (int, np.integer)) or n_particles < 2:
            raise InputError("n_particles", "must be an integer >= 2")
        if not isinstance(substeps, (int, np.integer)) or substeps < 1:
            raise InputError("substeps", "must be an integer >= 1")
        self.n_particles = int(n_particles)
        self.rng = rng
        self.substeps = int(substeps)
        self._chol_a = noise_factor(model.a)

    def initial_state(self, prior: Any | None = None) -> ParticleState:
        if prior is not None:
            raise InputError("prior", "the particle filter samples the model's prior")
        particles = sample_prior(self.model, self.n_particles, self.rng)
        uniform = np.full(self.n_particles, -np.log(self.n_particles))
        return ParticleState(particles=particles, log_weights=uniform)

    def propagate(self, particles: np.ndarray) -> np.ndarray:
        delta = self.model.dt / self.substeps
        x = particles
        for _ in range(self.substeps):
            noise = self.rng.standard_normal(x.shape) @ self._chol_a.T
            x = x + self.model.f(x) * delta + np.sqrt(delta) * noise
        return x

    def _advance(self, state: ParticleState, increment: np.ndarray | None) -> ParticleState:
        x = self.propagate(state.particles)
        log_w = state.log_weights
        loglik = 0.0
        if increment is not None:
            log_w = log_w + log_update_factor(self.model, x, increment)
            loglik = log_sum_exp(log_w)
            if not np.isfinite(loglik):
                return advance(state, self.model.dt, 0.0, particles=x, degenerate=True,
                               reason="every particle weight vanished")
            log_w = log_w - loglik
        weights = np.exp(log_w)
        if 1.0 / np.sum(weights**2) < self.n_particles / 2:
            x = x[systematic_resample(weights, self.rng)]
            log_w = np.full(self.n_particles, -np.log(self.n_particles))
        return advance(state, self.model.dt, loglik, particles=x, log_weights=log_w)

    def estimate(self, state: ParticleState) -> Estimate:
        w = np.exp(state.log_weights)
        mean = w @ state.particles
        d = state.particles - mean
        cov = (d * w[:, None]).T @ d
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=state.loglik_increment, degenerate=state.degenerate,
                        reason=state.reason)

    def density(self, state: ParticleState, points: np.ndarray) -> np.ndarray:
        """Weighted Gaussian kernel density estimate (Silverman's bandwidth)."""
        points = np.atleast_2d(np.asarray(points, float))
        w = np.exp(state.log_weights)
        n = self.model.n
        n_eff = 1.0 / np.sum(w**2)
        cov = np.atleast_2d(self.estimate(state).cov) * (4.0 / ((n + 2) * n_eff)) ** (2.0 / (n + 4))
        chol = np.linalg.cholesky(cov + 1e-12 * np.eye(n))
        z = np.linalg.solve(chol, (points[:, None, :] - state.particles[None, :, :]).reshape(-1, n).T)
        kernel = np.exp(-0.5 * (z * z).sum(axis=0)).reshape(len(points), -1)
        norm = (2 * np.pi) ** (n / 2) * np.prod(np.diag(chol))
        return kernel @ w / norm
