"""Model analysis: Wong matrix, η, the structural conditions and the estimation algebra.

For dx = f dt + G dv, dy = h dt + dw (a = GQGᵀ, E dw dwᵀ = R dt) the DMZ equation reads
dσ = L0 σ dt + Σ_i L_i σ dy_i with (seed 002 (2.2), seed 004 (2))

    L0 = ½ Σ a_ij ∂_i∂_j − Σ f_i ∂_i − div f − ½ hᵀR⁻¹h,      L_i = multiplication by (R⁻¹h)_i.

The estimation algebra E = ⟨L0, L1, …, Lm⟩ (seed 002 Def. 2.2) is built here by repeated Lie
brackets [X, Y] = XY − YX of differential operators (seed 002 Def. 2.1), each stored as a dict
from the multi-index of derivatives to its SymPy coefficient.  Linear dependence is decided
exactly over ℚ on a monomial basis when every coefficient is a rational polynomial, otherwise at
random points with 50-digit arithmetic (the report says which).

Also computed: the Wong matrix ω_ij = ∂f_j/∂x_i − ∂f_i/∂x_j (seed 004 Def. 4) and
η = fᵀa⁻¹f + div f + hᵀR⁻¹h (seed 004 §II, = |f|² + div f + |h|² when a = I, R = I), so that
L0 = ½(Dᵀ a D − η) with D = ∇ − a⁻¹f.
"""

from __future__ import annotations

import contextvars
import itertools
import math
import random
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import mpmath
import sympy as sp

from .model import Model

DEFAULT_MAX_DEPTH = 6  # rounds of brackets
DEFAULT_MAX_DIMENSION = 24
DEFAULT_TIME_LIMIT = 60.0  # seconds for the whole analysis (None: unbounded)
DEFAULT_MAX_SIZE = 4000  # tree nodes of one coefficient of an algebra element
_PRODUCT_TERMS = 20_000  # most terms of one product expanded in a composition
_SIMPLIFY_NODES = 60  # sp.simplify only on expressions this small (its cost explodes beyond)
_ZERO_POINTS = 6  # random points of the numeric zero test
_DIGITS = 50  # working precision of the numeric rank test
_TOL = mpmath.mpf(10) ** (-30)

Operator = dict  # tuple[int, ...] (derivative multi-index) -> sp.Expr coefficient


# ---------------------------------------------------------------------------------------------
# bounds: a deadline and an expression-size cap, checked between brackets, reductions, zero tests
# ---------------------------------------------------------------------------------------------
class BoundReached(Exception):
    """The analysis hit one of its bounds; str(self) names it ("time 10 s", "expression size 4000")."""


class Budget:
    """A deadline (monotonic clock) and a cap on the size of one expression."""

    def __init__(self, time_limit: float | None = None, max_size: int | None = None,
                 start: float | None = None, name: str | None = None):
        self.time_limit = time_limit
        self.name = name or ("" if time_limit is None else f"time {time_limit:g} s")  # in reports
        self.max_size = max_size
        self.start = time.monotonic() if start is None else start
        self.deadline = math.inf if time_limit is None else self.start + time_limit
        self.numeric_zero_tests = 0

    def check(self) -> None:
        if time.monotonic() > self.deadline:
            raise BoundReached(self.name)

    def remaining(self) -> float:
        return self.deadline - time.monotonic()

    def check_size(self, expr: sp.Expr) -> None:
        if self.max_size is not None and expression_size(expr, self.max_size) > self.max_size:
            raise BoundReached(f"expression size {self.max_size}")


_UNBOUNDED = Budget()
_BUDGET: contextvars.ContextVar[Budget] = contextvars.ContextVar("analysis_budget", default=_UNBOUNDED)


def _budget() -> Budget:
    return _BUDGET.get()


@contextmanager
def bounded(budget: Budget):
    """Run the analysis functions of this module under `budget` (they raise BoundReached)."""
    token = _BUDGET.set(budget)
    try:
        yield budget
    finally:
        _BUDGET.reset(token)


def expression_size(expr: sp.Expr, cap: int | None = None) -> int:
    """Number of nodes of the expression tree, counting stops just past `cap`."""
    count = 0
    for _ in sp.preorder_traversal(expr):
        count += 1
        if cap is not None and count > cap:
            break
    return count


