"""One observation interval of the Yau–Hu method (solver/exact/yau_hu.py), seed 000 Theorem 3.1.

The observation-free Kolmogorov equation (3.1) as a Gaussian Kolmogorov flow (solver/exact/riccati.py)
and the observation-driven linear ODEs (3.3)–(3.5) of (b, a, y) as one matrix exponential, over dt
or an irregular gap: :class:`YauHuStep`.  :func:`schedule_coefficients` writes the step out with
the data kept symbolic, the entries of the cached schedules (solver/exact/schedule.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from .riccati import FlowFamily, GaussianKolmogorov
from .yau_system import YauSystem

NODES = 8  # Gauss–Legendre nodes for c(dt) = ∫c'


def step_equations(D, d, E, e, e0, H):
    """The observation-free Kolmogorov equation (3.1) and the matrix of the (b, a, y) ODEs (3.3)–(3.4)."""
    n = len(d)
    # (3.1) as u_t = ½Δu − ℓ·∇u − (tr D + xᵀQx + qᵀx + r)u: Q, q, r from ½(η − |ℓ|² + tr D)
    kolmogorov = GaussianKolmogorov(D, d, Q=0.5 * (E - D.T @ D), q=0.5 * e - D.T @ d,
                                    r=0.5 * (e0 - d @ d - np.trace(D)))
    # (3.3)–(3.4) with y(s) = s ẏ:  b' = a + Db − Hᵀy,  a' = E b − Dᵀb'  (E symmetric)
    m = H.shape[0]
    M = np.zeros((2 * n + 2 * m, 2 * n + 2 * m))
    M[:n, :n], M[:n, n:2 * n], M[:n, 2 * n:2 * n + m] = D, np.eye(n), -H.T
    M[n:2 * n] = -D.T @ M[:n]
    M[n:2 * n, :n] += E
    M[2 * n:2 * n + m, 2 * n + m:] = np.eye(m)  # y' = ẏ
    return kolmogorov, M


class YauHuStep:
    """One observation interval of the method for a given (whitened) H, h0.

    ``gap=True``: a flow over an irregular gap (the Riccati flow from the eigen-decomposition,
    the (a, b, y) maps in one batched call; solver/exact/riccati.py ``gap_flow``)."""

    def __init__(self, system: YauSystem, H: np.ndarray, h0: np.ndarray, eta_shift, dt: float,
                 gap: bool = False):
        D, d, n = system.D, system.d, len(system.d)
        E, e, e0 = system.E + eta_shift[0], system.e + eta_shift[1], system.e0 + eta_shift[2]
        self.E, self.e, self.D, self.d, self.H, self.h0, self.dt = E, e, D, d, H, h0, dt
        kolmogorov, M = step_equations(D, d, E, e, e0, H)
        self.flow = kolmogorov.gap_flow(dt) if gap else kolmogorov.flow(dt)
        m = H.shape[0]
        nodes, w = np.polynomial.legendre.leggauss(NODES)
        self.s, self.w = 0.5 * dt * (nodes + 1), 0.5 * dt * w
        # state (b, a, y) at s as a linear map of ẏ (everything starts at 0)
        if gap:
            self.maps = expm(M[None] * np.append(self.s, dt)[:, None, None])[:, :2 * n + m, 2 * n + m:]
        else:
            self.maps = np.stack([expm(M * s)[:2 * n + m, 2 * n + m:] for s in np.append(self.s, dt)])
        self.n = n

    @staticmethod
    def rate(system: YauSystem, H: np.ndarray, eta_shift) -> float:
        """The larger spectral radius of the Riccati flow's and the (b, a, y) maps' linear systems:
        a long gap is split into pieces no longer than its inverse (riccati.gap_pieces)."""
        D, d = system.D, system.d
        E, e, e0 = system.E + eta_shift[0], system.e + eta_shift[1], system.e0 + eta_shift[2]
        kolmogorov, M = step_equations(D, d, E, e, e0, H)
        return max(kolmogorov.spectrum()[1], float(np.abs(np.linalg.eigvals(M)).max()))

    def increment_terms(self):
        """(Ga, Gb, Qc, lc): a = Ga y, b = Gb y, c = yᵀQc y + lcᵀy for the whitened increment y = ẏ dt.

        The maps of :meth:`observation_terms` with the data kept symbolic; seed 000 (3.3)–(3.5).
        """
        n = self.n
        maps = self.maps / self.dt  # y = ẏ dt
        Mb, Ma, My = maps[:, :n], maps[:, n:2 * n], maps[:, 2 * n:]
        P = Ma + self.D @ Mb - self.H.T @ My  # b' = P y
        Mb_, Ma_, P_ = Mb[:-1], Ma[:-1], P[:-1]  # quadrature nodes
        cross = np.swapaxes(Ma_, -1, -2) @ P_
        Qs = -0.5 * np.swapaxes(P_, -1, -2) @ P_ + 0.5 * (cross + np.swapaxes(cross, -1, -2)) \
            + 0.5 * np.swapaxes(Mb_, -1, -2) @ self.E @ Mb_
        ls = -np.swapaxes(P_, -1, -2) @ self.d + 0.5 * np.swapaxes(Mb_, -1, -2) @ self.e
        return Ma[-1], Mb[-1], np.einsum("s,sij->ij", self.w, Qs), self.w @ ls

    def observation_terms(self, ydot: np.ndarray):
        """(a, b, c) at dt for constant rates ẏ (K, m) -> (K, n), (K, n), (K,); seed 000 (3.3)–(3.5)."""
        n = self.n
        states = np.einsum("sij,kj->ksi", self.maps, ydot)
        b, a, y = states[..., :n], states[..., n:2 * n], states[..., 2 * n:]
        bp = a + b @ self.D.T - y @ self.H  # b' from (3.3)
        cp = (-0.5 * (bp * bp).sum(-1) + (a * bp).sum(-1) - bp @ self.d
              + 0.5 * np.einsum("ksi,ij,ksj->ks", b, self.E, b) + 0.5 * b @ self.e)  # (3.5)
        return a[:, -1], b[:, -1], cp[:, :-1] @ self.w


@dataclass(frozen=True)
class StepKit:
    """A step over a gap (or a piece of one): the method's maps and its flow."""

    step: YauHuStep
    family: FlowFamily
    q: np.ndarray
    r: np.ndarray


