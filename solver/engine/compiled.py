"""The engine's row loops compiled by numba: whole chunks without Python between the rows.

The fast path of solver/engine/loops.py (``YAUYAU_KERNEL``, solver/jit.py) for regular rows,
irregular rows (modal scaling, the Schur form's tables: :func:`run_schur`, or a nodal flow per run of
equal gaps) and a ball that moves inside the
loop (:func:`run_moving`: it also stops after a row whose trigger fires).  Each loop runs rows
``start ≤ k < stop`` of a chunk — s = P[c, ∫σ]/∫σ, σ = s ⊙ e_k on observed rows, [c, ∫σ] = Πσ — and
returns the first row it did not finish: ``stop``, or a row whose ∫σ is outside (tiny, huge) or
under the gate's floor.  That row's products are done (σ_k in ``sigma[k]``, the propagated values of an
observed row in ``scratch``, Πσ_k in the buffer that was ``following`` and its ∫σ in ``masses[k]``);
the Python driver (solver/engine/loops.py) takes its slow step with the tested Python code and
re-enters at the next row.  The carried vector alternates between the two buffers as in the Python
loops: after j rows it is in ``following`` when j is odd.

:func:`run_fused` (driven by solver/engine/fused.py) also computes each row's update factor and the sums
its moments and checks read inside the row, for chunks whose rows are all observed: no K×Q arrays (and
on regular rows, where the nodes are fewer than 2(N + 1), one product a row: s = PΠσ/∫σ).
Its numbers agree with the numpy path to rounding (the factors' exponential is this module's
:func:`exp_shifted`, within 2 ulp of numpy's; BLAS's sums), not bit for bit; the loops that keep σ
take the same exponential and sums (a compiled chunk's numbers do not depend on whether it ran fused).

The products call the very BLAS ``dgemv``/``sgemv`` that scipy.linalg.blas calls on the numpy path
(scipy.linalg.cython_blas, by address: bit-identical on the same inputs), and the elementwise products
are single IEEE operations (numba does not contract them into FMAs); the two paths differ by the
factors' exponential and the Schur form's triangular products (:func:`_packed_product`, a column loop
over packed matrices where the numpy path calls BLAS tpmv: faster than BLAS at these sizes), both to
rounding.  Importing this module imports numba; solver/engine/loops.py does so on first use only.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import binding as llvm
from numba import types
from numba.extending import get_cython_function_address

from ..jit import writable_cache_dir

TRANS_N = ord("N")
TRANS_T = ord("T")


def bind_blas(name: str, arguments: int = 11):
    """BLAS ``name`` of scipy.linalg.cython_blas as an external symbol: the compiled code refers to it
    by name (registered again in each process), so numba can cache it on disk."""
    symbol = f"yauyau_cython_blas_{name}"
    llvm.add_symbol(symbol, get_cython_function_address("scipy.linalg.cython_blas", name))
    return types.ExternalFunction(symbol, types.void(*[types.voidptr] * arguments))


_dgemv = bind_blas("dgemv")
_sgemv = bind_blas("sgemv")

CACHE_DIR = writable_cache_dir()
# numba picks a function's cache directory when it is decorated: ours, then numba's own setting back
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)
_jit = numba.njit(cache=CACHE_DIR is not None, nogil=True)
# FMAs allowed (the exponential's polynomial only: its rounding is its own, stated below)
_jit_fma = numba.njit(cache=CACHE_DIR is not None, nogil=True, fastmath={"contract"})

# exp for the update factors: Cody–Waite reduction x = k·ln 2 + r, |r| ≤ ln 2 / 2 (k·LN2_HI is exact for
# |k| < 2^11: LN2_HI's low bits are zero), r's Taylor polynomial of degree 12 (truncation ≤ (ln 2/2)^13/13!
# ≈ 1.7e-16 relative) and 2^k from its bits; within 2 ulp of libm's on [−708, 0]
# (tests/solver/engine/test_compiled.py).  Written so that LLVM vectorises it: libm's exp is one call a
# number, 0.98 against 0.19 µs for the 159 nodes of examples/cubic_sensor.toml's rows
LOG2E = 1.4426950408889634
LN2_HI = 6.93147180369123816490e-01
LN2_LO = 1.90821492927058770002e-10
EXP_LOW, EXP_HIGH = -708.0, 709.0  # beyond: 0 and inf (libm's: subnormal, or finite up to 709.78)


@_jit
def gemv(alpha, matrix, x, y, ints, scalars):
    """y = alpha · matrix · x[:n] for a Fortran-ordered matrix (m, n): gemv('N') as scipy calls it
    (``ints`` = [ord('N'), m, n, 1], ``scalars`` = [alpha, beta] in the matrix's dtype)."""
    ints[1] = matrix.shape[0]
    ints[2] = matrix.shape[1]
    scalars[0] = alpha
    scalars[1] = 0.0
    trans, m, n, inc = ints[0:1].ctypes, ints[1:2].ctypes, ints[2:3].ctypes, ints[3:4].ctypes
    if scalars.itemsize == 4:
        _sgemv(trans, m, n, scalars[0:1].ctypes, matrix.ctypes, m, x.ctypes, inc, scalars[1:2].ctypes,
               y.ctypes, inc)
    else:
        _dgemv(trans, m, n, scalars[0:1].ctypes, matrix.ctypes, m, x.ctypes, inc, scalars[1:2].ctypes,
               y.ctypes, inc)


@_jit
def summary_buffers(columns):
    """:func:`buffers` for the summary's ``gemv`` with ``columns`` (Q, S) transposed: y = columnsᵀ · x,
    S dot products of length Q (BLAS's gemv('T'); gemv('N') on the (S, Q) rows cost 2.7× as much at
    S = 5)."""
    ints, scalars = buffers(columns)
    ints[0] = TRANS_T
    return ints, scalars


@_jit_fma
def exp_shifted(x, shift, out, bits):
    """out = exp(x − shift) (x − shift ≤ 0: a factor relative to its largest; ``out`` not ``x``, ``bits``
    an int64 buffer of x's size): the module's polynomial exponential, 0 under EXP_LOW, inf over
    EXP_HIGH, NaN kept."""
    for q in range(x.shape[0]):
        v = x[q] - shift
        w = v if v > EXP_LOW else EXP_LOW
        w = w if w < EXP_HIGH else EXP_HIGH
        k = math.floor(w * LOG2E + 0.5)
        r = (w - k * LN2_HI) - k * LN2_LO
        p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (
            1.0 / 720.0 + r * (1.0 / 5040.0 + r * (1.0 / 40320.0 + r * (1.0 / 362880.0 + r * (
                1.0 / 3628800.0 + r * (1.0 / 39916800.0 + r * (1.0 / 479001600.0))))))))))))
        bits[q] = (np.int64(k) + 1023) << 52
        out[q] = p
    scale = bits.view(np.float64)
    for q in range(x.shape[0]):
        v = x[q] - shift
        e = out[q] * scale[q]
        e = e if v >= EXP_LOW else 0.0
        e = e if v <= EXP_HIGH else np.inf
        out[q] = e if v == v else v


