"""Filtering sessions over HTTP: create, feed chunks of rows exactly once, reset, read back.

The filter state lives in the :class:`storage.session_store.SessionStore` (SQLite).  A chunk is
applied inside ``apply_chunk``: the new state and the response are written in the same
transaction, so a repeated ``seq`` gets the stored response and a gap is refused (409) — a client
that lost an answer (server killed) re-sends the same chunk and nothing is lost or applied twice.
A reset (start again from a prior, at the session's step and time) is numbered and applied the
same way.

A chunk is checked and applied by service/sessions/chunks.py; the answers are built by
service/sessions/responses.py.  The session's options (stored with it): ``on_degenerate``
(solver/recovery.py), ``t0`` (the prior's time), ``gate`` (the outlier gate; None: the spec's),
``lost_track`` and ``monitor`` (solver/watch.py: when a filter that keeps gating or restarting has
lost track, and the innovation monitor's healthy rows per false alarm; None: the defaults, the
spec's).  The watch's own state (the
counts, the monitor's charts) is stored in the session's state under ``watch``.

Ownership: a session belongs to the tenant that created it (service/http/tenants.py).  Every operation
takes the caller's ``tenant``; another tenant's session is NotFound, exactly as an unknown id (so
its existence does not leak).  ``tenant`` None means the server has no tenants: every session is
visible; a session without owner (made before tenants) is then visible only that way.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import orjson
from pydantic import ValidationError
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.filtering import at_time, check_t0
from yauyau.solver.measurement import check_gate
from yauyau.solver.model import compile_model
from yauyau.solver.recovery import check_policy, restart, restart_from_last
from yauyau.solver.registry import DEFAULT_POLICY
from yauyau.solver.spec import DensityPrior, ModelSpec
from yauyau.solver.summarised import gate_of
from yauyau.solver.watch import (
    Watch,
    WatchSettings,
    check_lost_track,
    check_monitor,
    join_state,
    settings_for,
)
from yauyau.storage.errors import NotFound
from yauyau.storage.protocols import SessionStore

from .. import metrics
from ..models.cache import LoadedModel, Registry
from .batching import ChunkBatcher
from .chunks import (
    ChunkJob,
    ChunkRequest,
    checked_times,
    chunk_rows,
    compute_many,
    count_applied,
    digest,
    load_state,
    request_digest,
    rows_array,
)
from .lagged import check_can_smooth, check_smooth_lag
from .responses import Extras, encode_response, estimate_full, frame_body, summaries_of

DEFAULT_OPTIONS = {"on_degenerate": DEFAULT_POLICY, "t0": 0.0, "gate": None, "lost_track": None,
                   "monitor": None, "smooth_lag": None}


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
    gate = gate_of(filt)
    if gate is None:
        gate = float(filt.model.spec.measurement.gate)
    shown = {"on_degenerate": options["on_degenerate"], "t0": float(options["t0"]), "gate": gate}
    settings = _watch_settings(options, filt)
    if options.get("lost_track") is not None:
        shown["lost_track"] = settings.lost.to_dict()
    if settings.monitor > 0:
        shown["monitor"] = settings.monitor
    if options.get("smooth_lag") is not None:
        shown["smooth_lag"] = int(options["smooth_lag"])
    return shown


def _watch_settings(options: dict[str, Any], filt: Any) -> WatchSettings:
    return settings_for(filt, options.get("lost_track"), options.get("monitor"))


def _as_prior_error(exc: SpecError) -> SpecError:
    return SpecError(exc.field.replace("initial", "prior", 1), exc.message)


def _checked_prior(prior: Any, loaded: LoadedModel) -> Any:
    """Check the prior against the model (the spec's own rules), naming the field ``prior.*``."""
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
               monitor: float | None = None, owner: str | None = None,
               smooth_lag: int | None = None) -> dict[str, Any]:
        """A new session of ``model_id``; its options (``on_degenerate``, ``t0``, ``gate``,
        ``lost_track``, ``monitor``, ``smooth_lag``: service/sessions/lagged.py) and its ``owner`` (the
        tenant creating it, or None) are stored with it."""
        options = {"on_degenerate": check_policy(on_degenerate), "t0": check_t0(t0),
                   "gate": check_gate(gate),
                   "lost_track": None if lost_track is None else check_lost_track(lost_track).to_dict(),
                   "monitor": check_monitor(monitor), "smooth_lag": check_smooth_lag(smooth_lag)}
        loaded = self.registry.get(model_id)
        check_t0(t0, "t0", float(loaded.model.dt))  # a step of dt must still be a step at t0
        filt = loaded.filter(method, options["gate"])
        try:
            state = filt.initial_state(_checked_prior(prior, loaded) if prior is not None else None)
        except SpecError as exc:  # the prior of the request, not the spec's: name it so
            raise (_as_prior_error(exc) if prior is not None else exc) from None
        state = at_time(state, options["t0"])
        if options["smooth_lag"] is not None:
            check_can_smooth(filt, state)
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

    def observe_many(self, requests: list[ChunkRequest]) -> list[Any]:
        """Chunks of *different* sessions, each applied exactly once as :meth:`observe` applies it:
        per request its response's JSON text, or the exception that is its answer.  The chunks of
        one model (same method and gate, no extras) are stepped together (``run_batch``: one matrix
        product per step for all) and stored in one transaction; one request's error never touches
        another's result."""
        out: list[Any] = [None] * len(requests)
        groups: dict[tuple, list[tuple[int, ChunkJob]]] = {}
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
                                                      lambda pairs, jobs=jobs: compute_many(jobs, pairs),
                                                      encoded=True, records=[j.record for j in jobs])
            except Exception as exc:  # noqa: BLE001 - this group's answer only; the others committed
                answers = [exc] * len(jobs)
            for (i, job), answer in zip(group, answers, strict=True):
                out[i] = answer if isinstance(answer, BaseException) else answer[0]
                if not isinstance(answer, BaseException):
                    metrics.CHUNKS.labels("replayed" if answer[1] else "applied").inc()
                    if not answer[1]:
                        count_applied(job)
        return out

    def _chunk_job(self, request: ChunkRequest) -> ChunkJob:
        """A chunk checked against its session and model before anything is applied."""
        given = {name: value for name, value in (("increments", request.increments),
                                                 ("observations", request.observations)) if value is not None}
        for name, value in given.items():
            if len(value) > self.max_chunk_rows:
                raise InputError(name, f"at most {self.max_chunk_rows} rows per chunk, got {len(value)}")
        rec, loaded, filt = self._session(request.session_id, request.tenant)
        field, data = chunk_rows(loaded, given)
        array = rows_array(data, loaded.model.m, field)
        times = checked_times(request.times, len(data))
        asked = request_digest(data, request.extras, field, times)
        options = _options(rec)
        return ChunkJob(request.session_id, request.seq, asked, filt, array, times,
                         options["on_degenerate"], request.extras, rec, _watch_settings(options, filt),
                         lag=options.get("smooth_lag"))

    def reset(self, session_id: str, seq: int, prior: Any | None = None, source: str | None = None,
              encoded: bool = False, tenant: str | None = None) -> Any:
        """Start the session again at its step and time, exactly once under ``seq`` (like a chunk): from
        ``prior`` (a spec prior), or ``source`` "last" (a prior broadened around the last good estimate:
        a degenerate session recovers) or "model" (the model's prior).  The log-likelihood goes on."""
        if (prior is None) == (source is None):
            raise InputError("prior" if prior is None else "from",
                             'send exactly one of "prior" (a spec prior) and "from" ("last": around the last '
                             'good estimate; "model": the model\'s prior)')
        rec, loaded, filt = self._session(session_id, tenant)
        checked = _checked_prior(prior, loaded) if prior is not None else None
        asked = digest(["reset", source if prior is None else prior.model_dump(mode="json")])

        def compute(state_dict: dict[str, Any]) -> tuple[dict[str, Any], str]:
            state, _ = load_state(filt, state_dict)  # a reset starts the watch again (a lost track recovers)
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

        response, replayed = self._apply(session_id, seq, compute, encoded, asked)
        if not replayed:
            metrics.RESETS.inc()
        return response

    def forecast(self, session_id: str, t: float, extras: Extras | None = None,
                 tenant: str | None = None) -> dict[str, Any]:
        """The estimate at time ``t`` (not before the session's time) without an observation; the session
        is unchanged."""
        rec, loaded, filt = self._session(session_id, tenant)
        state, _ = load_state(filt, _record(rec, "state"))
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
        state, watch = load_state(filt, _record(rec, "state"))
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
        rec, loaded, filt = self._session(session_id, tenant)
        state, _ = load_state(filt, _record(rec, "state"))
        head = {"id": session_id, "model": loaded.id, "name": loaded.model.spec.name, "method": filt.method,
                "state": list(loaded.model.spec.state), "next_seq": int(_record(rec, "next_seq"))}
        return frame_body(filt, state, filt.estimate(state), head, points)

    def density(self, session_id: str, points: np.ndarray, tenant: str | None = None) -> dict[str, Any]:
        rec, loaded, filt = self._session(session_id, tenant)
        n = loaded.model.n
        if points.shape[1] != n:
            raise InputError("points", f"each point needs {n} coordinate(s), got {points.shape[1]}")
        if len(points) > self.max_density_points:
            raise InputError("points", f"at most {self.max_density_points} points, got {len(points)}")
        state, _ = load_state(filt, _record(rec, "state"))
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


