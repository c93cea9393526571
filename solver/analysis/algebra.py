"""The estimation algebra E = ⟨L0, h_1, …, h_m⟩ (seed 002 Def. 2.2, seed 004 Def. 2) by rounds of
Lie brackets, with its dimension, linear rank (seed 004 Def. 3) and whether it closes within bounds.

Linear dependence is decided exactly over ℚ on a monomial basis when every coefficient is a rational
polynomial, otherwise at random points with 50-digit arithmetic (the report says which).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import mpmath
import sympy as sp

from ..model import Model
from .budget import DEFAULT_MAX_SIZE, DEFAULT_TIME_LIMIT, BoundReached, Budget, bounded, current_budget
from .operators import (
    DIGITS,
    TOL,
    Operator,
    bracket,
    kolmogorov_operator,
    multiplication,
    rational_polynomial,
)

DEFAULT_MAX_DEPTH = 6  # rounds of brackets
DEFAULT_MAX_DIMENSION = 24


# ---------------------------------------------------------------------------------------------
# linear algebra over ℝ for operators: exact (ℚ, monomials) or at random points (50 digits)
# ---------------------------------------------------------------------------------------------
class _Echelon:
    """Reduced row echelon form of sparse vectors {key: number}; exact or with a tolerance."""

    def __init__(self, exact: bool):
        self.exact = exact
        self.rows: dict = {}  # pivot key -> row (row[pivot] == 1, zero at the other pivots)

    def _zero(self, v) -> bool:
        return v == 0 if self.exact else abs(v) <= TOL

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
            current_budget().check()
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
                current_budget().check()
                values.append(_real(fn(*[mpmath.mpf(p.numerator) / p.denominator for p in pt])))
            self._cache[key] = values
        return self._cache[key]


def _real(value) -> mpmath.mpf:
    value = mpmath.mpmathify(value)
    return value.real if isinstance(value, mpmath.mpc) else value


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
        with mpmath.workdps(DIGITS):  # mpf arithmetic runs at the context precision
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
        return bounded_algebra(model, max_depth, max_dimension)


def bounded_algebra(model: Model, max_depth: int, max_dimension: int) -> EstimationAlgebra:
    """The algebra under the current budget; a bound reached ends the search (not closed)."""
    budget = current_budget()
    search = _AlgebraSearch(model, max_dimension)
    with mpmath.workdps(DIGITS):  # mpf arithmetic of the numeric rank test runs at this precision
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
        self.exact = all(rational_polynomial(c, x) for op, _ in generators for c in op.values())
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
