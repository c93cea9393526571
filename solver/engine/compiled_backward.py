"""The smoother's backward pass over regular rows compiled by numba (solver/engine/smoother.py
``backward``): the same recursion with no Python between the rows, through the same BLAS ``dgemv`` as
scipy.linalg.blas (solver/engine/compiled.py ``gemv``), so the numbers are those of the numpy path.
Importing this module imports numba; smoother.py does so only where ``jit.enabled()``.
"""

from __future__ import annotations

import numba
import numpy as np

from .compiled import CACHE_DIR, buffers, gemv

# numba picks a function's cache directory when it is decorated: the engine's, then numba's own back
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)


@numba.njit(cache=CACHE_DIR is not None, nogil=True)
def backward_regular(sigma, weighted, scale, predicting, M, M_k, beta, v, check):
    """σ_k ← σ_k ⊙ β_k, β_(k−1) = scale_k · M_k (weighted_k ⊙ β_k) for k = K−1 … 0 (M where the row only
    predicted), β divided by its largest magnitude every ``check`` rows where that has left
    [1e-100, 1e100]; ``beta`` ends as β before row 0.  Returns −1, or the row where β lost every node."""
    ints, scalars = buffers(M)
    K, Q = sigma.shape
    for k in range(K - 1, -1, -1):
        for q in range(Q):
            sigma[k, q] *= beta[q]
            v[q] = weighted[k, q] * beta[q]
        if predicting[k]:
            gemv(scale[k], M, v, beta, ints, scalars)
        else:
            gemv(scale[k], M_k, v, beta, ints, scalars)
        if k % check == 0:
            top = 0.0
            for q in range(Q):
                a = abs(beta[q])
                if not a <= top:  # NaN as well
                    top = a
            if not np.isfinite(top) or top == 0.0:
                return k
            if not 1e-100 < top < 1e100:
                for q in range(Q):
                    beta[q] /= top
    return -1


numba.config.CACHE_DIR = _previous_cache_dir
