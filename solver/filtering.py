"""The filter contract: the protocol every filter implements and every type it uses.

A filter keeps the model apart from the algorithm (as in N. Chopin's ``particles``): it is
built once from a model, its state is a plain value, and ``run_arrays`` maps (state, a chunk of
observation increments) to (new state, a :class:`ChunkResult` of arrays) — a function of
(params, data), as in dynamax.  ``step`` and ``run`` are the same map for one row and as
:class:`Estimate` objects; :class:`ChunkedFilter` derives them from ``run_arrays``.  The state is
serialisable (``to_dict``/``state_from_dict``, JSON-safe) so that the service can store it between
chunks; the log normalising constant (the log-likelihood) is carried along in it.

A row is what arrives at one time (the spec's ``[measurement]``, solver/measurement.py): an increment
Δy_k = y(t_k) − y(t_(k−1)) (continuous kind) or a measurement z_k = h(x(t_k)) + v_k (discrete kind),
shape (m,).  Times are regular, t_k = t_(k−1) + dt, unless the chunk carries ``times`` (absolute,
strictly increasing): then every row is a step over its own gap.  A NaN component is not observed
(marginalised); a row of NaN means "no observation at this step": the filter only predicts.
``step(state, None)`` is the same as a row of NaN, and ``predict(state, t)`` a step to t without an
observation.  A filter whose representation cannot take a form (irregular times, discrete
measurements, a partly missing row: the Wei–Norman filter's (12) needs the whole path) raises
InputError naming the field and what to use instead.

Adding a filter: a module with a class implementing :class:`Filter` (usually ``ChunkedFilter`` plus
``initial_state``, ``run_arrays``, ``estimate``, ``density``, ``state_from_dict``) and one line in
the registry of solver/methods.py.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Protocol, Self, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from .errors import InputError
from .measurement import Observation, check_gate, check_spacing


@dataclass(slots=True)
class Estimate:
    """Summary of the conditional density after step ``step`` (time ``t``).

    Treated as a value (never mutated); not frozen because a frozen dataclass costs ~2.7x more to
    build (1.4 vs 0.5 µs measured), which is per observation in ``Filter.run``.
    """

    step: int
    """The step number k (0: the prior)."""
    t: float
    """The time t_k of the step."""
    mean: np.ndarray
    """(n,) the conditional mean E[x(t_k) | rows up to k]."""
    cov: np.ndarray
    """(n, n) the conditional covariance."""
    loglik: float
    """The cumulative log-likelihood (log of the normaliser ratio)."""
    loglik_increment: float
    """This step's contribution to ``loglik``."""
    degenerate: bool = False
    """The filter could not resolve this step (``reason`` says why)."""
    reason: str | None = None
    """Why the step is degenerate, gated or re-initialised (None: none of these)."""
    mode: np.ndarray | None = None
    """(n,) the MAP point, where the filter can tell (None otherwise)."""
    gated: bool = False
    """The observation was rejected by the gate: the step only predicted."""
    predictive_loglik: float | None = None
    """log p(row | rows before); None without an observation."""
    reinitialised: bool = False
    """The filter degenerated here and started again (``on_degenerate``)."""
    alarm: bool = False
    """The innovation monitor raised its alarm at this row (solver/watch.py)."""

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

    step: np.ndarray
    """(K,) int: the step numbers."""
    t: np.ndarray
    """(K,) the times of the steps."""
    mean: np.ndarray
    """(K, n) the conditional means."""
    cov: np.ndarray
    """(K, n, n) the conditional covariances."""
    mode: np.ndarray | None
    """(K, n) the MAP points, or None where the filter does not compute them."""
    loglik: np.ndarray
    """(K,) the cumulative log-likelihood."""
    loglik_increment: np.ndarray
    """(K,) each step's contribution to ``loglik``."""
    degenerate: np.ndarray
    """(K,) bool: the steps the filter could not resolve."""
    reason: str | None = None
    """Why the first degenerate step is degenerate."""
    predictive_loglik: np.ndarray | None = None
    """(K,) log p(row_k | rows before); NaN: no observation."""
    gated: np.ndarray | None = None
    """(K,) bool: the gate rejected the row (it only predicted)."""
    gate_score: np.ndarray | None = None
    """(K,) the predictive standard score of a gated row (NaN elsewhere)."""
    reinitialised: np.ndarray | None = None
    """(K,) bool: degenerate here, started again from a prior."""
    notes: dict[int, str] | None = None
    """Row -> why it was re-initialised."""
    gate: float | None = None
    """The gate the rows were checked against (predictive standard deviations; 0: off)."""
    center: np.ndarray | None = None
    """(K, n) the ball's centre after each row ([domain] follow; else None)."""
    recentred: np.ndarray | None = None
    """(K,) bool: the ball moved onto ``center`` after this row."""
    alarm: np.ndarray | None = None
    """(K,) bool: the innovation monitor's alarm (solver/watch.py)."""
    monitor: np.ndarray | None = None
    """(K,) the monitor's signed statistic after each row (±1: an alarm)."""

    def __post_init__(self):
        K = len(self.step)
        for name, fill in (("predictive_loglik", np.nan), ("gate_score", np.nan), ("monitor", np.nan)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(K, fill))
        for name in ("gated", "reinitialised", "recentred", "alarm"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(K, dtype=bool))

    def __len__(self) -> int:
        return len(self.step)

    def row_reason(self, k: int, gate: float | None = None) -> str | None:
        """Why row k is flagged (degenerate, re-initialised or gated), or None."""
        if self.reinitialised[k]:
            return (self.notes or {}).get(k, "re-initialised after the filter degenerated")
        if self.degenerate[k]:
            return self.reason
        if self.gated[k]:
            return gate_reason(float(self.gate_score[k]), self.gate if gate is None else gate)
        return None

    def estimates(self, gate: float | None = None) -> list[Estimate]:
        """One :class:`Estimate` per step (new objects; nothing is shared with later chunks)."""
        if self.mode is None:
            modes = [None] * len(self.step)
        else:
            known = (np.isfinite(self.mode).all(axis=1) & ~self.degenerate).tolist()
            modes = [m if ok else None for m, ok in zip(self.mode, known, strict=True)]
        flagged = (self.degenerate | self.gated | self.reinitialised).tolist()
        pll = [v if v == v else None for v in self.predictive_loglik.tolist()]  # NaN -> None
        columns = zip(self.step.tolist(), self.t.tolist(), self.mean, self.cov, self.loglik.tolist(),
                      self.loglik_increment.tolist(), self.degenerate.tolist(), modes, self.gated.tolist(),
                      pll, self.reinitialised.tolist(), flagged, self.alarm.tolist(), strict=True)
        return [Estimate(step=s, t=t, mean=m, cov=P, loglik=ll, loglik_increment=i, degenerate=bad,
                         reason=self.row_reason(k, gate) if flag else None, mode=mode, gated=gated,
                         predictive_loglik=p, reinitialised=again, alarm=alarm)
                for k, (s, t, m, P, ll, i, bad, mode, gated, p, again, flag, alarm) in enumerate(columns)]


