"""Applying a chunk of rows to a session: the request checked against its model, the filter run under
the session's policy and watch, the response built.

A chunk's rows are the model's kind of data ([measurement] kind): ``increments`` Δy of a continuous
model or ``observations`` z of a discrete one, optionally at ``times``; null marks a missing row or
component.  The chunks of one model that arrive together are stepped together (:func:`compute_many`:
``run_batch``, one matrix product per step for all of them); a chunk that asks for the mode or
quantiles, or whose filter lost track or must restart, is run alone (:func:`chunk_response`), row by
row when it asks for them (solver/summarised.py, the path ``yauyau filter`` takes too).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson
from yauyau.solver.errors import InputError
from yauyau.solver.measurement import resolve_times
from yauyau.solver.summarised import gate_of, summarised_rows
from yauyau.solver.watch import Watch, WatchSettings, join_state, settle, split_state, watched_run

from .. import metrics
from ..models.cache import LoadedModel
from .lagged import lagged_rows, split_lag
from .responses import Extras, encode_response, response_body, result_response, result_rows, summary_fields

ROW_FIELDS = {"continuous": "increments", "discrete": "observations"}


@dataclass(slots=True)
class ChunkRequest:
    """A chunk as the route receives it (checked by :meth:`Sessions.observe_many`)."""

    session_id: str
    seq: int
    increments: list | None
    extras: Extras | None = None
    observations: list | None = None
    times: list[float] | None = None
    tenant: str | None = None  # the caller (None: no tenants): another tenant's session is NotFound


@dataclass(slots=True)
class ChunkJob:
    """A checked chunk: its session, seq and request digest, the filter, the rows as an array."""

    session_id: str
    seq: int
    digest: str
    filt: Any
    array: np.ndarray
    times: list[float] | None
    policy: str
    extras: Extras | None
    record: Any = None  # the session as read to check the chunk (the store may use it)
    settings: WatchSettings | None = None  # the session's watch (solver/watch.py)
    applied: dict[str, Any] | None = None  # the response, once computed (for the metrics)
    lag: int | None = None  # the session's smooth_lag (service/sessions/lagged.py): run alone


def load_state(filt: Any, data: Any) -> tuple[Any, Watch]:
    """(filter state, watch) of a stored session state (its fixed-lag window, if any, left aside)."""
    data, _ = split_lag(data)
    data, watch = split_state(data)
    return filt.state_from_dict(data), watch


def chunk_rows(loaded: LoadedModel, given: dict[str, Any]) -> tuple[str, list]:
    """(field, rows) of a chunk: the one row field the model's kind takes, else InputError saying which."""
    kind = loaded.model.spec.measurement.kind
    wanted = ROW_FIELDS.get(kind, "increments")
    other = "observations" if wanted == "increments" else "increments"
    what = {"increments": "increments dy of y over each interval",
            "observations": "measurements z = h(x(t)) + v"}
    if wanted in given and other in given:
        raise InputError(other, f"send either increments or observations, not both: this model ({kind} "
                                f"measurements) takes \"{wanted}\" ({what[wanted]})")
    if wanted not in given:
        if other in given:
            raise InputError(other, f"this model's measurements are {kind} ([measurement] kind = {kind}): "
                                    f"send the rows as \"{wanted}\" ({what[wanted]}), not \"{other}\"")
        raise InputError(wanted, f"required: the rows of the chunk ({what[wanted]}; this model's "
                                 f"measurements are {kind})")
    return wanted, given[wanted]


def rows_array(rows: list[list[float | None] | None], m: int, field: str = "increments") -> np.ndarray:
    """Rows of m numbers (null: a missing row or component) -> (K, m) floats with NaN for missing,
    naming a row of the wrong width."""
    out = np.empty((len(rows), m))
    for i, row in enumerate(rows):
        if row is None:
            out[i] = np.nan
        elif len(row) != m:
            raise InputError(f"{field}[{i}]", f"needs {m} number(s) (one per observation component; null for "
                                              f"a missing one), got {len(row)}")
        else:
            out[i] = row  # None -> NaN
    return out


