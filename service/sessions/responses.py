"""The bodies of the session responses: estimates as JSON rows, a chunk's response, the extras (mode,
quantiles) a request asks for, and the live page's view of the density.

Every number leaves finite or as null: ``estimate_rows`` nulls a row with a non-finite mean or
covariance, :func:`response_body` a non-finite log-likelihood, :func:`summary_fields` a mode or
quantiles that are not finite.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import orjson
from yauyau.solver import summaries
from yauyau.solver.filtering import ChunkResult, Estimate
from yauyau.solver.summaries import check_probabilities
from yauyau.solver.summarised import gate_of
from yauyau.solver.watch import Watch, WatchSettings


class Extras:
    """What a request asks for besides mean and covariance: quantiles (probabilities) and the mode."""

    def __init__(self, quantiles: Any | None = None, mode: bool = False):
        self.quantiles = None if quantiles is None else check_probabilities(quantiles)
        self.mode = bool(mode)

    def __bool__(self) -> bool:
        return self.quantiles is not None or self.mode


def estimate_rows(steps, times, mean: np.ndarray, cov: np.ndarray) -> list[dict[str, Any]]:
    """Estimates as JSON rows; a row with a non-finite mean or covariance gets nulls (degenerate)."""
    k = len(mean)
    finite = np.isfinite(mean).reshape(k, -1).all(axis=1) & np.isfinite(cov).reshape(k, -1).all(axis=1)
    return [{"step": s, "t": t, "mean": mu if ok else None, "cov": c if ok else None}
            for s, t, mu, c, ok in zip(np.asarray(steps).tolist(), np.asarray(times, float).tolist(),
                                       mean.tolist(), cov.tolist(), finite.tolist(), strict=True)]


def estimate_full(est: Estimate) -> dict[str, Any]:
    """One estimate with its log-likelihood and degeneracy flag."""
    mean, cov = np.asarray(est.mean, float)[None], np.asarray(est.cov, float)[None]
    row = estimate_rows([est.step], [est.t], mean, cov)[0]
    finite = row["mean"] is not None and math.isfinite(est.loglik)
    if est.degenerate:
        reason = est.reason or "degenerate density"
    else:
        reason = None if finite else "non-finite estimate"
    row.update(loglik=float(est.loglik) if math.isfinite(est.loglik) else None,
               degenerate=bool(est.degenerate) or not finite, reason=reason)
    return row


def result_rows(result: ChunkResult,
                gate: float | None) -> tuple[list[dict], list[int], list[int], str | None]:
    """A chunk's :class:`ChunkResult` as JSON rows: step, t, mean, cov and the predictive
    log-likelihood on every row; ``gated``, ``reinitialised``, ``degenerate`` (true) and ``reason``
    only on the rows they concern.  (rows, gated rows, re-initialised rows, first degenerate reason)."""
    rows = estimate_rows(result.step, result.t, result.mean, result.cov)
    for row, value in zip(rows, result.predictive_loglik.tolist(), strict=True):
        row["predictive_loglik"] = value if math.isfinite(value) else None
    for k in np.flatnonzero(result.alarm).tolist():  # the innovation monitor (solver/watch.py)
        rows[k]["alarm"], rows[k]["monitor"] = True, float(result.monitor[k])
    first_reason = _flag_rows(rows, result, gate)
    if result.center is not None:  # a ball that follows the state: its centre after each row
        for row, center, moved in zip(rows, result.center.tolist(), result.recentred.tolist(), strict=True):
            row["center"] = center
            if moved:
                row["recentred"] = True
    for row in rows:
        if row["mean"] is None and not row.get("degenerate"):  # estimate_rows nulled a non-finite row
            row["degenerate"], row["reason"] = True, row.get("reason") or "non-finite estimate"
            first_reason = first_reason or row["reason"]
    gated = np.flatnonzero(result.gated).tolist()
    again = np.flatnonzero(result.reinitialised).tolist()
    return rows, gated, again, first_reason


def _flag_rows(rows: list[dict], result: ChunkResult, gate: float | None) -> str | None:
    """Mark the gated, re-initialised and degenerate rows with their reason; the first degenerate
    row's reason."""
    degenerate = np.asarray(result.degenerate, dtype=bool)
    flagged = degenerate | result.gated | result.reinitialised
    first_reason = None
    for k in np.flatnonzero(flagged).tolist():
        row = rows[k]
        if result.gated[k]:
            row["gated"] = True
        if result.reinitialised[k]:
            row["reinitialised"] = True
        if degenerate[k]:
            row["degenerate"] = True
        row["reason"] = result.row_reason(k, gate) or "degenerate density"
        if degenerate[k] and first_reason is None:
            first_reason = row["reason"]
    return first_reason


