"""An L²(B_R)-orthonormal basis: discrete Dirichlet eigenfunctions of −½ div(a∇).

Solves the generalised symmetric eigenproblem  ½K φ = λ W φ,  φ = 0 on ∂B_R,
with K the a-stiffness matrix and W = diag(weights) the lumped mass, and keeps the N
smallest eigenpairs.  With D = W^{1/2} it is the standard problem D⁻¹(½K)D⁻¹ ψ = λψ,
so Φ = D⁻¹Ψ satisfies Φᵀ W Φ = ΨᵀΨ = I to rounding and the projector Φᵀ W is an exact
left inverse of Φ.

Up to DENSE_NODES nodes the whole spectrum is computed (LAPACK's divide and conquer); above, the N
lowest pairs come from shift-invert Lanczos (ARPACK through scipy's ``eigsh``, σ = 0, a sparse LU of
the matrix), so a 3-D ball refined five times (Q ≈ 4·10⁴) is within reach.

Why the Laplacian: its eigenfunctions resolve the ball uniformly, and a conditional density
can sit anywhere in it (for the cubic sensor the sharpest posteriors sit far from the centre,
where h' = 3x² is large).  Another basis is another builder (solver/offline/pipeline.py).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps
import scipy.sparse.linalg as spla
from threadpoolctl import threadpool_limits

from ..errors import SpecError


@dataclass(frozen=True)
class OrthonormalBasis:
    values: np.ndarray  # (Q, N) nodal values Φ
    projector: np.ndarray  # (N, Q) Φᵀ W
    eigenvalues: np.ndarray  # (N,)


# Above this many nodes the dense solve (O(Q²) memory, O(Q³) time: 12000 nodes is ~1.1 GiB) gives way
# to shift-invert Lanczos.  Measured (one BLAS thread, 3-D ball of radius 4): Q = 4991, N = 500 took
# 8.9 s dense and 10.9 s Lanczos; Q = 41727, N = 1000 took 481 s Lanczos at a 2.6 GB peak, where
# the dense solve would need 13 GiB.
DENSE_NODES = 12000


def eigenbasis(half_stiffness: sps.spmatrix, weights: np.ndarray, size: int) -> OrthonormalBasis:
    """The ``size`` lowest W-orthonormal eigenfunctions of ½K."""
    q = len(weights)
    if not 1 <= size <= q:
        raise SpecError("discretization.basis", f"must be between 1 and the {q} interior nodes")
    scale = 1.0 / np.sqrt(weights)
    d = sps.diags(scale)
    symmetric = (d @ sps.csr_matrix(half_stiffness) @ d).tocsr()
    symmetric = 0.5 * (symmetric + symmetric.T)  # remove assembly rounding asymmetry
    with blas_threads(1):
        if q <= DENSE_NODES or size >= q - 1:
            lam, psi = _dense_lowest(symmetric, size)
        else:
            lam, psi = _lanczos_lowest(symmetric, size)
    psi = _fix_signs(psi)
    values = scale[:, None] * psi
    return OrthonormalBasis(values=values, projector=(values * weights[:, None]).T, eigenvalues=lam)


def _dense_lowest(symmetric: sps.spmatrix, size: int) -> tuple[np.ndarray, np.ndarray]:
    # the full divide-and-conquer solve beat the subset drivers (evr, evx) for N ≳ Q/4 in 2-D
    lam, psi = sla.eigh(symmetric.toarray(), driver="evd")
    return lam[:size], psi[:, :size]


def _lanczos_lowest(symmetric: sps.spmatrix, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The lowest pairs by shift-invert Lanczos about σ = 0 (the operator is positive definite: the
    Dirichlet condition).  A fixed start vector makes the result reproducible (ARPACK's default is
    random), so a file is identical whoever computes it."""
    start = np.ones(symmetric.shape[0])
    lam, psi = spla.eigsh(symmetric.tocsc(), k=size, sigma=0.0, which="LM", v0=start)
    order = np.argsort(lam)
    return lam[order], psi[:, order]


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
