"""Filtering sessions over HTTP: create, feed chunks of rows exactly once, reset, read back.

The filter state lives in the :class:`storage.session_store.SessionStore` (SQLite).  A chunk is
applied inside ``apply_chunk``: the new state and the response are written in the same
transaction, so a repeated ``seq`` gets the stored response and a gap is refused (409) — a client
that lost an answer (server killed) re-sends the same chunk and nothing is lost or applied twice.
A reset (start again from a prior, at the session's step and time) is numbered and applied the
same way.

A chunk's rows are the model's kind of data ([measurement] kind): ``increments`` Δy of a continuous
model or ``observations`` z of a discrete one, optionally at ``times``; null marks a missing row or
component.  The session's options (stored with it): ``on_degenerate`` (solver/recovery.py), ``t0``
(the prior's time), ``gate`` (the outlier gate; None: the spec's), ``lost_track`` and ``monitor``
(solver/watch.py: when a filter that keeps gating or restarting has lost track, and the innovation
monitor's healthy rows per false alarm; None: the defaults, the spec's).  The watch's own state (the
counts, the monitor's charts) is stored in the session's state under ``watch``.

Ownership: a session belongs to the tenant that created it (service/http/tenants.py).  Every operation
takes the caller's ``tenant``; another tenant's session is NotFound, exactly as an unknown id (so
its existence does not leak).  ``tenant`` None means the server has no tenants: every session is
visible; a session without owner (made before tenants) is then visible only that way.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.filtering import ChunkResult, Estimate, at_time, check_t0
from yauyau.solver.measurement import resolve_times
from yauyau.solver.watch import Watch, WatchSettings, join_state, settings_for, split_state
from yauyau.storage.errors import NotFound
from yauyau.storage.protocols import SessionStore

from .. import metrics
from ..models.cache import LoadedModel, Registry
from .batching import ChunkBatcher

ROW_FIELDS = {"continuous": "increments", "discrete": "observations"}
DEFAULT_OPTIONS = {"on_degenerate": "stop", "t0": 0.0, "gate": None, "lost_track": None, "monitor": None}


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


def _gate_of(filt: Any) -> float | None:
    gate = getattr(filt, "gate", None)
    return None if gate is None else float(gate)


def run_chunk(filt: Any, state: Any, rows: np.ndarray, times: list[float] | None = None,
              policy: str = "stop", watch: Watch | None = None, settings: WatchSettings | None = None):
    """Advance the filter over a chunk under the session's policy (solver/recovery.py) and its watch
    (solver/watch.py): (new state, new watch, estimate rows, gated rows, re-initialised rows, first
    degenerate reason, alarm rows).  The estimates come as arrays (``run_arrays``): no per-row objects
    on the hot path."""
    from yauyau.solver.watch import watched_run

    state, watch, result = watched_run(filt, state, watch or Watch(), rows, times, policy, settings)
    out, gated, again, reason = result_rows(result, _gate_of(filt))
    return state, watch, out, gated, again, reason, np.flatnonzero(result.alarm).tolist()


def summaries_of(filt: Any, state: Any, estimate: Estimate, extras: "Extras") -> dict[str, Any]:
    """The mode and quantiles asked for, of one estimate (null when degenerate or not finite)."""
    from yauyau.solver import summaries

    out: dict[str, Any] = {}
    healthy = not estimate.degenerate and not bool(getattr(state, "degenerate", False))
    if extras.mode:
        point = summaries.mode(filt, state, estimate) if healthy else None
        out["mode"] = point.tolist() if point is not None and np.all(np.isfinite(point)) else None
    if extras.quantiles is not None:
        q = summaries.quantiles(filt, state, extras.quantiles, estimate) if healthy else None
        names = filt.model.spec.state
        out["quantiles"] = ({v: q[i].tolist() for i, v in enumerate(names)}
                            if q is not None and np.all(np.isfinite(q)) else None)
    return out


class Extras:
    """What a request asks for besides mean and covariance: quantiles (probabilities) and the mode."""

    def __init__(self, quantiles: Any | None = None, mode: bool = False):
        from yauyau.solver.summaries import check_probabilities

        self.quantiles = None if quantiles is None else check_probabilities(quantiles)
        self.mode = bool(mode)

    def __bool__(self) -> bool:
        return self.quantiles is not None or self.mode


def run_chunk_with_summaries(filt: Any, state: Any, rows: np.ndarray, extras: Extras,
                             times: list[float] | None = None, policy: str = "stop",
                             watch: Watch | None = None, settings: WatchSettings | None = None):
    """Like :func:`run_chunk`, stepping row by row to summarise the density after each step."""
    from yauyau.solver.watch import watched_run

    out, gated, again, reason, alarms = [], [], [], None, []
    gate = _gate_of(filt)
    watch = watch or Watch()
    for k in range(len(rows)):
        state, watch, result = watched_run(filt, state, watch, rows[k:k + 1],
                                           None if times is None else times[k:k + 1], policy, settings)
        row_out, row_gated, row_again, row_reason = result_rows(result, gate)
        estimate = result.estimates(gate)[0]
        out.append(row_out[0] | summaries_of(filt, state, estimate, extras))
        gated += [k] * len(row_gated)
        again += [k] * len(row_again)
        alarms += [k] * int(result.alarm.sum())
        reason = reason or row_reason
    return state, watch, out, gated, again, reason, alarms


def chunk_response(seq: int, state: Any, rows: np.ndarray, filt: Any, extras: Extras | None = None,
                   times: list[float] | None = None, policy: str = "stop", watch: Watch | None = None,
                   settings: WatchSettings | None = None) -> tuple[Any, Watch, dict[str, Any]]:
    """(new state, new watch, response) of a chunk run from ``state``."""
    run = run_chunk_with_summaries if extras else run_chunk
    args = (extras,) if extras else ()
    state, watch, out, gated, again, reason, alarms = run(filt, state, rows, *args, times=times,
                                                          policy=policy, watch=watch, settings=settings)
    return state, watch, _response(seq, state, out, gated, again, reason, alarms, watch, settings)


def result_response(seq: int, state: Any, result: ChunkResult, filt: Any, watch: Watch | None = None,
                    settings: WatchSettings | None = None) -> dict[str, Any]:
    """The response of a chunk already run (``state`` after it, ``result`` its arrays)."""
    return _response(seq, state, *result_rows(result, _gate_of(filt)), np.flatnonzero(result.alarm).tolist(),
                     watch, settings)


def _response(seq: int, state: Any, out: list[dict], gated: list[int], again: list[int],
              reason: str | None, alarms: list[int] | None = None, watch: Watch | None = None,
              settings: WatchSettings | None = None) -> dict[str, Any]:
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
    row; ``chunk_response`` the log-likelihood), and orjson never writes a NaN token anyway."""
    return orjson.dumps(response).decode()


