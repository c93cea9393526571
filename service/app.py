"""The HTTP API of the Yau–Yau filter (FastAPI).

Models are loaded read-only at start-up (each worker keeps the compiled model, the offline
propagators and the filters in memory); sessions live in SQLite so that several workers share
them and a restarted server continues where it stopped.  Every error is RFC 9457
``application/problem+json``.  OpenAPI at /docs and /openapi.json.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from typing import Annotated, Any

import numpy as np
from fastapi import Body, FastAPI, Path, Query, Request
from fastapi.openapi.utils import get_openapi
from starlette.responses import JSONResponse, Response
from yauyau.solver.analysis import analyze as analyze_model
from yauyau.solver.model import compile_model
from yauyau.solver.spec import spec_from_dict

from . import metrics
from .density import parse_points
from .middleware import BodyLimit
from .problems import Problem, install_handlers
from .registry import Registry
from .schemas import (
    AnalyzeReport,
    ChunkResult,
    DensityOut,
    Health,
    ModelDetail,
    ModelSummary,
    Observations,
    ProblemOut,
    SessionCreate,
    SessionCreated,
    SessionInfo,
)
from .sessions import Sessions
from .settings import Settings

log = logging.getLogger("yauyau.service")
SessionId = Annotated[str, Path(min_length=1, max_length=100, description="session id")]
ModelId = Annotated[str, Path(min_length=1, max_length=100, description="model id")]

ERRORS = {400: "malformed request (e.g. invalid JSON)", 404: "unknown model, session or route",
          409: "seq gap or concurrent update", 413: "request body too large",
          422: "invalid input (the field is named)", 503: "models are still loading"}


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"description": ERRORS[code]} for code in codes}


def _problem_openapi(app: FastAPI) -> dict[str, Any]:
    """OpenAPI where every error response is application/problem+json (FastAPI says JSON)."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, summary=app.summary,
                             description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components["Problem"] = ProblemOut.model_json_schema(ref_template="#/components/schemas/{model}")
        components.pop("HTTPValidationError", None)
        components.pop("ValidationError", None)
        problem = {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}}
        for operation in (op for item in schema["paths"].values() for op in item.values()):
            responses = operation["responses"]
            for code in (400, 404, 413, 422):  # the body limit, routing and validation apply everywhere
                responses.setdefault(str(code), {"description": ERRORS[code]})
            for code, response in responses.items():
                if code[0] in "45":
                    response["content"] = problem
        app.openapi_schema = schema
    return app.openapi_schema


def _open_sessions(settings: Settings, registry: Registry) -> Sessions:
    from yauyau.storage.session_store import SessionStore

    path = settings.session_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    store = SessionStore(path, synchronous=settings.session_synchronous)
    return Sessions(store, registry, settings.max_chunk_rows, settings.max_density_points)


