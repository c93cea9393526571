"""An L²(B_R)-orthonormal basis: discrete Dirichlet eigenfunctions of −½ div(a∇) (+ V).

Solves the generalised symmetric eigenproblem  (½K + W V) φ = λ W φ,  φ = 0 on ∂B_R,
with K the a-stiffness matrix and W = diag(weights) the lumped mass, and keeps the N
smallest eigenpairs.  With D = W^{1/2} it is the standard problem D⁻¹(½K + WV)D⁻¹ ψ = λψ,
so Φ = D⁻¹Ψ satisfies Φᵀ W Φ = ΨᵀΨ = I to rounding and the projector Φᵀ W is an exact
left inverse of Φ.

Why the Laplacian (V = 0) is the default: its eigenfunctions resolve the ball uniformly,
and a conditional density can sit anywhere in it (for the cubic sensor the sharpest
posteriors sit far from the centre, where h' = 3x² is large).  A potential V (e.g.
½hᵀR⁻¹h) concentrates the basis where V is small and is available for experiments.
"""

from __future__ import annotations

import ctypes
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps

from .errors import SpecError


@dataclass(frozen=True)
class OrthonormalBasis:
    values: np.ndarray  # (Q, N) nodal values Φ
    projector: np.ndarray  # (N, Q) Φᵀ W
    eigenvalues: np.ndarray  # (N,)


def eigenbasis(half_stiffness: sps.spmatrix, weights: np.ndarray, size: int,
               potential: np.ndarray | None = None) -> OrthonormalBasis:
    """The ``size`` lowest W-orthonormal eigenfunctions of ½K + W·diag(potential)."""
    q = len(weights)
    if not 1 <= size <= q:
        raise SpecError("discretization.basis", f"must be between 1 and the {q} interior nodes")
    scale = 1.0 / np.sqrt(weights)
    operator = half_stiffness.toarray()
    if potential is not None:
        operator = operator + np.diag(weights * potential)
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


def _openblas_libraries() -> list:
    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.lower()})
    except OSError:
        return []
    libs = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for suffix in ("64_", ""):
            get = getattr(lib, f"scipy_openblas_get_num_threads{suffix}", None)
            put = getattr(lib, f"scipy_openblas_set_num_threads{suffix}", None)
            if get is not None and put is not None:
                libs.append((get, put))
                break
    return libs


@contextmanager
def blas_threads(count: int):
    """Temporarily set the thread count of the loaded scipy-openblas libraries (no-op elsewhere)."""
    libs = _openblas_libraries()
    saved = [get() for get, _ in libs]
    try:
        for _, put in libs:
            put(count)
        yield
    finally:
        for (_, put), value in zip(libs, saved, strict=True):
            put(value)