def _terms(expr: sp.Expr) -> int:
    return len(sp.Add.make_args(expr))


def is_zero(expr: sp.Expr, symbols) -> bool:
    """expr ≡ 0: exact after expansion for rational polynomials, else at random points (50 digits).

    sp.simplify decides the same identities (e.g. sin² + cos² − 1) but its cost explodes with the
    size of the expression; the evaluation test is the one the rank test of the algebra uses.
    """
    budget = _budget()
    budget.check()
    budget.check_size(expr)
    e = sp.expand(expr)
    if e == 0:
        return True
    variables = sorted(e.free_symbols | set(symbols), key=str)
    if _rational_polynomial(e, variables) or e.is_Rational:
        return False
    budget.numeric_zero_tests += 1
    return _vanishes_at_random_points(e, variables)


def _vanishes_at_random_points(e: sp.Expr, symbols) -> bool:
    rng = random.Random(271828)
    points = [[mpmath.mpf(rng.randint(-1900, 1900)) / 1000 for _ in symbols] for _ in range(_ZERO_POINTS)]
    with mpmath.workdps(_DIGITS):
        fn = sp.lambdify(list(symbols), e, modules="mpmath")
        evaluated = 0
        for point in points:
            _budget().check()
            try:
                value = mpmath.mpmathify(fn(*point))
            except (ZeroDivisionError, ValueError, OverflowError):
                continue  # a singular point tells nothing
            evaluated += 1
            if not abs(value) <= _TOL:
                return False
    return evaluated > 0  # nowhere evaluable: not shown to vanish


def tidy(expr: sp.Expr) -> sp.Expr:
    """A readable exact form: sp.simplify on small expressions, expansion otherwise (never raises)."""
    if _budget().remaining() > 0:
        for candidate in (expr, sp.expand(expr)):  # the form sp.simplify was given before bounds existed
            if expression_size(candidate, _SIMPLIFY_NODES) <= _SIMPLIFY_NODES:
                return sp.simplify(candidate)
    return sp.expand(expr)


# ---------------------------------------------------------------------------------------------
# differential operators with function coefficients
# ---------------------------------------------------------------------------------------------
def multiplication(expr: sp.Expr, n: int) -> Operator:
    """The zero-order operator φ ↦ expr·φ."""
    expr = sp.expand(expr)
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
    budget = _budget()
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
    budget = _budget()
    out = {}
    for alpha, c in terms.items():
        budget.check()
        c = sp.expand(c)
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
    return sp.expand((h.T * exact_matrix(model.R).inv() * h)[0, 0])


def is_identity(matrix) -> bool:
    return exact_matrix(matrix) == sp.eye(len(matrix))


# ---------------------------------------------------------------------------------------------
# Wong matrix, η, conditions
# ---------------------------------------------------------------------------------------------
def wong_matrix(model: Model) -> sp.Matrix:
    """ω_ij = ∂f_j/∂x_i − ∂f_i/∂x_j   (seed 004 Def. 4, seed 002 (2.5))."""
    x, f, n = model.symbols, model.drift, model.n
    return sp.Matrix(n, n, lambda i, j: _entry(sp.diff(f[j], x[i]) - sp.diff(f[i], x[j]), x))


def whitened_wong_matrix(model: Model) -> sp.Matrix:
    """a Jᵀ − J a (J = ∂f/∂x): L Ω̃ Lᵀ for the Wong matrix Ω̃ of z = L⁻¹x, a = LLᵀ; = Ω when a = I."""
    J = sp.Matrix(model.drift).jacobian(model.symbols)
    a = exact_matrix(model.a)
    return (a * J.T - J * a).applyfunc(lambda w: _entry(w, model.symbols))


def _entry(expr: sp.Expr, symbols) -> sp.Expr:
    """Expanded, and exactly 0 when it vanishes identically (a zero test, not sp.simplify)."""
    e = sp.expand(expr)
    return sp.Integer(0) if e != 0 and is_zero(e, symbols) else e


def eta(model: Model) -> sp.Expr:
    """η = fᵀa⁻¹f + div f + hᵀR⁻¹h   (seed 004 §II with a = R = I: |f|² + div f + |h|²)."""
    f = sp.Matrix(model.drift)
    div_f = sum(sp.diff(fi, xi) for fi, xi in zip(model.drift, model.symbols, strict=True))
    a_inv = exact_matrix(model.a).inv()
    e = sp.expand((f.T * a_inv * f)[0, 0] + div_f + observation_energy(model))
    _budget().check_size(e)
    return tidy(e)


