"""Filtering sessions over HTTP: create, feed chunks of increments exactly once, read back.

The filter state lives in the :class:`storage.session_store.SessionStore` (SQLite).  A chunk is
applied inside ``apply_chunk``: the new state and the response are written in the same
transaction, so a repeated ``seq`` gets the stored response and a gap is refused (409) — a client
that lost an answer (server killed) re-sends the same chunk and nothing is lost or applied twice.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import orjson
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.filtering import Estimate, check_increments
from yauyau.storage.protocols import SessionStore

from . import metrics
from .registry import LoadedModel, Registry


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


def run_chunk(filt: Any, state: Any, increments: np.ndarray) -> tuple[Any, list[dict], bool, str | None]:
    """Advance the filter; (new state, estimate rows, any row degenerate, reason).

    Filters with ``run_arrays`` (the engine, Kalman–Bucy) return the estimates as arrays: no
    per-row objects on the hot path."""
    if hasattr(filt, "run_arrays"):
        state, res = filt.run_arrays(state, increments)
        rows = estimate_rows(res.step, res.t, res.mean, res.cov)
        flagged = bool(np.any(res.degenerate))
        reason = res.reason
    else:
        state, estimates = filt.run(state, increments)
        mean = np.array([e.mean for e in estimates], float)  # chunks are never empty
        cov = np.array([e.cov for e in estimates], float)
        rows = estimate_rows([e.step for e in estimates], [e.t for e in estimates], mean, cov)
        bad = [e for e in estimates if e.degenerate]
        flagged, reason = bool(bad), (bad[0].reason if bad else None)
    if any(r["mean"] is None for r in rows):
        flagged, reason = True, reason or "non-finite estimate"
    return state, rows, flagged, reason


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


def run_chunk_with_summaries(filt: Any, state: Any, increments: np.ndarray, extras: Extras):
    """Like :func:`run_chunk`, stepping row by row to summarise the density after each step."""
    rows, bad = [], []
    for row in increments:
        state, estimate = filt.step(state, row)
        out = estimate_full(estimate)
        row = {k: out[k] for k in ("step", "t", "mean", "cov")}
        rows.append(row | summaries_of(filt, state, estimate, extras))
        if out["degenerate"]:
            bad.append(out["reason"])
    return state, rows, bool(bad), (bad[0] if bad else None)


def chunk_response(seq: int, state: Any, increments: np.ndarray, filt: Any,
                   extras: Extras | None = None) -> tuple[Any, dict[str, Any]]:
    if extras:
        state, rows, flagged, reason = run_chunk_with_summaries(filt, state, increments, extras)
    else:
        state, rows, flagged, reason = run_chunk(filt, state, increments)
    loglik = float(state.loglik)
    if not math.isfinite(loglik):
        flagged, reason = True, reason or "non-finite log-likelihood"
    degenerate = flagged or bool(state.degenerate)
    if degenerate and reason is None:
        reason = getattr(state, "reason", None) or "degenerate density"
    return state, {"seq": seq, "step": int(state.step), "t": float(state.t), "estimates": rows,
                   "loglik": loglik if math.isfinite(loglik) else None, "degenerate": degenerate,
                   "reason": reason}


def encode_response(response: dict[str, Any]) -> str:
    """JSON text of a chunk response (orjson: the floats are formatted ~10x faster than by json).

    Every number in it already passed a finiteness check (``estimate_rows`` nulls a non-finite
    row; ``chunk_response`` the log-likelihood), and orjson never writes a NaN token anyway."""
    return orjson.dumps(response).decode()


def request_digest(rows: list[list[float] | None], extras: "Extras | None") -> str:
    """A digest of what a chunk asks (its increments and extras): a re-sent seq must carry the same."""
    quantiles = None if extras is None or extras.quantiles is None else list(map(float, extras.quantiles))
    mode = bool(extras.mode) if extras is not None else False
    payload = orjson.dumps([rows, quantiles, mode])
    return hashlib.blake2b(payload, digest_size=16).hexdigest()


def increments_array(rows: list[list[float] | None], m: int) -> np.ndarray:
    """Rows of m numbers (null: missing) -> (K, m) floats with NaN rows, naming a bad row."""
    out = np.empty((len(rows), m))
    for i, row in enumerate(rows):
        if row is None:
            out[i] = np.nan
        elif len(row) != m:
            raise InputError(f"increments[{i}]", f"needs {m} number(s) (one per observation), got {len(row)}")
        else:
            out[i] = row
    return check_increments(out, m)


def _record(rec: Any, name: str) -> Any:
    return rec[name] if isinstance(rec, dict) else getattr(rec, name)


class Sessions:
    """The session operations behind the /v1/sessions routes."""

    def __init__(self, store: SessionStore, registry: Registry, max_chunk_rows: int, max_density_points: int):
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
        # event loop stays free to read the next requests while a chunk computes.
        self.chunk_executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="yauyau-chunk")
        self._deep_checked = 0.0

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

    def create(self, model_id: str, prior: Any | None, method: str | None) -> dict[str, Any]:
        loaded = self.registry.get(model_id)
        filt = loaded.filter(method)
        try:
            state = filt.initial_state(_checked_prior(prior, loaded) if prior is not None else None)
        except SpecError as exc:  # the prior of the request, not the spec's: name it so
            raise (_as_prior_error(exc) if prior is not None else exc) from None
        estimate = estimate_full(filt.estimate(state))
        response = {"model": model_id, "method": filt.method, "step": int(state.step), "t": float(state.t),
                    "estimate": estimate}
        session_id = self.store.create(model_id, filt.method, state.to_dict(), response)
        metrics.SESSIONS.labels(filt.method).inc()
        return {"id": session_id, **response}

    def _session(self, session_id: str) -> tuple[Any, LoadedModel, Any]:
        rec = self.store.get(session_id)
        loaded = self.registry.get(_record(rec, "model_id"), "session.model")
        return rec, loaded, loaded.filter(_record(rec, "method"))

    def observe(self, session_id: str, seq: int, rows: list[list[float] | None],
                encoded: bool = False, extras: Extras | None = None) -> Any:
        """Apply chunk ``seq`` exactly once; the response (``encoded``: its stored JSON text).
        ``extras``: quantiles and/or the mode with every estimate (a replay returns what was stored)."""
        if len(rows) > self.max_chunk_rows:
            raise InputError("increments", f"at most {self.max_chunk_rows} rows per chunk, got {len(rows)}")
        rec, loaded, filt = self._session(session_id)
        increments = increments_array(rows, loaded.model.m)
        digest = request_digest(rows, extras)
        applied: list[dict[str, Any]] = []

        def compute(state_dict: dict[str, Any]) -> tuple[dict[str, Any], str]:
            state, response = chunk_response(seq, filt.state_from_dict(state_dict), increments, filt, extras)
            applied.append(response)
            return state.to_dict(), encode_response(response)

        with self._write_lock:
            response, replayed = self.store.apply_chunk(session_id, seq, compute, encoded=encoded,
                                                        digest=digest)
        metrics.CHUNKS.labels("replayed" if replayed else "applied").inc()
        if not replayed:
            metrics.OBSERVATIONS.inc(len(rows))
            if applied[-1]["degenerate"]:
                metrics.DEGENERATE.inc()
        return response

    def info(self, session_id: str, extras: Extras | None = None) -> dict[str, Any]:
        rec, loaded, filt = self._session(session_id)
        state = filt.state_from_dict(_record(rec, "state"))
        estimate = filt.estimate(state)
        out = estimate_full(estimate)
        if extras:
            out.update(summaries_of(filt, state, estimate, extras))
        return {"id": session_id, "model": loaded.id, "method": filt.method, "step": int(state.step),
                "t": float(state.t), "next_seq": int(_record(rec, "next_seq")), "estimate": out}

    def version(self, session_id: str) -> int:
        """The seq the next chunk must carry (changes when a chunk is applied): what /events polls."""
        return int(_record(self.store.get(session_id), "next_seq"))

    def frame(self, session_id: str, points: int = 161) -> dict[str, Any]:
        """What the live page draws: the estimate and the density on a grid around its mass (a curve
        in 1-D, a heat map in 2-D, the marginals in 3-D)."""
        from yauyau.solver import summaries

        rec, loaded, filt = self._session(session_id)
        state = filt.state_from_dict(_record(rec, "state"))
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

    def density(self, session_id: str, points: np.ndarray) -> dict[str, Any]:
        rec, loaded, filt = self._session(session_id)
        n = loaded.model.n
        if points.shape[1] != n:
            raise InputError("points", f"each point needs {n} coordinate(s), got {points.shape[1]}")
        if len(points) > self.max_density_points:
            raise InputError("points", f"at most {self.max_density_points} points, got {len(points)}")
        state = filt.state_from_dict(_record(rec, "state"))
        values = np.asarray(filt.density(state, points), dtype=float)
        values = np.where(np.isfinite(values), np.maximum(values, 0.0), 0.0)
        return {"step": int(state.step), "t": float(state.t), "points": points.tolist(),
                "density": values.tolist()}

    def delete(self, session_id: str) -> None:
        self.store.delete(session_id)


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