def _digest(payload: Any) -> str:
    return hashlib.blake2b(orjson.dumps(payload), digest_size=16).hexdigest()


def request_digest(rows: list[list[float | None] | None], extras: "Extras | None", field: str = "increments",
                   times: list[float] | None = None) -> str:
    """A digest of what a chunk asks (its rows, their kind and times, the extras): a re-sent seq must
    carry the same.  A regular chunk of increments keeps the digest it had before rows had kinds and
    times (a replay across an upgrade is still a replay)."""
    quantiles = None if extras is None or extras.quantiles is None else list(map(float, extras.quantiles))
    mode = bool(extras.mode) if extras is not None else False
    if field == "increments" and times is None:
        return _digest([rows, quantiles, mode])
    return _digest([rows, quantiles, mode, field, times])


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


def _record(rec: Any, name: str) -> Any:
    return rec[name] if isinstance(rec, dict) else getattr(rec, name)


def visible(rec: Any, session_id: str, tenant: str | None) -> Any:
    """``rec`` when the caller may see it (no tenants, or the tenant owns it), else NotFound as for an
    unknown id."""
    if tenant is not None:
        owner = rec.get("owner") if isinstance(rec, dict) else getattr(rec, "owner", None)
        if owner != tenant:
            raise NotFound("session", f"no session {session_id!r}")
    return rec