def is_constant(expr: sp.Expr, symbols) -> bool:
    return all(is_zero(sp.diff(expr, s), symbols) for s in symbols)


def polynomial_degree_at_most(expr: sp.Expr, symbols, degree: int) -> bool:
    """All derivatives of order degree+1 vanish (works for non-polynomial expressions too)."""
    for combo in itertools.combinations_with_replacement(symbols, degree + 1):
        if not is_zero(sp.diff(expr, *combo), symbols):
            return False
    return True


@dataclass(frozen=True)
class Condition:
    holds: bool | None  # None: not decided within the bounds of the analysis
    detail: str
    title: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"holds": self.holds, "title": self.title, "detail": self.detail}


def seed004_structure(model: Model, k: int) -> dict[str, Any] | None:
    """The structure Theorem 1 of seed 004 needs, with x_k playing x1; None if it fails.

    Conditions (I) ω_kj = 0 for all j and (II) η = A x_k² + B x_k + γ(other x) with constants
    A, B, and h affine in x_k alone (v).  Returns A, B, the slopes c = ∂h/∂x_k, offsets h(x_k=0).
    """
    x, n = model.symbols, model.n
    xk = x[k]
    others = [s for i, s in enumerate(x) if i != k]
    omega = wong_matrix(model)
    if any(omega[k, j] != 0 for j in range(n)):
        return None
    e = sp.expand(eta(model))
    A = constant_value(sp.diff(e, xk, 2) / 2, x)
    B = constant_value(sp.diff(e, xk).subs(xk, 0), x)
    if A is None or B is None or not polynomial_degree_at_most(e, [xk], 2):
        return None
    slopes, offsets = [], []
    for hi in model.observation:
        c1 = constant_value(sp.diff(hi, xk), x)
        if c1 is None or not all(is_zero(sp.diff(hi, s), x) for s in others):
            return None
        slopes.append(c1)
        offsets.append(tidy(hi.subs(xk, 0)))
    return {"coordinate": k, "A": A, "B": B, "slopes": slopes, "offsets": offsets,
            "gamma": tidy(e - A * xk**2 - B * xk)}


def constant_value(expr: sp.Expr, symbols) -> sp.Expr | None:
    """The number expr equals if it is constant in the symbols (exactly: sin² + cos² -> 1), else None."""
    e = tidy(expr)
    if not (e.free_symbols & set(symbols)):
        return e
    if not is_constant(e, symbols):
        return None
    value = tidy(e.subs({s: 0 for s in symbols}))  # constant: its value anywhere, e.g. at the origin
    return value if value.is_finite and not value.free_symbols else None


def _seed004_items(model: Model, k: int) -> dict[str, Condition]:
    """Conditions (i)–(v) of seed 004 §III with x_k in the role of x1."""
    x, f, n = model.symbols, model.drift, model.n
    xk = x[k]
    others = [s for i, s in enumerate(x) if i != k]
    affine = all(is_zero(sp.diff(fi, xk, 2), x) for fi in f)
    a_coef = [tidy(sp.diff(fi, xk)) for fi in f]
    phi = [tidy(fi - ai * xk) for fi, ai in zip(f, a_coef, strict=True)]
    items = {"(i) f_i = a_i(x') x_k + phi_i(x')": Condition(affine, "f affine in x_k")}
    ii = affine and all(is_zero(sp.diff(phi[k], x[j]) - a_coef[j], x) for j in range(n) if j != k)
    items["(ii) d phi_k/dx_j = a_j"] = Condition(ii, "")
    norm2 = constant_value(sum(ai**2 for ai in a_coef), x)
    iii = (affine and constant_value(a_coef[k], x) is not None and norm2 is not None
           and bool(norm2 > 0))
    shown = norm2 if norm2 is not None else tidy(sum(ai**2 for ai in a_coef))
    items["(iii) a_k constant, sum a_i^2 positive constant"] = Condition(bool(iii), f"sum a_i^2 = {shown}")
    iv_expr = tidy(2 * sum(ai * pi for ai, pi in zip(a_coef, phi, strict=True))
                   + sum(sp.diff(a_coef[j], x[j]) for j in range(n) if j != k))
    items["(iv) 2 sum a_i phi_i + sum_j d a_j/dx_j constant"] = Condition(
        affine and is_constant(iv_expr, x), f"= {iv_expr}")
    v = all(polynomial_degree_at_most(hi, [xk], 1) and all(is_zero(sp.diff(hi, s), x) for s in others)
            for hi in model.observation)
    items["(v) h affine in x_k only"] = Condition(v, "")
    return items


