"""One piece of a Yau–Jia row in one compiled call: the step, the sensor, the error control.

The kernels of solver/exact/mixture_kernels.py and solver/exact/mixture_control.py in the order of
YauJiaFilter._row's loop body (the step over an interval, the normalisation, the error control, the
normalisation again), with the sensor's h, ∂h, ∂²h evaluated between them by the tape interpreter
(solver/exact/sensor_kernel.py) instead of by numpy in Python: one kernel call per piece, no Python
between the stages.  Returns a code (OK, or FALLBACK: the numpy path takes the piece) and the new
mixture; numbers as the stages called one by one (tests/solver/exact/test_yau_jia_fast.py).
"""

from __future__ import annotations

import numba
import numpy as np

from .mixture_control import control, finish_control, normalise_axes, rates
from .mixture_kernels import (
    CACHE_DIR,
    FALLBACK,
    OK,
    kernel,
    observe_finish,
    observe_flow,
    predict_flow,
    prepare,
)
from .sensor_kernel import run_tape

_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)


@kernel
def sense(tape, X, regs):
    """The tape's columns at the points X (P, n); ``tape``: (code, constants, outputs)."""
    code, constants, outputs = tape
    F = np.empty((X.shape[0], outputs.shape[0]))
    run_tape(code, constants, outputs, X, regs, F)
    return F


@kernel
def step(A, B, C, observed, c, c_dot, q, r, flow, full, regs, clipped):
    """The step over one interval (mixture_kernels.observe_flow and observe_finish; ``observed``
    False: predict_flow); ``flow``: (Phi, Psi, w, D, d, a, dt).  Returns (code, A, B, C)."""
    Phi, Psi, w, D, d, a, dt = flow
    J, n = B.shape
    A1, B1, C1 = np.empty_like(A), np.empty_like(B), np.empty_like(C)
    if not observed:
        return predict_flow(A, B, C, q, r, Phi, Psi, w, D, d, a, dt, A1, B1, C1), A1, B1, C1
    ws = np.empty((n, n))
    means, covs, lm = np.empty((J, n)), np.empty((J, n, n)), np.empty(J)
    points = np.empty((J, 2 * n, n))
    A2, B2, C2 = np.empty_like(A), np.empty_like(B), np.empty_like(C)
    if prepare(A, B, C, means, covs, lm, points, ws) != OK:
        return FALLBACK, A2, B2, C2
    F0 = sense(full, points.reshape((J * 2 * n, n)), regs)
    m = c.shape[0]
    means1, covs1, lm1 = np.empty((J, n)), np.empty((J, n, n)), np.empty(J)
    points1 = np.empty((J, 2 * n, n))
    h0, J0 = np.empty((J, m)), np.empty((J, m, n))
    if observe_flow(A, B, C, means, covs, F0, c, c_dot, q, r, Phi, Psi, w, D, d, a, dt, A1, B1, C1,
                    means1, covs1, lm1, points1, h0, J0, ws, clipped) != OK:
        return FALLBACK, A2, B2, C2
    F1 = sense(full, points1.reshape((J * 2 * n, n)), regs)
    return observe_finish(A1, B1, C1, means, means1, covs1, F1, h0, J0, c, A2, B2, C2, clipped), A2, B2, C2


@kernel
def piece(A, B, C, observed, c, c_dot, q, r, flow, full, values, whiten, settings, split):
    """The step (:func:`step`), the normalisation, the rates on the kept components, the split and
    merge choices, the new exponents, the normalisation again and σ's moments.  ``settings``: (prune,
    σ of the check points, split tolerance, split budget, cap); ``split``: (weights, offsets, width).
    Returns (code, A, B, C, log ∫σ gained, clipped, splits, logw, means, covs, mean, cov)."""
    prune, sigma, tolerance, budget, cap = settings
    J, n = B.shape
    registers = n + max(full[0].shape[0] + full[1].shape[0], values[0].shape[0] + values[1].shape[0])
    regs = np.empty((registers, 2 * n * J))  # Tape.registers rows, one column per point
    clipped = np.zeros(1, np.int64)
    code, A, B, C = step(A, B, C, observed, c, c_dot, q, r, flow, full, regs, clipped)
    means, covs, logw, C_norm = np.empty((J, n)), np.empty((J, n, n)), np.empty(J), np.empty(J)
    kept, lam, U = np.empty(J, np.int64), np.empty((J, n)), np.empty((J, n, n))
    points = np.empty((J, n, 2, n))
    mean, cov = np.empty(n), np.empty((n, n))
    if code != OK:
        return FALLBACK, A, B, C, 0.0, 0, 0, logw, means, covs, mean, cov
    code, gain, count = normalise_axes(A, B, C, prune, means, covs, logw, C_norm, kept, lam, U,
                                       points, np.empty((n, n)), sigma)
    if code != OK:
        return FALLBACK, A, B, C, 0.0, 0, 0, logw, means, covs, mean, cov
    idx = kept[:count]
    means_k, covs_k, logw_k = means[idx], covs[idx], logw[idx]
    lam_k, U_k = lam[:count], U[:count]
    F = sense(full, means_k, regs)
    h_at = sense(values, points.reshape((J * n * 2, n))[:count * n * 2], regs)
    rate = np.empty((count, n))
    rates(means_k, F, h_at, lam_k, U_k, whiten, sigma, rate)
    weights, offsets, width = split
    means2, covs2, logw2, splits = control(means_k, covs_k, logw_k, rate, lam_k, U_k, weights, offsets,
                                           width, tolerance, budget, cap)
    J2 = logw2.shape[0]
    A_out, B_out, C_out = np.empty((J2, n, n)), np.empty((J2, n)), np.empty(J2)
    code, _ = finish_control(means2, covs2, logw2, splits > 0 or J2 != J, A, B, C_norm, A_out, B_out,
                             C_out, mean, cov)
    return code, A_out, B_out, C_out, gain, clipped[0], splits, logw2, means2, covs2, mean, cov


numba.config.CACHE_DIR = _previous_cache_dir
