"""Differential operators with function coefficients, their products and brackets, and display.

An operator is a dict from the multi-index α of a derivative ∂^α to its SymPy coefficient.  The
estimation algebra is built from these by Lie brackets [X, Y] = XY − YX (seed 002 Def. 2.1,
seed 004 Def. 1).  Zero tests are exact after expansion for rational
polynomials, otherwise at random points with 50-digit arithmetic; both run under the budget of
:mod:`.budget`.
"""

from __future__ import annotations

import itertools
import random

import mpmath
import sympy as sp

from ..model import Model
from .budget import BoundReached, current_budget, expand, expanded_terms, expression_size

_PRODUCT_TERMS = 20_000  # most terms of one product expanded in a composition
_SIMPLIFY_NODES = 60  # sp.simplify only on expressions this small (its cost explodes beyond)
ZERO_POINTS = 6  # random points of the numeric zero test
DIGITS = 50  # working precision of the numeric rank test
TOL = mpmath.mpf(10) ** (-30)

Operator = dict  # tuple[int, ...] (derivative multi-index) -> sp.Expr coefficient


# ---------------------------------------------------------------------------------------------
# zero tests and readable forms, under the current budget
# ---------------------------------------------------------------------------------------------
def _terms(expr: sp.Expr) -> int:
    return len(sp.Add.make_args(expr))


def is_zero(expr: sp.Expr, symbols) -> bool:
    """expr ≡ 0: exact after expansion for rational polynomials, else at random points (50 digits).

    sp.simplify decides the same identities (e.g. sin² + cos² − 1) but its cost explodes with the
    size of the expression; the evaluation test is the one the rank test of the algebra uses.
    """
    budget = current_budget()
    budget.check()
    budget.check_size(expr)
    e = expand(expr)
    if e == 0:
        return True
    variables = sorted(e.free_symbols | set(symbols), key=str)
    if rational_polynomial(e, variables) or e.is_Rational:
        return False
    budget.numeric_zero_tests += 1
    return _vanishes_at_random_points(e, variables)


def _vanishes_at_random_points(e: sp.Expr, symbols) -> bool:
    rng = random.Random(271828)
    points = [[mpmath.mpf(rng.randint(-1900, 1900)) / 1000 for _ in symbols] for _ in range(ZERO_POINTS)]
    with mpmath.workdps(DIGITS):
        fn = sp.lambdify(list(symbols), e, modules="mpmath")
        evaluated = 0
        for point in points:
            current_budget().check()
            try:
                value = mpmath.mpmathify(fn(*point))
            except (ZeroDivisionError, ValueError, OverflowError):
                continue  # a singular point tells nothing
            evaluated += 1
            if not abs(value) <= TOL:
                return False
    return evaluated > 0  # nowhere evaluable: not shown to vanish


def tidy(expr: sp.Expr) -> sp.Expr:
    """A readable exact form: sp.simplify on small expressions, expansion otherwise (never raises)."""
    budget = current_budget()
    if budget.max_size is not None and expanded_terms(expr, budget.max_size) > budget.max_size:
        return expr  # too large to expand within the bound: shown as given
    if budget.remaining() > 0:
        for candidate in (expr, sp.expand(expr)):  # the form sp.simplify was given before bounds existed
            if expression_size(candidate, _SIMPLIFY_NODES) <= _SIMPLIFY_NODES:
                return sp.simplify(candidate)
    return sp.expand(expr)


def rational_polynomial(expr: sp.Expr, symbols) -> bool:
    """True when ``expr`` is a polynomial in ``symbols`` with rational coefficients (exact arithmetic)."""
    try:
        poly = sp.Poly(expr, *symbols)
    except sp.PolynomialError:
        return False
    return poly.domain.is_QQ or poly.domain.is_ZZ


# ---------------------------------------------------------------------------------------------
# differential operators with function coefficients
# ---------------------------------------------------------------------------------------------
def multiplication(expr: sp.Expr, n: int) -> Operator:
    """The zero-order operator φ ↦ expr·φ."""
    expr = expand(expr)
    return {} if expr == 0 else {(0,) * n: expr}


def derivative(i: int, n: int) -> Operator:
    """∂/∂x_i."""
    alpha = [0] * n
    alpha[i] = 1
    return {tuple(alpha): sp.Integer(1)}


def kolmogorov_operator(model: Model) -> Operator:
    """L0 = ½ Σ a_ij ∂_i∂_j − f·∇ − div f − ½ hᵀR⁻¹h   (seed 002 (2.2), seed 004 (2))."""
    n, x = model.n, model.symbols
    a = exact_matrix(model.a)
    terms: dict = {}
    for i in range(n):
        for j in range(n):
            alpha = [0] * n
            alpha[i] += 1
            alpha[j] += 1
            _accumulate(terms, tuple(alpha), a[i, j] / 2)
    for i in range(n):
        _accumulate(terms, derivative(i, n).popitem()[0], -model.drift[i])
    div_f = sum(sp.diff(model.drift[i], x[i]) for i in range(n))
    _accumulate(terms, (0,) * n, -div_f - observation_energy(model) / 2)
    return _clean(terms)


