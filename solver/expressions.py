"""Safe model expressions: user text -> a checked syntax tree -> numpy closures, or SymPy.

User text is parsed with :mod:`ast` and checked node by node against a whitelist
(numbers, the declared state names, parameters, ``+ - * / **``, unary minus and
calls of a fixed set of math functions).  Two builders walk the checked tree:

* :func:`numeric_expression` composes numpy closures (no code is generated or evaluated,
  and SymPy is not imported: this is what a stored model needs to filter, so start-up stays
  cheap);
* :func:`parse_expression` builds the exact SymPy expression for the offline stage and the
  analysis (derivatives, Lie brackets).

Nothing here calls ``eval``, ``exec``, ``sympify`` or ``parse_expr`` on user text, and the SymPy
symbols carry names chosen here (``x_0, x_1, ...``), never the user's: ``lambdify`` prints symbol
names into generated source, so a user-chosen name would be code.
"""

from __future__ import annotations

import ast
import math
import unicodedata
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .errors import SpecError

if TYPE_CHECKING:
    import sympy as sp

MAX_LENGTH = 2000  # characters of one expression
MAX_NODES = 400  # AST nodes of one expression
MAX_DEPTH = 40  # nesting depth of the AST
MAX_EXPONENT = 64  # |p| for a constant exponent
MAX_LOG_MAGNITUDE = 700.0  # |log|b**p|| for a constant power (float range)

# name -> arity of the allowed functions; both builders map every one of them
FUNCTIONS = {name: 1 for name in ("exp", "log", "sqrt", "sin", "cos", "tan", "tanh", "sinh", "cosh", "atan",
                                  "asin", "acos", "asinh", "acosh", "atanh", "abs", "sech", "sign")}
FUNCTIONS.update(atan2=2, min=2, max=2)
# Continuous but not differentiable everywhere: values are all the general engine needs; their
# derivatives are taken almost everywhere (d|x| = sign x, d sign x = 0 off x = 0) by the Gaussian
# filters' Jacobians, and the analysis refuses the exact filters for them (docs/models.md).
NONSMOOTH = ("abs", "sign", "min", "max")
CONSTANTS = {"pi": math.pi, "e": math.e}
RESERVED_NAMES = frozenset(FUNCTIONS) | frozenset(CONSTANTS)

_NUMPY_FUNCTIONS: dict[str, Callable[..., Any]] = {
    "exp": np.exp, "log": np.log, "sqrt": np.sqrt, "sin": np.sin, "cos": np.cos, "tan": np.tan,
    "tanh": np.tanh, "sinh": np.sinh, "cosh": np.cosh, "atan": np.arctan, "asin": np.arcsin,
    "acos": np.arccos, "asinh": np.arcsinh, "acosh": np.arccosh, "atanh": np.arctanh, "abs": np.abs,
    "sech": lambda u: 1.0 / np.cosh(u), "sign": np.sign, "atan2": np.arctan2, "min": np.minimum,
    "max": np.maximum,
}
assert set(_NUMPY_FUNCTIONS) == set(FUNCTIONS)


def _sympy_tables() -> tuple[dict[str, Callable[..., Any]], dict[str, Any]]:
    import sympy as sp

    functions = {"exp": sp.exp, "log": sp.log, "sqrt": sp.sqrt, "sin": sp.sin, "cos": sp.cos, "tan": sp.tan,
                 "tanh": sp.tanh, "sinh": sp.sinh, "cosh": sp.cosh, "atan": sp.atan, "asin": sp.asin,
                 "acos": sp.acos, "asinh": sp.asinh, "acosh": sp.acosh, "atanh": sp.atanh, "abs": sp.Abs,
                 "sech": lambda u: 1 / sp.cosh(u), "sign": sp.sign, "atan2": sp.atan2, "min": sp.Min,
                 "max": sp.Max}
    assert set(functions) == set(FUNCTIONS)
    return functions, {"pi": sp.pi, "e": sp.E}