# ---------------------------------------------------------------------------------------------
# linear algebra over ℝ for operators: exact (ℚ, monomials) or at random points (50 digits)
# ---------------------------------------------------------------------------------------------
class _Echelon:
    """Reduced row echelon form of sparse vectors {key: number}; exact or with a tolerance."""

    def __init__(self, exact: bool):
        self.exact = exact
        self.rows: dict = {}  # pivot key -> row (row[pivot] == 1, zero at the other pivots)

    def _zero(self, v) -> bool:
        return v == 0 if self.exact else abs(v) <= _TOL

    def reduce(self, vec: dict) -> dict:
        vec = dict(vec)
        for pivot, row in self.rows.items():
            c = vec.get(pivot)
            if c is None or self._zero(c):
                continue
            for key, value in row.items():
                vec[key] = vec.get(key, 0) - c * value
        return {k: v for k, v in vec.items() if not self._zero(v)}

    def add(self, vec: dict) -> bool:
        """Add vec to the span; False if it was already in it."""
        residual = self.reduce(vec)
        if not residual:
            return False
        pivot = max(residual, key=lambda k: abs(residual[k])) if not self.exact else min(residual)
        scale = residual[pivot]
        row = {k: v / scale for k, v in residual.items()}
        for other in self.rows.values():
            c = other.get(pivot)
            if c is not None and not self._zero(c):
                for key, value in row.items():
                    other[key] = other.get(key, 0) - c * value
                for key in [k for k, v in other.items() if self._zero(v)]:
                    del other[key]
        self.rows[pivot] = row
        return True

    @property
    def rank(self) -> int:
        return len(self.rows)


class _Vectorizer:
    """Coordinates of an operator: exact on monomials, or values at random points."""

    def __init__(self, symbols, exact: bool, points: int, radius: float, center):
        self.symbols = symbols
        self.exact = exact
        rng = random.Random(12345)
        self.points = [[Fraction(round(c * 1000)) / 1000 + Fraction(rng.randint(-1000, 1000), 1000)
                        * Fraction(round(radius * 1000), 1000) / len(symbols) for c in center]
                       for _ in range(points)]
        self._cache: dict = {}

    def __call__(self, A: Operator) -> dict:
        vec: dict = {}
        for alpha, c in A.items():
            _budget().check()
            if self.exact:
                for monom, coeff in sp.Poly(c, *self.symbols).terms():
                    vec[(alpha, monom)] = Fraction(int(coeff.p), int(coeff.q))
            else:
                for j, value in enumerate(self._values(c)):
                    vec[(alpha, j)] = value
        return vec

    def _values(self, expr: sp.Expr) -> list:
        key = sp.srepr(expr)
        if key not in self._cache:
            fn = sp.lambdify(self.symbols, expr, modules="mpmath")
            values = []
            for pt in self.points:
                _budget().check()
                values.append(_real(fn(*[mpmath.mpf(p.numerator) / p.denominator for p in pt])))
            self._cache[key] = values
        return self._cache[key]


def _real(value) -> mpmath.mpf:
    value = mpmath.mpmathify(value)
    return value.real if isinstance(value, mpmath.mpc) else value


def _rational_polynomial(expr: sp.Expr, symbols) -> bool:
    try:
        poly = sp.Poly(expr, *symbols)
    except sp.PolynomialError:
        return False
    return poly.domain.is_QQ or poly.domain.is_ZZ


