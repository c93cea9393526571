"""The Kalman–Bucy filter for linear models f = F x + f0, h = H x + h0 (method "kalman-bucy").

Continuous kind (default): between observation times the observation path is taken linear,
ẏ = Δy_k/dt, and the robust DMZ equation

    ∂σ/∂t = ½Σa_ij∂i∂jσ − div(fσ) − ½hᵀR⁻¹h σ + hᵀR⁻¹ẏ σ

is solved exactly over dt.  It is the Kolmogorov equation of solver/exact/riccati.py with
D = F, d = f0, Q = ½HᵀR⁻¹H, q = HᵀR⁻¹(h0 − ẏ), r = ½h0ᵀR⁻¹h0 − h0ᵀR⁻¹ẏ, so a Gaussian σ stays
Gaussian and its mean and covariance follow the Kalman–Bucy equations

    dm = (F m + f0) dt + P HᵀR⁻¹ (dy − (H m + h0) dt),   dP = (FP + PFᵀ + a − PHᵀR⁻¹HP) dt,

integrated exactly (matrix exponentials of the Hamiltonian matrix, see GaussianFlow).

Discrete kind (kind="discrete"): the exact Kalman filter of the sampled model
x_k = e^{F dt} x_{k−1} + w_k, w_k ~ N(0, ∫0^dt e^{Fs} a e^{Fᵀs} ds), Δy_k = H x_k dt + h0 dt + N(0, R dt)
(solver.reference.DiscreteKalmanFilter, shared rather than duplicated).

Log-likelihood convention: the log of the ratio of the normalisers ∫σ, i.e. the density of the
observations relative to the Brownian reference measure (Δy ~ N(0, R dt)); it is the quantity
log ∫σ the Yau–Yau engine accumulates, so the two are comparable.  A NaN row only predicts
(log-likelihood increment 0).
"""

from __future__ import annotations

import numpy as np

from ..errors import SpecError
from ..model import Model
from ..reference._base import GaussianReferenceFilter, GaussianState, advance
from ..reference.kalman import DiscreteKalmanFilter, affine_coefficients
from .riccati import GaussianKolmogorov, gaussian_to_terms, terms_to_gaussian

KINDS = ("continuous", "discrete")


class KalmanBucyFilter(GaussianReferenceFilter):
    """Filter protocol implementation; state: mean, cov and the accumulated log-likelihood."""

    method = "kalman-bucy"

    def __init__(self, model: Model, kind: str = "continuous"):
        if kind not in KINDS:
            raise SpecError("kind", f"must be one of {KINDS}, got {kind!r}")
        super().__init__(model)
        self.kind = kind
        self.F, self.f0 = affine_coefficients(model.drift, model.symbols, "drift")
        self.H, self.h0 = affine_coefficients(model.observation, model.symbols, "observation")
        HtR = self.H.T @ model.R_inv
        self._HtR = HtR
        self._observed = GaussianKolmogorov(self.F, self.f0, Q=0.5 * HtR @ self.H, a=model.a).flow(model.dt)
        self._predicted = GaussianKolmogorov(self.F, self.f0, a=model.a).flow(model.dt)
        self._discrete = DiscreteKalmanFilter(model) if kind == "discrete" else None

    def potential_terms(self, increment: np.ndarray) -> tuple[np.ndarray, float]:
        """(q, r) of the observation potential ½hᵀR⁻¹h − hᵀR⁻¹ẏ for ẏ = Δy/dt."""
        ydot = increment / self.model.dt
        R_inv = self.model.R_inv
        q = self._HtR @ (self.h0 - ydot)
        r = 0.5 * self.h0 @ R_inv @ self.h0 - self.h0 @ R_inv @ ydot
        return q, float(r)

    def _advance(self, state: GaussianState, increment: np.ndarray | None) -> GaussianState:
        if self._discrete is not None:
            return self._discrete._advance(state, increment)
        terms = gaussian_to_terms(state.mean, state.cov)  # unit mass: the new log mass is log Z ratio
        if increment is None:
            new = self._predicted.step(terms.A, terms.B, terms.C)
        else:
            q, r = self.potential_terms(increment)
            new = self._observed.step(terms.A, terms.B, terms.C, q=q, r=r)
        mean, cov, log_ratio = terms_to_gaussian(new.A, new.B, new.C)
        return advance(state, self.model.dt, 0.0 if increment is None else log_ratio, mean=mean, cov=cov)
