"""Service configuration: command-line flags and ``YAUYAU_*`` environment variables.

Every field can be set from the environment with the prefix ``YAUYAU_`` (e.g.
``YAUYAU_STORE=/srv/models``, ``YAUYAU_MAX_CHUNK_ROWS=5000``).  ``yauyau serve`` writes its
flags into the same variables so that every uvicorn worker process reads one configuration.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="YAUYAU_", extra="ignore")

    store: Path = Field(Path("var/store"), description="model store directory (read-only at run time)")
    session_db: str | None = Field(
        None, description="the sessions' database: a SQLite file (default: <store>/sessions.sqlite3), or "
                          "postgresql://user@host:port/db for a PostgreSQL database shared by several hosts")
    session_synchronous: Literal["normal", "full"] = Field(
        "normal", description="SQLite durability of a chunk: 'normal' survives a killed process (WAL, no "
                              "fsync per chunk), 'full' also an OS crash or power loss (one fsync per chunk)")
    session_db_timeout: float = Field(
        5.0, gt=0, le=300, description="seconds a request waits for a connection to a PostgreSQL session "
                                       "database before it is answered 503 with Retry-After (the database "
                                       "is down or every connection busy)")
    session_idle_expiry: float = Field(
        7 * 86_400.0, ge=0, description="seconds without a chunk after which a session is deleted with its "
                                        "stored responses (default one week; 0: never)")
    session_sweep: float = Field(60.0, gt=0, le=86_400, description="seconds between looks for idle sessions")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(1, ge=1, le=64)
    batch_window: float = Field(
        0.0, ge=0, le=1.0, description="seconds a worker waits for more chunks before stepping the ones it "
                                       "has together (0, the chunks already waiting, measured best: "
                                       "bench/results/load-windows.md)")
    max_batch: int = Field(256, ge=1, le=100_000, description="most chunks stepped together in one batch")
    max_precompute_basis: int = Field(
        1000, ge=1, le=100_000, description="largest basis a POST /v1/models may precompute (413 beyond)")
    max_precompute_nodes: int = Field(
        6000, ge=1, le=50_000, description="most mesh nodes a POST /v1/models may precompute (413 beyond)")
    max_precompute_centres: int = Field(
        256, ge=1, le=4096, description="most atlas centres ([domain] region) a POST /v1/models may "
                                        "precompute (413 beyond)")
    max_chunk_rows: int = Field(10_000, ge=1, le=10_000_000, description="most rows per chunk")
    max_body_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="largest request body accepted")
    max_density_points: int = Field(100_000, ge=1, description="most points per density request")
    analyze_time_limit: float = Field(
        10.0, gt=0, le=3600, description="seconds one POST /v1/analyze may compute (the report then says "
                                         "which bound stopped the analysis)")
    analyze_grace: float = Field(
        2.0, gt=0, le=60, description="seconds past analyze_time_limit before the analysis process is killed")
    precompute_time_limit: float = Field(
        60.0, gt=0, le=3600, description="seconds the analysis of a POST /v1/models job may take to choose "
                                         "the method (method auto); its process is killed analyze_grace "
                                         "later and the job goes on with what it decided (the general "
                                         "engine, yau-yau, when nothing)")
    analyze_concurrency: int = Field(
        1, ge=1, le=64, description="analyses one worker runs at once, each in a process of its own that is "
                                    "killed at analyze_time_limit + analyze_grace")
    events_poll: float = Field(
        0.2, gt=0, le=60, description="seconds between looks at the session store for /events "
                                      "(the live page)")
    blas_threads: int = Field(
        1, ge=1, le=1024, description="BLAS threads per worker process for the online products (1: fastest "
                                      "on a busy host, bench/results/blas.md)")
    model_cache: int = Field(
        8, ge=1, le=100_000, description="models each worker keeps loaded (least recently used dropped "
                                         "first); models load on first use")
    header_timeout: float = Field(
        10.0, gt=0, le=3600, description="seconds a connection may take to send a complete request head "
                                         "(from its opening, or from the first byte of a kept-alive "
                                         "connection's next head); it is closed then")
    max_connections: int | None = Field(
        None, ge=1, le=1_000_000, description="connections one worker keeps open; a newcomer beyond closes "
                                              "the one waiting longest for its request head, or is answered "
                                              "503 (default: what the descriptor limit allows, less a "
                                              "reserve and the listen backlog, at most 4096)")
    max_jobs: int = Field(
        2, ge=1, le=256, description="precompute jobs (processes) running at once for one model store, all "
                                     "workers and hosts together; the others wait in a queue")
    max_queued_jobs: int = Field(
        16, ge=0, le=100_000, description="precompute jobs waiting for a slot; POST /v1/models answers 503 "
                                          "beyond")
    max_session_listeners: int = Field(
        8, ge=1, le=100_000, description="/events listeners of one session on one worker (429 beyond)")
    max_listeners: int = Field(
        64, ge=1, le=100_000, description="/events listeners on one worker, all sessions (503 beyond)")
    rate_requests: float = Field(
        2000.0, ge=0, description="/v1 requests per second per client (its tenant, else its IP address), "
                                  "each worker allowing its share (rate / workers); 429 beyond; 0: no limit")
    rate_requests_burst: int = Field(
        2000, ge=1, description="/v1 requests a client may send at once above rate_requests")
    rate_sessions: float = Field(
        50.0, ge=0, description="sessions created per second per client (its tenant, else its IP address), "
                                "each worker allowing its share (rate / workers); 429 beyond; 0: no limit")
    rate_sessions_burst: int = Field(
        100, ge=1, description="sessions a client may create at once above rate_sessions")
    log_level: Literal["critical", "error", "warning", "info", "debug", "trace"] = "info"
    metrics_dir: Path | None = Field(
        None, description="prometheus multiprocess directory (set by `serve` when workers > 1)")
    tenants_file: Path | None = Field(
        None, description="a TOML file of [[tenant]] tables (name, token_sha256, admin): every /v1 "
                          "request then needs Authorization: Bearer TOKEN and a session belongs to the "
                          "tenant that made it (http/tenants.py); unset: no authentication, loopback only")
    insecure_bind: bool = Field(
        False, description="allow a non-loopback host without a tenants file (authentication done in front)")
    allowed_hosts: str | None = Field(
        None, description="comma-separated names the Host header may carry ('*': any), against DNS "
                          "rebinding; default: localhost, 127.0.0.1, ::1 and the bind address")

    @field_validator("session_db", mode="before")
    @classmethod
    def _path_as_text(cls, value):
        return str(value) if isinstance(value, Path) else value

    def session_path(self) -> Path:
        """The SQLite file of the sessions (when session_db is not a PostgreSQL URL)."""
        return Path(self.session_db) if self.session_db is not None else self.store / "sessions.sqlite3"

    def session_postgres(self) -> str | None:
        """The PostgreSQL URL of the sessions, or None (SQLite)."""
        db = self.session_db
        return db if db is not None and db.startswith(("postgresql://", "postgres://")) else None

    def to_env(self) -> dict[str, str]:
        """The environment variables that reproduce these settings in a worker process."""
        env = {}
        for name, value in self.model_dump().items():
            if value is not None:
                env[f"YAUYAU_{name.upper()}"] = str(value)
        return env