@_jit
def _packed_product(packed, row, lower, subs, w, out):
    """w ← M w for a quasi-upper-triangular M, ``packed`` its upper triangle column by column (powers.py's
    SchurPowers.product, whose BLAS tpmv sums in another order): out = Σ_j M[:j+1, j]·w_j four columns
    at a time, then the 2×2 blocks' subdiagonal terms (``subs[row]`` are M's entries), copied to w."""
    n = w.shape[0]
    for i in range(n):
        out[i] = 0.0
    j = 0
    while j + 4 <= n:
        x0, x1, x2, x3 = w[j], w[j + 1], w[j + 2], w[j + 3]
        s0 = j * (j + 1) // 2
        s1 = s0 + j + 1
        s2 = s1 + j + 2
        s3 = s2 + j + 3
        c0, c1, c2, c3 = packed[s0:s1], packed[s1:s2], packed[s2:s3], packed[s3:s3 + j + 4]
        for i in range(j + 1):
            out[i] += c0[i] * x0 + c1[i] * x1 + c2[i] * x2 + c3[i] * x3
        out[j + 1] += c1[j + 1] * x1 + c2[j + 1] * x2 + c3[j + 1] * x3
        out[j + 2] += c2[j + 2] * x2 + c3[j + 2] * x3
        out[j + 3] += c3[j + 3] * x3
        j += 4
    while j < n:
        x0 = w[j]
        s0 = j * (j + 1) // 2
        for i in range(j + 1):
            out[i] += packed[s0 + i] * x0
        j += 1
    for q in range(lower.size):
        out[lower[q]] += subs[row, q] * w[lower[q] - 1]
    for i in range(n):
        w[i] = out[i]