_ROW_FIELDS = ("step", "t", "mean", "cov", "mode", "loglik", "loglik_increment", "degenerate",
               "predictive_loglik", "gated", "gate_score", "reinitialised", "center", "recentred", "alarm",
               "monitor")


def slice_result(result: ChunkResult, rows: slice) -> ChunkResult:
    """The rows ``rows`` (a slice with step 1) of a chunk's result."""
    start = rows.start or 0
    values = {name: (None if getattr(result, name) is None else getattr(result, name)[rows])
              for name in _ROW_FIELDS}
    K = len(values["step"])
    notes = {k - start: v for k, v in (result.notes or {}).items() if 0 <= k - start < K}
    reason = result.reason if values["degenerate"].any() else None
    return ChunkResult(**values, reason=reason, notes=notes or None, gate=result.gate)


def concat_results(parts: list[ChunkResult]) -> ChunkResult:
    """One result of consecutive chunks' results (the reason of the first degenerate row)."""
    if len(parts) == 1:
        return parts[0]
    values = {}
    for name in _ROW_FIELDS:
        arrays = [getattr(p, name) for p in parts]
        if name == "mode" and any(a is None for a in arrays):
            arrays = [p.mean if a is None else a for p, a in zip(parts, arrays, strict=True)]
        values[name] = None if name == "center" and any(a is None for a in arrays) else np.concatenate(arrays)
    notes, offset = {}, 0
    for p in parts:
        notes.update({offset + k: v for k, v in (p.notes or {}).items()})
        offset += len(p)
    reason = next((p.reason for p in parts if p.degenerate.any()), None)
    gate = next((p.gate for p in parts if p.gate is not None), None)
    return ChunkResult(**values, reason=reason, notes=notes or None, gate=gate)