# ---------------------------------------------------------------------------------------------
# the estimation algebra
# ---------------------------------------------------------------------------------------------
@dataclass
class EstimationAlgebra:
    closed: bool
    dimension: int | None  # None when it does not close within the bound
    basis: list  # operators found (a basis of E when closed)
    labels: list[str]
    linear_rank: int | None
    maximal_rank: bool | None
    rounds: int
    max_depth: int
    max_dimension: int
    exact: bool
    generators: int = 0
    stopped_by: str | None = None  # the bound that stopped the search before closing
    time_limit: float | None = None
    max_size: int | None = None
    _vectorize: Any = field(default=None, repr=False)
    _echelon: Any = field(default=None, repr=False)

    def contains(self, A: Operator) -> bool:
        """Is A in the span found (E itself when closed)?"""
        with mpmath.workdps(_DIGITS):  # mpf arithmetic runs at the context precision
            return not self._echelon.reduce(self._vectorize(A))


def estimation_algebra(model: Model, max_depth: int = DEFAULT_MAX_DEPTH,
                       max_dimension: int = DEFAULT_MAX_DIMENSION,
                       time_limit: float | None = DEFAULT_TIME_LIMIT,
                       max_size: int | None = DEFAULT_MAX_SIZE) -> EstimationAlgebra:
    """E = ⟨L0, h_1, …, h_m⟩ (seed 002 Def. 2.2) by rounds of brackets, up to the bounds.

    Round r brackets each element added in round r−1 with every element found so far; when a
    round adds nothing the span is closed under brackets, i.e. it is E.  The search also stops,
    reporting E as not closing within that bound, after `time_limit` seconds or when a
    coefficient exceeds `max_size` tree nodes.
    """
    with bounded(Budget(time_limit, max_size)):
        return _bounded_algebra(model, max_depth, max_dimension)


def _bounded_algebra(model: Model, max_depth: int, max_dimension: int) -> EstimationAlgebra:
    """The algebra under the current budget; a bound reached ends the search (not closed)."""
    budget = _budget()
    search = _AlgebraSearch(model, max_dimension)
    with mpmath.workdps(_DIGITS):  # mpf arithmetic of the numeric rank test runs at this precision
        try:
            stopped_by = search.run(max_depth)
            rank = _linear_rank(search.echelon, search.vectorize, model.n) if stopped_by is None else None
        except BoundReached as bound:
            stopped_by, rank = str(bound), None
    closed = stopped_by is None
    return EstimationAlgebra(
        closed=closed, dimension=len(search.basis) if closed else None, basis=search.basis,
        labels=search.labels, linear_rank=rank, maximal_rank=None if rank is None else rank == model.n,
        rounds=search.rounds, max_depth=max_depth, max_dimension=max_dimension, exact=search.exact,
        generators=search.generators, stopped_by=stopped_by, time_limit=budget.time_limit,
        max_size=budget.max_size, _vectorize=search.vectorize, _echelon=search.echelon)


class _AlgebraSearch:
    """Rounds of brackets; basis, labels and rounds stay readable when a bound interrupts it."""

    def __init__(self, model: Model, max_dimension: int):
        self.model, self.max_dimension = model, max_dimension
        self.basis: list = []
        self.labels: list[str] = []
        self.rounds = self.generators = 0
        self.exact = False
        self.vectorize = self.echelon = None

    def admit(self, op: Operator, label: str) -> bool:
        if op and self.echelon.add(self.vectorize(op)):
            self.basis.append(op)
            self.labels.append(label)
            return True
        return False

    def run(self, max_depth: int) -> str | None:
        """None when the span closes under brackets, else the bound that stopped it."""
        model, x, n = self.model, self.model.symbols, self.model.n
        generators = [(kolmogorov_operator(model), "L0")]
        generators += [(multiplication(hi, n), f"h{i + 1}") for i, hi in enumerate(model.observation)]
        self.exact = all(_rational_polynomial(c, x) for op, _ in generators for c in op.values())
        self.vectorize = _Vectorizer(x, self.exact, points=3 * self.max_dimension + 8, radius=model.radius,
                                     center=[float(c) for c in model.center])
        self.echelon = _Echelon(self.exact)
        fresh = [op for op, label in generators if self.admit(op, label)]
        self.generators = len(self.basis)
        while fresh:
            if len(self.basis) > self.max_dimension:
                return f"dimension {self.max_dimension}"
            if self.rounds >= max_depth:
                return f"depth {max_depth}"
            self.rounds += 1
            fresh = self._round(fresh, x)
        return None

    def _round(self, fresh: list, x) -> list:
        new = []
        for A in fresh:
            for B in list(self.basis):
                if self.admit(bracket(A, B, x), "bracket"):
                    new.append(self.basis[-1])
                if len(self.basis) > self.max_dimension:
                    return new
        return new


