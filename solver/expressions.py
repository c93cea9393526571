"""Safe model expressions: user text -> SymPy -> vectorised numpy.

User text is parsed with :mod:`ast` and checked node by node against a whitelist
(numbers, the declared state names, parameters, ``+ - * / **``, unary minus and
calls of a fixed set of math functions).  The SymPy expression is then built by
hand from the checked tree.  Nothing here calls ``eval``, ``exec``, ``sympify``
or ``parse_expr`` on user text, and the SymPy symbols carry names chosen here
(``x_0, x_1, ...``), never the user's: ``lambdify`` prints symbol names into
generated source, so a user-chosen name would be code.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping, Sequence

import numpy as np
import sympy as sp

from .errors import SpecError

MAX_LENGTH = 2000  # characters of one expression
MAX_NODES = 400  # AST nodes of one expression
MAX_DEPTH = 40  # nesting depth of the AST
MAX_EXPONENT = 64  # |p| for a constant exponent
MAX_LOG_MAGNITUDE = 700.0  # |log|b**p|| for a constant power (float range)

_UNARY_FUNCTIONS = {
    "exp": sp.exp,
    "log": sp.log,
    "sqrt": sp.sqrt,
    "sin": sp.sin,
    "cos": sp.cos,
    "tan": sp.tan,
    "tanh": sp.tanh,
    "sinh": sp.sinh,
    "cosh": sp.cosh,
    "atan": sp.atan,
    "asin": sp.asin,
    "acos": sp.acos,
    "asinh": sp.asinh,
    "acosh": sp.acosh,
    "atanh": sp.atanh,
    "abs": sp.Abs,
    "sech": lambda u: 1 / sp.cosh(u),
    "sign": sp.sign,
}
_BINARY_FUNCTIONS = {"atan2": sp.atan2, "min": sp.Min, "max": sp.Max}
_CONSTANTS = {"pi": sp.pi, "e": sp.E}
RESERVED_NAMES = frozenset(_UNARY_FUNCTIONS) | frozenset(_BINARY_FUNCTIONS) | frozenset(_CONSTANTS)

_BINOPS = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
}


def state_symbols(n: int) -> tuple[sp.Symbol, ...]:
    """Internal, real symbols for the state coordinates (never user names)."""
    return tuple(sp.Symbol(f"x_{i}", real=True) for i in range(n))


def number(value: float | int) -> sp.Expr:
    """Exact SymPy number for a Python number (0.2 -> 1/5), so the analysis is exact."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError("not a number")
    if isinstance(value, int):
        return sp.Integer(value)
    if not math.isfinite(value):
        raise ValueError("number must be finite")
    return sp.Rational(repr(value))