def checked_times(times: list[float] | None, K: int) -> list[float] | None:
    """The times of a chunk of K rows, checked before the session is touched: one per row, finite,
    strictly increasing (InputError naming ``times`` or ``times[i]``); that the first comes after the
    session's time, the filter checks as it applies the chunk."""
    if times is None:
        return None
    resolve_times(-math.inf, True, K, 0.0, times)
    return [float(v) for v in times]


def digest(payload: Any) -> str:
    """A short hash of a JSON payload (what a numbered request asked)."""
    return hashlib.blake2b(orjson.dumps(payload), digest_size=16).hexdigest()


def request_digest(rows: list[list[float | None] | None], extras: Extras | None, field: str = "increments",
                   times: list[float] | None = None) -> str:
    """A digest of what a chunk asks (its rows, their kind and times, the extras): a re-sent seq must
    carry the same.  A regular chunk of increments keeps the digest it had before rows had kinds and
    times (a replay across an upgrade is still a replay)."""
    quantiles = None if extras is None or extras.quantiles is None else list(map(float, extras.quantiles))
    mode = bool(extras.mode) if extras is not None else False
    if field == "increments" and times is None:
        return digest([rows, quantiles, mode])
    return digest([rows, quantiles, mode, field, times])


def run_chunk(filt: Any, state: Any, rows: np.ndarray, times: list[float] | None = None,
              policy: str = "stop", watch: Watch | None = None, settings: WatchSettings | None = None):
    """Advance the filter over a chunk under the session's policy (solver/recovery.py) and its watch
    (solver/watch.py): (new state, new watch, estimate rows, gated rows, re-initialised rows, first
    degenerate reason, alarm rows).  The estimates come as arrays (``run_arrays``): no per-row objects
    on the hot path."""
    state, watch, result = watched_run(filt, state, watch or Watch(), rows, times, policy, settings)
    out, gated, again, reason = result_rows(result, gate_of(filt))
    return state, watch, out, gated, again, reason, np.flatnonzero(result.alarm).tolist()


def run_chunk_with_summaries(filt: Any, state: Any, rows: np.ndarray, extras: Extras,
                             times: list[float] | None = None, policy: str = "stop",
                             watch: Watch | None = None, settings: WatchSettings | None = None):
    """Like :func:`run_chunk`, stepping row by row to summarise the density after each step
    (solver/summarised.py)."""
    out, gated, again, reason, alarms = [], [], [], None, []
    gate = gate_of(filt)
    watch = watch or Watch()
    names = filt.model.spec.state
    for k, row in enumerate(summarised_rows(filt, state, watch, rows, times, policy, settings,
                                            mode=extras.mode, probs=extras.quantiles)):
        row_out, row_gated, row_again, row_reason = result_rows(row.result, gate)
        out.append(row_out[0] | summary_fields(names, extras, row.mode, row.quantiles))
        gated += [k] * len(row_gated)
        again += [k] * len(row_again)
        alarms += [k] * int(row.result.alarm.sum())
        reason = reason or row_reason
        state, watch = row.state, row.watch
    return state, watch, out, gated, again, reason, alarms


def chunk_response(seq: int, state: Any, rows: np.ndarray, filt: Any, extras: Extras | None = None,
                   times: list[float] | None = None, policy: str = "stop", watch: Watch | None = None,
                   settings: WatchSettings | None = None) -> tuple[Any, Watch, dict[str, Any]]:
    """(new state, new watch, response) of a chunk run from ``state``."""
    run = run_chunk_with_summaries if extras else run_chunk
    args = (extras,) if extras else ()
    state, watch, out, gated, again, reason, alarms = run(filt, state, rows, *args, times=times,
                                                          policy=policy, watch=watch, settings=settings)
    return state, watch, response_body(seq, state, out, gated, again, reason, alarms, watch, settings)