def _linear_rank(echelon: _Echelon, vectorize, n: int) -> int:
    """dim(E ∩ span{x_1, …, x_n})   (seed 004 Def. 3) = dim E + n − dim(E + span{x_i})."""
    symbols = vectorize.symbols
    both = _Echelon(echelon.exact)
    for row in echelon.rows.values():
        both.add(row)
    for s in symbols:
        both.add(vectorize(multiplication(s, n)))
    return echelon.rank + n - both.rank


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


# ---------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------
@dataclass
class AnalysisReport:
    model: str
    state: list[str]
    wong_matrix: list[list[str]]
    wong_constant: bool | None
    eta: str
    notes: list[str]
    conditions: dict[str, Condition]
    seed004: dict[str, Condition]
    algebra: EstimationAlgebra
    algebra_basis: list[str]
    method: str
    reason: str
    elapsed: float = 0.0  # seconds the analysis took

    def to_dict(self) -> dict[str, Any]:
        alg = self.algebra
        return {
            "model": self.model, "state": self.state,
            "wong_matrix": self.wong_matrix, "wong_constant": self.wong_constant,
            "eta": self.eta, "notes": self.notes,
            "conditions": {k: c.to_dict() for k, c in self.conditions.items()},
            "seed004_conditions": {k: c.to_dict() for k, c in self.seed004.items()},
            "estimation_algebra": {
                "closed": alg.closed, "dimension": alg.dimension, "basis": self.algebra_basis,
                "linear_rank": alg.linear_rank, "maximal_rank": alg.maximal_rank,
                "rounds": alg.rounds, "max_depth": alg.max_depth, "max_dimension": alg.max_dimension,
                "stopped_by": alg.stopped_by, "time_limit": alg.time_limit, "max_size": alg.max_size,
                "rank_test": "exact over Q" if alg.exact else f"numeric, {_DIGITS} digits at random points"},
            "recommendation": {"method": self.method, "reason": self.reason},
            "elapsed_s": round(self.elapsed, 3),
        }

    def render(self) -> str:
        d = self.to_dict()
        width = max(len(e) for row in self.wong_matrix for e in row)
        lines = [f"model: {self.model}   state: {', '.join(self.state)}", "",
                 "Wong matrix Omega (omega_ij = df_j/dx_i - df_i/dx_j):"]
        lines += ["  [ " + "  ".join(e.rjust(width) for e in row) + " ]" for row in self.wong_matrix]
        constant = _mark(self.wong_constant, "yes", "no", "undecided")
        lines += [f"  constant: {constant}", "", f"eta = {self.eta}"]
        lines += [f"  note: {note}" for note in self.notes]
        lines += ["", "conditions:"]
        lines += [f"  [{_mark(c.holds)}] {c.title}" + (f"  ({c.detail})" if c.detail else "")
                  for c in self.conditions.values()]
        if self.seed004:
            lines += ["  seed 004 class, items:"]
            lines += [f"    [{_mark(c.holds)}] {k}" + (f"  ({c.detail})" if c.detail else "")
                      for k, c in self.seed004.items()]
        alg = d["estimation_algebra"]
        lines += ["", "estimation algebra E = <L0, h_1, ..., h_m>:"]
        if alg["closed"]:
            lines += [f"  dimension {alg['dimension']}, linear rank {alg['linear_rank']}, "
                      f"{'maximal' if alg['maximal_rank'] else 'non-maximal'} rank  ({alg['rank_test']})"]
            lines += [f"  basis: {{{', '.join(alg['basis'])}}}"]
        else:
            lines += [f"  does not close within {alg['stopped_by']} "
                      f"({alg['rounds']} rounds of brackets, {len(alg['basis'])} independent elements found)"]
        lines += ["", f"recommended method: {self.method}", f"  reason: {self.reason}",
                  f"  (analysis took {self.elapsed:.2f} s)"]
        return "\n".join(lines)


def _mark(holds: bool | None, yes: str = "x", no: str = " ", undecided: str = "?") -> str:
    return undecided if holds is None else (yes if holds else no)


