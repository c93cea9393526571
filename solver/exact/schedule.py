"""Cached schedules of data-free step coefficients, shared by the Kalman–Bucy and Yau–Hu filters.

For a time-invariant model the covariance-type path (P of Kalman–Bucy, the exponents A of Yau–Hu)
from a given start does not depend on the data and converges geometrically to its steady state.
A schedule stores the coefficients of consecutive observed steps from one start until the path
stops moving (to rounding); its last entry is then the steady step, reused for every later step.
Positions are remembered by the bytes of the covariance-type variable a step starts from: the
coefficients of a step depend only on it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

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
