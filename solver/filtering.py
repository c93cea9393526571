"""The filter contract: the protocol every filter implements and every type it uses.

A filter keeps the model apart from the algorithm (as in N. Chopin's ``particles``): it is
built once from a model, its state is a plain value, and ``run_arrays`` maps (state, a chunk of
observation increments) to (new state, a :class:`ChunkResult` of arrays) — a function of
(params, data), as in dynamax.  ``step`` and ``run`` are the same map for one row and as
:class:`Estimate` objects; :class:`ChunkedFilter` derives them from ``run_arrays``.  The state is
serialisable (``to_dict``/``state_from_dict``, JSON-safe) so that the service can store it between
chunks; the log normalising constant (the log-likelihood) is carried along in it.

Observation times τ_k = k·dt; increment Δy_k = y(τ_k) − y(τ_{k−1}) (shape (m,)).  A row of
NaN means "no observation at this step": the filter only predicts.  ``step(state, None)`` is the
same as a row of NaN.  A filter whose representation cannot predict without the observation (the
Wei–Norman filter: its (12) needs the whole path) raises InputError('increment') saying so.

Adding a filter: a module with a class implementing :class:`Filter` (usually ``ChunkedFilter`` plus
``initial_state``, ``run_arrays``, ``estimate``, ``density``, ``state_from_dict``) and one line in
the registry of solver/methods.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from .errors import InputError


@dataclass(slots=True)
class Estimate:
    """Summary of the conditional density after step ``step`` (time ``t``).

    Treated as a value (never mutated); not frozen because a frozen dataclass costs ~2.7x more to
    build (1.4 vs 0.5 µs measured), which is per observation in ``Filter.run``.
    """

    step: int
    t: float
    mean: np.ndarray  # (n,)
    cov: np.ndarray  # (n, n)
    loglik: float  # cumulative log-likelihood (log of the normaliser ratio)
    loglik_increment: float  # this step's contribution
    degenerate: bool = False
    reason: str | None = None
    mode: np.ndarray | None = None  # (n,), where the filter can tell

    def to_dict(self) -> dict[str, Any]:
        out = {"step": self.step, "t": self.t, "mean": self.mean.tolist(), "cov": self.cov.tolist(),
               "loglik": self.loglik, "loglik_increment": self.loglik_increment,
               "degenerate": self.degenerate, "reason": self.reason}
        out["mode"] = None if self.mode is None else self.mode.tolist()
        return out


@dataclass(frozen=True)
class ChunkResult:
    """The estimates of a chunk of K steps as arrays (what ``run_arrays`` returns).

    ``mode`` is None where a filter does not compute it (a mixture); a row of ``mode`` that is not
    finite means "unknown at that step".  ``degenerate[k]`` flags the steps the filter could not
    resolve (``reason`` says why, for the first); their arrays hold finite stand-ins (the engine
    repeats the last good estimate) and their :class:`Estimate` has no mode.
    """

    step: np.ndarray  # (K,) int
    t: np.ndarray  # (K,)
    mean: np.ndarray  # (K, n)
    cov: np.ndarray  # (K, n, n)
    mode: np.ndarray | None  # (K, n) or None
    loglik: np.ndarray  # (K,) cumulative
    loglik_increment: np.ndarray  # (K,)
    degenerate: np.ndarray  # (K,) bool
    reason: str | None = None  # of the first degenerate step

    def __len__(self) -> int:
        return len(self.step)

    def estimates(self) -> list[Estimate]:
        """One :class:`Estimate` per step (new objects; nothing is shared with later chunks)."""
        if self.mode is None:
            modes = [None] * len(self.step)
        else:
            known = (np.isfinite(self.mode).all(axis=1) & ~self.degenerate).tolist()
            modes = [m if ok else None for m, ok in zip(self.mode, known, strict=True)]
        columns = zip(self.step.tolist(), self.t.tolist(), self.mean, self.cov, self.loglik.tolist(),
                      self.loglik_increment.tolist(), self.degenerate.tolist(), modes, strict=True)
        reason = self.reason
        return [Estimate(step=s, t=t, mean=m, cov=P, loglik=ll, loglik_increment=i, degenerate=bad,
                         reason=reason if bad else None, mode=mode)
                for s, t, m, P, ll, i, bad, mode in columns]


@runtime_checkable
class FilterState(Protocol):
    """What every filter state has: where it is, the carried log-likelihood, its health."""

    step: int
    t: float
    loglik: float
    degenerate: bool

    def to_dict(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class StepState:
    """Common bookkeeping of a filter state (a base for the filters' own state classes)."""

    step: int = 0
    t: float = 0.0
    loglik: float = 0.0
    loglik_increment: float = 0.0
    degenerate: bool = False
    reason: str | None = None


@runtime_checkable
class Filter(Protocol):
    """The interface of every filter (general engine and exact filters alike)."""

    method: ClassVar[str]  # the registry name: "yau-yau", "kalman-bucy", "yau-hu", "wei-norman", ...
    model: Any

    def initial_state(self, prior: Any | None = None) -> FilterState:
        """State at t = 0; ``prior`` (a spec prior) overrides the model's."""

    def run_arrays(self, state: FilterState, increments: np.ndarray) -> tuple[FilterState, ChunkResult]:
        """Advance over a chunk of increments (K, m); rows of NaN are missing observations."""

    def step(self, state: FilterState, increment: np.ndarray | None) -> tuple[FilterState, Estimate]:
        """Advance by one observation interval dt (``None``: no observation, predict only)."""

    def run(self, state: FilterState, increments: np.ndarray) -> tuple[FilterState, list[Estimate]]:
        """``run_arrays`` with one :class:`Estimate` per row."""

    def estimate(self, state: FilterState) -> Estimate:
        """The current estimate (without stepping)."""

    def density(self, state: FilterState, points: np.ndarray) -> np.ndarray:
        """Normalised conditional density at points (P, n)."""

    def state_from_dict(self, data: dict[str, Any]) -> FilterState:
        """Inverse of ``state.to_dict()``."""


class ChunkedFilter:
    """``step`` and ``run`` of a filter that advances whole chunks with ``run_arrays``."""

    model: Any

    def step(self, state: Any, increment: np.ndarray | None) -> tuple[Any, Estimate]:
        if increment is None:
            rows = np.full((1, self.model.m), np.nan)
        else:
            try:
                rows = np.reshape(np.asarray(increment, dtype=float), (1, -1))
            except (TypeError, ValueError):
                raise InputError("increment", "must be a list of numbers (or null)") from None
        new_state, result = self.run_arrays(state, rows)  # validates the row
        return new_state, result.estimates()[0]

    def run(self, state: Any, increments: np.ndarray) -> tuple[Any, list[Estimate]]:
        new_state, result = self.run_arrays(state, increments)
        return new_state, result.estimates()


def marginal_by_quadrature(density: Any, n: int, variable: int, grid: np.ndarray, low: np.ndarray,
                           high: np.ndarray, resolution: int = 64) -> np.ndarray:
    """Marginal of coordinate ``variable`` at ``grid`` (G,) from a joint ``density(points (P, n))``:
    the other coordinates integrated out with the trapezoidal rule on ``resolution`` points per
    direction over the box [low, high] (arrays of n bounds; the marginal coordinate's are unused).
    ``density`` may return (P, k) values (k functions at once): the result is then (G, k)."""
    if n == 1:
        return density(grid[:, None])
    rest = [i for i in range(n) if i != variable]
    axes = [np.linspace(low[i], high[i], resolution) for i in rest]
    others = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n - 1)
    points = np.empty((len(grid), len(others), n))
    points[:, :, variable] = grid[:, None]
    points[:, :, rest] = others[None, :, :]
    values = np.asarray(density(points.reshape(-1, n)))
    values = values.reshape((len(grid),) + (resolution,) * (n - 1) + values.shape[1:])
    for k in range(n - 1, 0, -1):  # trailing dimensions (e.g. basis functions) are kept
        values = np.trapezoid(values, axes[k - 1], axis=k)
    return values


