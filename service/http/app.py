"""The HTTP API of the Yau–Yau filter (FastAPI): the application, its lifespan and middleware.

The routes are on APIRouters (service/http/routes.py) and reach the sessions, the models and the
settings through dependencies (service/http/deps.py).  Models are listed at start-up from the store's
file attributes and loaded on first use (service/models/cache.py, a bounded cache), so the server is
ready at once; sessions live in SQLite so that several workers share them and a restarted server
continues where it stopped.  The online products run with ``blas_threads`` BLAS threads per worker
(default 1, bench/results/blas.md).  Every error is RFC 9457 ``application/problem+json``.  OpenAPI at
/docs and /openapi.json.
"""

from __future__ import annotations

import gc
import logging
import threading
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from yauyau import __version__

from .. import metrics
from ..models.cache import Registry
from ..models.jobs import Jobs
from ..problems import hide_paths, install_handlers
from ..sessions.manager import Sessions
from ..settings import Settings
from .chunk_path import ChunkFastPath
from .limits import RateLimits, rate_limits
from .listeners import Feeds, ListenerSlots
from .middleware import BodyLimit, JsonBodies
from .routes import ERRORS, routers
from .schemas import ProblemOut
from .stream import stream
from .tenants import TenantGuard, allowed_hosts, load_tenants

log = logging.getLogger("yauyau.service")


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
            for code in (400, 404, 413, 415, 422, 429, 431, 503):  # limits, routing, validation, store
                responses.setdefault(str(code), {"description": ERRORS[code]})
            for code, response in responses.items():
                if code[0] in "45":
                    response["content"] = problem
        app.openapi_schema = schema
    return app.openapi_schema


def open_session_store(settings: Settings) -> Any:
    """The session store the settings name: PostgreSQL for a postgresql:// URL, else the SQLite file."""
    idle = settings.session_idle_expiry or None
    if settings.session_postgres() is not None:
        from yauyau.storage.postgres_store import PostgresSessionStore

        return PostgresSessionStore(settings.session_postgres(), idle_expiry=idle,
                                    timeout=settings.session_db_timeout)
    from yauyau.storage.session_store import SqliteSessionStore

    path = settings.session_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    return SqliteSessionStore(path, synchronous=settings.session_synchronous, idle_expiry=idle)


def _open_sessions(settings: Settings, registry: Registry) -> Sessions:
    store = open_session_store(settings)
    return Sessions(store, registry, settings.max_chunk_rows, settings.max_density_points,
                    settings.batch_window, settings.max_batch)


class _Sweeper:
    """A thread that deletes idle sessions every ``interval`` seconds (each worker runs one: the
    deletes are idempotent)."""

    def __init__(self, sessions: Sessions, interval: float):
        self.sessions, self.interval = sessions, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="yauyau-sweeper", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                gone = self.sessions.expire()
                if gone:
                    log.info("deleted %d session(s) idle for longer than the expiry", gone)
            except Exception as exc:  # noqa: BLE001 - a store that is unavailable now may come back
                log.warning("idle sessions not swept: %s", exc)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


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
        from yauyau.solver.blas import limit_process_blas

        limit_process_blas(settings.blas_threads)  # this worker process, for good (scipy's BLAS too)
        # A lifespan that ends gives back what was there before it: one application object may be run
        # by two lifespans at once (a test client inside a fuzzer's), and the outer one goes on.
        before = {name: getattr(app.state, name, None) for name in ("registry", "sessions", "ready")}
        registry = Registry.open(settings.store, settings.model_cache)
        sessions = _open_sessions(settings, registry)
        app.state.registry = registry
        app.state.sessions = sessions
        app.state.jobs = Jobs(settings.store, settings.max_precompute_basis, settings.max_precompute_nodes,
                              settings.max_precompute_centres, settings.precompute_time_limit,
                              settings.analyze_grace, max_jobs=settings.max_jobs,
                              max_queued=settings.max_queued_jobs)
        app.state.ready = True
        from ..models.analysis import warm_analysis  # lazy: the analysis (SymPy) loads in its thread

        app.state.analysis_warm = warm_analysis(app)  # forkserver, row loops: now, not in a request
        sweeper = _Sweeper(sessions, settings.session_sweep)
        # What start-up made lives as long as the process: moved out of the cyclic collector's reach,
        # its full collections stop scanning it (measured: 1.27 -> 0.91 ms of CPU per chunk with 64
        # concurrent streams, bench/results/load.md).  Garbage made later is collected as before.
        gc.freeze()
        yield
        app.state.ready = False
        sweeper.stop()
        sessions.chunk_executor.shutdown(wait=True)  # the chunk in flight is committed
        close = getattr(sessions.store, "close", None)
        if close is not None:
            close()  # a PostgreSQL store's pool; this thread's SQLite connection
        if before["sessions"] is not None:
            app.state.registry, app.state.sessions = before["registry"], before["sessions"]
            app.state.ready = bool(before["ready"])

    app = FastAPI(title="yauyau", version=__version__, lifespan=lifespan,
                  summary="Real-time optimal nonlinear filtering (the Yau–Yau algorithm) as a service",
                  description="Stream observations into a session — increments of dy = h(x)dt + dw, or "
                              "measurements z = h(x(t)) + v at any times, partly missing or not — and get "
                              "the conditional mean and covariance of x(t) after every row, outliers gated, "
                              "degenerate sessions reset or re-initialised.")
    app.state.ready = False
    app.state.settings = settings
    app.state.tenants = load_tenants(settings.tenants_file)  # None: no tenants file, no authentication
    hide_paths(store=settings.store, session_database=None if settings.session_postgres() else
               settings.session_path())  # never in a 5xx detail (service/problems.py)
    app.state.listener_slots = ListenerSlots(settings.max_session_listeners, settings.max_listeners)
    app.state.feeds = Feeds()
    app.state.stream_slots = ListenerSlots(settings.max_session_listeners, settings.max_listeners,
                                           "WebSocket streams")  # service/http/stream.py
    install_handlers(app)
    app.openapi = lambda: _problem_openapi(app)
    for router in routers:
        app.include_router(router)
    app.include_router(stream)  # WS /v1/sessions/{id}/stream (service/http/stream.py)
    app.add_middleware(ChunkFastPath)  # innermost: the chunk route without routing (chunk_path.py)
    app.add_middleware(JsonBodies)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(RateLimits, **rate_limits(settings))  # inside the tenants' middleware: per tenant
    app.add_middleware(TenantGuard, tenants=app.state.tenants, hosts=allowed_hosts(settings))
    app.add_middleware(metrics.RequestMetrics)
    return app