@_jit
def _row(k, propagator, observing, projection, carried, following, mass, factor, observed, sigma,
         scratch, ints, scalars):
    """Row k (kernel.py's observe or predict, then project): returns ∫σ_k (following[N])."""
    row = sigma[k]
    if observed[k]:
        gemv(1.0 / mass, observing, carried, scratch, ints, scalars)
        e = factor[k]
        for q in range(row.shape[0]):
            row[q] = scratch[q] * e[q]
    else:
        gemv(1.0 / mass, propagator, carried, row, ints, scalars)
    gemv(1.0, projection, row, following, ints, scalars)
    return float(following[propagator.shape[1] - 1])


@_jit
def buffers(matrix):
    ints = np.empty(4, np.int32)
    ints[0] = TRANS_N
    ints[3] = 1
    return ints, np.empty(2, matrix.dtype)


@_jit
def run_rows(start, stop, propagator, observing, projection, carried, following, mass, factor, observed,
             floors, sigma, scratch, masses, tiny, huge):
    """Rows start..stop−1 with the same propagators (loop_regular; loop_irregular's nodal flow over a
    run of equal gaps).  Returns the row it stopped at (``stop``: all done)."""
    ints, scalars = buffers(propagator)
    for k in range(start, stop):
        new_mass = _row(k, propagator, observing, projection, carried, following, mass, factor, observed,
                        sigma, scratch, ints, scalars)
        masses[k] = new_mass
        if not tiny < new_mass < huge or new_mass < floors[k]:
            return k
        mass = new_mass
        carried, following = following, carried
    return stop


@_jit
def scale_modal(carried, real_scale, pair_first, pair_second):
    """e^{τΛ} on the modal coefficients in place: the real modes, then each pair (u, w) ←
    (u·a + w·b) with a = (Re z, Im z), b = (−Im z, Re z) (loops.py's ModalScale, the same operations)."""
    r = real_scale.shape[0]
    for i in range(r):
        carried[i] = carried[i] * real_scale[i]
    for j in range(pair_first.shape[0]):
        u = carried[r + 2 * j]
        w = carried[r + 2 * j + 1]
        carried[r + 2 * j] = u * pair_first[j, 0] + w * pair_second[j, 0]
        carried[r + 2 * j + 1] = u * pair_first[j, 1] + w * pair_second[j, 1]


@_jit
def run_modal(start, stop, propagator, projection, carried, following, mass, factor, observed, floors,
              sigma, scratch, masses, tiny, huge, real_scale, pair_first, pair_second):
    """Rows start..stop−1 at any times in modal coordinates (loop_irregular): each row scales the carried
    coefficients by e^{τ_kΛ} (``real_scale`` (K, r), the pairs' ``pair_first``/``pair_second`` (K, p, 2))
    before the two products.  Returns the row it stopped at (``stop``: all done)."""
    ints, scalars = buffers(propagator)
    for k in range(start, stop):
        scale_modal(carried, real_scale[k], pair_first[k], pair_second[k])
        new_mass = _row(k, propagator, propagator, projection, carried, following, mass, factor, observed,
                        sigma, scratch, ints, scalars)
        masses[k] = new_mass
        if not tiny < new_mass < huge or new_mass < floors[k]:
            return k
        mass = new_mass
        carried, following = following, carried
    return stop


@_jit
def _advance(carried, schur, tables, lower, subs, indices, remainder, degree, w, saved, ints, scalars):
    """carried[:N] ← e^{τT} carried[:N]: powers.py's SchurPowers.advance, the same steps in the same
    order (Horner's Taylor polynomial with T, then the row's tables; ``schur`` and ``tables[m]`` packed;
    ``saved`` a buffer of N)."""
    n = w.shape[0]
    for q in range(n):
        w[q] = carried[q]
    if remainder != 0.0:
        for i in range(degree, 0, -1):
            _packed_product(schur, 0, lower, subs, w, saved)
            scalars[0] = remainder / i  # in the matrices' precision, as numpy's scalar
            a = scalars[0]
            for q in range(n):
                w[q] = w[q] * a + carried[q]  # two roundings, as numpy's two operations
    for j in range(indices.shape[0]):
        m = indices[j]
        if m >= 0:
            _packed_product(tables[m], m + 1, lower, subs, w, saved)
    for q in range(n):
        carried[q] = w[q]


