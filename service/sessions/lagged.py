"""Fixed-lag smoothing in a session (option ``smooth_lag`` L, issue 38): each chunk response also carries
the estimate of the row L rows back given the rows up to the newest, stored with the response (a resent
seq gets the same answer, as for everything else).

The session's state holds, under ``lag``, what the lag needs: the rows not yet smoothed (at most L, with
their times) and the filter's state before the first of them (``anchor``).  A chunk of C rows joins them
(W ≤ L stored): the first E = W + C − L rows of the window now have L rows after them and are smoothed by
``solver.smoothing.smooth_lag`` from the anchor (the engine: one forward pass, L backward steps a row;
Kalman–Bucy: Rauch–Tung–Striebel over each row's L + 1 rows), which is exactly the fixed-lag smoother
``flt.smooth(rows, lag=L)`` over the session's rows; the anchor then moves over those E rows.  Stored:
L rows of m numbers and their times, and one filter state (the engine: its coefficient vector; the
stored state about doubles plus 16·L·(m + 1) bytes).  A degenerate, re-initialised or lost-track chunk,
and a reset, start the window again from the session's new state (the rows before are not smoothed).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.filtering import slice_result
from yauyau.solver.smoothed_summaries import smooth_lag_with_quantiles
from yauyau.solver.smoothing import SMOOTHING_METHODS, can_smooth, smooth, smooth_lag
from yauyau.solver.summaries import is_gaussian

from .responses import Extras, estimate_rows, summaries_of

MAX_LAG = 1000  # rows: the window the session's state stores (and each chunk smooths over)


def check_smooth_lag(lag: Any) -> int | None:
    """None (off) or a whole number of rows in 1 … MAX_LAG (InputError naming ``smooth_lag``)."""
    if lag is None:
        return None
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or not 1 <= lag <= MAX_LAG:
        raise InputError("smooth_lag", f"must be a whole number of rows from 1 to {MAX_LAG} (the rows the "
                                       f"session keeps to smooth over), got {lag!r}")
    return int(lag)


def check_can_smooth(filt: Any, state: Any) -> None:
    """SpecError naming ``smooth_lag`` and the method when the session's filter has no smoother."""
    why = None
    if not can_smooth(filt):
        why = "it has no smoother"
    else:
        try:
            smooth(filt, state, np.empty((0, filt.model.m)))  # the smoother's own refusals (kind)
        except (SpecError, InputError) as exc:
            why = exc.message
    if why is not None:
        raise SpecError("smooth_lag", f"method {filt.method} cannot smooth this model ({why}); smooth_lag "
                                      f"needs one of {', '.join(SMOOTHING_METHODS)} (the general engine "
                                      "yau-yau on a fixed ball smooths any model)")


def split_lag(data: Any) -> tuple[Any, dict[str, Any] | None]:
    """(the state dict without the window, the stored window or None)."""
    if isinstance(data, dict) and "lag" in data:
        rest = dict(data)
        return rest, rest.pop("lag")
    return data, None


def _rows_json(rows: np.ndarray) -> list:
    return [[None if np.isnan(v) else float(v) for v in row] for row in rows]


def lagged_rows(filt: Any, lag: int, before: Any, window: dict[str, Any] | None, rows: np.ndarray,
                times: list[float] | None, stamps: np.ndarray, extras: Extras | None = None,
                ) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """(the smoothed estimates this chunk completes, the window to store) for a chunk of ``rows`` (at
    ``times``, or one dt apart; ``stamps``: the times the filter gave them) run from the session state
    ``before`` with the stored ``window``.  ``extras`` (the chunk's mode and quantiles): each smoothed
    estimate carries them as the filtered ones do, by the same code (``summaries_of``) on its smoothed
    density (the engine) or its Gaussian (Kalman–Bucy)."""
    timed = times is not None
    if window is None or not window["rows"]:
        anchor, old_rows, old_times, was_timed = before, np.empty((0, rows.shape[1])), [], timed
    else:
        anchor = filt.state_from_dict(window["anchor"])
        old_rows = np.array([[np.nan if v is None else v for v in row] for row in window["rows"]],
                            dtype=float)
        old_times, was_timed = list(window["times"]), bool(window["timed"])
    if was_timed != timed:
        raise InputError("times", "a session with smooth_lag takes its chunks all with times or all "
                                  "without (the rows it keeps to smooth over were sent "
                                  f"{'with' if was_timed else 'without'} them)")
    all_rows = np.concatenate([old_rows, rows])
    all_times = old_times + [float(t) for t in stamps]
    done = len(all_rows) - lag
    if done <= 0:
        return [], {"anchor": anchor.to_dict(), "rows": _rows_json(all_rows), "times": all_times,
                    "timed": timed}
    given = np.asarray(all_times) if timed else None
    result, fields = _smoothed(filt, anchor, all_rows, given, lag, extras, done)
    head = slice_result(result, slice(0, done))
    out = estimate_rows(head.step, head.t, np.asarray(head.mean, float), np.asarray(head.cov, float))
    out = [row | extra for row, extra in zip(out, fields, strict=True)]
    anchor, _ = filt.run_arrays(anchor, all_rows[:done], None if given is None else given[:done])
    return out, {"anchor": anchor.to_dict(), "rows": _rows_json(all_rows[done:]), "times": all_times[done:],
                 "timed": timed}


def _smoothed(filt: Any, anchor: Any, rows: np.ndarray, given: np.ndarray | None, lag: int,
              extras: Extras | None, done: int) -> tuple[Any, list[dict[str, Any]]]:
    """(the fixed-lag smoothed result over the window, the mode and quantiles asked for of its first
    ``done`` rows: {} each without ``extras``)."""
    if not extras:
        return smooth_lag(filt, anchor, rows, given, lag)[1], [{}] * done
    if is_gaussian(filt):
        result = smooth_lag(filt, anchor, rows, given, lag)[1]
        return result, [summaries_of(filt, None, est, extras) for est in result.estimates()[:done]]
    found: dict[int, dict[str, Any]] = {}

    def each(k: int, smoothed: Any) -> None:
        if k < done:
            found[k] = summaries_of(filt, smoothed, smoothed.last, extras)

    _, result, _ = smooth_lag_with_quantiles(filt, anchor, rows, given, lag, None, each)
    return result, [found[k] for k in range(done)]