_BINOPS = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
}


def state_symbols(n: int) -> tuple["sp.Symbol", ...]:
    """Internal, real symbols for the state coordinates (never user names)."""
    import sympy as sp

    return tuple(sp.Symbol(f"x_{i}", real=True) for i in range(n))


def number(value: float | int) -> "sp.Expr":
    """Exact SymPy number for a Python number (0.2 -> 1/5), so the analysis is exact."""
    import sympy as sp

    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError("not a number")
    if isinstance(value, int):
        return sp.Integer(value)
    if not math.isfinite(value):
        raise ValueError("number must be finite")
    return sp.Rational(repr(value))


class _Builder:
    def __init__(self, field: str, names: Mapping[str, "sp.Expr"]):
        self.field = field
        self.names = names
        self.functions, self.constants = _sympy_tables()

    def fail(self, message: str) -> SpecError:
        return SpecError(self.field, message)

    def build(self, node: ast.AST) -> "sp.Expr":
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

    def _constant(self, value: object) -> "sp.Expr":
        return number(_checked_constant(self, value))

    def _name(self, name: str) -> "sp.Expr":
        if name in self.names:
            return self.names[name]
        if name in self.constants:
            return self.constants[name]
        raise self.fail(_unknown_name(name, self.names))

    def _power(self, base: "sp.Expr", exponent: "sp.Expr") -> "sp.Expr":
        import sympy as sp

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

    def _call(self, node: ast.Call) -> "sp.Expr":
        name = _checked_call(self, node)
        return self._checked(self.functions[name](*(self.build(a) for a in node.args)))

    def _checked(self, expr: "sp.Expr") -> "sp.Expr":
        import sympy as sp

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


def _checked_constant(builder: Any, value: object) -> float | int:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise builder.fail(f"only real numbers are allowed as constants, not {type(value).__name__}")
    if isinstance(value, int) and abs(value) > 10**15:
        raise builder.fail("integer constant too large")
    if isinstance(value, float) and not math.isfinite(value):
        raise builder.fail("constant is not finite")
    return value


def _unknown_name(name: str, names: Mapping[str, Any]) -> str:
    known = ", ".join(sorted(names)) or "none"
    return f"unknown name '{name}' (state variables and parameters: {known})"


def _checked_call(builder: Any, node: ast.Call) -> str:
    """The called function's name, after checking it is allowed with its arity."""
    if not isinstance(node.func, ast.Name):
        raise builder.fail("only calls of the allowed math functions are allowed")
    name = node.func.id
    if node.keywords:
        raise builder.fail(f"{name}() takes no keyword arguments")
    if name not in FUNCTIONS:
        raise builder.fail(f"unknown function '{name}' (allowed: {', '.join(sorted(FUNCTIONS))})")
    arity = FUNCTIONS[name]
    if len(node.args) != arity or any(isinstance(a, ast.Starred) for a in node.args):
        raise builder.fail(f"{name}() takes exactly {arity} argument(s)")
    return name


# -- numpy closures -------------------------------------------------------------------------------
Columns = tuple  # the state coordinates x_0, x_1, ... as arrays of the points


@dataclass(frozen=True)
class _Num:
    """A built node: ``value`` for a constant (folded), else ``fn(columns) -> array``."""

    fn: Callable[[Columns], Any] | None = None
    value: float | None = None

    def __call__(self, cols: Columns) -> Any:
        return self.value if self.fn is None else self.fn(cols)


