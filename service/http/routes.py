"""The routes of the HTTP API, on APIRouters: health, models, sessions, analysis.

Each route takes what it needs as a dependency (service/http/deps.py) and returns JSON (``NaN`` never
leaves: ``allow_nan=False``); errors are raised and become problem+json (service/problems.py).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Body, Depends, Path, Query, Request
from fastapi.sse import EventSourceResponse, ServerSentEvent
from starlette.responses import HTMLResponse, JSONResponse, Response
from yauyau.solver.errors import SpecError

from .. import metrics
from ..models.jobs import QUEUE_RETRY_S, PrecomputeLimit, QueueFull
from ..problems import Problem
from ..sessions.chunks import ChunkRequest
from ..sessions.responses import Extras
from .density import parse_points
from .deps import AdminOnly, JobsDep, RegistryDep, SessionsDep, SettingsDep, TenantDep
from .live import live_response
from .schemas import (
    AnalyzeReport,
    ChunkResult,
    DensityOut,
    Forecast,
    Health,
    Job,
    ModelCreate,
    ModelDetail,
    ModelSummary,
    Observations,
    Reset,
    ResetResult,
    SessionCreate,
    SessionCreated,
    SessionInfo,
    SessionPage,
)

SessionId = Annotated[str, Path(min_length=1, max_length=100, description="session id")]
ModelId = Annotated[str, Path(min_length=1, max_length=100, description="model id")]

ERRORS = {400: "malformed request (e.g. invalid JSON) or a Host that is not this server's",
          401: "no tenant's bearer token (a server with a tenants file)",
          403: "the tenant is not an admin (admin = true in the tenants file)",
          404: "unknown model, session or route (or another tenant's session)",
          409: "seq gap or concurrent update", 413: "request body too large",
          415: "the body is not JSON (send Content-Type: application/json)",
          422: "invalid input (the field is named)", 431: "request line and headers too large",
          429: "too many requests: a client's request or session rate, or a session's listeners (see "
               "Retry-After)",
          503: "not ready, store unavailable (disk full, database damaged), analysis busy, or a worker's "
               "connection, listener or job queue limit reached: see Retry-After"}


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"description": ERRORS[code]} for code in codes}


def _json(content: Any, status: int = 200) -> Response:
    return JSONResponse(content, status_code=status)  # allow_nan=False: NaN never leaves


health = APIRouter(tags=["health"])
models = APIRouter(prefix="/v1/models", tags=["models"], responses=_errors(401))
sessions = APIRouter(prefix="/v1/sessions", tags=["sessions"], responses=_errors(401))
analysis = APIRouter(prefix="/v1/analyze", tags=["analysis"], responses=_errors(401))
jobs_router = APIRouter(prefix="/v1/jobs", tags=["models"], responses=_errors(401))


@health.get("/livez", response_model=Health)
def livez() -> Response:
    return _json({"status": "ok"})


@health.get("/readyz", response_model=Health, responses=_errors(503))
def readyz(request: Request) -> Response:
    """Ready when the models are listed and the session store is usable: its file is the one opened,
    intact (header, write-ahead log, and SQLite's quick_check at most every 30 s) and has not lost
    committed transactions.  A load balancer takes a worker whose store failed out of rotation."""
    if not request.app.state.ready:
        raise Problem(503, "models are still loading")
    problem = request.app.state.sessions.store_health()
    if problem is not None:
        raise Problem(503, f"session store unusable: {problem}", "sessions")
    return _json({"status": "ready", "models": len(request.app.state.registry.ids())})


@health.get("/metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus exposition"}})
def prometheus() -> Response:
    body, content_type = metrics.render()
    return Response(body, media_type=content_type)


@models.get("", response_model=list[ModelSummary])
def list_models(registry: RegistryDep) -> Response:
    return _json(registry.summaries())


@models.post("", status_code=202, response_model=Job,
             responses={200: {"description": "the model is already stored"}, **_errors(403, 413, 422, 503)},
             dependencies=AdminOnly)
def create_model(jobs: JobsDep, body: ModelCreate) -> Response:
    """Precompute a spec in the background: 202 with the job to poll (``GET /v1/jobs/{id}``); the
    model appears in ``GET /v1/models`` when it is done.  The id is the spec's content hash: the same
    spec again is the same job (computed once), or 200 when the model is already stored.  Oversize
    specs (basis, mesh nodes) are refused with 413 before any work.  At most ``YAUYAU_MAX_JOBS`` jobs run
    at once (all workers and hosts of the store), the others are ``queued``; beyond
    ``YAUYAU_MAX_QUEUED_JOBS`` waiting, 503 with Retry-After."""
    try:
        job, _ = jobs.submit(body.spec)
    except SpecError as exc:
        raise SpecError(f"spec.{exc.field}", exc.message) from None
    except PrecomputeLimit as exc:
        raise Problem(413, exc.message, exc.field) from None
    except QueueFull as exc:
        raise Problem(503, str(exc), "spec", retry_after=QUEUE_RETRY_S) from None
    out = {**job, "job": f"/v1/jobs/{job['id']}", "model": f"/v1/models/{job['id']}"}
    response = _json(out, 200 if job["status"] == "done" else 202)
    response.headers["Location"] = out["job"]
    return response


@jobs_router.get("/{job_id}", response_model=Job, responses=_errors(403, 404), dependencies=AdminOnly)
def get_job(jobs: JobsDep, job_id: Annotated[str, Path(min_length=1, max_length=100)]) -> Response:
    """A precompute job: queued (with its position, 1: next), running (with its progress), done (the model
    is in /v1/models) or failed (why)."""
    try:
        job = jobs.status(job_id)
    except KeyError:
        raise Problem(404, f"no precompute job or model {job_id!r} (POST /v1/models starts one)",
                      "job") from None
    return _json({**job, "job": f"/v1/jobs/{job_id}", "model": f"/v1/models/{job_id}"})


@models.get("/{model_id}", response_model=ModelDetail, responses=_errors(404))
def get_model(registry: RegistryDep, model_id: ModelId) -> Response:
    loaded = registry.get(model_id)
    return _json({**loaded.summary(), "spec": loaded.spec})


@sessions.post("", status_code=201, response_model=SessionCreated, responses=_errors(400, 404, 413, 422))
def create_session(service: SessionsDep, tenant: TenantDep, body: SessionCreate) -> Response:
    """A filtering session of a stored model: its prior (at time ``t0``), method, outlier ``gate``,
    what it does when the density degenerates (``on_degenerate``), when it has lost track
    (``lost_track``) and its innovation ``monitor``, all kept with the session, which belongs to the
    tenant creating it."""
    return _json(service.create(body.model, body.prior, body.method, body.on_degenerate, body.t0, body.gate,
                                lost_track=None if body.lost_track is None else body.lost_track.model_dump(),
                                monitor=body.monitor, owner=tenant, smooth_lag=body.smooth_lag), 201)


@sessions.get("", response_model=SessionPage, responses=_errors(422))
def list_sessions(service: SessionsDep, tenant: TenantDep,
                  limit: Annotated[int, Query(ge=1, le=1000, description="sessions per page")] = 100,
                  after: Annotated[str | None, Query(max_length=100, description=(
                      "the `next` of the previous page"))] = None,
                  model: Annotated[str | None, Query(max_length=100, description="only this model's")] = None
                  ) -> Response:
    """The tenant's sessions, a page at a time (by id; no states); idle ones are deleted after
    ``idle_expiry``."""
    return _json(service.page(limit, after, model, tenant))


@sessions.post("/{session_id}/observations", response_model=ChunkResult,
               responses=_errors(400, 404, 409, 413, 422))
async def observe(service: SessionsDep, tenant: TenantDep, session_id: SessionId, body: Observations
                  ) -> Response:
    """Apply chunk ``seq`` exactly once: ``increments`` (continuous models) or ``observations``
    (discrete models), optionally at ``times``; null marks a missing row or component.  A re-sent
    seq returns the stored answer (the same bytes); other data under a used seq, or a gap, is 409."""
    # The JSON text the store keeps for replays is sent as is (encoded once, finite numbers only).
    request = ChunkRequest(session_id, body.seq, body.increments, Extras(body.quantiles, body.mode),
                           observations=body.observations, times=body.times, tenant=tenant)
    text = await asyncio.wrap_future(service.chunk_executor.submit_chunk(request))  # applied in a batch
    return Response(text, media_type="application/json")


@sessions.post("/{session_id}/reset", response_model=ResetResult, responses=_errors(400, 404, 409, 413, 422))
async def reset(service: SessionsDep, tenant: TenantDep, session_id: SessionId, body: Reset) -> Response:
    """Start the session again at its step and time (the log-likelihood goes on) from ``prior`` or
    ``from`` "last" (a prior broadened around the last good estimate: a degenerate session recovers)
    or "model".  Numbered like a chunk: it takes seq, a replay returns the stored answer."""
    text = await asyncio.get_running_loop().run_in_executor(
        service.chunk_executor,
        lambda: service.reset(session_id, body.seq, body.prior, body.from_, True, tenant))
    return Response(text, media_type="application/json")


Quantiles = Annotated[str | None, Query(max_length=2000, description=(
    "comma-separated probabilities: add these marginal quantiles of every state variable to the estimate "
    "(e.g. 0.05,0.5,0.95)"))]


@sessions.get("/{session_id}", response_model=SessionInfo, responses=_errors(404, 422))
def get_session(service: SessionsDep, tenant: TenantDep, session_id: SessionId, quantiles: Quantiles = None,
                mode: Annotated[bool, Query(description="add the mode (MAP point) to the estimate")] = False
                ) -> Response:
    return _json(service.info(session_id, Extras(quantiles, mode), tenant))


@sessions.get("/{session_id}/forecast", response_model=Forecast, responses=_errors(404, 422))
def forecast(service: SessionsDep, tenant: TenantDep, session_id: SessionId,
             t: Annotated[float, Query(allow_inf_nan=False, description=(
                 "the time to forecast to: at or after the session's time"))],
             quantiles: Quantiles = None,
             mode: Annotated[bool, Query(description="add the mode (MAP point) to the estimate")] = False
             ) -> Response:
    """The estimate at time ``t`` without an observation (the prediction); the session is unchanged."""
    return _json(service.forecast(session_id, t, Extras(quantiles, mode), tenant))


@sessions.get("/{session_id}/view", response_class=HTMLResponse, responses=_errors(404))
def view(service: SessionsDep, tenant: TenantDep, session_id: SessionId) -> Response:
    """A live page of the session: the density now (curve in 1-D, heat map in 2-D, marginals in 3-D)
    with the mean, the covariance ellipse and the step, redrawn as chunks arrive (from /events).  With
    tenants a browser gets the page with 401 and the page asks for the token (service/http/live.py)."""
    service.version(session_id, tenant)  # 404 for an unknown session
    return live_response()


def _known_session(service: SessionsDep, tenant: TenantDep, session_id: SessionId) -> int:
    """The session's version; 404 (before any event is streamed) when there is no such session."""
    return service.version(session_id, tenant)


async def _listener_slot(request: Request, session_id: SessionId) -> AsyncIterator[None]:
    """A listener's slot on this worker (429 or 503 at the caps), given back when its response ends."""
    slots = request.app.state.listener_slots
    slots.take(session_id)
    try:
        yield
    finally:
        slots.give_back(session_id)


@sessions.get("/{session_id}/events", response_class=EventSourceResponse, responses=_errors(404, 429, 503))
async def events(service: SessionsDep, settings: SettingsDep, tenant: TenantDep, request: Request,
                 session_id: SessionId, seen: Annotated[int, Depends(_known_session)],
                 slot: Annotated[None, Depends(_listener_slot)]
                 ) -> AsyncIterator[ServerSentEvent]:
    """Server-Sent Events: one ``frame`` event now and one after every applied chunk (the estimate
    and the density on a grid, as /view draws them); ``gone`` when the session is deleted.  The
    session store is polled (every ``YAUYAU_EVENTS_POLL`` s), so a chunk applied by any worker or
    host shows; the listeners of a session on one worker share that poll and each frame
    (service/http/listeners.py).  At most ``YAUYAU_MAX_SESSION_LISTENERS`` per session (429 beyond) and
    ``YAUYAU_MAX_LISTENERS`` in all (503 beyond) on one worker."""
    frames = request.app.state.feeds.listen((session_id, tenant), lambda: service.version(session_id, tenant),
                                            lambda: service.frame(session_id, 161, tenant),
                                            settings.events_poll)
    async for frame in frames:
        if frame is None:
            yield ServerSentEvent(event="gone", data={"id": session_id})
            return
        yield ServerSentEvent(event="frame", id=str(frame.version), raw_data=frame.text)


@sessions.get("/{session_id}/density", response_model=DensityOut, responses=_errors(404, 422))
def density(service: SessionsDep, tenant: TenantDep, session_id: SessionId,
            points: Annotated[str | None, Query(max_length=100_000, description=(
                "points separated by ';', coordinates by ',' (e.g. '0.1;0.5' or '0,1;1,0')"))] = None,
            grid: Annotated[str | None, Query(max_length=1000, description=(
                "a product grid, one 'lo:hi:count' per coordinate, separated by ','"))] = None,
            ) -> Response:
    pts = parse_points(points, grid, service.max_density_points)
    return _json(service.density(session_id, np.asarray(pts, dtype=float), tenant))


@sessions.delete("/{session_id}", status_code=204, response_class=Response, responses=_errors(404))
def delete_session(service: SessionsDep, tenant: TenantDep, session_id: SessionId) -> Response:
    service.delete(session_id, tenant)
    return Response(status_code=204)


_EXAMPLE_SPEC = {"name": "cubic-sensor", "state": ["x"], "drift": ["-0.2*x"], "observation": ["x**3"],
                 "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]}, "domain": {"radius": 7.0},
                 "discretization": {"dt": 0.01, "basis": 128}}


_ANALYZE_BODY = Body(description='{"spec": a model spec}, the body POST /v1/models takes, or the bare spec '
                                "(the JSON form of the TOML spec)",
                     examples=[{"spec": _EXAMPLE_SPEC}, _EXAMPLE_SPEC])


@analysis.post("", response_model=AnalyzeReport, responses=_errors(400, 413, 422, 503))
def analyze(settings: SettingsDep, request: Request,
            body: Annotated[dict[str, Any], _ANALYZE_BODY]) -> Response:
    """The estimation-algebra analysis, in a process of its own that is killed at the time limit
    (YAUYAU_ANALYZE_TIME_LIMIT) plus YAUYAU_ANALYZE_GRACE (2 s): a request never takes longer,
    whatever the spec; a killed analysis answers the bounded report (what it had not decided is
    undecided, with a note saying it was stopped)."""
    from ..models.analysis import AnalysisBusy, analysis_runner

    spec = _checked_analysis_spec(body)  # a bad spec is refused here, at once (422 naming the field)
    limit = settings.analyze_time_limit
    try:
        done = analysis_runner(request.app).run(spec, limit)
    except AnalysisBusy as exc:
        raise Problem(503, f"{exc}; retry later", "spec", retry_after=max(1, round(limit))) from None
    return _json(done.report)


def _checked_analysis_spec(body: dict[str, Any]) -> dict[str, Any]:
    """The spec of a POST /v1/analyze body, compiled once to refuse a bad one: ``{"spec": {...}}`` as
    POST /v1/models takes it (a field at fault is named ``spec.<field>``, as there), or the bare spec (no
    spec has a field named spec)."""
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import spec_from_dict

    if "spec" not in body:
        compile_model(spec_from_dict(body))
        return body
    extra = sorted(set(body) - {"spec"})
    if extra:
        raise SpecError(extra[0], 'not a field of the body: {"spec": {...}} holds the spec alone (or '
                                  "send the spec itself as the body)")
    if not isinstance(body["spec"], dict):
        raise SpecError("spec", "must be an object: the model spec (JSON form of the TOML spec)")
    try:
        compile_model(spec_from_dict(body["spec"]))
    except SpecError as exc:
        raise SpecError(f"spec.{exc.field}", exc.message) from None
    return body["spec"]


routers = [health, models, jobs_router, sessions, analysis]
