"""Many streams' fused chunks stepped together by numba: matrix–matrix products a row for all of them.

solver/engine/batch.py steps S states of one model together (seed 002 (5.35)/(5.38) as matrix–matrix
products); where every row of their chunks is observed and the rows are regular (solver/engine/fused.py
``batch_fusable``), this kernel runs the whole group's rows in one call.  Where the nodes are fewer
than 2(N + 1) (the 1-D meshes, double precision: fused.py ``_operator``) a row is one product,

    S_k = (PΠ) [σ_{k−1,1} … σ_{k−1,a}]           (one gemm over the a states still active at row k)

else two, S_k = P [c_{k−1,1} … c_{k−1,a}] and [c_k, ∫σ_k] = Π [σ_{k,1} … σ_{k,a}] (the weights ride
along as Π's last row); between them, per state,

    s_{k,j} = S_k[:, j] / ∫σ_{k−1,j},   σ_{k,j} = s_{k,j} ⊙ e_{k,j}

with the state's update factor and the sums its moments and checks read made inside the row by
solver/engine/compiled.py ``fused_row`` (the single fused loop's), so no K×S×Q array is kept.  With
one product a row, a state's first row comes from its carried (c, ∫σ) — or its last chunk's σ where
that is the one they came from (compiled.py ``nodal_matches``) — by one gemv, as in ``run_fused``, and
after its last row [c, ∫σ] = Πσ.  A state whose row leaves the fast path (an exponent not finite, ∫σ
out of (tiny, huge) or under the gate's floor) is marked at that row and its chunk is run again alone
by the caller.

The products sum in gemm's order (against gemv's alone) and s is divided by ∫σ after them (against
the gemv's alpha): a state's numbers are those of stepping it alone up to rounding (batch.py
``BATCH_RTOL``).  Importing this module imports numba.
"""

from __future__ import annotations

import numba
import numpy as np

from .compiled import CACHE_DIR, bind_blas, buffers, fused_row, gemv, row_mass, summary_buffers

_dgemm = bind_blas("dgemm", 13)
_sgemm = bind_blas("sgemm", 13)

# numba picks a function's cache directory when it is decorated: the engine's, then numba's own back
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)
_jit = numba.njit(cache=CACHE_DIR is not None, nogil=True)


@_jit
def _products(matrix, columns, out, count, ints, scalars):
    """out[:count] = columns[:count] · matrixᵀ: the rows of C-ordered (S, K) and (S, M) arrays are the
    columns of Fortran (K, S) and (M, S) ones, so this is gemm('N', 'N') of the Fortran M × K ``matrix``
    by the first ``count`` columns (dgemm or sgemm by the matrix's precision)."""
    ints[0] = ord("N")
    ints[1] = matrix.shape[0]
    ints[2] = count
    ints[3] = matrix.shape[1]
    scalars[0] = 1.0
    scalars[1] = 0.0
    trans, m, n, k = ints[0:1].ctypes, ints[1:2].ctypes, ints[2:3].ctypes, ints[3:4].ctypes
    if scalars.itemsize == 4:
        _sgemm(trans, trans, m, n, k, scalars[0:1].ctypes, matrix.ctypes, m, columns.ctypes, k,
               scalars[1:2].ctypes, out.ctypes, m)
    else:
        _dgemm(trans, trans, m, n, k, scalars[0:1].ctypes, matrix.ctypes, m, columns.ctypes, k,
               scalars[1:2].ctypes, out.ctypes, m)


@_jit
def _stopped(done, j, k, row):
    """Mark state j as leaving the fast path at row k; its row rides along as zeros."""
    done[j] = k
    row[:] = 0.0


@_jit
def run_fused_batch(lengths, combined, operator, propagator, projection, initial, from_nodal, nodal, terms, y,
                    taus, constants, discrete, limit, floor_exponents, summary, weights, sums, negative, mode,
                    top, masses, tiny, huge, following, done):
    """States j = 0..S−1 (``lengths`` non-increasing, ≥ 1) through their ``lengths[j]`` rows (module
    docstring): ``combined``, one product by ``operator`` = PΠ a row (the first from ``nodal[j]`` where
    ``from_nodal[j]``); else the two products P and Π, each one gemm for all.  Per state: ``initial[j]``
    its carried [c, ∫σ]; ``y[j]``, ``constants[j]``, ``floor_exponents[j]`` its rows' inputs (padded to
    the longest); out: ``sums[j]``, ``negative[j]``, ``mode[j]``, ``top[j]``, ``masses[j]`` per row as
    ``run_fused`` gives them, ``following[j]`` the [c, ∫σ] after its last row and (combined) ``nodal[j]``
    that row's σ; ``done[j]`` its first row that needs the Python path, or ``lengths[j]``."""
    ints, scalars = buffers(propagator)
    wide_ints, wide_scalars = summary_buffers(summary)
    products_ints, products_scalars = np.empty(4, np.int32), np.empty(2, propagator.dtype)
    S, Q, n = lengths.shape[0], propagator.shape[0], propagator.shape[1] - 1
    previous, current = np.empty((S, Q), propagator.dtype), np.empty((S, Q), propagator.dtype)
    carried, projected = initial.copy(), np.empty_like(initial)
    mass = np.empty(S)
    factor = np.empty(1, propagator.dtype)
    ex, bits, wide = np.empty(Q), np.empty(Q, np.int64), np.empty(Q)
    for j in range(S):
        mass[j] = initial[j, n]
        done[j] = lengths[j]
    active = S
    for k in range(lengths[0]):
        while lengths[active - 1] <= k:
            active -= 1
        if not combined:
            _products(propagator, carried, current, active, products_ints, products_scalars)
        elif k == 0:
            for j in range(S):
                source = nodal[j] if from_nodal[j] else initial[j]
                gemv(1.0, operator if from_nodal[j] else propagator, source, current[j], ints, scalars)
        else:
            _products(operator, previous, current, active, products_ints, products_scalars)
        for j in range(active):
            row = current[j]
            if done[j] < lengths[j]:  # left the fast path: rides along as zeros
                row[:] = 0.0
                continue
            inverse = 1.0 / mass[j]
            for q in range(Q):
                row[q] = row[q] * inverse
            if not fused_row(k, terms, y[j], taus, constants[j], discrete, limit, factor, row, wide, ex,
                              bits, summary, sums[j], weights, negative[j], mode[j], top[j], wide_ints,
                              wide_scalars):
                _stopped(done, j, k, row)
        if not combined:
            _products(projection, current, projected, active, products_ints, products_scalars)
        for j in range(active):
            if done[j] < lengths[j]:
                continue
            row = current[j]
            new_mass = row_mass(weights, row) if combined else float(projected[j, n])
            masses[j, k] = new_mass
            if not tiny < new_mass < huge or new_mass < np.exp(floor_exponents[j, k] - top[j, k]):
                _stopped(done, j, k, row)
                continue
            mass[j] = new_mass
            if k + 1 == lengths[j]:
                if combined:
                    gemv(1.0, projection, row, following[j], ints, scalars)
                    following[j, n] = new_mass
                    nodal[j][:] = row
                else:
                    following[j][:] = projected[j]
        previous, current = current, previous
        carried, projected = projected, carried


numba.config.CACHE_DIR = _previous_cache_dir