def _configure_logging(level: str) -> None:
    """The service's own logger only (uvicorn configures its loggers; the root logger is left alone)."""
    if not log.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        log.addHandler(handler)
    log.setLevel("DEBUG" if level == "trace" else level.upper())


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application; ``settings`` default to the ``YAUYAU_*`` environment (uvicorn factory)."""
    settings = settings or Settings()
    _configure_logging(settings.log_level)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        registry = Registry.load(settings.store)
        app.state.registry = registry
        app.state.sessions = _open_sessions(settings, registry)
        app.state.ready = True
        yield
        app.state.ready = False
        app.state.sessions.chunk_executor.shutdown(wait=True)  # the chunk in flight is committed

    app = FastAPI(title="yauyau", version="0.1.0", lifespan=lifespan,
                  summary="Real-time optimal nonlinear filtering (the Yau–Yau algorithm) as a service",
                  description="Stream observation increments of dy = h(x)dt + dw into a session and get the "
                              "conditional mean and covariance of x(t) after every step.")
    app.state.ready = False
    app.state.settings = settings
    install_handlers(app)
    app.openapi = lambda: _problem_openapi(app)
    _add_routes(app)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(metrics.RequestMetrics)
    return app


def _json(content: Any, status: int = 200) -> Response:
    return JSONResponse(content, status_code=status)  # allow_nan=False: NaN never leaves


def _sessions(request: Request) -> Sessions:
    sessions = getattr(request.app.state, "sessions", None)
    if sessions is None:
        raise Problem(503, "models are still loading")
    return sessions


def _add_routes(app: FastAPI) -> None:
    @app.get("/livez", response_model=Health, tags=["health"])
    def livez() -> Response:
        return _json({"status": "ok"})

    @app.get("/readyz", response_model=Health, tags=["health"], responses=_errors(503))
    def readyz(request: Request) -> Response:
        if not request.app.state.ready:
            raise Problem(503, "models are still loading")
        return _json({"status": "ready", "models": len(request.app.state.registry.models)})

    @app.get("/metrics", tags=["health"], response_class=Response,
             responses={200: {"content": {"text/plain": {}}, "description": "Prometheus exposition"}})
    def prometheus() -> Response:
        body, content_type = metrics.render()
        return Response(body, media_type=content_type)

    @app.get("/v1/models", response_model=list[ModelSummary], tags=["models"])
    def list_models(request: Request) -> Response:
        models = _sessions(request).registry.models
        return _json([m.summary() for m in models.values()])

    @app.get("/v1/models/{model_id}", response_model=ModelDetail, tags=["models"], responses=_errors(404))
    def get_model(request: Request, model_id: ModelId) -> Response:
        loaded = _sessions(request).registry.get(model_id)
        return _json({**loaded.summary(), "spec": loaded.spec})

    @app.post("/v1/sessions", status_code=201, response_model=SessionCreated, tags=["sessions"],
              responses=_errors(400, 404, 413, 422))
    def create_session(request: Request, body: SessionCreate) -> Response:
        created = _sessions(request).create(body.model, body.prior, body.method)
        return _json(created, 201)

    @app.post("/v1/sessions/{session_id}/observations", response_model=ChunkResult, tags=["sessions"],
              responses=_errors(400, 404, 409, 413, 422))
    async def observe(request: Request, session_id: SessionId, body: Observations) -> Response:
        # The JSON text the store keeps for replays is sent as is (encoded once, finite numbers only).
        sessions = _sessions(request)
        text = await asyncio.get_running_loop().run_in_executor(
            sessions.chunk_executor, sessions.observe, session_id, body.seq, body.increments, True)
        return Response(text, media_type="application/json")

    @app.get("/v1/sessions/{session_id}", response_model=SessionInfo, tags=["sessions"],
             responses=_errors(404))
    def get_session(request: Request, session_id: SessionId) -> Response:
        return _json(_sessions(request).info(session_id))

    @app.get("/v1/sessions/{session_id}/density", response_model=DensityOut, tags=["sessions"],
             responses=_errors(404, 422))
    def density(request: Request, session_id: SessionId,
                points: Annotated[str | None, Query(max_length=100_000, description=(
                    "points separated by ';', coordinates by ',' (e.g. '0.1;0.5' or '0,1;1,0')"))] = None,
                grid: Annotated[str | None, Query(max_length=1000, description=(
                    "a product grid, one 'lo:hi:count' per coordinate, separated by ','"))] = None,
                ) -> Response:
        sessions = _sessions(request)
        pts = parse_points(points, grid, sessions.max_density_points)
        return _json(sessions.density(session_id, np.asarray(pts, dtype=float)))

    @app.delete("/v1/sessions/{session_id}", status_code=204, tags=["sessions"], response_class=Response,
                responses=_errors(404))
    def delete_session(request: Request, session_id: SessionId) -> Response:
        _sessions(request).delete(session_id)
        return Response(status_code=204)

    @app.post("/v1/analyze", response_model=AnalyzeReport, tags=["analysis"],
              responses=_errors(400, 413, 422))
    def analyze(request: Request,
                spec: Annotated[dict[str, Any], Body(description="a model spec (JSON form of the TOML spec)",
                                                     examples=[_EXAMPLE_SPEC])]) -> Response:
        limit = request.app.state.settings.analyze_time_limit  # a request cannot hold a worker longer
        report = analyze_model(compile_model(spec_from_dict(spec)), time_limit=limit)
        return _json(report.to_dict())


_EXAMPLE_SPEC = {"name": "cubic-sensor", "state": ["x"], "drift": ["-0.2*x"], "observation": ["x**3"],
                 "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]}, "domain": {"radius": 7.0},
                 "discretization": {"dt": 0.01, "basis": 128}}
