"""The steps of the Kalman–Bucy filter (solver/exact/kalman_bucy.py) written out as arrays.

:class:`LinearSteps` is one regular step of a discrete-time Kalman filter (the sampled increment
model, or discrete measurements) and :func:`kalman_covariances` its covariance recursion over a chunk.

Cached schedules, the data-free coefficients of consecutive observed steps: for a time-invariant
model the covariance path from a given start does not depend on the data and converges
geometrically to the steady state.  A schedule (solver/exact/schedule.py) stores, step by step, the
recursion x_k = W_k x_{k−1} + Vy_k Δy_k + v0_k of the data-carrying variable x (B of the exponent
for the continuous kind, :func:`continuous_coefficients`; the mean for the discrete one,
:func:`kalman_coefficients`), the covariance P_k, and the log-likelihood increment as one quadratic
form ll_k = κ_k + ℓ_kᵀu + ½uᵀ𝕄_k u in u = (x_{k−1}, Δy_k) (:func:`quadratic`).  Once the path stops
moving (to rounding) the last entry is the steady step and is reused for every later step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..measurement import LOG_2PI
from ..model import Model
from .riccati import FlowFamily


@dataclass(frozen=True)
class LinearSteps:
    """One regular step of a discrete-time Kalman filter: x ← Φx + shift + N(0, Q), then the row
    y = C x + c + N(0, V); ``relative``: the log-likelihood is relative to N(y; 0, V) (the sampled
    increment model's Brownian reference), else the density itself (discrete measurements)."""

    phi: np.ndarray
    shift: np.ndarray
    Q: np.ndarray
    C: np.ndarray
    c: np.ndarray
    V: np.ndarray
    relative: bool


def kalman_covariances(phi, Q, Hd, Rdt, P0, missing):
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


def quadratic(kappa, ell, M, u) -> np.ndarray:
    """κ_k + ℓ_kᵀu_k + ½u_kᵀ𝕄_k u_k for rows u (K, n + m)."""
    if u.shape[1] == 2:  # n = m = 1: elementwise
        z, y = u[:, 0], u[:, 1]
        return kappa + ell[:, 0] * z + ell[:, 1] * y + 0.5 * (M[:, 0, 0] * z * z + M[:, 1, 1] * y * y) \
            + M[:, 0, 1] * z * y
    return kappa + (ell * u).sum(-1) + 0.5 * np.einsum("ka,kab,kb->k", u, M, u)


def swap(X: np.ndarray) -> np.ndarray:
    """The transposes of stacked matrices (..., a, b) -> (..., b, a)."""
    return np.swapaxes(X, -1, -2)


def scalar_ops(n: int):
    """(product, inverse, log det) of stacked n×n matrices; elementwise for n = 1 (no per-matrix calls)."""
    if n == 1:
        return np.multiply, np.reciprocal, lambda X: np.log(X[..., 0, 0])
    return np.matmul, np.linalg.inv, lambda X: np.linalg.slogdet(X)[1]


def continuous_coefficients(model: Model, family: FlowFamily, HtR: np.ndarray, h0: np.ndarray,
                            A_prev: np.ndarray, A_next: np.ndarray) -> dict:
    """Schedule entries of observed continuous steps from A_prev (L, n, n) (A_next: after each step).

    The flow of riccati.StepBatch written out with the data kept symbolic: B(s) = X(s)⁻ᵀ[B_prev +
    IX(s)ᵀq − 2IY(s)ᵀd] with q = HᵀR⁻¹(h0 − Δy/dt) is affine in u = (B_prev, Δy), so the C gain
    (Gauss–Legendre in s) and log ∫σ_k − log ∫σ_{k−1} are quadratic in u.
    """
    n, dt, eq = model.n, model.dt, family.eq
    mm, inv, log_det = scalar_ops(n)
    Phi, Psi, w = family.Phi[0], family.Psi[0], family.w  # the observed flow: (S+1, 2n, 2n)
    A = A_prev[:, None]
    X = Phi[:, :n, :n] + mm(Phi[:, :n, n:], A)  # (L, S+1, n, n)
    IX = Psi[:, :n, :n] + mm(Psi[:, :n, n:], A)
    IY = Psi[:, n:, :n] + mm(Psi[:, n:, n:], A)
    X_dt = X[:, -1]
    if n == 1 and not np.all(X_dt > 0) or n > 1 and np.any(np.linalg.slogdet(X_dt)[0] <= 0):
        raise InputError("dt", "the Riccati solution blows up within the step (det X <= 0)")
    T = swap(inv(X))
    TF = mm(T, swap(IX))
    Ls = np.concatenate([T, mm(TF, -HtR / dt)], axis=-1)  # B(s) = Ls u + c(s), (L, S+1, n, n+m)
    forcing = mm(TF, (HtR @ h0)[:, None]) - 2.0 * mm(T, mm(swap(IY), eq.d[:, None]))
    c = forcing[..., 0]
    # Σ_s w_s(½B(s)ᵀaB(s) + dᵀB(s)) at the quadrature nodes, as batched products over (s, i)
    root_w = np.sqrt(w)[:, None, None]  # Gauss–Legendre weights are positive
    Ln, cn = Ls[:, :-1] * root_w, c[:, :-1]
    L_flat = swap(Ln.reshape(len(Ln), -1, Ln.shape[-1]))  # (L, n+m, S·n)
    Mw = L_flat @ (eq.a @ Ln).reshape(len(Ln), -1, Ln.shape[-1])
    lw = (L_flat @ ((cn @ eq.a + eq.d) * root_w[..., 0]).reshape(len(Ln), -1, 1))[..., 0]
    cw = (0.5 * ((cn @ eq.a) * cn).sum(-1) + cn @ eq.d) @ w
    G, v0 = Ls[:, -1], c[:, -1]
    P, P_prev = inv(2.0 * A_next), inv(2.0 * A_prev)
    P, P_prev = 0.5 * (P + swap(P)), 0.5 * (P_prev + swap(P_prev))
    R_inv = model.R_inv
    g0 = 0.5 * log_det(X_dt) + (0.5 * h0 @ R_inv @ h0 + 0.5 * np.trace(eq.D)) * dt
    Pv = mm(P, v0[..., None])
    M = mm(mm(swap(G), P), G) + Mw
    M[:, :n, :n] -= P_prev
    ell = mm(swap(G), Pv)[..., 0] + lw
    ell[:, n:] += R_inv @ h0  # − ∂gain/∂Δy, the r dt = (½h0ᵀR⁻¹h0 − (R⁻¹h0)ᵀΔy/dt) dt part
    # log ∫σ = ½ log det(2πP) + ½BᵀPB: the log det parts of steps k and k−1
    kappa = 0.5 * (log_det(A_prev) - log_det(A_next)) + 0.5 * (v0 * Pv[..., 0]).sum(-1) - g0 + cw
    return {"W": G[..., :n], "Vy": G[..., n:], "v0": v0, "kappa": kappa, "ell": ell, "M": M,
            "prev": A_prev, "cov": P}


def kalman_coefficients(kf: LinearSteps, model: Model, P_prev, cov_pred, gain, innovation,
                        cov) -> dict:
    """Schedule entries of observed discrete-time Kalman steps (x = the mean).

    ll = log N(y; C(Φx + shift) + c, S) [− log N(y; 0, V) for the sampled increment model] with the
    residual E u + e0.
    """
    n, m = model.n, model.m
    Hd, Rdt = kf.C, kf.V
    I_GH = np.eye(n) - gain @ Hd
    E = np.concatenate([np.broadcast_to(-Hd @ kf.phi, (len(gain), m, n)),
                        np.broadcast_to(np.eye(m), (len(gain), m, m))], axis=-1)
    e0 = -(Hd @ kf.shift + kf.c)
    S_inv = np.linalg.inv(innovation)
    M = -swap(E) @ S_inv @ E
    if kf.relative:
        M[:, n:, n:] += np.linalg.inv(Rdt)
        log_det_ratio = np.linalg.slogdet(innovation)[1] - np.linalg.slogdet(Rdt)[1]
    else:
        log_det_ratio = np.linalg.slogdet(innovation)[1] + m * LOG_2PI
    ell = -(swap(E) @ (S_inv @ e0)[..., None])[..., 0]
    kappa = -0.5 * np.einsum("i,kij,j->k", e0, S_inv, e0) - 0.5 * log_det_ratio
    return {"W": I_GH @ kf.phi, "Vy": gain, "v0": (I_GH @ kf.shift) - gain @ kf.c, "kappa": kappa,
            "ell": ell, "M": M, "prev": P_prev, "cov": cov}
