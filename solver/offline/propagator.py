"""Propagators over one observation interval: nodal values of e^{dt L} φ_k and e^{dt L_K} φ_k.

Solves the semi-discrete equation  W du/dt = A u  (W lumped mass, or the stabilised consistent mass M
of ``scheme = "supg"``; A the Fokker–Planck or the Kolmogorov matrix of solver.fem, seed 002 (5.31))
over [0, dt] in ``substeps`` steps of the
2-stage SDIRK method of Alexander (1977), γ = 1 − 1/√2:

    (W − γτA) k₁ = A u,   (W − γτA) k₂ = A (u + (1 − γ) τ k₁),   u ← u + τ((1 − γ) k₁ + γ k₂).

It is L-stable (the stiff, unresolved modes of a basis function are damped, not reflected as
Crank–Nicolson would) and second order; both stages share one matrix, factored ONCE and
applied to a block of basis functions at a time.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
from scipy.sparse.linalg import splu

GAMMA = 1.0 - 1.0 / np.sqrt(2.0)


class SdirkPropagator:
    """e^{t W⁻¹A} applied to blocks of initial values, with (W − γτA) factored once (``mass``: a
    sparse mass matrix M in place of W = diag(weights))."""

    def __init__(self, operator: sps.spmatrix, weights: np.ndarray, duration: float, substeps: int,
                 mass: sps.spmatrix | None = None):
        self.operator = sps.csr_matrix(operator)
        self.substeps = int(substeps)
        self.tau = duration / self.substeps
        mass = sps.diags(weights) if mass is None else sps.csr_matrix(mass)
        shifted = mass - GAMMA * self.tau * self.operator
        self._lu = splu(sps.csc_matrix(shifted))

    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(np.asfortranarray(rhs))

    def step(self, u: np.ndarray) -> np.ndarray:
        k1 = self._solve(self.operator @ u)
        k2 = self._solve(self.operator @ (u + (1.0 - GAMMA) * self.tau * k1))
        return u + self.tau * ((1.0 - GAMMA) * k1 + GAMMA * k2)

    def apply(self, u0: np.ndarray) -> np.ndarray:
        u = np.array(u0, dtype=float, copy=True)
        for _ in range(self.substeps):
            u = self.step(u)
        return u