@_jit
def run_schur(start, stop, propagator, projection, carried, following, mass, factor, observed, floors,
              sigma, scratch, masses, tiny, huge, schur, tables, lower, subs, indices, remainders, degree, w,
              saved):
    """Rows start..stop−1 at any times in the Schur coordinates of an ill-conditioned generator
    (loop_irregular's schur_rows): each row takes the carried coefficients through e^{τ_kT}
    (:func:`_advance`) before the two products.  Returns the row it stopped at (``stop``: all done)."""
    ints, scalars = buffers(propagator)
    for k in range(start, stop):
        _advance(carried, schur, tables, lower, subs, indices[k], remainders[k], degree, w, saved, ints,
                 scalars)
        new_mass = _row(k, propagator, propagator, projection, carried, following, mass, factor, observed,
                        sigma, scratch, ints, scalars)
        masses[k] = new_mass
        if not tiny < new_mass < huge or new_mass < floors[k]:
            return k
        mass = new_mass
        carried, following = following, carried
    return stop


@_jit
def _strayed(carried, mass, first, d, reach, shell_limit):
    """loops.py's trigger: the shell's Σwσ (carried[first + d]) over limit·∫σ, or an offset Σw(x − c)_iσ
    (carried[first:first + d]) beyond ±reach·∫σ, compared in double as there."""
    if float(carried[first + d]) > shell_limit * mass:
        return True
    for i in range(first, first + d):
        if not -reach * mass <= float(carried[i]) <= reach * mass:
            return True
    return False


@_jit
def run_moving(start, stop, propagator, observing, projection, carried, following, mass, factor, observed,
               floors, sigma, scratch, masses, tiny, huge, d, reach, shell_limit, quiet, last, modal, taus,
               real_rates, pair_rates):
    """Rows start..stop−1 on a ball that moves (loop_moving: the carried vector holds the trigger's d
    offsets and the shell's mass after ∫σ; ``modal``: irregular rows at gaps ``taus``, the modal
    coefficients first scaled by e^{τ_kΛ}, :func:`_scale_flow`).  Returns (row, strayed): the row it
    stopped at as :func:`run_rows` does, or (k + 1, True) after a row k ≠ ``last``, k ≥ ``quiet``,
    whose trigger fired (the driver moves the ball)."""
    ints, scalars = buffers(propagator)
    first = propagator.shape[1]
    scale = np.empty(3, propagator.dtype)
    for k in range(start, stop):
        if modal:
            _scale_flow(carried, taus[k], real_rates, pair_rates, scale)
        new_mass = _row(k, propagator, observing, projection, carried, following, mass, factor, observed,
                        sigma, scratch, ints, scalars)
        masses[k] = new_mass
        if not tiny < new_mass < huge or new_mass < floors[k]:
            return k, False
        mass = new_mass
        carried, following = following, carried
        if d > 0 and k != last and k >= quiet and _strayed(carried, mass, first, d, reach, shell_limit):
            return k + 1, True
    return stop, False


