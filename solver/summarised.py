"""A chunk run row by row with the mode and quantiles of the density after each row: the one path of
the CLI (``yauyau filter --mode/--quantiles/--density``) and of the service (a chunk that asks for
``mode`` or ``quantiles``).

Each row is a watched run (solver/watch.py: the policy on a degenerate density, lost track, the
innovation monitor) of one row, so that the density after it can be summarised
(:func:`yauyau.solver.summaries.summarise`); the callers format the rows (CSV columns, JSON fields).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .filtering import ChunkResult, Estimate
from .summaries import summarise
from .watch import Watch, WatchSettings, watched_run

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from .filtering import Filter, FilterState


@dataclass(frozen=True, slots=True)
class SummarisedRow:
    """One row of a summarised run: the state and the watch after it, its one-row ``result`` and its
    ``estimate``, the ``mode`` (n,) and the ``quantiles`` (n, len(probs)) of the density after it
    (None: not asked for, or degenerate)."""

    state: FilterState
    watch: Watch
    result: ChunkResult
    estimate: Estimate
    mode: np.ndarray | None
    quantiles: np.ndarray | None


def gate_of(flt: Filter) -> float | None:
    """The filter's outlier gate in predictive standard deviations (None: a method without one)."""
    gate = getattr(flt, "gate", None)
    return None if gate is None else float(gate)


def summarised_rows(flt: Filter, state: FilterState, watch: Watch, rows: np.ndarray,
                    times: ArrayLike | None = None, policy: str = "stop",
                    settings: WatchSettings | None = None, *, mode: bool = False,
                    probs: np.ndarray | None = None) -> Iterator[SummarisedRow]:
    """The rows (K, m) run one at a time from ``state`` and ``watch`` (``times`` (K,) or None: regular)
    under the degenerate-density ``policy`` and the watch ``settings``, each with the mode (``mode``)
    and the marginal quantiles ``probs`` of the density after it."""
    gate = gate_of(flt)
    for k in range(len(rows)):
        state, watch, result = watched_run(flt, state, watch, rows[k:k + 1],
                                           None if times is None else times[k:k + 1], policy, settings)
        estimate = result.estimates(gate)[0]
        point, q = summarise(flt, state, estimate, mode, probs)
        yield SummarisedRow(state, watch, result, estimate, point, q)