class _Builder:
    def __init__(self, field: str, names: Mapping[str, sp.Expr]):
        self.field = field
        self.names = names

    def fail(self, message: str) -> SpecError:
        return SpecError(self.field, message)

    def build(self, node: ast.AST) -> sp.Expr:
        if isinstance(node, ast.Constant):
            return self._constant(node.value)
        if isinstance(node, ast.Name):
            return self._name(node.id)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            inner = self.build(node.operand)
            return -inner if isinstance(node.op, ast.USub) else inner
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return self._checked(_BINOPS[type(node.op)](self.build(node.left), self.build(node.right)))
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow):
            return self._power(self.build(node.left), self.build(node.right))
        if isinstance(node, ast.Call):
            return self._call(node)
        raise self.fail(f"'{type(node).__name__}' is not allowed in an expression")

    def _constant(self, value: object) -> sp.Expr:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(f"only real numbers are allowed as constants, not {type(value).__name__}")
        if isinstance(value, int) and abs(value) > 10**15:
            raise self.fail("integer constant too large")
        if isinstance(value, float) and not math.isfinite(value):
            raise self.fail("constant is not finite")
        return number(value)

    def _name(self, name: str) -> sp.Expr:
        if name in self.names:
            return self.names[name]
        if name in _CONSTANTS:
            return _CONSTANTS[name]
        known = ", ".join(sorted(self.names)) or "none"
        raise self.fail(f"unknown name '{name}' (state variables and parameters: {known})")

    def _power(self, base: sp.Expr, exponent: sp.Expr) -> sp.Expr:
        if exponent.is_number:
            p = complex(exponent.evalf())
            if p.imag != 0 or abs(p.real) > MAX_EXPONENT:
                raise self.fail(f"exponent must be a real number with |p| <= {MAX_EXPONENT}")
            if base.is_number:
                b = abs(complex(base.evalf()))
                if b != 0 and abs(p.real * math.log(b)) > MAX_LOG_MAGNITUDE:
                    raise self.fail("constant power out of floating-point range")
        elif not (base.is_number and base.is_positive):
            raise self.fail("a non-constant exponent needs a positive constant base (use exp(...))")
        return self._checked(sp.Pow(base, exponent))

    def _call(self, node: ast.Call) -> sp.Expr:
        if not isinstance(node.func, ast.Name):
            raise self.fail("only calls of the allowed math functions are allowed")
        name = node.func.id
        if node.keywords:
            raise self.fail(f"{name}() takes no keyword arguments")
        if name in _UNARY_FUNCTIONS:
            arity, fn = 1, _UNARY_FUNCTIONS[name]
        elif name in _BINARY_FUNCTIONS:
            arity, fn = 2, _BINARY_FUNCTIONS[name]
        else:
            allowed = ", ".join(sorted(set(_UNARY_FUNCTIONS) | set(_BINARY_FUNCTIONS)))
            raise self.fail(f"unknown function '{name}' (allowed: {allowed})")
        if len(node.args) != arity or any(isinstance(a, ast.Starred) for a in node.args):
            raise self.fail(f"{name}() takes exactly {arity} argument(s)")
        return self._checked(fn(*(self.build(a) for a in node.args)))

    def _checked(self, expr: sp.Expr) -> sp.Expr:
        if expr.has(sp.zoo, sp.oo, -sp.oo, sp.nan):
            raise self.fail("expression is undefined (division by zero or infinite value)")
        if expr.is_number and expr.has(sp.I):
            raise self.fail("expression is not real")
        return expr


def _depth(node: ast.AST, limit: int) -> int:
    stack = [(node, 1)]
    deepest = 0
    while stack:
        current, d = stack.pop()
        deepest = max(deepest, d)
        if deepest > limit:
            return deepest
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(current))
    return deepest


def parse_expression(text: str, names: Mapping[str, sp.Expr], field: str = "expression") -> sp.Expr:
    """Parse one user expression into SymPy, or raise :class:`SpecError` naming ``field``.

    ``names`` maps the allowed user names (state variables, parameters) to SymPy objects
    chosen by the caller (internal symbols or exact numbers).
    """
    if not isinstance(text, str):
        raise SpecError(field, "expression must be a string")
    if not text.strip():
        raise SpecError(field, "expression is empty")
    if len(text) > MAX_LENGTH:
        raise SpecError(field, f"expression longer than {MAX_LENGTH} characters")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        detail = exc.msg if isinstance(exc, SyntaxError) else "cannot be parsed"
        raise SpecError(field, f"invalid expression syntax: {detail}") from None
    if sum(1 for _ in ast.walk(tree)) > MAX_NODES:
        raise SpecError(field, f"expression has more than {MAX_NODES} syntax nodes")
    if _depth(tree, MAX_DEPTH) > MAX_DEPTH:
        raise SpecError(field, f"expression nested deeper than {MAX_DEPTH}")
    try:
        expr = _Builder(field, names).build(tree.body)
    except SpecError:
        raise
    except (RecursionError, MemoryError, OverflowError, ValueError, TypeError, ZeroDivisionError):
        raise SpecError(field, "expression cannot be evaluated safely") from None
    return expr


def vectorize(expr: sp.Expr, symbols: Sequence[sp.Symbol]):
    """numpy function of points X (shape (P, n)) returning shape (P,) for one expression."""
    fn = sp.lambdify(list(symbols), expr, modules="numpy")

    def evaluate(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        with np.errstate(all="ignore"):
            value = fn(*X.T)
        return np.broadcast_to(np.asarray(value, dtype=float), (X.shape[0],)).copy()

    return evaluate


def vectorize_many(exprs: Sequence[sp.Expr], symbols: Sequence[sp.Symbol]):
    """numpy function of points X (P, n) returning (P, len(exprs))."""
    parts = [vectorize(e, symbols) for e in exprs]

    def evaluate(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if not parts:
            return np.zeros((X.shape[0], 0))
        return np.stack([p(X) for p in parts], axis=1)

    return evaluate
