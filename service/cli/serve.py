"""`yauyau serve`: run the HTTP API with uvicorn (one or several worker processes).

Flags override the ``YAUYAU_*`` environment; the resulting settings are written back into the
environment so that every worker process (spawned by uvicorn) builds the same application.
"""

from __future__ import annotations

import os
import sys
import tempfile

_LIMIT_FLAGS = [
    ("--header-timeout", float, "seconds a connection may take to send a complete request head, then it is "
                                "closed (env YAUYAU_HEADER_TIMEOUT; default 10)"),
    ("--max-connections", int, "connections per worker; a newcomer beyond closes the one waiting longest for "
                               "its request head, or gets 503 (env YAUYAU_MAX_CONNECTIONS; default from the "
                               "descriptor limit, at most 4096)"),
    ("--max-jobs", int, "precompute jobs running at once for the model store, the rest queued "
                        "(env YAUYAU_MAX_JOBS; default 2)"),
    ("--max-queued-jobs", int, "precompute jobs waiting; POST /v1/models answers 503 beyond "
                               "(env YAUYAU_MAX_QUEUED_JOBS; default 16)"),
    ("--max-listeners", int, "/events listeners per worker, all sessions; 503 beyond "
                             "(env YAUYAU_MAX_LISTENERS; default 64)"),
    ("--max-session-listeners", int, "/events listeners of one session per worker; 429 beyond "
                                     "(env YAUYAU_MAX_SESSION_LISTENERS; default 8)"),
    ("--rate-requests", float, "/v1 requests per second per client (tenant, else IP address); 429 beyond; "
                               "0: off (env YAUYAU_RATE_REQUESTS; default 2000; burst "
                               "YAUYAU_RATE_REQUESTS_BURST, default 2000)"),
    ("--rate-sessions", float, "sessions created per second per client (tenant, else IP address); 429 "
                               "beyond; 0: off (env YAUYAU_RATE_SESSIONS; default 50; burst "
                               "YAUYAU_RATE_SESSIONS_BURST, default 100)"),
]


def add_arguments(parser):
    parser.add_argument("--store", help="model store directory (env YAUYAU_STORE; default var/store)")
    parser.add_argument("--host", help="interface to bind (env YAUYAU_HOST; default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (env YAUYAU_PORT; default 8000)")
    parser.add_argument("--workers", type=int, help="worker processes (env YAUYAU_WORKERS; default 1)")
    parser.add_argument("--session-db",
                        help="the sessions' database: a SQLite file (default <store>/sessions.sqlite3) or a "
                             "postgresql://user@host:port/db URL shared by several hosts "
                             "(env YAUYAU_SESSION_DB)")
    parser.add_argument("--session-synchronous", choices=["normal", "full"],
                        help="durability of each chunk: normal (default) survives a killed server, full also "
                             "an OS crash or power loss (an fsync per chunk; env YAUYAU_SESSION_SYNCHRONOUS)")
    parser.add_argument("--session-db-timeout", type=float,
                        help="seconds a request waits for a PostgreSQL session database before its 503 "
                             "with Retry-After (env YAUYAU_SESSION_DB_TIMEOUT; default 5)")
    parser.add_argument("--blas-threads", type=int,
                        help="BLAS threads per worker for the online products "
                             "(env YAUYAU_BLAS_THREADS; default 1)")
    parser.add_argument("--model-cache", type=int,
                        help="models each worker keeps loaded, least recently used dropped first "
                             "(env YAUYAU_MODEL_CACHE; default 8); models load on first use")
    parser.add_argument("--session-idle-expiry", type=float,
                        help="seconds without a chunk after which a session is deleted "
                             "(env YAUYAU_SESSION_IDLE_EXPIRY; default 604800, one week; 0: never)")
    parser.add_argument("--batch-window", type=float,
                        help="seconds a worker waits for more chunks before stepping those it has together "
                             "(env YAUYAU_BATCH_WINDOW; default 0: the chunks already waiting)")
    limits = parser.add_argument_group("limits on what clients make the server hold (docs/reliability.md)")
    for flag, kind, text in _LIMIT_FLAGS:
        limits.add_argument(flag, type=kind, help=text)
    parser.add_argument("--log-level", choices=["critical", "error", "warning", "info", "debug"])
    parser.add_argument("--tenants", metavar="FILE",
                        help="TOML file of [[tenant]] tables (name, token_sha256, admin): every /v1 request "
                             "then needs Authorization: Bearer TOKEN (env YAUYAU_TENANTS_FILE)")
    parser.add_argument("--insecure-bind", action="store_true", default=None,
                        help="listen on a non-loopback --host without a tenants file, when something in "
                             "front authenticates (env YAUYAU_INSECURE_BIND)")
    parser.add_argument("--allowed-hosts", metavar="NAMES",
                        help="comma-separated names the Host header may carry, * for any (env "
                             "YAUYAU_ALLOWED_HOSTS; default localhost, 127.0.0.1, ::1 and --host)")