class _NumericBuilder:
    """The whitelisted tree as composed numpy closures; constants are folded as they are met."""

    def __init__(self, field: str, states: Mapping[str, int], parameters: Mapping[str, float]):
        self.field = field
        self.states = states
        self.parameters = parameters

    def fail(self, message: str) -> SpecError:
        return SpecError(self.field, message)

    def build(self, node: ast.AST) -> _Num:
        if isinstance(node, ast.Constant):
            return self._const(float(_checked_constant(self, node.value)))
        if isinstance(node, ast.Name):
            return self._name(node.id)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            inner = self.build(node.operand)
            if isinstance(node.op, ast.UAdd):
                return inner
            return self._apply(lambda u: -u, inner)
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return self._apply(_BINOPS[type(node.op)], self.build(node.left), self.build(node.right))
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow):
            return self._power(self.build(node.left), self.build(node.right))
        if isinstance(node, ast.Call):
            name = _checked_call(self, node)
            return self._apply(_NUMPY_FUNCTIONS[name], *(self.build(a) for a in node.args))
        raise self.fail(f"'{type(node).__name__}' is not allowed in an expression")

    def _const(self, value: float) -> _Num:
        if not math.isfinite(value):
            raise self.fail("expression is undefined (division by zero or infinite value)")
        return _Num(value=value)

    def _name(self, name: str) -> _Num:
        if name in self.states:
            index = self.states[name]
            return _Num(fn=lambda cols: cols[index])
        if name in self.parameters:
            return self._const(float(self.parameters[name]))
        if name in CONSTANTS:
            return _Num(value=CONSTANTS[name])
        raise self.fail(_unknown_name(name, {**self.states, **self.parameters}))

    def _apply(self, op: Callable[..., Any], *args: _Num) -> _Num:
        if all(a.fn is None for a in args):
            with np.errstate(all="ignore"):
                try:
                    value = op(*(np.float64(a.value) for a in args))
                except ZeroDivisionError:
                    value = math.inf
            value = complex(value)
            if value.imag != 0:
                raise self.fail("expression is not real")
            return self._const(value.real)
        fns = [a.fn if a.fn is not None else (lambda cols, v=a.value: v) for a in args]
        if len(fns) == 1:
            f0 = fns[0]
            return _Num(fn=lambda cols: op(f0(cols)))
        f0, f1 = fns
        return _Num(fn=lambda cols: op(f0(cols), f1(cols)))

    def _power(self, base: _Num, exponent: _Num) -> _Num:
        if exponent.fn is None:
            p = exponent.value
            if abs(p) > MAX_EXPONENT:
                raise self.fail(f"exponent must be a real number with |p| <= {MAX_EXPONENT}")
            if base.fn is None and base.value != 0 and abs(p * math.log(abs(base.value))) > MAX_LOG_MAGNITUDE:
                raise self.fail("constant power out of floating-point range")
            if float(p).is_integer():
                exponent = _Num(value=int(p))  # x**3 as numpy's integer power, as lambdify prints it
                if base.fn is not None and 2 <= abs(int(p)) <= MAX_PRODUCT_POWER:
                    return self._apply(lambda b, q=int(p): integer_power(b, q), base)
        elif not (base.fn is None and base.value > 0):
            raise self.fail("a non-constant exponent needs a positive constant base (use exp(...))")
        return self._apply(lambda b, p: b ** p, base, exponent)


# x**p for a small integer p as products (binary powering): numpy's float power calls libm's pow per
# element, measured 828 µs for 4 096 points against 12.6 µs for x*x*x on an AVX-512 machine (and the
# cubic sensor's h = x**3 is evaluated at every point of every row by the point filters); the products
# are within a few ulps of pow
MAX_PRODUCT_POWER = 32


def integer_power(x: np.ndarray, p: int) -> np.ndarray:
    """x**p for an integer 2 <= |p| <= MAX_PRODUCT_POWER by repeated squaring."""
    q, result, square = abs(p), None, x
    while True:
        if q & 1:
            result = square if result is None else result * square
        q >>= 1
        if not q:
            break
        square = square * square
    return 1.0 / result if p < 0 else result