def summary_fields(names: list[str], extras: Extras, point: np.ndarray | None,
                   q: np.ndarray | None) -> dict[str, Any]:
    """The mode and quantiles asked for as JSON fields (null when degenerate or not finite)."""
    out: dict[str, Any] = {}
    if extras.mode:
        out["mode"] = point.tolist() if point is not None and np.all(np.isfinite(point)) else None
    if extras.quantiles is not None:
        out["quantiles"] = ({v: q[i].tolist() for i, v in enumerate(names)}
                            if q is not None and np.all(np.isfinite(q)) else None)
    return out


def summaries_of(filt: Any, state: Any, estimate: Estimate, extras: Extras) -> dict[str, Any]:
    """The mode and quantiles asked for, of one estimate (null when degenerate or not finite)."""
    point, q = summaries.summarise(filt, state, estimate, extras.mode, extras.quantiles)
    return summary_fields(filt.model.spec.state, extras, point, q)


def result_response(seq: int, state: Any, result: ChunkResult, filt: Any, watch: Watch | None = None,
                    settings: WatchSettings | None = None) -> dict[str, Any]:
    """The response of a chunk already run (``state`` after it, ``result`` its arrays)."""
    alarms = np.flatnonzero(result.alarm).tolist()
    return response_body(seq, state, *result_rows(result, gate_of(filt)), alarms, watch, settings)


def response_body(seq: int, state: Any, out: list[dict], gated: list[int], again: list[int],
                  reason: str | None, alarms: list[int] | None = None, watch: Watch | None = None,
                  settings: WatchSettings | None = None) -> dict[str, Any]:
    """A chunk's response: its rows ``out`` (with the gated, re-initialised and alarm rows, the first
    degenerate ``reason``) and the session after it (``state``, the monitor's statistic when on)."""
    flagged = reason is not None
    loglik = float(state.loglik)
    if not math.isfinite(loglik):
        flagged, reason = True, reason or "non-finite log-likelihood"
    degenerate = flagged or bool(state.degenerate)
    if degenerate and reason is None:
        reason = getattr(state, "reason", None) or "degenerate density"
    monitoring = watch is not None and settings is not None and settings.monitor > 0
    return {"seq": seq, "step": int(state.step), "t": float(state.t), "estimates": out,
            "loglik": loglik if math.isfinite(loglik) else None, "degenerate": degenerate,
            "reason": reason, "gated": gated, "reinitialised": again, "alarms": alarms or [],
            "monitor": watch.statistic if monitoring else None}


def encode_response(response: dict[str, Any]) -> str:
    """JSON text of a chunk response (orjson: the floats are formatted ~10x faster than by json).

    Every number in it already passed a finiteness check (``estimate_rows`` nulls a non-finite
    row; ``response_body`` the log-likelihood), and orjson never writes a NaN token anyway."""
    return orjson.dumps(response).decode()


def view_axes(filt: Any, state: Any, estimate: Estimate, points: int) -> list[np.ndarray]:
    """Per variable, a grid over where the density is (quantiles 1e-4 .. 1 − 1e-4, padded by a
    quarter of that width; the support when the quantiles are unknown)."""
    q = summaries.quantiles(filt, state, [1e-4, 1 - 1e-4], estimate)
    axes = []
    for i in range(filt.model.n):
        lo, hi = summaries.support(filt, state, estimate, i)
        a, b = q[i]
        if np.isfinite(a) and np.isfinite(b) and b > a:
            pad = 0.25 * (b - a)
            lo, hi = max(lo, a - pad), min(hi, b + pad)
        axes.append(np.linspace(lo, hi, points))
    return axes


def frame_body(filt: Any, state: Any, estimate: Estimate, head: dict[str, Any],
               points: int) -> dict[str, Any]:
    """What the live page draws: ``head`` (the session), the estimate and the density on a grid around
    its mass (a curve in 1-D, a heat map in 2-D, the marginals in 3-D; none when degenerate)."""
    out = estimate_full(estimate)
    frame = {**head, **out, "plot": None}
    if out["degenerate"]:
        return frame
    frame.update(summaries_of(filt, state, estimate, Extras(mode=True)))
    n = filt.model.n
    axes = view_axes(filt, state, estimate, points if n == 1 else min(points, 81))
    marginals = summaries.marginals_on_grid(filt, state, axes, estimate)
    plot: dict[str, Any] = {"kind": "curve" if n == 1 else "heatmap" if n == 2 else "marginals",
                            "axes": [a.tolist() for a in axes],
                            "marginals": [np.round(m, 8).tolist() for m in marginals]}
    if n == 2:
        plot["density"] = np.round(summaries.joint_on_grid(filt, state, axes), 8).tolist()
    frame["plot"] = plot
    return frame