@_jit
def fused_row(k, terms, y, taus, constants, discrete, limit, factor, row, wide, ex, bits, summary, sums,
               weights, negative, mode, top, wide_ints, wide_scalars):
    """Row k's update and its moments' sums (fused.py), ``row`` holding s_k: the exponent
    Σ_j y_kj (hR⁻¹)_jq − τ_k·½hᵀR⁻¹h_q (continuous) or − ½hᵀR⁻¹h_q + c_k (discrete Gaussian) in
    measurement.py's order, its max ``top[k]``, e = exp(exponent − top) (:func:`exp_shifted`) rounded to
    the matrices' precision (0 under ``limit``), σ = s ⊙ e in ``row``; then ``sums[k]`` =
    the summary's columnsᵀ · σ (gemv('T')), ``negative[k]`` = Σ w min(σ, 0) and ``mode[k]`` = argmax σ
    (the first largest, as np.argmax).  False: an exponent not finite (the caller's Python path
    decides)."""
    hR, half = terms[:-1], terms[-1]
    best = -np.inf
    for q in range(row.shape[0]):
        a = y[k, 0] * hR[0, q]
        for j in range(1, hR.shape[0]):
            a += y[k, j] * hR[j, q]
        if discrete:
            a = a - half[q]
            a = a + constants[k]
        else:
            a = a - taus[k] * half[q]
        if not -np.inf < a < np.inf:
            return False
        wide[q] = a
        if a > best:
            best = a
    top[k] = best
    exp_shifted(wide, best, ex, bits)
    low, index, peak = 0.0, 0, -np.inf
    for q in range(row.shape[0]):
        factor[0] = ex[q]  # in the matrices' precision, as numpy's astype
        if factor[0] < limit[0]:
            factor[0] = 0.0
        v = row[q] * factor[0]
        row[q] = v
        wide[q] = v
        if v < 0.0:
            low += weights[q] * v
        if v > peak:
            peak, index = v, q
    negative[k], mode[k] = low, index
    gemv(1.0, summary, wide, sums[k], wide_ints, wide_scalars)
    return True


@_jit
def _scale_flow(carried, tau, real_rates, pair_rates, scale):
    """e^{τΛ} on the modal coefficients in place, the scales made here (semigroup.py's ``scales`` for
    one τ: exp(τλ) rounded to the matrices' precision through ``scale``), then :func:`scale_modal`'s
    operations."""
    r = real_rates.shape[0]
    for i in range(r):
        scale[0] = np.exp(tau * real_rates[i])
        carried[i] = carried[i] * scale[0]
    for j in range(pair_rates.shape[0]):
        z = np.exp(tau * pair_rates[j])
        scale[0] = z.real
        scale[1] = z.imag
        scale[2] = -z.imag
        u = carried[r + 2 * j]
        w = carried[r + 2 * j + 1]
        carried[r + 2 * j] = u * scale[0] + w * scale[2]
        carried[r + 2 * j + 1] = u * scale[1] + w * scale[0]


@_jit
def run_fused(start, stop, propagator, projection, carried, following, mass, terms, y, taus, constants,
              discrete, limit, floor_exponents, summary, weights, sums, negative, mode, top, masses, tiny,
              huge, modal, real_rates, pair_rates, triangular, schur, tables, lower, subs, indices,
              remainders, degree, w, saved, combined, operator, nodal, from_nodal):
    """Rows start..stop−1, every one observed, with the update factor and the moments' sums fused into
    each row (:func:`fused_row`): no K×Q arrays.  Irregular rows first take the carried coefficients
    through the row's flow: ``modal``, scaled by e^{τ_kΛ} (:func:`_scale_flow`); ``triangular``, through
    e^{τ_kT} in the Schur coordinates of an ill-conditioned generator (:func:`_advance`, with
    :func:`run_schur`'s arguments; placeholders of the same types otherwise).  ``combined`` (regular
    rows, ``operator`` = PΠ, Q × Q): after the chunk's first row, s_k = PΠσ_{k−1}/∫σ_{k−1} in one
    product, ∫σ_k = Σ w σ_k (``weights``, the projection's last row; the carried vector's ∫σ too) and
    Πσ only after the last row, whose σ is left in ``nodal``; ``from_nodal``: the first row too, from
    the previous chunk's ``nodal`` (:func:`nodal_matches`), so that chunks continue bit for bit.
    Returns the first row that needs the Python path (an exponent not finite, ∫σ out of (tiny, huge) or
    under the gate's floor exp(floor_exponent − top)), or ``stop``."""
    ints, scalars = buffers(propagator)
    wide_ints, wide_scalars = summary_buffers(summary)
    n = propagator.shape[1] - 1
    row, factor = np.empty(propagator.shape[0], propagator.dtype), np.empty(1, propagator.dtype)
    previous = np.empty(propagator.shape[0], propagator.dtype)
    ex, bits = np.empty(propagator.shape[0]), np.empty(propagator.shape[0], np.int64)
    wide, scale = np.empty(propagator.shape[0]), np.empty(3, propagator.dtype)
    for k in range(start, stop):
        if modal:
            _scale_flow(carried, taus[k], real_rates, pair_rates, scale)
        elif triangular:
            _advance(carried, schur, tables, lower, subs, indices[k], remainders[k], degree, w, saved, ints,
                     scalars)
        if combined and k > start:
            gemv(1.0 / mass, operator, previous, row, ints, scalars)  # s_k = PΠσ_{k−1}/∫σ_{k−1}
        elif combined and from_nodal:
            gemv(1.0 / mass, operator, nodal, row, ints, scalars)
        else:
            gemv(1.0 / mass, propagator, carried, row, ints, scalars)
        if not fused_row(k, terms, y, taus, constants, discrete, limit, factor, row, wide, ex, bits, summary,
                          sums, weights, negative, mode, top, wide_ints, wide_scalars):
            return k
        if combined:
            new_mass = row_mass(weights, row)
            if k + 1 < stop:
                previous, row = row, previous
            else:
                gemv(1.0, projection, row, following, ints, scalars)
                following[n] = new_mass
                nodal[:] = row
        else:
            gemv(1.0, projection, row, following, ints, scalars)
            new_mass = float(following[n])
        masses[k] = new_mass
        if not tiny < new_mass < huge or new_mass < np.exp(floor_exponents[k] - top[k]):
            return k
        mass = new_mass
        carried, following = following, carried  # combined: only the last row's is written (the same buffer)
    return stop