def _options(rec: Any) -> dict[str, Any]:
    """A session's stored options, the defaults filled in (a session stored before options: all)."""
    stored = rec.get("options") if isinstance(rec, dict) else getattr(rec, "options", None)
    return {**DEFAULT_OPTIONS, **(stored or {})}


def _shown_options(options: dict[str, Any], filt: Any) -> dict[str, Any]:
    """The options as GET shows them: the gate in force (the session's, else the spec's); the
    lost-track rule when the session set one, the monitor when it is on (the session's, else the
    spec's); absent, they are the defaults (solver/watch.py)."""
    gate = _gate_of(filt)
    if gate is None:
        gate = float(filt.model.spec.measurement.gate)
    shown = {"on_degenerate": options["on_degenerate"], "t0": float(options["t0"]), "gate": gate}
    settings = _watch_settings(options, filt)
    if options.get("lost_track") is not None:
        shown["lost_track"] = settings.lost.to_dict()
    if settings.monitor > 0:
        shown["monitor"] = settings.monitor
    return shown


def _watch_settings(options: dict[str, Any], filt: Any) -> WatchSettings:
    return settings_for(filt, options.get("lost_track"), options.get("monitor"))


def _load(filt: Any, data: Any) -> tuple[Any, Watch]:
    """(filter state, watch) of a stored session state."""
    data, watch = split_state(data)
    return filt.state_from_dict(data), watch


def _chunk_rows(loaded: LoadedModel, given: dict[str, Any]) -> tuple[str, list]:
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


