"""Cached schedules of data-free step coefficients, shared by the Kalman–Bucy and Yau–Hu filters.

For a time-invariant model the covariance-type path (P of Kalman–Bucy, the exponents A of Yau–Hu)
from a given start does not depend on the data and converges geometrically to its steady state.
A schedule stores the coefficients of consecutive observed steps from one start until the path
stops moving (to rounding); its last entry is then the steady step, reused for every later step.
Positions are remembered by the bytes of the covariance-type variable a step starts from: the
coefficients of a step depend only on it.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..measurement import standard_score

EXTEND = 512  # most steps added beyond the need (the length doubles up to it: one-row chunks share the cost)
MAX_STEPS = 1 << 16  # a path that has not settled by then is left to the general chunk code
MAX_ENTRIES = 1 << 21  # cap on steps × components × (n + m)² stored by one schedule (memory)
MAX_KEYS = 4096  # starting points remembered as schedule positions


@dataclass
class Schedule:
    """Coefficient arrays (leading axis: step) from one start; ``settled``: the last entry is steady.

    ``parts`` holds the named coefficient arrays (also readable as attributes); ``end`` is the
    covariance-type variable after the last stored step (where an extension starts); ``scalars``
    and ``rows`` are the filters' plain-float and row views, rebuilt after each extension.
    """

    end: np.ndarray
    parts: dict[str, np.ndarray] = field(default_factory=dict)
    settled: bool = False
    scalars: list | None = None
    rows: dict | None = None

    def __getattr__(self, name: str) -> Any:
        parts = self.__dict__.get("parts") or {}
        if name in parts:
            return parts[name]
        raise AttributeError(name)

    @property
    def length(self) -> int:
        return len(next(iter(self.parts.values()))) if self.parts else 0

    def append(self, parts: dict[str, np.ndarray], settled: bool, end: np.ndarray) -> None:
        for name, value in parts.items():
            old = self.parts.get(name)
            self.parts[name] = value if old is None else np.concatenate([old, value])
        self.settled, self.end, self.scalars, self.rows = settled, end, None, None

    def row_view(self) -> dict[str, np.ndarray]:
        """The parts but the covariance-type "A" as contiguous (components, steps) rows (n = m = 1:
        sums over components vectorise along time)."""
        if self.rows is None:
            J = self.end.shape[0]
            self.rows = {name: np.ascontiguousarray(value.reshape(self.length, J).T)
                         for name, value in self.parts.items() if name != "A"}
        return self.rows

    def extension(self, j: int, K: int, cap: int = MAX_STEPS) -> int | None:
        """Steps to append so that steps j..j+K−1 are stored: 0 if they are (or the schedule is
        settled), None if that is past ``cap`` (the general chunk code takes over)."""
        if self.settled or j + K <= self.length:
            return 0
        if j + K > cap:
            return None
        return j + K - self.length + min(EXTEND, self.length)


class ScheduleCache:
    """Schedule positions by the bytes of the starting covariance-type variable (at most MAX_KEYS;
    the cache starts over when full)."""

    def __init__(self) -> None:
        self._positions: dict[bytes, tuple[Schedule, int]] = {}

    @staticmethod
    def key(start: np.ndarray) -> bytes:
        return np.ascontiguousarray(start, dtype=float).tobytes()

    def at(self, start: np.ndarray, first: Any = None) -> tuple[Schedule, int]:
        """The schedule and position for ``start``; if unseen, a new schedule from ``first()``
        (a callable, evaluated only then; default ``start`` itself)."""
        found = self._positions.get(self.key(start))
        if found is None:
            origin = np.array(start if first is None else first(), dtype=float)
            found = self.remember(start, Schedule(end=origin), 0)
        return found

    def remember(self, start: np.ndarray, schedule: Schedule, position: int) -> tuple[Schedule, int]:
        if len(self._positions) >= MAX_KEYS:
            self._positions.clear()
        found = self._positions[self.key(start)] = (schedule, position)
        return found

    def __len__(self) -> int:
        return len(self._positions)


# -- irregular rows: bounded caches per gap, the chunk's clock and the outlier gate -------------
FLOW_CACHE = 256  # flows (matrix exponentials) kept per filter, by gap (and pattern of observed components)


class BoundedCache:
    """A least-recently-used map of at most ``size`` entries: ``get(key, make)`` returns the entry,
    building it with ``make()`` when absent (the oldest entry goes when full)."""

    def __init__(self, size: int = FLOW_CACHE) -> None:
        self.size = size
        self._items: OrderedDict = OrderedDict()

    def get(self, key: Any, make: Callable[[], Any]) -> Any:
        items = self._items
        found = items.get(key, _ABSENT)
        if found is _ABSENT:
            found = items[key] = make()
            if len(items) > self.size:
                items.popitem(last=False)
        else:
            items.move_to_end(key)
        return found

    def __len__(self) -> int:
        return len(self._items)


_ABSENT = object()


def regular_gaps(taus: np.ndarray | None, dt: float, times: np.ndarray, t0: float) -> np.ndarray | None:
    """None (a regular chunk: the fast paths) when every gap is dt to the resolution of the time
    stamps (a few ulps of the largest |t|: t_k = k·dt computed in floating point), else the gaps."""
    if taus is None or not len(taus):
        return taus
    resolution = 4.0 * np.finfo(float).eps * (max(abs(t0), float(np.abs(times).max())) + dt)
    return None if np.all(np.abs(taus - dt) <= resolution) else taus


@dataclass
class Segment:
    """What a filter's chunk code returns for consecutive rows: estimates, the Girsanov (continuous)
    or predictive (discrete) log-likelihood increments, and ``after(i)``: the filter's carried
    representation after row i (what the next row starts from)."""

    mean: np.ndarray
    cov: np.ndarray
    ll: np.ndarray
    after: Callable[[int], Any]


@dataclass
class Gated:
    """A chunk's rows after the gate: estimates, log-likelihood increments, predictive
    log-likelihoods, the gated rows and their scores, and the representation after the last row."""

    mean: np.ndarray
    cov: np.ndarray
    ll: np.ndarray
    predictive: np.ndarray
    gated: np.ndarray
    score: np.ndarray
    last: Any


GATE_WINDOW = 64  # rows re-run after a gated row before the window doubles again


def gated_chunk(start: Any, rows: np.ndarray, keys: np.ndarray, taus: np.ndarray | None, gaps: np.ndarray,
                obs: Any, terms: Any, segment: Callable, h_cov: Callable | None) -> Gated:
    """Run a chunk through ``segment(start, rows, keys, taus) -> Segment`` and the outlier gate.

    The gate (solver/measurement.py): row k's score is d² = −2 log p(row_k | past) − log det 2πS,
    S = κ²C + S₀ with C = Cov_pred(h_o); the cheap bound g = −2 log p − log det 2πS₀ ≥ d² is checked
    first, and only where g is over the threshold C = ``h_cov(before, τ_k, index)`` (the
    representation before row k, its gap gaps[k], the observed components; ``h_cov`` None or
    returning None: the bound is the score).  A gated row only predicts, which changes every later
    step: the chunk is re-run from the first gated row with that row treated as missing, in windows
    of GATE_WINDOW rows that double while clean (a clean chunk is one ``segment`` call, as without a
    gate; each outlier costs at most a window).  A gated row keeps its predictive log-likelihood.
    """
    K = len(rows)
    gating = obs.gating
    predictive_offset = terms.offset
    bias = -terms.log_det_S0
    means, covs, lls, plls = [], [], [], []
    gated, score = np.zeros(K, dtype=bool), np.full(K, np.nan)
    kept: dict[int, float] = {}
    own = False  # rows and keys copied (the caller's are left alone)
    pos, size, current = 0, K, start
    while pos < K:
        end = min(K, pos + size)
        part = segment(current, rows[pos:end], keys[pos:end], None if taus is None else taus[pos:end])
        pll = part.ll + predictive_offset[pos:end]
        pll[keys[pos:end] == 0] = np.nan
        hit = _first_gated(current, part, pos, pll, keys, gaps, obs, terms, bias, h_cov) if gating else None
        take = (end if hit is None else hit[0]) - pos
        means.append(part.mean[:take])
        covs.append(part.cov[:take])
        lls.append(part.ll[:take])
        plls.append(pll[:take])
        if take:
            current = part.after(take - 1)
        if hit is None:
            pos, size = end, max(2 * size, GATE_WINDOW)
            continue
        k, d2 = hit
        size_o = int(keys[k]).bit_count()
        gated[k], score[k], kept[k] = True, standard_score(d2, size_o), float(pll[k - pos])
        if not own:
            rows, keys, own = rows.copy(), keys.copy(), True
        rows[k], keys[k] = np.nan, 0
        pos, size = k, GATE_WINDOW
    predictive = np.concatenate(plls)
    for k, value in kept.items():
        predictive[k] = value
    return Gated(np.concatenate(means), np.concatenate(covs), np.concatenate(lls), predictive, gated, score,
                 current)


def _first_gated(current, part: Segment, pos: int, pll, keys, gaps, obs, terms, bias, h_cov):
    """(row, d²) of the first row of a segment the gate rejects, or None."""
    with np.errstate(invalid="ignore"):
        bound = bias[pos:pos + len(pll)] - 2.0 * pll
        over = np.flatnonzero(bound > terms.threshold[pos:pos + len(pll)])
    for j in over.tolist():
        k = pos + j
        key = int(keys[k])
        if key == 0:
            continue
        d2 = float(bound[j])
        if h_cov is not None and math.isfinite(d2):
            before = current if j == 0 else part.after(j - 1)
            gap = float(gaps[k])
            cov = h_cov(before, gap, obs.pattern(key).index)
            if cov is not None:
                d2 -= max(0.0, obs.covariance_correction(key, float(terms.kappa2[k]), cov, obs.S0_scale(gap)))
        if d2 > terms.threshold[k]:
            return k, d2
    return None
