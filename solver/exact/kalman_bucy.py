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
(the matrices of solver.reference.DiscreteKalmanFilter, shared rather than duplicated).

A chunk is filtered in three passes, because the covariance does not depend on the data:
the covariance path (sequential, scalar loop for n = 1), then the mean as the affine recursion
m_k = W_k m_{k−1} + v_k (W, v batched; one scalar loop), then estimates and log-likelihoods
batched.  ``run_arrays`` returns the arrays (as the engine's); ``run``/``step`` wrap it.

Log-likelihood convention: the log of the ratio of the normalisers ∫σ, i.e. the density of the
observations relative to the Brownian reference measure (Δy ~ N(0, R dt)); it is the quantity
log ∫σ the Yau–Yau engine accumulates, so the two are comparable.  A NaN row only predicts
(log-likelihood increment 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..engine import ChunkResult
from ..errors import SpecError
from ..filtering import Estimate, check_increments
from ..model import Model
from ..reference._base import GaussianReferenceFilter, GaussianState, observed
from ..reference.kalman import DiscreteKalmanFilter, affine_coefficients
from .riccati import (
    FlowFamily,
    GaussianKolmogorov,
    affine_path,
    gaussian_terms_batch,
    gaussian_to_terms,
)

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
        self._HtR = self.H.T @ model.R_inv
        observed_eq = GaussianKolmogorov(self.F, self.f0, Q=0.5 * self._HtR @ self.H, a=model.a)
        predicted_eq = GaussianKolmogorov(self.F, self.f0, a=model.a)
        self._flows = FlowFamily([observed_eq.flow(model.dt), predicted_eq.flow(model.dt)])
        self._discrete = DiscreteKalmanFilter(model) if kind == "discrete" else None

    def potential_terms(self, increment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q, r) of the observation potential ½hᵀR⁻¹h − hᵀR⁻¹ẏ for ẏ = Δy/dt; rows for (K, m)."""
        ydot = np.asarray(increment, dtype=float) / self.model.dt
        R_inv = self.model.R_inv
        q = (self.h0 - ydot) @ self._HtR.T
        r = 0.5 * self.h0 @ R_inv @ self.h0 - ydot @ (R_inv @ self.h0)
        return q, r

    # -- Filter protocol -----------------------------------------------------------------
    def step(self, state: GaussianState, increment: np.ndarray | None):
        row = observed(increment, self.model.m)
        rows = np.full((1, self.model.m), np.nan) if row is None else row[None]
        new_state, estimates = self.run(state, rows)
        return new_state, estimates[0]

    def run(self, state: GaussianState, increments: np.ndarray):
        new_state, result = self.run_arrays(state, increments)
        return new_state, result.estimates()

    def run_arrays(self, state: GaussianState, increments: np.ndarray) -> tuple[GaussianState, "ExactChunk"]:
        """Advance over a chunk (K, m) of increments (NaN rows: prediction only); estimates as arrays."""
        dy = check_increments(increments, self.model.m)
        K, n = len(dy), self.model.n
        steps = state.step + 1 + np.arange(K)
        if K == 0:
            empty = np.empty((0, n))
            return state, ExactChunk(steps, steps * 1.0, empty, np.empty((0, n, n)), empty, np.empty(0),
                                      np.empty(0), np.zeros(0, bool))
        missing = np.isnan(dy[:, 0])
        dy = np.where(missing[:, None], 0.0, dy)
        chunk = self._discrete_chunk if self._discrete is not None else self._continuous_chunk
        mean, cov, increments_ll = chunk(state, dy, missing)
        loglik = np.cumsum(np.concatenate([[state.loglik], increments_ll]))[1:]  # sequential sums
        times = steps * self.model.dt
        new_state = replace(state, step=int(steps[-1]), t=float(times[-1]), loglik=float(loglik[-1]),
                            loglik_increment=float(increments_ll[-1]), mean=mean[-1].copy(),
                            cov=cov[-1].copy())
        return new_state, ExactChunk(step=steps, t=times, mean=mean, cov=cov, mode=mean.copy(),
                                      loglik=loglik, loglik_increment=increments_ll,
                                      degenerate=np.zeros(K, bool))

    # -- the two kinds ---------------------------------------------------------------------
    def _continuous_chunk(self, state: GaussianState, dy: np.ndarray, missing: np.ndarray):
        """σ = exp(−xᵀAx − Bᵀx − C): A by the Riccati flow, B affine in the data, log ∫σ at the end."""
        start = gaussian_to_terms(state.mean, state.cov)
        choice = missing.astype(int)  # 0: observed flow, 1: prediction only (no potential)
        q, r = self.potential_terms(dy)
        q[missing], r[missing] = 0.0, 0.0
        A = self._flows.path(choice, start.A[None])  # (K+1, 1, n, n)
        batch = self._flows.batch(choice, A[:-1], q, r)
        B = affine_path(batch.W, batch.v, start.B[None])  # (K+1, 1, n)
        _, gain = batch.finish(B[:-1])
        mean, cov, log_mass = gaussian_terms_batch(A[:, 0], B[:, 0], np.zeros(len(A)))
        # log ∫σ_k / ∫σ_{k−1}, with C_{k−1} = 0 and C_k = gain_k (C only shifts the mass)
        increments_ll = np.where(missing, 0.0, log_mass[1:] - gain[:, 0] - log_mass[:-1])
        return mean[1:], cov[1:], increments_ll

    def _discrete_chunk(self, state: GaussianState, dy: np.ndarray, missing: np.ndarray):
        """Kalman filter of the sampled model: covariance path, then the mean recursion."""
        kf, model = self._discrete, self.model
        dt, n, m = model.dt, model.n, model.m
        Hd, Rdt = kf.H * dt, model.R * dt
        cov_pred, gain, innovation, cov = _kalman_covariances(kf.phi, kf.Q, Hd, Rdt, state.cov, missing)
        # m_k = (I − G_k Hd)(Φ m_{k−1} + shift) + G_k (Δy_k − h0 dt)
        I_GH = np.eye(n) - gain @ Hd
        W = I_GH @ kf.phi
        v = (I_GH @ kf.shift) + (gain @ (dy - kf.h0 * dt)[..., None])[..., 0]
        means = affine_path(W[:, None], v[:, None], state.mean[None])[:, 0]
        predicted = (means[:-1] @ kf.phi.T + kf.shift) @ Hd.T + kf.h0 * dt
        ll = _log_normal_batch(dy, predicted, innovation) - _log_normal_batch(dy, np.zeros(m), Rdt[None])
        return means[1:], cov, np.where(missing, 0.0, ll)


@dataclass(frozen=True)
class ExactChunk(ChunkResult):
    """The engine's chunk arrays; ``mode`` may be None (a mixture's mode is not computed)."""

    def estimates(self) -> list[Estimate]:
        modes = [None] * len(self.step) if self.mode is None else list(self.mode)
        columns = zip(self.step.tolist(), self.t.tolist(), self.mean, self.cov, self.loglik.tolist(),
                      self.loglik_increment.tolist(), modes, strict=True)
        return [Estimate(step=s, t=t, mean=m, cov=P, loglik=ll, loglik_increment=i, mode=mode)
                for s, t, m, P, ll, i, mode in columns]


def _kalman_covariances(phi, Q, Hd, Rdt, P0, missing):
    """Predicted covariances, gains, innovation covariances and filtered covariances (K, ·, ·)."""
    K, n, m = len(missing), phi.shape[0], Hd.shape[0]
    cov_pred, cov = np.empty((K, n, n)), np.empty((K, n, n))
    gain, innovation = np.zeros((K, n, m)), np.empty((K, m, m))
    innovation[:] = Rdt  # placeholder on missing rows (their log-likelihood is 0)
    if n == 1 and m == 1:  # scalar fast path
        f, q, hd, rdt = float(phi[0, 0]) ** 2, float(Q[0, 0]), float(Hd[0, 0]), float(Rdt[0, 0])
        p, rows = float(P0[0, 0]), []
        for miss in missing.tolist():
            pp = f * p + q
            if miss:
                rows.append((pp, 0.0, rdt, pp))
                p = pp
            else:
                s = hd * hd * pp + rdt
                g = pp * hd / s
                p = pp - g * s * g
                rows.append((pp, g, s, p))
        table = np.array(rows)
        cov_pred[:, 0, 0], gain[:, 0, 0], innovation[:, 0, 0], cov[:, 0, 0] = table.T
        return cov_pred, gain, innovation, cov
    P = np.asarray(P0, dtype=float)
    for k, miss in enumerate(missing.tolist()):
        pp = cov_pred[k] = phi @ P @ phi.T + Q
        if not miss:
            S = innovation[k] = Hd @ pp @ Hd.T + Rdt
            G = gain[k] = np.linalg.solve(S, Hd @ pp).T
            pp = pp - G @ S @ G.T
        P = cov[k] = 0.5 * (pp + pp.T)
    return cov_pred, gain, innovation, cov


def _log_normal_batch(x, mean, cov) -> np.ndarray:
    """log N(x_k; mean_k, cov_k) for rows x (K, m), mean (K, m) or (m,), cov (K, m, m) or (1, m, m)."""
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, (x - mean)[..., None])[..., 0]
    log_det = np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return -0.5 * (z * z).sum(-1) - log_det - 0.5 * x.shape[-1] * np.log(2 * np.pi)