class Sessions:
    """The session operations behind the /v1/sessions routes."""

    def __init__(self, store: SessionStore, registry: Registry, max_chunk_rows: int, max_density_points: int,
                 batch_window: float = 0.0, max_batch: int = 256):
        self.store = store
        self.registry = registry
        self.max_chunk_rows = max_chunk_rows
        self.max_density_points = max_density_points
        # One chunk at a time per process: threads of one worker would otherwise queue on SQLite's
        # write lock, whose busy handler sleeps (up to 100 ms a try); the GIL serialises the
        # filter arithmetic anyway.  Several workers still share the store through SQLite.
        self._write_lock = threading.Lock()
        # The HTTP route hands chunks to this one thread: first come, first served (threads
        # queueing on the lock are woken in no particular order, which made p99 ≫ p50), and the
        # event loop stays free to read the next requests while a chunk computes.  The chunks that
        # queued meanwhile are applied together (service/sessions/batching.py).
        self.chunk_executor = ChunkBatcher(self.observe_many, batch_window, max_batch)
        self._deep_checked = 0.0

    def _apply(self, session_id: str, seq: int, compute, encoded: bool, digest: str):
        """Apply numbered step ``seq`` (a chunk or a reset) exactly once: (response, replayed)."""
        with self._write_lock:
            response, replayed = self.store.apply_chunk(session_id, seq, compute, encoded=encoded,
                                                        digest=digest)
        metrics.CHUNKS.labels("replayed" if replayed else "applied").inc()
        return response, replayed

    def store_health(self, deep_every: float = 30.0) -> str | None:
        """None when the session store is usable, else why not (SQLite's quick_check at most every
        ``deep_every`` seconds; the cheap file checks every time)."""
        health = getattr(self.store, "health", None)
        if health is None:
            return None
        deep = time.monotonic() - self._deep_checked >= deep_every
        if deep:
            self._deep_checked = time.monotonic()
        return health(deep=deep)

    def create(self, model_id: str, prior: Any | None, method: str | None, on_degenerate: str = "stop",
               t0: float = 0.0, gate: float | None = None, lost_track: Any | None = None,
               monitor: float | None = None, owner: str | None = None) -> dict[str, Any]:
        """A new session of ``model_id``; its options (``on_degenerate``, ``t0``, ``gate``,
        ``lost_track``, ``monitor``) and its ``owner`` (the tenant creating it, or None) are stored
        with it."""
        from yauyau.solver.measurement import check_gate
        from yauyau.solver.recovery import check_policy
        from yauyau.solver.watch import check_lost_track, check_monitor

        options = {"on_degenerate": check_policy(on_degenerate), "t0": check_t0(t0),
                   "gate": check_gate(gate),
                   "lost_track": None if lost_track is None else check_lost_track(lost_track).to_dict(),
                   "monitor": check_monitor(monitor)}
        loaded = self.registry.get(model_id)
        check_t0(t0, "t0", float(loaded.model.dt))  # a step of dt must still be a step at t0
        filt = loaded.filter(method, options["gate"])
        try:
            state = filt.initial_state(_checked_prior(prior, loaded) if prior is not None else None)
        except SpecError as exc:  # the prior of the request, not the spec's: name it so
            raise (_as_prior_error(exc) if prior is not None else exc) from None
        state = at_time(state, options["t0"])
        estimate = estimate_full(filt.estimate(state))
        response = {"model": model_id, "method": filt.method, "step": int(state.step), "t": float(state.t),
                    "estimate": estimate, "options": _shown_options(options, filt)}
        session_id = self.store.create(model_id, filt.method, join_state(state, Watch()), response, options,
                                       owner=owner)
        metrics.SESSIONS.labels(filt.method).inc()
        return {"id": session_id, **response}

    def _session(self, session_id: str, tenant: str | None = None) -> tuple[Any, LoadedModel, Any]:
        rec = visible(self.store.get(session_id), session_id, tenant)
        loaded = self.registry.get(_record(rec, "model_id"), "session.model")
        return rec, loaded, loaded.filter(_record(rec, "method"), _options(rec)["gate"])

    def observe(self, session_id: str, seq: int, rows: list[list[float | None] | None] | None,
                encoded: bool = False, extras: Extras | None = None, *,
                observations: list[list[float | None] | None] | None = None,
                times: list[float] | None = None) -> Any:
        """Apply chunk ``seq`` exactly once; the response (``encoded``: its stored JSON text).
        ``rows`` are increments (continuous models), ``observations`` measurements (discrete models):
        exactly one of the two, as the model's kind says; ``times`` their absolute times (default:
        one dt apart).  ``extras``: quantiles and/or the mode with every estimate (a replay returns
        what was stored)."""
        request = ChunkRequest(session_id, seq, rows, extras, observations, times)
        answer = self.observe_many([request])[0]
        if isinstance(answer, BaseException):
            raise answer
        return answer if encoded else orjson.loads(answer)

    def observe_many(self, requests: list["ChunkRequest"]) -> list[Any]:
        """Chunks of *different* sessions, each applied exactly once as :meth:`observe` applies it:
        per request its response's JSON text, or the exception that is its answer.  The chunks of
        one model (same method and gate, no extras) are stepped together (``run_batch``: one matrix
        product per step for all) and stored in one transaction; one request's error never touches
        another's result."""
        out: list[Any] = [None] * len(requests)
        groups: dict[tuple, list[tuple[int, _ChunkJob]]] = {}
        for i, request in enumerate(requests):
            try:
                job = self._chunk_job(request)
            except Exception as exc:  # noqa: BLE001 - that request's answer (a 4xx, or a 500 alone)
                out[i] = exc
                continue
            key = (id(job.filt), bool(job.extras))
            groups.setdefault(key, []).append((i, job))
        for group in groups.values():
            jobs = [job for _, job in group]
            try:
                with self._write_lock:
                    answers = self.store.apply_chunks([(j.session_id, j.seq, j.digest) for j in jobs],
                                                      lambda pairs, jobs=jobs: _compute_many(jobs, pairs),
                                                      encoded=True, records=[j.record for j in jobs])
            except Exception as exc:  # noqa: BLE001 - this group's answer only; the others committed
                answers = [exc] * len(jobs)
            for (i, job), answer in zip(group, answers, strict=True):
                out[i] = answer if isinstance(answer, BaseException) else answer[0]
                if not isinstance(answer, BaseException):
                    metrics.CHUNKS.labels("replayed" if answer[1] else "applied").inc()
                    if not answer[1]:
                        _count(job)
        return out

    def _chunk_job(self, request: "ChunkRequest") -> "_ChunkJob":
        """A chunk checked against its session and model before anything is applied."""
        given = {name: value for name, value in (("increments", request.increments),
                                                 ("observations", request.observations)) if value is not None}
        for name, value in given.items():
            if len(value) > self.max_chunk_rows:
                raise InputError(name, f"at most {self.max_chunk_rows} rows per chunk, got {len(value)}")
        rec, loaded, filt = self._session(request.session_id, request.tenant)
        field, data = _chunk_rows(loaded, given)
        array = rows_array(data, loaded.model.m, field)
        times = checked_times(request.times, len(data))
        digest = request_digest(data, request.extras, field, times)
        options = _options(rec)
        return _ChunkJob(request.session_id, request.seq, digest, filt, array, times,
                         options["on_degenerate"], request.extras, rec, _watch_settings(options, filt))

    def reset(self, session_id: str, seq: int, prior: Any | None = None, source: str | None = None,
              encoded: bool = False, tenant: str | None = None) -> Any:
        """Start the session again at its step and time, exactly once under ``seq`` (like a chunk): from
        ``prior`` (a spec prior), or ``source`` "last" (a prior broadened around the last good estimate:
        a degenerate session recovers) or "model" (the model's prior).  The log-likelihood goes on."""
        from yauyau.solver.recovery import restart, restart_from_last

        if (prior is None) == (source is None):
            raise InputError("prior" if prior is None else "from",
                             'send exactly one of "prior" (a spec prior) and "from" ("last": around the last '
                             'good estimate; "model": the model\'s prior)')
        rec, loaded, filt = self._session(session_id, tenant)
        checked = _checked_prior(prior, loaded) if prior is not None else None
        digest = _digest(["reset", source if prior is None else prior.model_dump(mode="json")])

        def compute(state_dict: dict[str, Any]) -> tuple[dict[str, Any], str]:
            state, _ = _load(filt, state_dict)  # a reset starts the watch again (a lost track recovers)
            if source == "last":
                new, note = restart_from_last(filt, state)
            else:
                try:
                    new = restart(filt, state, checked)
                except SpecError as exc:
                    raise (_as_prior_error(exc) if checked is not None else exc) from None
                note = "re-initialised from the " + ("prior sent" if checked is not None else "model's prior")
            note += f" at step {int(new.step)}, t = {float(new.t):g}"
            response = {"seq": seq, "step": int(new.step), "t": float(new.t),
                        "estimate": estimate_full(filt.estimate(new)), "note": note}
            return join_state(new, Watch()), encode_response(response)

        response, replayed = self._apply(session_id, seq, compute, encoded, digest)
        if not replayed:
            metrics.RESETS.inc()
        return response

    def forecast(self, session_id: str, t: float, extras: Extras | None = None,
                 tenant: str | None = None) -> dict[str, Any]:
        """The estimate at time ``t`` (not before the session's time) without an observation; the session
        is unchanged."""
        rec, loaded, filt = self._session(session_id, tenant)
        state, _ = _load(filt, _record(rec, "state"))
        if not math.isfinite(t):
            raise InputError("t", "must be a finite number (the time to forecast to)")
        if t < state.t:
            raise InputError("t", f"t = {t!r} is before the session's time {float(state.t)!r}: a forecast "
                                  "looks ahead (the estimates of past times are in the chunk responses)")
        try:
            ahead, estimate = filt.predict(state, t)
        except InputError as exc:  # the only input is t: whatever the filter objects to is about it
            if exc.field == "t":
                raise
            why = f"method {filt.method} cannot forecast to t = {t!r}: {exc.message}"
            raise InputError("t", why) from None
        out = estimate_full(estimate)
        out["step"] = int(state.step)
        if extras:
            out.update(summaries_of(filt, ahead, estimate, extras))
        return {"id": session_id, "step": int(state.step), "t": float(t), "estimate": out}

    def info(self, session_id: str, extras: Extras | None = None,
             tenant: str | None = None) -> dict[str, Any]:
        rec, loaded, filt = self._session(session_id, tenant)
        state, watch = _load(filt, _record(rec, "state"))
        estimate = filt.estimate(state)
        out = estimate_full(estimate)
        if extras:
            out.update(summaries_of(filt, state, estimate, extras))
        options = _shown_options(_options(rec), filt)
        info = {"id": session_id, "model": loaded.id, "method": filt.method, "step": int(state.step),
                "t": float(state.t), "next_seq": int(_record(rec, "next_seq")), "estimate": out,
                "options": options, "lost": watch.lost,
                "monitor": {"statistic": watch.statistic if options.get("monitor", 0.0) > 0 else None,
                            "alarms": watch.alarms}}
        if getattr(state, "center", None) is not None:  # a ball that follows the state
            info["center"] = np.asarray(filt.ball_center(state), dtype=float).tolist()
        return info

    def version(self, session_id: str, tenant: str | None = None) -> int:
        """The seq the next chunk must carry (changes when a chunk is applied): what /events polls."""
        return int(_record(visible(self.store.get(session_id), session_id, tenant), "next_seq"))

    def frame(self, session_id: str, points: int = 161, tenant: str | None = None) -> dict[str, Any]:
        """What the live page draws: the estimate and the density on a grid around its mass (a curve
        in 1-D, a heat map in 2-D, the marginals in 3-D)."""
        from yauyau.solver import summaries

        rec, loaded, filt = self._session(session_id, tenant)
        state, _ = _load(filt, _record(rec, "state"))
        estimate = filt.estimate(state)
        out = estimate_full(estimate)
        frame = {"id": session_id, "model": loaded.id, "name": loaded.model.spec.name,
                 "method": filt.method, "state": list(loaded.model.spec.state),
                 "next_seq": int(_record(rec, "next_seq")), **out, "plot": None}
        if out["degenerate"]:
            return frame
        frame.update(summaries_of(filt, state, estimate, Extras(mode=True)))
        n = loaded.model.n
        axes = view_axes(filt, state, estimate, points if n == 1 else min(points, 81))
        marginals = summaries.marginals_on_grid(filt, state, axes, estimate)
        plot: dict[str, Any] = {"kind": "curve" if n == 1 else "heatmap" if n == 2 else "marginals",
                                "axes": [a.tolist() for a in axes],
                                "marginals": [np.round(m, 8).tolist() for m in marginals]}
        if n == 2:
            plot["density"] = np.round(summaries.joint_on_grid(filt, state, axes), 8).tolist()
        frame["plot"] = plot
        return frame

    def density(self, session_id: str, points: np.ndarray, tenant: str | None = None) -> dict[str, Any]:
        rec, loaded, filt = self._session(session_id, tenant)
        n = loaded.model.n
        if points.shape[1] != n:
            raise InputError("points", f"each point needs {n} coordinate(s), got {points.shape[1]}")
        if len(points) > self.max_density_points:
            raise InputError("points", f"at most {self.max_density_points} points, got {len(points)}")
        state, _ = _load(filt, _record(rec, "state"))
        values = np.asarray(filt.density(state, points), dtype=float)
        values = np.where(np.isfinite(values), np.maximum(values, 0.0), 0.0)
        return {"step": int(state.step), "t": float(state.t), "points": points.tolist(),
                "density": values.tolist()}

    def delete(self, session_id: str, tenant: str | None = None) -> None:
        if tenant is not None:
            visible(self.store.get(session_id), session_id, tenant)
        self.store.delete(session_id)

    def page(self, limit: int = 100, after: str | None = None, model: str | None = None,
             tenant: str | None = None) -> dict[str, Any]:
        """A page of sessions by id (``after``: the previous page's ``next``): the tenant's only, all
        of them without tenants."""
        rows = self.store.list_sessions(limit + 1, after, model, owner=tenant)
        more = len(rows) > limit
        rows = rows[:limit]
        return {"sessions": [{"id": r["id"], "model": r["model_id"], "method": r["method"], "step": r["step"],
                              "t": r["t"], "next_seq": r["next_seq"], "created": r["created"],
                              "updated": r["updated"]} for r in rows],
                "next": rows[-1]["id"] if more else None,
                "idle_expiry": getattr(self.store, "idle_expiry", None)}

    def expire(self) -> int:
        """Delete the sessions idle for longer than the store's expiry (how many went)."""
        gone = self.store.expire()
        if gone:
            metrics.EXPIRED.inc(gone)
        return gone


