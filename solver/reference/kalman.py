"""Exact Kalman filter of the time-sampled linear model (the oracle of the Yau–Yau engine).

For f(x) = F x + f0 and h(x) = H x + h0 the Fokker–Planck flow over dt maps N(m, P) to
N(e^{F dt} m + Γ f0, e^{F dt} P e^{Fᵀ dt} + Q_d) with Γ = ∫0^dt e^{Fs} ds and
Q_d = ∫0^dt e^{Fs} a e^{Fᵀs} ds (Van Loan's block exponentials), and the update by
exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt) is the Kalman update for Δy = H x dt + h0 dt + v, v ~ N(0, R dt).
Both are exact, so this is the time discretisation the engine approximates, without space error.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from ..expressions import affine_coefficients
from ..gaussian import GaussianState
from ..model import Model
from ._base import GaussianReferenceFilter, advance, gaussian_update


def van_loan(F: np.ndarray, a: np.ndarray, f0: np.ndarray, dt: float):
    """(Φ, Γ f0, Q_d): e^{F dt}, ∫0^dt e^{Fs} ds f0 and ∫0^dt e^{Fs} a e^{Fᵀs} ds."""
    n = F.shape[0]
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n] = -F
    block[:n, n:] = a
    block[n:, n:] = F.T
    E = expm(block * dt)
    phi = E[n:, n:].T
    q = phi @ E[:n, n:]
    aug = np.zeros((n + 1, n + 1))
    aug[:n, :n] = F
    aug[:n, n] = f0
    shift = expm(aug * dt)[:n, n]
    return phi, shift, 0.5 * (q + q.T)


class DiscreteKalmanFilter(GaussianReferenceFilter):
    """Exact filter of the sampled linear model: FP flow over dt, then the update at τ_k."""

    method = "kalman-discrete"

    def __init__(self, model: Model):
        super().__init__(model)
        self.F, self.f0 = affine_coefficients(model.drift, model.symbols, "drift")
        self.H, self.h0 = affine_coefficients(model.observation, model.symbols, "observation")
        self.phi, self.shift, self.Q = van_loan(self.F, model.a, self.f0, model.dt)

    def predict(self, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.phi @ mean + self.shift, self.phi @ cov @ self.phi.T + self.Q

    def _advance(self, state: GaussianState, increment: np.ndarray | None) -> GaussianState:
        mean, cov = self.predict(state.mean, state.cov)
        loglik = 0.0
        if increment is not None:
            dt = self.model.dt
            Hd = self.H * dt
            predicted = Hd @ mean + self.h0 * dt
            innovation = Hd @ cov @ Hd.T + self.model.R * dt
            mean, cov, loglik = gaussian_update(self.model, mean, cov, predicted, innovation, cov @ Hd.T,
                                                increment)
        return advance(state, self.model.dt, loglik, mean=mean, cov=cov)
