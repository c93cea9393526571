"""PostgreSQL session store: the sessions of several server processes on several hosts in one database.

``YAUYAU_SESSION_DB=postgresql://user@host:port/db`` (``yauyau serve --session-db``) selects it; SQLite
(storage/session_store.py) stays the embedded default.  The semantics are storage/session_base.py's,
unchanged: a chunk is accepted in the transaction that stores its state and its response, only if
the session's version is still the one its state was read at (optimistic concurrency: a writer on
another host that moved the session on makes this one re-read — a replay, or the chunk recomputed
on the new state; never a lost update), a replay returns the stored bytes.  psycopg 3 with a
connection pool per process; each operation borrows a connection for one transaction.  The
schema is created on first use (an advisory lock serialises the processes that start together).

Faults: a connection that cannot be made or is lost, a server that is shutting down or out of
disk gives :class:`Unavailable` with ``retry_after`` (nothing was stored; the same chunk can be
re-sent), other database errors a StoreError naming the sessions.  Storage knows rows, not math.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import psycopg
from psycopg.rows import dict_row
from psycopg_pool import ConnectionPool, PoolTimeout

from .errors import StoreError, Unavailable
from .session_base import SessionStoreBase, schema

RETRY_S = 5
_SCHEMA = schema("BIGINT", "DOUBLE PRECISION") + """;
ALTER TABLE sessions ADD COLUMN IF NOT EXISTS owner TEXT
"""  # databases made before tenants: their sessions are owned by no tenant
_SCHEMA_LOCK = 0x79617579  # pg_advisory_xact_lock key: the processes that create the schema at once


def is_postgres_dsn(value: Any) -> bool:
    """Whether a --session-db value names a PostgreSQL database (else it is a SQLite file)."""
    return isinstance(value, str) and value.startswith(("postgresql://", "postgres://"))


class _Rows:
    """A read's rows, fetched before its connection went back to the pool."""

    def __init__(self, rows: list[dict[str, Any]]):
        self._rows = rows

    def fetchone(self) -> dict[str, Any] | None:
        return self._rows[0] if self._rows else None

    def fetchall(self) -> list[dict[str, Any]]:
        return self._rows


class _Executor:
    """The base class's ``db``: execute with its ``?`` placeholders on a psycopg connection."""

    def __init__(self, conn: psycopg.Connection):
        self.conn = conn

    def execute(self, sql: str, args: tuple = ()) -> psycopg.Cursor:
        return self.conn.execute(sql.replace("?", "%s"), args)


class PostgresSessionStore(SessionStoreBase):
    """Sessions in a PostgreSQL database, shared by every process that connects to it."""

    _db_errors = (psycopg.Error,)
    _INSERT_CHUNK = ("INSERT INTO chunks (session_id, seq, response, digest, stored, size) "
                     "VALUES (?,?,?,?,?,?) ON CONFLICT (session_id, seq) DO UPDATE SET "
                     "response = EXCLUDED.response, digest = EXCLUDED.digest, stored = EXCLUDED.stored, "
                     "size = EXCLUDED.size")

    def __init__(self, dsn: str, retention: int = 16, retention_bytes: int = 256 * 1024,
                 retention_seconds: float = 86_400.0, idle_expiry: float | None = None, pool_size: int = 8,
                 connect_timeout: float = 30.0):
        if not is_postgres_dsn(dsn):
            raise StoreError("session_db", "a PostgreSQL store needs a postgresql://user@host:port/db URL")
        self._configure(retention, retention_bytes, retention_seconds, idle_expiry)
        self.dsn = dsn
        options = {"row_factory": dict_row, "connect_timeout": int(connect_timeout)}
        self.pool = ConnectionPool(dsn, min_size=1, max_size=int(pool_size), open=False,
                                   name="yauyau-sessions", kwargs=options)
        try:
            self.pool.open(wait=True, timeout=connect_timeout)
        except (PoolTimeout, psycopg.Error) as exc:
            self.pool.close()
            raise StoreError("session_db", f"cannot connect to the PostgreSQL session database "
                                           f"{_shown(dsn)}: {exc}") from None
        try:
            with self._transaction() as db:
                db.execute(f"SELECT pg_advisory_xact_lock({_SCHEMA_LOCK})")
                for statement in filter(str.strip, _SCHEMA.split(";")):
                    db.execute(statement)
        except StoreError:
            self.pool.close()
            raise

    def close(self) -> None:
        self.pool.close()

    # -- what the base class needs ------------------------------------------------------
    @contextmanager
    def _transaction(self) -> Iterator[_Executor]:
        try:
            with self.pool.connection() as conn:
                with conn.transaction():
                    yield _Executor(conn)
        except PoolTimeout as exc:
            raise Unavailable("sessions", f"no connection to the session database: {exc}",
                              retry_after=RETRY_S) from None
        except psycopg.Error as exc:
            raise self._error(exc, "database error") from None

    def _query(self, sql: str, args: tuple = ()) -> _Rows:
        if any(isinstance(a, str) and "\x00" in a for a in args):
            return _Rows([])  # PostgreSQL text cannot hold NUL: no row has it (SQLite finds none either)
        with self._transaction() as db:
            return _Rows(db.execute(sql, args).fetchall())

    def _error(self, exc: Exception, what: str) -> StoreError:
        if isinstance(exc, StoreError):
            return exc
        transient = (psycopg.OperationalError, psycopg.errors.DiskFull, psycopg.errors.AdminShutdown,
                     psycopg.errors.SerializationFailure, psycopg.errors.DeadlockDetected)
        if isinstance(exc, transient):
            return Unavailable("sessions", f"{what}: {exc}".strip(), retry_after=RETRY_S)
        return StoreError("sessions", f"{what}: {exc}".strip())

    def health(self, deep: bool = False) -> str | None:
        """None when the database answers, else why not."""
        try:
            self._query("SELECT 1 AS ok")
        except StoreError as exc:
            return exc.message
        return None


def _shown(dsn: str) -> str:
    """The DSN without its password."""
    try:
        info = psycopg.conninfo.conninfo_to_dict(dsn)
    except psycopg.Error:
        return "(unparsable URL)"
    return f"{info.get('host', '')}:{info.get('port', '5432')}/{info.get('dbname', '')}"