def _settings(args):
    from pydantic import ValidationError
    from yauyau.service.settings import Settings
    from yauyau.solver.errors import InputError

    overrides = {k: v for k, v in {"store": args.store, "host": args.host, "port": args.port,
                                   "workers": args.workers, "session_db": args.session_db,
                                   "session_synchronous": args.session_synchronous,
                                   "session_db_timeout": args.session_db_timeout,
                                   "blas_threads": args.blas_threads, "model_cache": args.model_cache,
                                   "session_idle_expiry": args.session_idle_expiry,
                                   "batch_window": args.batch_window,
                                   **{flag[2:].replace("-", "_"): getattr(args, flag[2:].replace("-", "_"))
                                      for flag, _, _ in _LIMIT_FLAGS},
                                   "log_level": args.log_level, "tenants_file": args.tenants,
                                   "insecure_bind": args.insecure_bind,
                                   "allowed_hosts": args.allowed_hosts}.items() if v is not None}
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(".".join(str(p) for p in err["loc"]) or "settings", err["msg"]) from None


def _check_session_db(settings) -> None:
    """Open (create) the session database once before any worker starts, so that a read-only store
    directory is one clear message, not a traceback from every worker."""
    from yauyau.storage.errors import StoreError
    from yauyau.storage.session_store import SqliteSessionStore

    if settings.session_postgres() is not None:  # connect once: a wrong URL is one clear message
        from yauyau.service.http.app import open_session_store

        open_session_store(settings).close()
        return
    path = settings.session_path()
    hint = ("pass --session-db PATH (env YAUYAU_SESSION_DB) on a writable disk"
            if settings.session_db is None else "choose a writable --session-db")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists() and not os.access(path, os.W_OK):
            raise PermissionError(f"{path} is read-only")
        if not os.access(path.parent, os.W_OK):
            raise PermissionError(f"directory {path.parent} is read-only")
        SqliteSessionStore(path, synchronous=settings.session_synchronous).close()
    except (OSError, StoreError) as exc:
        reason = exc.message if isinstance(exc, StoreError) else str(exc)
        raise StoreError("session_db", f"cannot open the session database {path} ({reason}); the "
                                       f"sessions need a writable file next to the models by default: {hint}"
                         ) from None


def run(args):
    import uvicorn
    from yauyau.service.http.connections import FD_RESERVE, descriptor_limit, plan
    from yauyau.service.http.protocol import MAX_HEAD_BYTES, protocol_class
    from yauyau.service.http.tenants import serve_notes
    from yauyau.storage.errors import StoreError

    settings = _settings(args)
    notes = serve_notes(settings)  # the tenants file loads; loopback only without one (else exit 2)
    if not settings.store.is_dir():
        raise StoreError("store", f"no model store {settings.store} (run `yauyau precompute` first)")
    _check_session_db(settings)
    if settings.workers > 1 and settings.metrics_dir is None:
        # prometheus multiprocess mode: must be set before any worker imports prometheus_client
        settings.metrics_dir = tempfile.mkdtemp(prefix="yauyau-metrics-")
    os.environ.update(settings.to_env())
    for note in notes:
        print(note, file=sys.stderr, flush=True)
    if settings.metrics_dir is not None:
        os.environ["PROMETHEUS_MULTIPROC_DIR"] = str(settings.metrics_dir)
    cap, backlog = plan(settings.max_connections)
    if cap + backlog + FD_RESERVE > descriptor_limit():
        print(f"yauyau serve: warning: --max-connections {cap} with a listen backlog of {backlog} does not "
              f"fit the descriptor limit ({descriptor_limit()}, ulimit -n) with {FD_RESERVE} to spare: raise "
              "the limit or lower the cap", file=sys.stderr)
    uvicorn.run("yauyau.service.http.app:create_app", factory=True, host=settings.host, port=settings.port,
                workers=settings.workers, log_level=settings.log_level, access_log=False,
                http=protocol_class(), h11_max_incomplete_event_size=MAX_HEAD_BYTES, backlog=backlog,
                ws_max_size=settings.max_body_bytes)  # a bigger stream message: closed with 1009
    return 0
