"""Bounds of the analysis: a deadline (monotonic clock) and a cap on the size of one expression.

The budget in force is a context variable: :func:`bounded` installs one, and the brackets, reductions
and zero tests of the other modules call :func:`current_budget`\\ ``().check()`` between their steps,
so that a bound reached raises :class:`BoundReached` wherever the analysis happens to be.
"""

from __future__ import annotations

import contextvars
import math
import time
from contextlib import contextmanager

import sympy as sp

DEFAULT_TIME_LIMIT = 60.0  # seconds for the whole analysis (None: unbounded)
DEFAULT_MAX_SIZE = 4000  # tree nodes of one coefficient of an algebra element


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


def current_budget() -> Budget:
    return _BUDGET.get()


@contextmanager
def bounded(budget: Budget):
    """Run the analysis functions of this package under `budget` (they raise BoundReached)."""
    token = _BUDGET.set(budget)
    try:
        yield budget
    finally:
        _BUDGET.reset(token)


def expanded_terms(expr: sp.Expr, cap: int) -> int:
    """An upper bound on the number of terms of ``sp.expand(expr)`` (and on the work inside function
    arguments it expands too), counted without expanding; values past ``cap`` are reported as cap + 1.

    Add: the sum over its terms; Mul: the product; b**p for an integer p > 0: the multinomial count
    C(t + p - 1, p) of the t terms of b; any other node: one term, plus what its arguments cost.
    ``(x + y + z + 1)**64`` gives 47 905 without building one of them (sp.expand takes minutes)."""
    over = cap + 1
    memo: dict[sp.Basic, tuple[int, int]] = {}

    def walk(e: sp.Basic) -> tuple[int, int]:  # (terms at this level, work inside arguments)
        if e in memo:
            return memo[e]
        if e.is_Atom:
            out = (1, 0)
        elif e.is_Add or e.is_Mul:
            parts = [walk(a) for a in e.args]
            work = min(over, sum(w for _, w in parts))
            terms = sum(t for t, _ in parts) if e.is_Add else math.prod(t for t, _ in parts)
            out = (min(over, terms), work)
        elif e.is_Pow and e.exp.is_Integer and e.exp > 0:
            t, w = walk(e.base)
            p = int(e.exp)
            out = (over if t >= over else min(over, math.comb(t + p - 1, p)), w)
        else:
            parts = [walk(a) for a in e.args]
            out = (1, min(over, sum(t + w for t, w in parts)))
        memo[e] = out
        return out

    terms, work = walk(expr)
    return max(terms, work)


def expand(expr: sp.Expr) -> sp.Expr:
    """``sp.expand`` under the current budget: BoundReached before a blow-up, never after it (one
    expand call cannot be interrupted, so its size is bounded before it starts)."""
    budget = current_budget()
    budget.check()
    if budget.max_size is not None and expanded_terms(expr, budget.max_size) > budget.max_size:
        raise BoundReached(f"expression size {budget.max_size}")
    return sp.expand(expr)


def expression_size(expr: sp.Expr, cap: int | None = None) -> int:
    """Number of nodes of the expression tree, counting stops just past `cap`."""
    count = 0
    for _ in sp.preorder_traversal(expr):
        count += 1
        if cap is not None and count > cap:
            break
    return count