def schedule_coefficients(observed: YauHuStep, family: FlowFamily, q: np.ndarray, r: np.ndarray,
                          A_prev: np.ndarray, A_next: np.ndarray) -> dict:
    """Schedule entries of observed steps from A_prev (L, J, n, n) (A_next: after each step).

    The general chunk written out with the data kept symbolic: with u = (B_prev, y) (y the
    whitened increment) B_next = W B_prev + Vy y + v0 and the C gain is κ + ℓᵀu + ½uᵀ𝕄u.
    """
    zeros = np.zeros(len(A_prev), dtype=int)
    batch = family.batch(zeros, A_prev, q[zeros], r[zeros])
    T = batch.XinvT  # B(s) = T(s)(B_prev + forcing(s)), (L, S+1, J, n, n)
    cs = np.einsum("lsjab,lsjb->lsja", T, batch.forcing)
    Tn, cn, w, d = T[:, :-1], cs[:, :-1], batch.w, family.eq.d
    # gain = gain0 − Σ_s w_s(½|B(s)|² + dᵀB(s)) (a = I)
    kappa = batch.gain0 - np.einsum("s,lsj->lj", w, 0.5 * (cn * cn).sum(-1) + cn @ d)
    lx = -np.einsum("s,lsjba,lsjb->lja", w, Tn, cn + d)
    Mxx = -np.einsum("s,lsjca,lsjcb->ljab", w, Tn, Tn)
    W, v = batch.W, batch.v
    Ga, Gb, Qc, lc = observed.increment_terms()
    AGb = A_next @ Gb  # (L, J, n, m)
    # B_next = B_flow − 2A b + a − Hᵀy;  dC += (A b − B_flow)ᵀb + c − aᵀb − h0ᵀy
    Vy = -2.0 * AGb + (Ga - observed.H.T)
    ly = -v @ Gb + lc - observed.h0
    Mxy = -np.swapaxes(W, -1, -2) @ Gb
    GaGb = Ga.T @ Gb
    Myy = 2.0 * (Gb.T @ AGb) + 2.0 * Qc - (GaGb + GaGb.T)
    cov = np.linalg.inv(2.0 * A_next)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    half_log_det = 0.5 * np.linalg.slogdet(2 * np.pi * cov)[1]
    return {"A": A_next, "W": W, "Vy": Vy, "v0": v, "kappa": kappa, "lx": lx, "ly": ly, "Mxx": Mxx,
            "Mxy": Mxy, "Myy": Myy, "cov": cov, "half_log_det": half_log_det}
