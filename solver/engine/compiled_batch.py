"""Many streams' fused chunks stepped together by numba: one matrix–matrix product a row for all of them.

solver/engine/batch.py steps S states of one model together (seed 002 (5.35)/(5.38) as a matrix–matrix
product); where every row of their chunks is observed, the rows are regular, in double precision and
with fewer nodes than 2(N + 1) (the 1-D meshes: solver/engine/fused.py ``_operator``), this kernel runs
the whole group's rows in one call:

    S_k = (PΠ) [σ_{k−1,1} … σ_{k−1,a}]           (one dgemm over the a states still active at row k)
    s_{k,j} = S_k[:, j] / ∫σ_{k−1,j},   σ_{k,j} = s_{k,j} ⊙ e_{k,j}

each state's update factor, ∫σ and the sums its moments and checks read made inside the row by
solver/engine/compiled.py ``_fused_row`` (the single fused loop's), so no K×S×Q array is kept.  A state's
first row comes from its carried (c, ∫σ) — or its last chunk's σ where that is the one they came from
(compiled.py ``nodal_matches``) — by one gemv, as in ``run_fused``; after its last row, [c, ∫σ] = Πσ.
A state whose row leaves the fast path (an exponent not finite, ∫σ out of (tiny, huge) or under the
gate's floor) is marked at that row and its chunk is run again alone by the caller.

The product sums in gemm's order (against gemv's alone) and s is divided by ∫σ after it (against the
gemv's alpha): a state's numbers are those of stepping it alone up to rounding (batch.py
``BATCH_RTOL``).  Importing this module imports numba.
"""

from __future__ import annotations

import numba
import numpy as np

from .compiled import CACHE_DIR, _bind, _fused_row, _mass, buffers, gemv, summary_buffers

_dgemm = _bind("dgemm", 13)

# numba picks a function's cache directory when it is decorated: the engine's, then numba's own back
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)


@numba.njit(cache=CACHE_DIR is not None, nogil=True)
def _products(operator, previous, out, active, ints, scalars):
    """out[:active] = previous[:active] · operatorᵀ: rows of (S, Q) C-ordered arrays are columns of
    (Q, S) Fortran ones, so this is dgemm('N', 'N') of the Fortran Q × Q operator by the first ``active``
    columns."""
    ints[0] = ord("N")
    ints[1] = operator.shape[0]
    ints[2] = active
    scalars[0] = 1.0
    scalars[1] = 0.0
    trans, m, n = ints[0:1].ctypes, ints[1:2].ctypes, ints[2:3].ctypes
    _dgemm(trans, trans, m, n, m, scalars[0:1].ctypes, operator.ctypes, m, previous.ctypes, m,
           scalars[1:2].ctypes, out.ctypes, m)


@numba.njit(cache=CACHE_DIR is not None, nogil=True)
def run_fused_batch(lengths, operator, propagator, projection, initial, from_nodal, nodal, terms, y, taus,
                    constants, discrete, limit, floor_exponents, summary, weights, sums, negative, mode, top,
                    masses, tiny, huge, following, done):
    """States j = 0..S−1 (``lengths`` non-increasing, ≥ 1) through their ``lengths[j]`` rows (module
    docstring).  Per state: ``initial[j]`` its carried [c, ∫σ]; ``y[j]``, ``constants[j]``,
    ``floor_exponents[j]`` its rows' inputs (padded to the longest); out: ``sums[j]``, ``negative[j]``,
    ``mode[j]``, ``top[j]``, ``masses[j]`` per row as ``run_fused`` gives them, ``following[j]`` the
    [c, ∫σ] after its last row and ``nodal[j]`` that row's σ; ``done[j]`` its first row that needs the
    Python path, or ``lengths[j]``."""
    ints, scalars = buffers(propagator)
    wide_ints, wide_scalars = summary_buffers(summary)
    products_ints, products_scalars = np.empty(3, np.int32), np.empty(2)
    S, Q, n = lengths.shape[0], operator.shape[0], propagator.shape[1] - 1
    previous, current = np.empty((S, Q)), np.empty((S, Q))
    mass = np.empty(S)
    factor = np.empty(1)
    ex, bits, wide = np.empty(Q), np.empty(Q, np.int64), np.empty(Q)
    for j in range(S):
        mass[j] = initial[j, n]
        done[j] = lengths[j]
    active = S
    for k in range(lengths[0]):
        while lengths[active - 1] <= k:
            active -= 1
        if k == 0:
            for j in range(S):
                if from_nodal[j]:
                    gemv(1.0 / mass[j], operator, nodal[j], current[j], ints, scalars)
                else:
                    gemv(1.0 / mass[j], propagator, initial[j], current[j], ints, scalars)
        else:
            _products(operator, previous, current, active, products_ints, products_scalars)
        for j in range(active):
            row = current[j]
            if done[j] < lengths[j]:  # left the fast path: rides along as zeros
                row[:] = 0.0
                continue
            if k:
                inverse = 1.0 / mass[j]
                for q in range(Q):
                    row[q] = row[q] * inverse
            if not _fused_row(k, terms, y[j], taus, constants[j], discrete, limit, factor, row, wide, ex,
                              bits, summary, sums[j], weights, negative[j], mode[j], top[j], wide_ints,
                              wide_scalars):
                done[j] = k
                row[:] = 0.0
                continue
            new_mass = _mass(weights, row)
            masses[j, k] = new_mass
            if not tiny < new_mass < huge or new_mass < np.exp(floor_exponents[j, k] - top[j, k]):
                done[j] = k
                row[:] = 0.0
                continue
            mass[j] = new_mass
            if k + 1 == lengths[j]:
                gemv(1.0, projection, row, following[j], ints, scalars)
                following[j, n] = new_mass
                nodal[j] = row
        previous, current = current, previous


numba.config.CACHE_DIR = _previous_cache_dir
