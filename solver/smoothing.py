"""The optimal smoother, for any filter that has one (issue 38): p(x_k | every row of a chunk).

A filter that can smooth has ``smooth_arrays(state, rows, times)`` returning (the state after the
chunk, a :class:`~solver.filtering.ChunkResult` whose ``mean``, ``cov`` and ``mode`` are the smoothed
ones; its log-likelihoods, gating and flags are the forward pass's):

* yau-yau: the general engine (solver/engine/smoother.py), the forward–backward smoother of its
  discretised model, any model (on a ball that follows the state: solver/engine/follow_smoother.py, over
  its sequence of balls);
* kalman-bucy, exact: Rauch–Tung–Striebel for discrete measurements and the time-sampled increment model
  (solver/exact/kalman_smoother.py); for continuous increments (the robust flow) the two-filter form,
  filtered × the backward message of the adjoint flow (solver/exact/kalman_bucy_backward.py);
* yau-hu, exact: the seeds give no smoother, but the filter's step is the exact robust flow, whose
  adjoint keeps β = e^{−F}·(a finite sum of exponential-quadratics) (solver/exact/yau_hu_smoother.py):
  the smoothed density is the filter's mixture times that sum, a Gaussian mixture in closed form.

Refused by name (SpecError('method'), pointing to yau-yau), :data:`NO_SMOOTHER` says why: yau-jia, whose
step is not a fixed kernel — each component takes the data term linearised about its own mean, then is
split, merged and pruned — so no backward pass is the adjoint of what the filter did, and a backward
mixture filter would need approximations of its own (the smoother would not be exact, nor exact to the
filter's approximation).
:func:`smooth_lag` is the fixed-lag smoother: row k given the rows up to k + L.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import InputError, SpecError
from .filtering import ChunkResult, concat_results, slice_result

ENGINE_STATES = 3  # the general engine's finite elements: up to 3 states
SMOOTHING_METHODS = ("yau-yau", "kalman-bucy", "yau-hu")
NO_SMOOTHER = {"yau-jia": "its mixture steps linearise the data term about each component's mean and split, "
                          "merge and prune components, so no backward pass is exact for it",
               "yau-niu": "its weighted point set has no backward pass yet"}


def can_smooth(flt: Any) -> bool:
    """Whether ``flt`` has a smoother."""
    return callable(getattr(type(flt), "smooth_arrays", None))


def smooth(flt: Any, state: Any, rows: Any, times: Any = None) -> tuple[Any, ChunkResult]:
    """(state after the chunk, the smoothed ChunkResult) of ``flt``; SpecError('method') naming a method
    without a smoother."""
    if not can_smooth(flt):
        why = NO_SMOOTHER.get(flt.method)
        engine = (f"the general engine smooths models of at most {ENGINE_STATES} states (method yau-yau, "
                  "precomputed: e.g. `yauyau precompute` of the spec with method = \"yau-yau\", then "
                  "--method yau-yau); this model has no smoother yet" if flt.model.n > ENGINE_STATES else
                  "the general engine smooths any model (method yau-yau, e.g. open_filter(..., "
                  "method='yau-yau') or --method yau-yau)")
        raise SpecError("method", f"method {flt.method} has no smoother{f' ({why})' if why else ''}; "
                                  + engine)
    return flt.smooth_arrays(state, rows, times)


def check_lag(lag: Any, field: str = "lag") -> int:
    """A fixed lag: a non-negative whole number of rows (InputError naming ``field``)."""
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
        raise InputError(field, f"must be a non-negative whole number of rows, got {lag!r}")
    return int(lag)


def smooth_lag(flt: Any, state: Any, rows: Any, times: Any = None, lag: int = 0,
               visit: Any = None) -> tuple[Any, ChunkResult]:
    """Fixed-lag smoothing of a recorded chunk: row k's estimate given the rows up to k + ``lag`` (the
    last ``lag`` rows: given every row), ``lag = 0`` the filter.  The engine (yau-yau on a fixed ball):
    solver/engine/fixed_lag.py, one forward pass and ``lag`` backward steps a row.  Any other smoother
    (and the engine's increments in pieces): row k is the first row of the fixed-interval smoother over
    rows k … k + lag from the filter's state after row k − 1 (the filter is bit for bit the same however
    its rows are chunked), about lag + 1 smoothed rows a row.  Returns (the filter's state after the
    chunk, the result with the smoothed mean, cov, mode).  ``visit(k, [state])``, where given (the engine),
    gets row k's fixed-lag smoothed density as a filter state (solver/smoothed_summaries.py reads it)."""
    lag = check_lag(lag)
    if not can_smooth(flt):
        smooth(flt, state, rows, times)  # raises, naming the method
    arr = np.asarray(rows, dtype=float)
    if arr.ndim == 1 and flt.model.m == 1:
        arr = arr[:, None]
    K = len(arr)
    stamps = None if times is None else np.asarray(times, dtype=float).reshape(-1)
    if stamps is not None and len(stamps) != K:
        raise InputError("times", f"one time per row: {K} row(s), {len(stamps)} time(s)")
    if K == 0 or (lag == 0 and visit is None):
        return flt.run_arrays(state, arr, stamps)
    from .engine.filter import YauYauFilter  # the engine's own: one forward pass, L backward steps a row

    if isinstance(flt, YauYauFilter):
        from .engine.fixed_lag import smooth_lag_arrays

        found = smooth_lag_arrays(flt, state, arr, stamps, lag, visit=visit)
        if found is not None:
            return found
    parts = []
    for k in range(K):
        end = min(k + lag + 1, K)
        try:
            result, first = _window(flt, state, arr[k:end], None if stamps is None else stamps[k:end], visit)
            state, _ = flt.run_arrays(state, arr[k:k + 1], None if stamps is None else stamps[k:k + 1])
        except InputError as exc:  # name the row in the whole chunk
            raise exc.shifted(k) from None
        parts.append(slice_result(result, slice(0, 1)))
        if visit is not None:
            visit(k, first)
    return state, concat_results(parts)


def _window(flt: Any, state: Any, rows: np.ndarray, times: Any, visit: Any) -> tuple[ChunkResult, list]:
    """The fixed-interval smoother over one window: (its result, [its first row's smoothed density] where
    ``visit`` asks for densities, else [])."""
    if visit is None:
        return flt.smooth_arrays(state, rows, times)[1], []
    first: list = []

    def keep(start: int, states: list) -> None:
        if start == 0:
            first.append(states[0])

    return flt.smooth_arrays(state, rows, times, visit=keep)[1], first
