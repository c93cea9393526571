"""Continuous–discrete extended and unscented Kalman filters (Gaussian approximations).

Between observations the mean and covariance follow the moment ODEs of dx = f dt + G dv,

    EKF:  ṁ = f(m),        Ṗ = J_f(m) P + P J_f(m)ᵀ + a,
    UKF:  ṁ = E f(X),      Ṗ = E[(X − m) f(X)ᵀ + f(X)(X − m)ᵀ] + a   (X sigma points of N(m, P)),

integrated by classical RK4 with ``substeps`` steps per dt.  The update at τ_k treats
Δy = h(x) dt + v, v ~ N(0, R dt): linearised at m (EKF) or by the unscented transform (UKF).
On a linear model both reduce to the exact Kalman filter.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..gaussian import GaussianState
from ..model import Model
from ._base import GaussianReferenceFilter, advance, gaussian_update


def rk4_moments(derivative, mean: np.ndarray, cov: np.ndarray, dt: float, substeps: int):
    """Integrate (ṁ, Ṗ) = derivative(m, P) over dt with RK4."""
    delta = dt / substeps
    for _ in range(substeps):
        k1 = derivative(mean, cov)
        k2 = derivative(mean + 0.5 * delta * k1[0], cov + 0.5 * delta * k1[1])
        k3 = derivative(mean + 0.5 * delta * k2[0], cov + 0.5 * delta * k2[1])
        k4 = derivative(mean + delta * k3[0], cov + delta * k3[1])
        mean = mean + delta / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        cov = cov + delta / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        cov = 0.5 * (cov + cov.T)
    return mean, cov


class _GaussianFilter(GaussianReferenceFilter):
    def __init__(self, model: Model, substeps: int = 4):
        super().__init__(model)
        if not isinstance(substeps, (int, np.integer)) or substeps < 1:
            raise InputError("substeps", "must be an integer >= 1")
        self.substeps = int(substeps)

    def _moments_rate(self, mean: np.ndarray, cov: np.ndarray):
        raise NotImplementedError

    def _observation_moments(self, mean: np.ndarray, cov: np.ndarray):
        """(predicted Δy, its covariance S, cross covariance C of x and Δy)."""
        raise NotImplementedError

    def _advance(self, state: GaussianState, increment: np.ndarray | None) -> GaussianState:
        mean, cov = rk4_moments(self._moments_rate, state.mean, state.cov, self.model.dt, self.substeps)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            return advance(state, self.model.dt, 0.0, degenerate=True,
                           reason="the moment equations diverged")
        loglik = 0.0
        if increment is not None:
            try:
                moments = self._observation_moments(mean, cov)
                mean, cov, loglik = gaussian_update(self.model, mean, cov, *moments, increment)
            except np.linalg.LinAlgError:
                return advance(state, self.model.dt, 0.0, mean=mean, cov=cov, degenerate=True,
                               reason="the covariance lost positive definiteness")
        return advance(state, self.model.dt, loglik, mean=mean, cov=cov)


class ExtendedKalmanFilter(_GaussianFilter):
    method = "ekf"

    def _moments_rate(self, mean, cov):
        jac = self.model.jac_f(mean[None, :])[0]
        return self.model.f(mean[None, :])[0], jac @ cov + cov @ jac.T + self.model.a

    def _observation_moments(self, mean, cov):
        dt = self.model.dt
        Hd = self.model.jac_h(mean[None, :])[0] * dt
        return self.model.h(mean[None, :])[0] * dt, Hd @ cov @ Hd.T + self.model.R * dt, cov @ Hd.T


class UnscentedKalmanFilter(_GaussianFilter):
    """Sigma points m, m ± √(n+λ) L_i with α = 1, β = 0, κ = 3 − n (Julier's choice, λ = κ)."""

    method = "ukf"

    def __init__(self, model: Model, substeps: int = 4):
        super().__init__(model, substeps)
        n = model.n
        self._scale = np.sqrt(3.0)  # √(n + λ) with λ = 3 − n
        self._weights = np.concatenate([[(3.0 - n) / 3.0], np.full(2 * n, 1.0 / 6.0)])

    def sigma_points(self, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
        chol = np.linalg.cholesky(cov)
        offsets = self._scale * chol.T  # rows: scaled columns of L
        return np.vstack([mean, mean + offsets, mean - offsets])

    def _moments_rate(self, mean, cov):
        X = self.sigma_points(mean, cov)
        F = self.model.f(X)
        w = self._weights
        d = X - mean
        cross = (d * w[:, None]).T @ F
        return w @ F, cross + cross.T + self.model.a

    def _observation_moments(self, mean, cov):
        X = self.sigma_points(mean, cov)
        Y = self.model.h(X) * self.model.dt
        w = self._weights
        predicted = w @ Y
        dY = Y - predicted
        innovation = (dY * w[:, None]).T @ dY + self.model.R * self.model.dt
        return predicted, innovation, ((X - mean) * w[:, None]).T @ dY