def _check_ascii(text: str, field: str) -> None:
    """Expressions are ASCII: Python would fold look-alikes (fullwidth 'ｘ', mathematical '𝐱') into
    'x' while the model id hashes the text as written, giving one model two ids."""
    for position, char in enumerate(text):
        if ord(char) > 127:
            folded = unicodedata.normalize("NFKC", char)
            hint = f"; did you mean {folded!r}?" if folded.isascii() and folded.isprintable() else ""
            name = unicodedata.name(char, "unnamed")
            raise SpecError(field, f"only ASCII characters are allowed: {char!r} (U+{ord(char):04X} {name}) "
                                   f"at position {position}{hint}")


def _checked_tree(text: Any, field: str) -> ast.expr:
    """Parse ``text`` and check its size (length, nodes, depth); the expression's syntax tree."""
    if not isinstance(text, str):
        raise SpecError(field, "expression must be a string")
    if not text.strip():
        raise SpecError(field, "expression is empty")
    if len(text) > MAX_LENGTH:
        raise SpecError(field, f"expression longer than {MAX_LENGTH} characters")
    _check_ascii(text, field)
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        detail = exc.msg if isinstance(exc, SyntaxError) else "cannot be parsed"
        raise SpecError(field, f"invalid expression syntax: {detail}") from None
    if sum(1 for _ in ast.walk(tree)) > MAX_NODES:
        raise SpecError(field, f"expression has more than {MAX_NODES} syntax nodes")
    if _depth(tree, MAX_DEPTH) > MAX_DEPTH:
        raise SpecError(field, f"expression nested deeper than {MAX_DEPTH}")
    _check_caret(tree, field)
    return tree.body


def _check_caret(tree: ast.AST, field: str) -> None:
    """``x^3`` parses as Python's exclusive or (BitXor): say what was meant instead of 'not allowed'."""
    if any(isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitXor) for node in ast.walk(tree)):
        raise SpecError(field, "'^' is not a power here: use ** for powers (x**3, not x^3)")


def numeric_expression(text: str, states: Mapping[str, int], parameters: Mapping[str, float],
                       field: str = "expression") -> Callable[[np.ndarray], np.ndarray]:
    """One user expression as a numpy function of points X (P, n) -> (P,), built without SymPy;
    raises :class:`SpecError` naming ``field``.  ``states`` maps the user's state names to columns."""
    tree = _checked_tree(text, field)
    try:
        node = _NumericBuilder(field, states, parameters).build(tree)
    except SpecError:
        raise
    except (RecursionError, MemoryError, OverflowError, ValueError, TypeError, ZeroDivisionError):
        raise SpecError(field, "expression cannot be evaluated safely") from None

    def on_columns(cols: tuple[np.ndarray, ...], P: int) -> np.ndarray:
        """The expression of the state columns ``cols`` (n arrays (P,)), as a new array (P,)."""
        with np.errstate(all="ignore"):
            value = node(cols)
        return np.broadcast_to(np.asarray(value, dtype=float), (P,)).copy()

    def evaluate(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return on_columns(tuple(X.T), X.shape[0])

    evaluate.on_columns = on_columns  # type: ignore[attr-defined]
    evaluate.node = node  # type: ignore[attr-defined]  # numeric_many's: many expressions, one errstate
    evaluate.template = _template(tree, field, states, parameters)  # type: ignore[attr-defined]
    return evaluate


class _Renamed(ast.NodeTransformer):
    """The tree with one name replaced by a placeholder (``_template``'s shape of an expression)."""

    def __init__(self, name: str):
        self.name = name

    def visit_Name(self, node: ast.Name) -> ast.Name:
        return ast.Name(id="<state>", ctx=node.ctx) if node.id == self.name else node  # no name's spelling


def _template(tree: ast.expr, field: str, states: Mapping[str, int],
              parameters: Mapping[str, float]) -> tuple[str, int, _Num] | None:
    """For an expression of one state coordinate (``-0.5*x3``, ``x3**3``): (its shape, the tree
    with that name as a placeholder; the coordinate; the expression built on a single column, which
    takes an array of any shape), so that expressions of the same shape on their own coordinates are
    evaluated as one array operation (:func:`numeric_many`); else None."""
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and n.id in states}
    if len(used) != 1:
        return None
    (name,) = used
    shape = ast.dump(_Renamed(name).visit(ast.parse(ast.unparse(tree), mode="eval").body))
    return shape, int(states[name]), _NumericBuilder(field, {name: 0}, parameters).build(tree)


