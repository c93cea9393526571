"""The interpreter of a sensor tape (solver/exact/sensor_tape.py), compiled by numba and cached on disk
with the mixture kernels (solver/exact/mixture_kernels.py): one kernel for every expression."""

from __future__ import annotations

import math

import numba
import numpy as np

from .mixture_kernels import CACHE_DIR, kernel

_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)


@kernel
def apply(op, u, v):
    """Instruction ``op`` of solver/exact/sensor_tape.py on the values u (and v), for the ops
    :func:`run_tape` does not loop over itself; NaN in, NaN out, as numpy."""
    if op == 5:
        return 1.0 / u
    if op == 7:
        return math.sqrt(u) if u >= 0.0 else np.nan
    if op == 8:
        return u**v
    if op == 9:
        return math.exp(u)
    if op == 10:
        return math.log(u) if u > 0.0 else (-np.inf if u == 0.0 else np.nan)
    if op == 11:
        return math.sin(u)
    if op == 12:
        return math.cos(u)
    if op == 13:
        return math.tan(u)
    if op == 14:
        return math.tanh(u)
    if op == 15:
        return math.sinh(u)
    if op == 16:
        return math.cosh(u)
    if op == 17:
        return math.atan(u)
    if op == 20:
        return math.asinh(u)
    if op == 23:
        return abs(u)
    if op == 25:
        return math.atan2(u, v)
    return inverse_or_step(op, u, v)


@kernel
def inverse_or_step(op, u, v):
    """asin, acos, acosh, atanh (NaN outside their domain, ±inf at atanh(±1)), sign, min, max and
    Heaviside (v at 0)."""
    if u != u:
        return u
    if op == 18 or op == 19:
        if abs(u) > 1.0:
            return np.nan
        return math.asin(u) if op == 18 else math.acos(u)
    if op == 21:
        return math.acosh(u) if u >= 1.0 else np.nan
    if op == 22:
        return math.atanh(u) if abs(u) < 1.0 else (math.copysign(np.inf, u) if abs(u) == 1.0 else np.nan)
    if op == 24:
        return 1.0 if u > 0.0 else (-1.0 if u < 0.0 else 0.0)
    if op == 28:
        return 1.0 if u > 0.0 else (0.0 if u < 0.0 else v)
    if v != v:
        return v
    return min(u, v) if op == 26 else max(u, v)


@kernel
def run_tape(code, constants, outputs, X, regs, F):
    """F[p, c] = output c of the tape at the point X[p]; instruction by instruction over all points
    (the op chosen once per instruction, the loop over points vectorised).  ``regs``: scratch of at
    least (Tape.registers, len(X))."""
    P, n = X.shape
    C = constants.shape[0]
    for i in range(n):
        for p in range(P):
            regs[i, p] = X[p, i]
    for c in range(C):
        regs[n + c, :P] = constants[c]
    base = n + C
    for k in range(code.shape[0]):
        op, a, b = code[k, 0], code[k, 1], code[k, 2]
        out, u, v = regs[base + k], regs[a], regs[b]
        if op == 2:
            for p in range(P):
                out[p] = u[p] * v[p]
        elif op == 0:
            for p in range(P):
                out[p] = u[p] + v[p]
        elif op == 1:
            for p in range(P):
                out[p] = u[p] - v[p]
        elif op == 3:
            for p in range(P):
                out[p] = u[p] / v[p]
        elif op == 6:
            for p in range(P):
                out[p] = u[p] * u[p]
        elif op == 4:
            for p in range(P):
                out[p] = -u[p]
        else:
            for p in range(P):
                out[p] = apply(op, u[p], v[p])
    for p in range(P):
        for c in range(outputs.shape[0]):
            F[p, c] = regs[outputs[c], p]


numba.config.CACHE_DIR = _previous_cache_dir
