"""The sensor's expressions as a register program (a tape) that one compiled kernel interprets.

The Yau–Jia kernels need h, ∂h and ∂²h at each component's cubature points and h at the check
points of the error control (solver/exact/yau_jia_fast.py).  The expressions are SymPy trees built
from the whitelisted ast of solver/expressions.py (never from user text); here they are walked, after
SymPy's common-subexpression elimination, into a flat list of instructions ``(op, a, b)`` on a
register file: registers 0..n−1 hold the point, then the constants, then one register per
instruction.  :func:`solver.exact.sensor_kernel.run_tape` interprets it for every point — one kernel
for every sensor, cached on disk by numba like the others, so a new expression costs no compilation
(measured against numba-compiling a ``lambdify(..., modules='math')`` function per expression:
bench/results/yau-jia-speed.md).

Arithmetic as the numpy path's ``lambdify`` prints it: x**2 as x·x, x**0.5 as sqrt, x**−1 as 1/x,
other powers by pow; Heaviside(x) (∂ max, ∂ min) is ½ at 0, DiracDelta (∂ sign) is 0.  A node
outside this table raises :class:`Uncompilable` (the caller keeps the numpy path).  Imports no numba.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np
import sympy as sp

# op codes of run_tape (solver/exact/sensor_kernel.py); "b" is a second register where the op has one
ADD, SUB, MUL, DIV, NEG, INV, SQUARE, SQRT, POW = range(9)
UNARY = {sp.exp: 9, sp.log: 10, sp.sin: 11, sp.cos: 12, sp.tan: 13, sp.tanh: 14, sp.sinh: 15,
         sp.cosh: 16, sp.atan: 17, sp.asin: 18, sp.acos: 19, sp.asinh: 20, sp.acosh: 21, sp.atanh: 22,
         sp.Abs: 23, sp.sign: 24}
ATAN2, MIN, MAX, HEAVISIDE = 25, 26, 27, 28


class Uncompilable(ValueError):
    """The expressions hold a node the tape has no instruction for (the message names it)."""


@dataclass(frozen=True)
class Tape:
    """``code`` (K, 3) int64 rows (op, a, b) writing register n + C + k; ``constants`` (C,) loaded into
    registers n..n+C−1; ``outputs``: the register of each output column."""

    n: int
    code: np.ndarray
    constants: np.ndarray
    outputs: np.ndarray

    @property
    def registers(self) -> int:
        return self.n + len(self.constants) + len(self.code)


class _Builder:
    def __init__(self, symbols: Sequence[sp.Symbol]):
        self.n = len(symbols)
        self.reg: dict[sp.Expr, int] = {s: i for i, s in enumerate(symbols)}
        self.constants: list[float] = []
        self.code: list[tuple[int, int, int]] = []
        self.pending: dict[tuple[int, int, int], int] = {}

    def constant(self, value: float) -> int:
        key = ("const", float(value))
        if key not in self.reg:
            self.reg[key] = len(self.constants)  # renumbered in tape()
            self.constants.append(float(value))
        return -1 - self.reg[key]  # negative: a constant's index, resolved in tape()

    def emit(self, op: int, a: int, b: int = 0) -> int:
        key = (op, a, b)
        if key not in self.pending:
            self.code.append(key)
            self.pending[key] = len(self.code) - 1 + (1 << 40)  # an instruction's result, resolved in tape()
        return self.pending[key]

    def build(self, expr: sp.Expr) -> int:
        if expr in self.reg:
            return self.reg[expr]
        out = self._node(expr)
        self.reg[expr] = out
        return out

    def _node(self, expr: sp.Expr) -> int:
        if expr.is_Number or expr.is_NumberSymbol:
            return self.constant(float(expr))
        if expr.is_Add:
            return self._add(expr.args)
        if expr.is_Mul:
            return self._mul(expr.args)
        if expr.is_Pow:
            return self._pow(*expr.args)
        head = expr.func
        if head in UNARY and len(expr.args) == 1:
            return self.emit(UNARY[head], self.build(expr.args[0]))
        if head is sp.atan2:
            return self.emit(ATAN2, self.build(expr.args[0]), self.build(expr.args[1]))
        if head in (sp.Min, sp.Max):
            regs = [self.build(a) for a in expr.args]
            out = regs[0]
            for r in regs[1:]:
                out = self.emit(MIN if head is sp.Min else MAX, out, r)
            return out
        if head is sp.Heaviside:
            at_zero = float(expr.args[1]) if len(expr.args) > 1 else 0.5
            return self.emit(HEAVISIDE, self.build(expr.args[0]), self.constant(at_zero))
        if head is sp.DiracDelta:
            return self.constant(0.0)
        raise Uncompilable(f"no tape instruction for {head.__name__}")

    def _add(self, args) -> int:
        plus, minus = [], []
        for a in args:
            coeff = a.as_coeff_Mul()[0]
            (minus if coeff.is_negative else plus).append(-a if coeff.is_negative else a)
        regs_plus, regs_minus = [self.build(a) for a in plus], [self.build(a) for a in minus]
        out = regs_plus[0] if regs_plus else self.emit(NEG, regs_minus.pop(0))
        for r in regs_plus[1:]:
            out = self.emit(ADD, out, r)
        for r in regs_minus:
            out = self.emit(SUB, out, r)
        return out

    def _mul(self, args) -> int:
        num, den, sign = [], [], 1
        for a in args:
            if a == -1:
                sign = -sign
            elif a.is_Pow and a.exp.is_Number and a.exp.is_negative:
                den.append(a.base if a.exp == -1 else sp.Pow(a.base, -a.exp, evaluate=False))
            else:
                num.append(a)
        regs_num, regs_den = [self.build(a) for a in num], [self.build(a) for a in den]
        out = regs_num[0] if regs_num else None
        for r in regs_num[1:]:
            out = self.emit(MUL, out, r)
        if regs_den:
            below = regs_den[0]
            for r in regs_den[1:]:
                below = self.emit(MUL, below, r)
            out = self.emit(INV, below) if out is None else self.emit(DIV, out, below)
        return self.emit(NEG, out) if sign < 0 else out

    def _pow(self, base: sp.Expr, exponent: sp.Expr) -> int:
        if exponent == 2:
            return self.emit(SQUARE, self.build(base))
        if exponent == sp.Rational(1, 2):
            return self.emit(SQRT, self.build(base))
        if exponent == -1:
            return self.emit(INV, self.build(base))
        if base == sp.E:
            return self.emit(UNARY[sp.exp], self.build(exponent))
        return self.emit(POW, self.build(base), self.build(exponent))

    def tape(self, outputs: list[int]) -> Tape:
        n, C = self.n, len(self.constants)

        def resolve(r: int) -> int:
            if r < 0:
                return n + (-1 - r)
            if r >= 1 << 40:
                return n + C + (r - (1 << 40))
            return r

        code = np.array([(op, resolve(a), resolve(b)) for op, a, b in self.code], np.int64).reshape(-1, 3)
        return Tape(n, code, np.array(self.constants, float),
                    np.array([resolve(r) for r in outputs], np.int64))


@lru_cache(maxsize=32)
def build_tape(exprs: tuple[sp.Expr, ...], symbols: tuple[sp.Symbol, ...]) -> Tape:
    """The tape of ``exprs`` (one output column each) in ``symbols``, cached on their content (SymPy
    compares trees); :class:`Uncompilable` where a node has no instruction."""
    replacements, reduced = sp.cse(list(exprs))
    builder = _Builder(symbols)
    for symbol, expr in replacements:
        builder.reg[symbol] = builder.build(expr)
    return builder.tape([builder.build(e) for e in reduced])


def sensor_tapes(h: Sequence[sp.Expr], symbols: Sequence[sp.Symbol]) -> tuple[Tape, Tape]:
    """(the tape of h, ∂h, ∂²h row-major: the columns of yau_jia._Sensor.flat; the tape of h alone)."""
    jac = [sp.diff(hi, s) for hi in h for s in symbols]
    hess = [sp.diff(hi, s, t) for hi in h for s in symbols for t in symbols]
    symbols = tuple(symbols)
    return build_tape(tuple(h) + tuple(jac + hess), symbols), build_tape(tuple(h), symbols)