def numeric_many(
        functions: Sequence[Callable[[np.ndarray], np.ndarray]]) -> Callable[[np.ndarray], np.ndarray]:
    """Stack one-expression functions: points X (P, n) -> (P, len(functions)).  Expressions that are one
    shape each on its own coordinate (ten or a hundred ``x_i**3``: ``_template``) are evaluated as one
    array operation over their coordinates' rows instead of one per expression (the same elementwise
    operations, so the same numbers; at 100 states and 4096 points ~200 numpy calls a row fewer)."""
    templates = [getattr(f, "template", None) for f in functions]
    shared = None
    if functions and all(t is not None for t in templates) and len({t[0] for t in templates}) == 1:
        shared = templates[0][2], np.array([t[1] for t in templates], np.int64)

    def on_template(XT: np.ndarray) -> np.ndarray:
        """The expressions at the coordinate rows XT (n, P) by their shared template: (m, P), a new array."""
        node, index = shared
        rows = XT if len(index) == len(XT) and (index == np.arange(len(XT))).all() else XT[index]
        with np.errstate(all="ignore"):
            value = node((rows,))
        if value is rows or np.may_share_memory(value, XT):  # the identity: x_i itself
            return np.array(value, dtype=float)
        return np.asarray(value, dtype=float)

    def evaluate(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if not functions:
            return np.zeros((X.shape[0], 0))
        if X.shape[1] < 8 or not all(hasattr(f, "node") for f in functions):
            return np.stack([f(X) for f in functions], axis=1)
        # many states: each column made contiguous once for all the expressions (X.T's rows are strided
        # by n: at 100 states every element of a column sits on its own cache line); points whose
        # columns are contiguous (Fortran order) get theirs back the same way, without a transpose
        columns = X.T.flags.c_contiguous
        if shared is not None:
            out = on_template(X.T if columns else np.ascontiguousarray(X.T))
            return out.T if columns else np.ascontiguousarray(out.T)
        cols, P = tuple(X.T if columns else np.ascontiguousarray(X.T)), X.shape[0]
        out = np.empty((len(functions), P))
        with np.errstate(all="ignore"):
            for j, f in enumerate(functions):
                out[j] = f.node(cols)  # a scalar (a constant expression) fills its row
        return out.T if columns else np.ascontiguousarray(out.T)

    def on_rows(XT: np.ndarray) -> np.ndarray:
        """The functions at points given as coordinate rows XT (n, P): (len(functions), P), each row
        written once (no strided stack); the same numbers as ``evaluate(XT.T).T``."""
        XT = np.asarray(XT, dtype=float)
        if not all(hasattr(f, "node") for f in functions):
            return np.ascontiguousarray(evaluate(XT.T).T)
        if shared is not None and len(functions) >= 8:
            return on_template(XT)
        cols, out = tuple(XT), np.empty((len(functions), XT.shape[1]))
        with np.errstate(all="ignore"):
            for j, f in enumerate(functions):
                out[j] = f.node(cols)
        return out

    evaluate.rows = on_rows  # type: ignore[attr-defined]
    return evaluate


def parse_expression(text: str, names: Mapping[str, "sp.Expr"], field: str = "expression") -> "sp.Expr":
    """Parse one user expression into SymPy, or raise :class:`SpecError` naming ``field``.

    ``names`` maps the allowed user names (state variables, parameters) to SymPy objects
    chosen by the caller (internal symbols or exact numbers).
    """
    tree = _checked_tree(text, field)
    try:
        expr = _Builder(field, names).build(tree)
    except SpecError:
        raise
    except (RecursionError, MemoryError, OverflowError, ValueError, TypeError, ZeroDivisionError):
        raise SpecError(field, "expression cannot be evaluated safely") from None
    return expr


def parameters_used(texts: Sequence[str], state: Sequence[str], parameters: Sequence[str],
                    field: str) -> frozenset[str]:
    """The ``parameters`` that the expressions ``texts`` depend on: the free symbols of the SymPy
    expressions built from their checked trees with each parameter an internal symbol (``p_0, p_1, ...``,
    never the user's name), so ``a`` is not found in ``alpha`` and ``0*a`` or ``a - a`` use no ``a``.  An
    expression that SymPy builds only with the parameters as numbers (``x**theta``: a non-constant
    exponent) counts every parameter named in its tree (ast.Name nodes), the safe side."""
    import sympy as sp

    symbols = {name: sp.Symbol(f"p_{i}", real=True) for i, name in enumerate(parameters)}
    names: dict[str, Any] = dict(symbols)
    names.update(zip(state, state_symbols(len(state)), strict=True))
    used: set[str] = set()
    for i, text in enumerate(texts):
        try:
            found = parse_expression(text, names, f"{field}[{i}]").free_symbols
            used.update(name for name, symbol in symbols.items() if symbol in found)
        except SpecError:
            tree = _checked_tree(text, f"{field}[{i}]")
            named = (node.id for node in ast.walk(tree) if isinstance(node, ast.Name))
            used.update(name for name in named if name in symbols)
    return frozenset(used)


def nonsmooth_functions(exprs: Sequence["sp.Expr"]) -> list[str]:
    """The names (as the user writes them) of the non-differentiable functions in ``exprs``."""
    import sympy as sp

    kinds = {"abs": sp.Abs, "sign": sp.sign, "min": sp.Min, "max": sp.Max}
    return [name for name in NONSMOOTH if any(e.has(kinds[name]) for e in exprs)]


def affine_coefficients(exprs: Sequence["sp.Expr"], symbols: Sequence["sp.Symbol"],
                        field: str) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with exprs = A x + b exactly; SpecError naming ``field`` if not affine."""
    import sympy as sp

    jac = sp.Matrix(exprs).jacobian(symbols)
    if any(entry.free_symbols & set(symbols) for entry in jac):
        raise SpecError(field, "is not affine in the state; this filter needs an affine (linear) model")
    at_zero = {s: 0 for s in symbols}
    try:
        A = np.array([[float(v) for v in row] for row in jac.tolist()], dtype=float).reshape(len(exprs),
                                                                                               len(symbols))
        b = np.array([float(e.subs(at_zero)) for e in exprs], dtype=float)
    except TypeError:
        raise SpecError(field, "has non-real coefficients") from None
    return A, b


def _dirac_delta(*args: Any) -> Any:
    """The derivative of a jump (sign, and of abs/min/max twice) almost everywhere: 0."""
    return np.zeros_like(np.asarray(args[0], dtype=float))


def vectorize(expr: "sp.Expr", symbols: Sequence["sp.Symbol"],
              functions: Mapping[str, Callable[..., Any]] | None = None):
    """numpy function of points X (shape (P, n)) returning shape (P,) for one expression;
    ``functions`` maps the names of SymPy functions of our own to their numpy forms.  A
    ``DiracDelta`` (a derivative of sign, abs, min or max) is 0: derivatives hold almost everywhere."""
    import sympy as sp

    table = {"DiracDelta": _dirac_delta, **(functions or {})}
    fn = sp.lambdify(list(symbols), expr, modules=[table, "numpy"])

    def evaluate(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        with np.errstate(all="ignore"):
            value = fn(*X.T)
        return np.broadcast_to(np.asarray(value, dtype=float), (X.shape[0],)).copy()

    return evaluate


def vectorize_many(exprs: Sequence["sp.Expr"], symbols: Sequence["sp.Symbol"]):
    """numpy function of points X (P, n) returning (P, len(exprs))."""
    return numeric_many([vectorize(e, symbols) for e in exprs])