@_jit
def row_mass(weights, row):
    """∫σ = Σ w σ in one pass (the combined rows' mass, :func:`run_fused`)."""
    total = 0.0
    for q in range(row.shape[0]):
        total += weights[q] * row[q]
    return total


@_jit
def nodal_matches(projection, nodal, weights, carried):
    """Whether σ ``nodal`` is the one whose Πσ and Σ w σ :func:`run_fused` left as ``carried`` (c, ∫σ):
    a state's ``nodal`` continues its chunk only then (the coefficients changed since: not)."""
    ints, scalars = buffers(projection)
    out = np.empty(projection.shape[0], projection.dtype)
    gemv(1.0, projection, nodal, out, ints, scalars)
    n = projection.shape[0] - 1
    for i in range(n):
        if out[i] != carried[i]:
            return False
    return row_mass(weights, nodal) == carried[n]


@_jit
def sum_rows(sigma, summary, weights, sums, negative, mode):
    """What :func:`fused_row` keeps of each row of a chunk's σ (K, Q) that the loops kept: the same
    operations in the same order (a compiled chunk's moments do not depend on whether it ran fused)."""
    wide_ints, wide_scalars = summary_buffers(summary)
    wide = np.empty(sigma.shape[1])
    for k in range(sigma.shape[0]):
        low, index, peak = 0.0, 0, -np.inf
        for q in range(sigma.shape[1]):
            v = sigma[k, q]
            wide[q] = v
            if v < 0.0:
                low += weights[q] * v
            if v > peak:
                peak, index = v, q
        negative[k], mode[k] = low, index
        gemv(1.0, summary, wide, sums[k], wide_ints, wide_scalars)


@_jit
def exp_factors(log_factor, limit, factor):
    """factor = exp(log factor) (:func:`exp_shifted`, as :func:`fused_row`'s) in the matrices'
    precision, 0 under ``limit``: for the compiled loops that keep σ."""
    wide, bits = np.empty(log_factor.shape[1]), np.empty(log_factor.shape[1], np.int64)
    for k in range(log_factor.shape[0]):
        exp_shifted(log_factor[k], 0.0, wide, bits)
        for q in range(log_factor.shape[1]):
            factor[k, q] = wide[q]
            if factor[k, q] < limit[0]:
                factor[k, q] = 0.0


@_jit
def products(rows, propagator, projection, carried, following, row):
    """Only the two products of each row, ``rows`` times (bench/compiled_kernels.py: the BLAS floor)."""
    ints, scalars = buffers(propagator)
    for _ in range(rows):
        gemv(1.0, propagator, carried, row, ints, scalars)
        gemv(1.0, projection, row, following, ints, scalars)


numba.config.CACHE_DIR = _previous_cache_dir