def observed(increment: np.ndarray | None, m: int) -> np.ndarray | None:
    """The increment as an (m,) array, or None for a missing observation (None or a NaN row)."""
    if increment is None:
        return None
    row = check_increments(np.reshape(np.asarray(increment, dtype=float), (1, -1)), m, "increment")[0]
    return None if np.isnan(row).all() else row


def check_increments(increments: Any, m: int, field: str = "increments") -> np.ndarray:
    """Validate a chunk of increments: shape (K, m) of finite floats or whole-row NaN (missing).

    Raises :class:`InputError` naming the field (and row) at fault.
    """
    try:
        arr = np.asarray(increments, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "must be a list of rows of numbers (or null rows)") from None
    if arr.ndim == 1 and m == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != m:
        raise InputError(field, f"each row must have {m} number(s); got shape {arr.shape}")
    missing = np.isnan(arr)
    partial = missing.any(axis=1) & ~missing.all(axis=1)
    if partial.any():
        row = int(np.argmax(partial))
        raise InputError(f"{field}[{row}]", "a row is either all numbers or missing (null), not partly")
    if np.isinf(arr).any():
        row = int(np.argmax(np.isinf(arr).any(axis=1)))
        raise InputError(f"{field}[{row}]", "increments must be finite")
    return arr


def cumulative_hint(increments: np.ndarray, model: Any, min_rows: int = 50) -> str | None:
    """Why these rows look like the observation path y(τ_k) rather than its increments Δy_k (or None).

    Increments of dy = h dt + dw are nearly uncorrelated with variance ≈ R dt: successive differences
    have about twice their variance.  A cumulative y is a random walk: its spread grows along the
    file while its successive differences stay small.  Flagged when, for some component, the
    differences' mean square is below 1/5 of the rows' variance and that variance exceeds 20 R_jj dt.
    """
    rows = np.asarray(increments, dtype=float)
    rows = rows[~np.isnan(rows).any(axis=1)]
    if len(rows) < min_rows:
        return None
    for j in range(rows.shape[1]):
        column = rows[:, j]
        spread = float(np.var(column))
        differences = float(np.mean(np.diff(column) ** 2))
        noise = float(model.R[j, j]) * float(model.dt)
        if spread > 20.0 * noise and differences < 0.2 * spread:
            half = len(column) // 2
            return (f"increment column {j} looks like the cumulative observation "
                    f"y(t_k), not the increments dy_k = y(t_k) - y(t_(k-1)): its spread grows along the file "
                    f"(variance {np.var(column[:half]):.3g} in the first half, "
                    f"{np.var(column[half:]):.3g} in the second; increments of this model have variance "
                    f"about {noise:.3g}); difference it first, e.g. numpy.diff(y, axis=0, prepend=0)")
    return None
