"""An L²(B_R)-orthonormal basis: discrete Dirichlet eigenfunctions of −½ div(a∇).

Solves the generalised symmetric eigenproblem  ½K φ = λ W φ,  φ = 0 on ∂B_R,
with K the a-stiffness matrix and W = diag(weights) the lumped mass, and keeps the N
smallest eigenpairs.  With D = W^{1/2} it is the standard problem D⁻¹(½K)D⁻¹ ψ = λψ,
so Φ = D⁻¹Ψ satisfies Φᵀ W Φ = ΨᵀΨ = I to rounding and the projector Φᵀ W is an exact
left inverse of Φ.

Why the Laplacian: its eigenfunctions resolve the ball uniformly, and a conditional density
can sit anywhere in it (for the cubic sensor the sharpest posteriors sit far from the centre,
where h' = 3x² is large).  Another basis is another builder (solver/offline.py).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps
from threadpoolctl import threadpool_limits

from .errors import SpecError


@dataclass(frozen=True)
class OrthonormalBasis:
    values: np.ndarray  # (Q, N) nodal values Φ
    projector: np.ndarray  # (N, Q) Φᵀ W
    eigenvalues: np.ndarray  # (N,)


def eigenbasis(half_stiffness: sps.spmatrix, weights: np.ndarray, size: int) -> OrthonormalBasis:
    """The ``size`` lowest W-orthonormal eigenfunctions of ½K."""
    q = len(weights)
    if not 1 <= size <= q:
        raise SpecError("discretization.basis", f"must be between 1 and the {q} interior nodes")
    scale = 1.0 / np.sqrt(weights)
    operator = half_stiffness.toarray()
    symmetric = scale[:, None] * operator * scale[None, :]
    symmetric = 0.5 * (symmetric + symmetric.T)  # remove assembly rounding asymmetry
    # the full divide-and-conquer solve beat the subset drivers (evr, evx) for N ≳ Q/4 in 2-D
    with blas_threads(1):
        lam, psi = sla.eigh(symmetric, driver="evd")
    lam, psi = lam[:size], psi[:, :size]
    psi = _fix_signs(psi)
    values = scale[:, None] * psi
    return OrthonormalBasis(values=values, projector=(values * weights[:, None]).T, eigenvalues=lam)


def _fix_signs(psi: np.ndarray) -> np.ndarray:
    """Make each eigenvector's largest-magnitude entry positive (reproducible output)."""
    pivot = psi[np.argmax(np.abs(psi), axis=0), np.arange(psi.shape[1])]
    return psi * np.where(pivot < 0, -1.0, 1.0)


# -- BLAS threads ------------------------------------------------------------------------------------
# Measured on the shared 2-core machine under load: the dense eigensolve of Q = 259 took 0.15–0.54 s
# with two OpenBLAS threads and 0.01–0.02 s with one; for Q = 2107 (2-D, N = 1000) 6.5–12.9 s with
# two and 1.2–2.7 s with one.  So the solve runs on one thread.


@contextmanager
def blas_threads(count: int):
    """Temporarily limit the BLAS libraries' threads (threadpoolctl)."""
    with threadpool_limits(limits=count, user_api="blas"):
        yield