def view_axes(filt: Any, state: Any, estimate: Estimate, points: int) -> list[np.ndarray]:
    """Per variable, a grid over where the density is (quantiles 1e-4 .. 1 − 1e-4, padded by a
    quarter of that width; the support when the quantiles are unknown)."""
    from yauyau.solver import summaries

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


def _as_prior_error(exc: SpecError) -> SpecError:
    return SpecError(exc.field.replace("initial", "prior", 1), exc.message)


def _checked_prior(prior: Any, loaded: LoadedModel) -> Any:
    """Check the prior against the model (the spec's own rules), naming the field ``prior.*``."""
    from pydantic import ValidationError
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import DensityPrior, ModelSpec

    doc = dict(loaded.spec, initial=prior.model_dump(mode="json"))
    try:
        spec = ModelSpec.model_validate(doc)
        if isinstance(prior, DensityPrior):
            compile_model(spec)  # parses the expression safely and checks it on the ball
    except SpecError as exc:
        raise _as_prior_error(exc) from None
    except ValidationError as exc:  # pydantic wraps the SpecError of a model validator
        inner = (exc.errors()[0].get("ctx") or {}).get("error")
        if isinstance(inner, SpecError):
            raise _as_prior_error(inner) from None
        raise SpecError("prior", exc.errors()[0].get("msg", "invalid prior")) from None
    return prior


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
class _ChunkJob:
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