def analyze(model: Model, max_depth: int = DEFAULT_MAX_DEPTH, max_dimension: int = DEFAULT_MAX_DIMENSION,
            time_limit: float | None = DEFAULT_TIME_LIMIT,
            max_size: int | None = DEFAULT_MAX_SIZE) -> AnalysisReport:
    """Wong matrix, η, conditions, estimation algebra and the recommended exact/general method.

    Bounded: the conditions get at most half of `time_limit` (they usually take milliseconds), the
    algebra the rest; an item that reaches a bound is reported undecided (holds None) and the
    algebra as not closing within that bound.  A single SymPy call cannot be interrupted, so the
    size cap keeps each one small; the report may come back a little after the deadline.
    """
    start = time.monotonic()
    half = None if time_limit is None else time_limit / 2
    name = None if time_limit is None else f"time {time_limit:g} s (half of it for the conditions)"
    with bounded(Budget(half, max_size, start, name)) as budget:
        facts = _conditions(model)
        facts.numeric = budget.numeric_zero_tests
    with bounded(Budget(time_limit, max_size, start)) as budget:
        algebra = _bounded_algebra(model, max_depth, max_dimension)
        basis = [show_operator(op, model, label)
                 for op, label in zip(algebra.basis, algebra.labels, strict=True)]
        facts.numeric += budget.numeric_zero_tests
        report = _report(model, facts, algebra, basis)  # simplifies for display only while time is left
    report.elapsed = time.monotonic() - start
    return report


@dataclass
class _Facts:
    """The structural conditions; None marks an item not decided within the bounds."""

    omega: Any = None
    omega_a: Any = None
    eta: Any = None
    c1: bool | None = None
    c2: bool | None = None
    c3: bool | None = None
    linear: bool | None = None
    wong_constant: bool | None = None
    k: int | None = None
    structure: Any = None
    structure_holds: bool | None = None
    seed004: dict = field(default_factory=dict)
    stopped_by: list = field(default_factory=list)
    numeric: int = 0

    def decide(self, fn):
        """fn() under the current budget, or None (recorded) when it reaches a bound."""
        try:
            return fn()
        except BoundReached as bound:
            if str(bound) not in self.stopped_by:
                self.stopped_by.append(str(bound))
            return None


def _all(values) -> bool | None:
    """Three-valued and: False if any is False, None if any is undecided, else True."""
    values = list(values)
    return False if False in values else (None if None in values else True)


def _conditions(model: Model) -> _Facts:
    x = model.symbols
    a_is_identity = is_identity(model.a)
    facts = _Facts(k=observed_coordinate(model))
    facts.omega = facts.decide(lambda: wong_matrix(model))
    facts.omega_a = facts.omega if a_is_identity else facts.decide(lambda: whitened_wong_matrix(model))
    facts.eta = facts.decide(lambda: eta(model))
    if facts.omega_a is not None:
        facts.c1 = _all(facts.decide(lambda w=w: is_constant(w, x)) for w in facts.omega_a)
    if facts.omega is not None:
        facts.wong_constant = _all(facts.decide(lambda w=w: is_constant(w, x)) for w in facts.omega)
    facts.c2 = _all(facts.decide(lambda hi=hi: polynomial_degree_at_most(hi, x, 1))
                    for hi in model.observation)
    if facts.eta is not None:
        facts.c3 = facts.decide(lambda: polynomial_degree_at_most(facts.eta, x, 2))
    affine_f = _all(facts.decide(lambda fi=fi: polynomial_degree_at_most(fi, x, 1)) for fi in model.drift)
    facts.linear = _all([facts.c2, affine_f])
    if facts.k is not None and a_is_identity:
        facts.structure = facts.decide(lambda: seed004_structure(model, facts.k) or False)
        facts.structure_holds = None if facts.structure is None else facts.structure is not False
        if model.n > 1:
            facts.seed004 = facts.decide(lambda: _seed004_items(model, facts.k)) or {}
    else:
        facts.structure_holds = False
    return facts