def compute_many(jobs: list[ChunkJob], pairs: list[tuple[int, dict[str, Any]]]) -> list[Any]:
    """The store's ``compute_many``: the states of ``pairs`` (index into ``jobs``, stored state)
    advanced over their chunks, together where they can be: [(new state, response text) or error]."""
    out: list[Any] = [None] * len(pairs)
    states: list[Any] = [None] * len(pairs)
    watches: list[Watch] = [Watch()] * len(pairs)
    for p, (i, state_dict) in enumerate(pairs):
        try:
            states[p], watches[p] = load_state(jobs[i].filt, state_dict)
        except Exception as exc:  # noqa: BLE001 - that chunk's answer
            out[p] = exc
    # a filter that lost track computes nothing (it answers held rows): alone, with its reason
    together = [p for p in range(len(pairs))
                if out[p] is None and not jobs[pairs[p][0]].extras and watches[p].lost is None
                and jobs[pairs[p][0]].lag is None]
    if together:
        _run_together(jobs, pairs, together, states, watches, out)
    for p in range(len(pairs)):
        if out[p] is None:
            try:
                out[p] = _alone(jobs[pairs[p][0]], states[p], watches[p], split_lag(pairs[p][1])[1])
            except Exception as exc:  # noqa: BLE001 - that chunk's answer
                out[p] = exc
    return out


def _run_together(jobs: list[ChunkJob], pairs: list[tuple[int, dict[str, Any]]], together: list[int],
                  states: list[Any], watches: list[Watch], out: list[Any]) -> None:
    """The chunks ``together`` (indices into ``pairs``) stepped as one batch (``run_batch``); their
    answers into ``out`` (one the policy restarts: alone, from its state)."""
    members = [jobs[pairs[p][0]] for p in together]
    try:
        results = members[0].filt.run_batch([states[p] for p in together], [job.array for job in members],
                                            [job.times for job in members], return_exceptions=True)
    except Exception as exc:  # noqa: BLE001 - the batch failed as a whole: each alone
        results = [exc] * len(together)
    for p, job, result in zip(together, members, results, strict=True):
        try:
            if isinstance(result, InputError):
                raise result
            if isinstance(result, BaseException) or (job.policy != "stop" and (
                    states[p].degenerate or result[1].degenerate.any())):
                out[p] = _alone(job, states[p], watches[p])  # the policy restarts it: alone, from its state
            else:
                settings = job.settings or WatchSettings()
                new, watch, rows = settle(job.filt, states[p], result[0], watches[p], result[1], job.array,
                                          settings)
                response = result_response(job.seq, new, rows, job.filt, watch, settings)
                job.applied = response
                out[p] = (join_state(new, watch), encode_response(response))
        except Exception as exc:  # noqa: BLE001 - that chunk's answer
            out[p] = exc


def _alone(job: ChunkJob, state: Any, watch: Watch, window: dict[str, Any] | None = None,
           ) -> tuple[dict[str, Any], str]:
    before = state
    state, watch, response = chunk_response(job.seq, state, job.array, job.filt, job.extras, job.times,
                                            job.policy, watch, job.settings or WatchSettings())
    job.applied = response
    stored = join_state(state, watch)
    if job.lag is not None:  # fixed-lag smoothing (service/sessions/lagged.py)
        if response["degenerate"] or response["reinitialised"] or watch.lost is not None:
            response["smoothed"] = []  # the window starts again from the new state
        else:
            stamps = np.array([row["t"] for row in response["estimates"]], dtype=float)
            response["smoothed"], window = lagged_rows(job.filt, job.lag, before, window, job.array,
                                                       job.times, stamps, job.extras)
            stored["lag"] = window
    return stored, encode_response(response)


def count_applied(job: ChunkJob) -> None:
    """The metrics of an applied chunk."""
    metrics.OBSERVATIONS.inc(len(job.array))
    done = job.applied
    if done is None:
        return
    if done["degenerate"]:
        metrics.DEGENERATE.inc()
    if done["gated"]:
        metrics.GATED.inc(len(done["gated"]))
    if done["reinitialised"]:
        metrics.REINITIALISED.inc(len(done["reinitialised"]))
    if done.get("alarms"):
        metrics.ALARMS.inc(len(done["alarms"]))
    if done["degenerate"] and (done["reason"] or "").startswith("lost track"):
        metrics.LOST.inc()