def _compute_many(jobs: list[_ChunkJob], pairs: list[tuple[int, dict[str, Any]]]) -> list[Any]:
    """The store's ``compute_many``: the states of ``pairs`` (index into ``jobs``, stored state)
    advanced over their chunks, together where they can be: [(new state, response text) or error]."""
    from yauyau.solver.watch import settle

    out: list[Any] = [None] * len(pairs)
    states: list[Any] = [None] * len(pairs)
    watches: list[Watch] = [Watch()] * len(pairs)
    for p, (i, state_dict) in enumerate(pairs):
        try:
            states[p], watches[p] = _load(jobs[i].filt, state_dict)
        except Exception as exc:  # noqa: BLE001 - that chunk's answer
            out[p] = exc
    # a filter that lost track computes nothing (it answers held rows): alone, with its reason
    together = [p for p in range(len(pairs))
                if out[p] is None and not jobs[pairs[p][0]].extras and watches[p].lost is None]
    if together:
        members = [jobs[pairs[p][0]] for p in together]
        try:
            results = members[0].filt.run_batch([states[p] for p in together], [job.array for job in members],
                                                [job.times for job in members], return_exceptions=True)
        except Exception as exc:  # noqa: BLE001 - the batch failed as a whole: each alone (below)
            results = [exc] * len(together)
        for p, job, result in zip(together, members, results, strict=True):
            try:
                if isinstance(result, InputError):
                    raise result
                if isinstance(result, BaseException) or (job.policy != "stop" and (
                        states[p].degenerate or result[1].degenerate.any())):
                    out[p] = _alone(job, states[p], watches[p])  # the policy restarts it: alone, from its
                    # state
                else:
                    settings = job.settings or WatchSettings()
                    new, watch, rows = settle(job.filt, states[p], result[0], watches[p], result[1],
                                              job.array, settings)
                    response = result_response(job.seq, new, rows, job.filt, watch, settings)
                    job.applied = response
                    out[p] = (join_state(new, watch), encode_response(response))
            except Exception as exc:  # noqa: BLE001 - that chunk's answer
                out[p] = exc
    for p in range(len(pairs)):
        if out[p] is None:
            try:
                out[p] = _alone(jobs[pairs[p][0]], states[p], watches[p])
            except Exception as exc:  # noqa: BLE001 - that chunk's answer
                out[p] = exc
    return out


def _alone(job: _ChunkJob, state: Any, watch: Watch) -> tuple[dict[str, Any], str]:
    state, watch, response = chunk_response(job.seq, state, job.array, job.filt, job.extras, job.times,
                                            job.policy, watch, job.settings or WatchSettings())
    job.applied = response
    return join_state(state, watch), encode_response(response)


def _count(job: _ChunkJob) -> None:
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