def _report(model: Model, facts: _Facts, algebra: EstimationAlgebra, basis: list[str]) -> AnalysisReport:
    a_is_identity = is_identity(model.a)
    notes = []
    if not is_identity(model.R):
        notes.append("R != I: eta and L0 use h^T R^-1 h")
    if not a_is_identity:
        notes.append("a != I: the seeds assume a = I (g orthogonal); eta here is f^T a^-1 f + div f + "
                     "h^T R^-1 h and (C'1) is tested on a J^T - J a "
                     "(the Wong matrix of z = L^-1 x, a = L L^T); "
                     "the seed 004 class is only tested for a = I")
    if facts.numeric:
        notes.append(f"non-polynomial zero tests are numeric ({_DIGITS} digits at {_ZERO_POINTS} "
                     "random points)")
    undecided = ""
    if facts.stopped_by:
        undecided = f"not decided within {' / '.join(facts.stopped_by)}"
        notes.append(f"some conditions were {undecided}")
    k = facts.k
    conditions = {
        "yau_filtering_system": Condition(
            facts.c1, "" if facts.c1 is not None else undecided,
            "(C'1) Omega constant (seed 000), equivalently f = affine + gradient (C1)"),
        "h_affine": Condition(facts.c2, "" if facts.c2 is not None else undecided, "(C2) h affine"),
        "eta_quadratic": Condition(facts.c3, "" if facts.c3 is not None else undecided,
                                   "(C3) eta a polynomial of degree <= 2"),
        "linear": Condition(facts.linear, "" if facts.linear is not None else undecided,
                            "linear model: f and h affine (Kalman-Bucy)"),
        "seed004_structure": Condition(
            facts.structure_holds,
            ("" if k is None else f"x_k = {model.spec.state[k]}")
            + ("" if facts.structure_holds is not None else f"; {undecided}"),
            "seed 004 (I), (II), (v): omega_kj = 0, eta quadratic in x_k plus a function of the others, "
            "h affine in x_k only"),
    }
    if facts.seed004:
        conditions["seed004_class"] = Condition(all(c.holds for c in facts.seed004.values()), "",
                                                "seed 004 class: conditions (i)-(v)")
    yau = _all([facts.c1, facts.c2, facts.c3])
    method, reason = recommend_method_from(model, facts.linear is True, yau is True,
                                           facts.structure_holds is True, a_is_identity)
    if method == "yau-yau" and undecided:
        reason += f" (the exact-filter conditions were {undecided}; the general engine is always valid)"
    n = model.n
    shown = f"not computed within {' / '.join(facts.stopped_by)}" if facts.stopped_by else "not computed"
    return AnalysisReport(
        model=model.spec.name, state=list(model.spec.state),
        wong_matrix=[[show(facts.omega[i, j], model) if facts.omega is not None else shown
                      for j in range(n)] for i in range(n)],
        wong_constant=facts.wong_constant, eta=show(facts.eta, model) if facts.eta is not None else shown,
        notes=notes, conditions=conditions, seed004=facts.seed004, algebra=algebra, algebra_basis=basis,
        method=method, reason=reason)


def observed_coordinate(model: Model) -> int | None:
    """The single state coordinate h depends on (x1 of seed 004 §III), if there is one."""
    used = {i for hi in model.observation for i, s in enumerate(model.symbols) if hi.has(s)}
    return next(iter(used)) if len(used) == 1 else None


def recommend_method_from(model: Model, linear: bool, yau: bool, seed004: bool,
                          a_is_identity: bool) -> tuple[str, str]:
    gaussian = model.spec.initial.kind == "gaussian"
    if linear and gaussian:
        return "kalman-bucy", "f and h are affine and the prior is Gaussian: the Kalman-Bucy filter is exact"
    if yau and a_is_identity:
        return "yau-hu", ("Yau filtering system with (C1), (C2), (C3): the DMZ equation reduces to a "
                          "Kolmogorov equation and ODEs (seed 000 Thm 3.1, seed 002 §4)")
    if seed004 and a_is_identity:
        return "wei-norman", ("seed 004 class: E = {L0, D1, x1, 1} is finite dimensional; "
                              "u = e^r0 e^(r1 x1) e^(r2 D1) e^(t L0) sigma0 (seed 004 Thm 1)")
    if (linear or yau or seed004) and not a_is_identity:
        return "yau-yau", "an exact filter would apply with a = I, but a != I here: the general engine"
    return "yau-yau", ("no finite-dimensional exact filter applies: the general Yau-Yau algorithm "
                      "(seed 002 §5)")


def recommend_method(report: AnalysisReport) -> tuple[str, str]:
    """The method the analysis recommends and why: kalman-bucy | yau-hu | wei-norman | yau-yau."""
    return report.method, report.reason