def gate_reason(score: float, gate: float | None = None) -> str:
    """The note of a gated row: its predictive standard score against the gate."""
    where = "beyond the gate" if gate is None else f"beyond the gate of {gate:g}"
    size = "an impossible value" if not np.isfinite(score) else f"{score:.3g} predictive standard deviations"
    return f"observation gated: {size} from the prediction, {where}; the step only predicted"


@runtime_checkable
class FilterState(Protocol):
    """What every filter state has: where it is, the carried log-likelihood, its health."""

    # read-only members: the states are frozen dataclasses (a settable member would not match them)
    @property
    def step(self) -> int:
        """The number of rows taken (0: the prior)."""
        ...

    @property
    def t(self) -> float:
        """The state's time."""
        ...

    @property
    def loglik(self) -> float:
        """The log-likelihood carried along (log of the normaliser ratio)."""
        ...

    @property
    def degenerate(self) -> bool:
        """The filter could not resolve a step: it stays so until restarted."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """The state as JSON-safe data (the filter's ``state_from_dict`` reads it back, exactly)."""
        ...


State = TypeVar("State", bound=FilterState)


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
class MarginalFilter(Protocol):
    """A filter that computes a marginal density itself (the engine, on its nodes); the others get
    one by quadrature of their joint density (:func:`marginal_by_quadrature`)."""

    def marginal(self, state: FilterState, variable: int, grid: np.ndarray, resolution: int = 64,
                 /) -> np.ndarray:
        """Marginal density of state variable ``variable`` at the values ``grid`` (G,)."""
        ...


@runtime_checkable
class Filter(Protocol):
    """The interface of every filter (general engine and exact filters alike)."""

    method: ClassVar[str]
    """The registry name: "yau-yau", "kalman-bucy", "yau-hu", "wei-norman", ..."""
    follows: ClassVar[bool]
    """Its domain ball follows the state: results carry the centre (``[domain] follow``)."""
    model: Any  # solver/model.Model (importing it here would close the circle model -> gaussian -> here)
    """The compiled model the filter was built for (solver/model.Model)."""

    def initial_state(self, prior: Any | None = None) -> FilterState:
        """State at t = 0; ``prior`` (a spec prior) overrides the model's."""

    def run_arrays(self, state: FilterState, increments: np.ndarray,
                   times: np.ndarray | None = None) -> tuple[FilterState, ChunkResult]:
        """Advance over a chunk of rows (K, m) (NaN: a missing component; a row of NaN: no observation),
        at ``times`` (K,) if given (absolute, strictly increasing), else one dt apart."""

    def step(self, state: FilterState, increment: np.ndarray | None,
             t: float | None = None) -> tuple[FilterState, Estimate]:
        """Advance by one row (``None``: no observation, predict only), to time ``t`` (default + dt)."""

    def run(self, state: FilterState, increments: np.ndarray,
            times: np.ndarray | None = None) -> tuple[FilterState, list[Estimate]]:
        """``run_arrays`` with one :class:`Estimate` per row."""

    def predict(self, state: FilterState, t: float) -> tuple[FilterState, Estimate]:
        """The state at time ``t`` (after the state's time) without an observation: the forecast."""

    def estimate(self, state: FilterState) -> Estimate:
        """The current estimate (without stepping)."""

    def density(self, state: FilterState, points: np.ndarray) -> np.ndarray:
        """Normalised conditional density at points (P, n)."""

    def state_from_dict(self, data: dict[str, Any]) -> FilterState:
        """Inverse of ``state.to_dict()``."""


class ChunkedFilter:
    """``step``, ``run`` and ``predict`` of a filter that advances whole chunks with ``run_arrays``."""

    model: Any
    """The compiled model the filter was built for (solver/model.Model)."""

    follows: ClassVar[bool] = False
    """Whether the domain ball follows the state (the engine's FollowingFilter says True)."""
    gate_override: float | None = None
    """The gate set for this filter (``with_gate``; None: the spec's ``[measurement] gate``)."""

    @property
    def observation(self):
        """The spec's ``[measurement]`` with this filter's gate (solver/measurement.Observation), one
        per gate, kept."""
        cache = self.__dict__.setdefault("_observations", {})
        gate = self.gate
        found = cache.get(gate)
        if found is None:
            found = cache[gate] = Observation(self.model, gate)
        return found

    def with_gate(self, gate: float | None) -> Self:
        """This filter with another gate (None: the spec's): a shallow copy that shares every array
        and cache of this one (cheap: what a service keeps per session option)."""
        new = copy.copy(self)
        new.gate_override = check_gate(gate)
        return new

    @property
    def gate(self) -> float:
        """The gate in predictive standard deviations (0: off): the filter's override, else the
        spec's ``[measurement] gate``."""
        if self.gate_override is not None:
            return self.gate_override
        return float(self.model.spec.measurement.gate)

    def step(self, state: State, increment: np.ndarray | None,
             t: float | None = None) -> tuple[State, Estimate]:
        rows = one_row(increment, self.model.m, "increment")
        new_state, result = self.run_arrays(state, rows, None if t is None else [t])  # validates the row
        return new_state, result.estimates(self.gate)[0]

    def run(self, state: State, increments: np.ndarray,
            times: ArrayLike | None = None) -> tuple[State, list[Estimate]]:
        new_state, result = self.run_arrays(state, increments, times)
        return new_state, result.estimates(self.gate)

    def run_batch(self, states: list[State], chunks: list[ArrayLike],
                  times: list[ArrayLike | None] | None = None,
                  return_exceptions: bool = False) -> list[tuple[State, ChunkResult] | InputError]:
        """``run_arrays`` for many states of this model: [(new state, ChunkResult)] (solver/engine/batch.py;
        the Yau–Yau engine steps them together, other filters one after another)."""
        return run_batch_alone(self, states, chunks, times, return_exceptions)

    def predict(self, state: State, t: float) -> tuple[State, Estimate]:
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise InputError("t", "must be a number (the time to forecast to)") from None
        if not np.isfinite(t) or t < state.t:
            raise InputError("t", f"must be a finite time not before the filter's time "
                                  f"{float(state.t):.17g}, got {t!r}")
        if t == state.t:
            return state, self.estimate(state)
        return self.step(state, None, t)


def run_batch_alone(engine: Any, states: list[Any], chunks: list[ArrayLike],
                    times: list[ArrayLike | None] | None = None,
                    return_exceptions: bool = False) -> list[tuple[Any, ChunkResult] | InputError]:
    """The contract of ``run_batch`` (solver/engine/batch.py), one ``run_arrays`` per item (any filter)."""
    return per_item(states, chunks, times, return_exceptions,
                    lambda i, state, chunk, chunk_times: engine.run_arrays(state, chunk, chunk_times))


def per_item(states: list[Any], chunks: list[ArrayLike], times: list[ArrayLike | None] | None,
             return_exceptions: bool,
             item: Callable[[int, Any, ArrayLike, ArrayLike | None], Any]) -> list[Any]:
    """``item(i, state, chunk, times)`` for every i; a refused item's InputError in its place
    (``return_exceptions``) or raised naming it (``chunks[i]…``)."""
    if len(states) != len(chunks):
        raise InputError("chunks", f"one chunk per state: {len(states)} state(s), {len(chunks)} chunk(s)")
    if times is not None and len(times) != len(chunks):
        raise InputError("times", f"one list of times (or None) per chunk: {len(chunks)} chunk(s), "
                                  f"{len(times)} list(s)")
    out: list[Any] = []
    for i, (state, chunk) in enumerate(zip(states, chunks, strict=True)):
        try:
            out.append(item(i, state, chunk, None if times is None else times[i]))
        except InputError as exc:
            if not return_exceptions:
                raise InputError(f"chunks[{i}].{exc.field}", exc.message) from None
            out.append(exc)
    return out


def one_row(row: ArrayLike | None, m: int, field: str) -> np.ndarray:
    """A single row (m numbers, NaN: missing; None: no observation) as a (1, m) chunk; InputError
    naming ``field`` when it is not numbers (its width is checked with the chunk)."""
    if row is None:
        return np.full((1, m), np.nan)
    try:
        return np.reshape(np.asarray(row, dtype=float), (1, -1))
    except (TypeError, ValueError):
        raise InputError(field, f"must be {m} number(s) (NaN: missing), or None") from None


def check_t0(t0: Any, field: str = "t0", dt: float | None = None, what: str = "t0") -> float:
    """The time of a prior: a finite real number, else InputError naming ``field``; with the model's
    ``dt``, one where a step of dt keeps its precision (:func:`solver.measurement.check_spacing`; the
    message calls it ``what``)."""
    if isinstance(t0, bool) or not isinstance(t0, numbers.Real) or not math.isfinite(t0):
        raise InputError(field, "must be a finite number (the time of the prior)")
    if dt is not None:
        check_spacing(float(t0), float(dt), field, what)
    return float(t0)


def at_time(state: State, t0: float) -> State:
    """An initial state held at time ``t0`` (the prior's time) instead of 0."""
    if t0 == 0.0:
        return state
    if hasattr(state, "last"):
        return dataclasses.replace(state, t=t0, last=dataclasses.replace(state.last, t=t0))
    return dataclasses.replace(state, t=t0)


def chunk_clock(state: FilterState, K: int, dt: float, times: ArrayLike | None,
                taus: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(steps (K,), times (K,)) of a chunk: the given times, else one dt apart (on the grid k·dt
    while the state is on it, as the regular filters always were)."""
    steps = state.step + 1 + np.arange(K)
    if taus is not None:
        return steps, np.asarray(times, dtype=float).reshape(-1)
    if K:  # regular rows step by dt: at the chunk's last time that must still be a step
        check_spacing(float(state.t) + K * dt, dt, "t0", "the filter's time")
    if state.t == state.step * dt:
        return steps, steps * dt
    return steps, state.t + dt * np.arange(1, K + 1)


def refuse_form(method: str, rows: np.ndarray, times: ArrayLike | None, model: Any, *, times_ok: bool = False,
                discrete_ok: bool = False, partial_ok: bool = False) -> None:
    """InputError naming what ``method`` cannot take: irregular ``times``, discrete measurements or a
    partly missing row (the methods that take everything never call this)."""
    other = "yau-yau (the general engine) takes it"
    if times is not None and not times_ok:
        raise InputError("times", f"method {method} cannot take irregular observation times; {other}, "
                                  "or send regular rows without times")
    if model.spec.measurement.kind == "discrete" and not discrete_ok:
        raise InputError("measurement.kind", f"method {method} cannot take discrete measurements; {other}")
    if not partial_ok:
        missing = np.isnan(rows)
        partial = missing.any(axis=1) & ~missing.all(axis=1)
        if partial.any():
            row = int(np.argmax(partial))
            field = "observations" if model.spec.measurement.kind == "discrete" else "increments"
            raise InputError(f"{field}[{row}]", f"method {method} cannot take a partly missing row; "
                                                f"{other} (or send the whole row as missing)")


def marginal_by_quadrature(density: Callable[[np.ndarray], np.ndarray], n: int, variable: int,
                           grid: np.ndarray, low: np.ndarray, high: np.ndarray,
                           resolution: int = 64) -> np.ndarray:
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


def check_increments(increments: ArrayLike, m: int, field: str = "increments") -> np.ndarray:
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