def add(A: Operator, B: Operator, scale: sp.Expr | int = 1) -> Operator:
    """A + scale·B."""
    out = dict(A)
    for alpha, c in B.items():
        _accumulate(out, alpha, scale * c)
    return _clean(out)


def compose(A: Operator, B: Operator, symbols) -> Operator:
    """The product A∘B by Leibniz: ∂^α (b φ) = Σ_{γ≤α} C(α,γ) (∂^{α−γ} b) ∂^γ φ."""
    budget = current_budget()
    out: dict = {}
    for alpha, a in A.items():
        for beta, b in B.items():
            budget.check()
            for gamma in itertools.product(*(range(k + 1) for k in alpha)):
                weight = 1
                db = b
                for k, (ak, gk) in enumerate(zip(alpha, gamma, strict=True)):
                    weight *= sp.binomial(ak, gk)
                    if ak - gk:
                        db = sp.diff(db, symbols[k], ak - gk)
                if db == 0:
                    continue
                if _terms(a) * _terms(db) > _PRODUCT_TERMS:  # its expansion alone would be huge
                    raise BoundReached(f"expression size {budget.max_size or _PRODUCT_TERMS}")
                target = tuple(bk + gk for bk, gk in zip(beta, gamma, strict=True))
                _accumulate(out, target, weight * a * db)
    return _clean(out)


def bracket(A: Operator, B: Operator, symbols) -> Operator:
    """[A, B] = A∘B − B∘A   (seed 002 Def. 2.1)."""
    return add(compose(A, B, symbols), compose(B, A, symbols), -1)


def order(A: Operator) -> int:
    return max((sum(alpha) for alpha in A), default=-1)


def _accumulate(terms: dict, alpha: tuple, coefficient: sp.Expr) -> None:
    terms[alpha] = terms.get(alpha, sp.Integer(0)) + coefficient


def _clean(terms: dict) -> Operator:
    budget = current_budget()
    out = {}
    for alpha, c in terms.items():
        budget.check()
        c = expand(c)
        if c != 0:
            budget.check_size(c)
            out[alpha] = c
    return out


# ---------------------------------------------------------------------------------------------
# exact numbers from the spec
# ---------------------------------------------------------------------------------------------
def exact_matrix(values) -> sp.Matrix:
    """Rational SymPy matrix of a float matrix (0.2 -> 1/5, as compile_model does)."""
    return sp.Matrix([[sp.Rational(repr(float(v))) for v in row] for row in values])


def observation_energy(model: Model) -> sp.Expr:
    """hᵀR⁻¹h with R⁻¹ inverted exactly."""
    h = sp.Matrix(model.observation)
    return expand((h.T * exact_matrix(model.R).inv() * h)[0, 0])


def is_identity(matrix) -> bool:
    return exact_matrix(matrix) == sp.eye(len(matrix))


# ---------------------------------------------------------------------------------------------
# rendering with the user's names
# ---------------------------------------------------------------------------------------------
def _user_names(model: Model) -> dict:
    return {s: sp.Symbol(name) for s, name in zip(model.symbols, model.spec.state, strict=True)}


def show(expr: sp.Expr, model: Model) -> str:
    return str(tidy(expr).xreplace(_user_names(model)))


def show_operator(A: Operator, model: Model, label: str | None = None) -> str:
    """First-order operators as Σ c_i D_i + g with D_i = ∂_i − f_i (a = I); others term by term."""
    if label == "L0":
        return "L0"
    if not A:
        return "0"
    lead = A[min(A, key=lambda alpha: (-sum(alpha), tuple(-k for k in alpha)))]
    if lead.is_number:  # show the element scaled to a leading coefficient 1 (still a basis element)
        A = {alpha: sp.expand(c / lead) for alpha, c in A.items()}
    names = model.spec.state
    n = model.n
    if order(A) <= 1:
        g = A.get((0,) * n, sp.Integer(0))
        parts = []
        for i in range(n):
            alpha = tuple(1 if j == i else 0 for j in range(n))
            c = A.get(alpha)
            if c is not None:
                g = g + c * model.drift[i]
                parts.append(_scaled(c, f"D_{names[i]}", model))
        g = tidy(g)
        if g != 0 or not parts:
            parts.append(show(g, model))
        return " + ".join(parts).replace("+ -", "- ")
    parts = []
    for alpha, c in sorted(A.items(), key=lambda kv: (-sum(kv[0]), kv[0])):
        d = "*".join(f"d{names[i]}" + (f"^{k}" if k > 1 else "") for i, k in enumerate(alpha) if k)
        parts.append(_scaled(c, d, model) if d else show(c, model))
    return " + ".join(parts).replace("+ -", "- ")


def _scaled(c: sp.Expr, name: str, model: Model) -> str:
    if c == 1:
        return name
    if c == -1:
        return f"-{name}"
    text = show(c, model)
    return f"({text})*{name}" if any(ch in text for ch in "+- ") else f"{text}*{name}"
