"""SQLite session store (the embedded default :class:`storage.protocols.SessionStore`): filter states
advanced by numbered chunks, each applied exactly once.

A session holds the filter state (any JSON-able dict), ``next_seq`` (the seq the next chunk must
carry; the first chunk is seq 0) and a ``version``.  ``apply_chunk(id, seq, compute)``:

* seq == next_seq: ``compute(state) -> (new_state, response)`` runs outside any lock, then the new
  state and the response are written in ONE transaction, only if the version is unchanged
  (optimistic concurrency); on a clash the row is re-read and either the response stored by the
  winner is returned (replayed) or the chunk is recomputed on the new state;
* seq <  next_seq: the stored response is returned (replayed, nothing applied);
* seq >  next_seq: :class:`Conflict` naming the expected seq, nothing changed.

Responses of the last ``retention`` chunks per session are kept.  The file is shared by several
processes (WAL mode, busy timeout); each thread of each process has its own connection.
``apply_chunk(..., encoded=True)`` returns the response as the JSON text stored, so that a server
can send it as is (one encoding per chunk, not two); ``compute`` may also return the response
already encoded (a ``str`` of a JSON object with finite numbers, stored as given).

Durability (``synchronous``): ``"normal"`` (default) — in WAL mode a commit is appended to the
log without an fsync; it survives the process being killed (SIGKILL, crash) because the log is in
the OS page cache, and only an OS crash or power loss can lose the last commits (never corrupt
the file).  ``"full"`` fsyncs the log on every commit: an acknowledged chunk also survives power
loss, at the price of one fsync per chunk.
Storage knows files, not math: it never imports solver or service.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import secrets
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import orjson

from .errors import Conflict, NotFound, StoreError

Compute = Callable[[dict[str, Any]], tuple[dict[str, Any], dict[str, Any] | str]]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    model_id TEXT NOT NULL,
    method TEXT NOT NULL,
    state TEXT NOT NULL,
    initial_response TEXT NOT NULL,
    next_seq INTEGER NOT NULL,
    step INTEGER NOT NULL,
    t REAL NOT NULL,
    loglik REAL,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    version INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS chunks (
    session_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    response TEXT NOT NULL,
    PRIMARY KEY (session_id, seq)
) WITHOUT ROWID;
"""
_MAX_ATTEMPTS = 100
_SYNCHRONOUS = ("normal", "full")


@dataclass(frozen=True)
class SessionRecord:
    id: str
    model_id: str
    method: str
    state: dict[str, Any]
    initial_response: dict[str, Any]
    next_seq: int
    step: int
    t: float
    loglik: float | None
    created: str
    updated: str
    version: int


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _finite(value: Any) -> bool:
    """No NaN or ±inf anywhere in a JSON-like value (orjson would write them as null, not refuse)."""
    if isinstance(value, float):
        return value - value == 0.0
    if isinstance(value, (list, tuple)):
        try:
            total = sum(value)  # one C loop over a list of numbers: NaN and inf propagate
        except TypeError:
            return all(map(_finite, value))
        return total - total == 0.0 or all(map(_finite, value))  # finite values may overflow the sum
    if isinstance(value, dict):
        return all(map(_finite, value.values()))
    return True


def _default(value: Any) -> Any:
    """What orjson does not take itself: subclasses of float and int (e.g. numpy.float64)."""
    if isinstance(value, float):
        return float(value)
    if isinstance(value, int):
        return int(value)
    raise TypeError(f"type {type(value).__name__} is not JSON serializable")


def _dumps(value: Any, field: str) -> str:
    """Compact JSON of a dict with finite numbers (orjson: ~10x faster than json on float lists)."""
    if not isinstance(value, dict):
        raise StoreError(field, f"must be a JSON object (dict), got {type(value).__name__}")
    if not _finite(value):
        raise StoreError(field, "is not JSON-serialisable with finite numbers: it holds NaN or infinity")
    try:
        return orjson.dumps(value, default=_default, option=orjson.OPT_NON_STR_KEYS).decode()
    except TypeError as exc:  # orjson.JSONEncodeError is a TypeError
        raise StoreError(field, f"is not JSON-serialisable with finite numbers: {exc}") from None


def _progress(new_state: dict[str, Any], response: dict[str, Any], default: tuple) -> tuple:
    """step, t, loglik for the indexed columns: from the new state, else the response, else ``default``."""
    def pick(key: str, cast: Callable, fallback: Any) -> Any:
        for source in (new_state, response):
            value = source.get(key)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                return cast(value)
        return fallback
    keys, casts = ("step", "t", "loglik"), (int, float, float)
    return tuple(pick(k, c, d) for k, c, d in zip(keys, casts, default, strict=True))


class SqliteSessionStore:
    """Sessions in one SQLite file; safe to share between threads and processes."""

    def __init__(self, path: str | os.PathLike, retention: int = 256, busy_timeout_ms: int = 30_000,
                 synchronous: str = "normal"):
        if not isinstance(retention, int) or retention < 1:
            raise StoreError("retention", "must be a positive integer")
        if synchronous not in _SYNCHRONOUS:
            raise StoreError("synchronous", f"must be one of {', '.join(_SYNCHRONOUS)}, got {synchronous!r}")
        self.synchronous = synchronous
        self.path = Path(path)
        self.retention = retention
        self.busy_timeout_ms = int(busy_timeout_ms)
        self._local = threading.local()
        with self._transaction() as db:
            for statement in filter(str.strip, _SCHEMA.split(";")):
                db.execute(statement)

    # -- connections ----------------------------------------------------------------
    def _connection(self) -> sqlite3.Connection:
        local = self._local
        if getattr(local, "pid", None) != os.getpid():  # a forked child must not reuse the parent's
            local.db = self._connect()
            local.pid = os.getpid()
        return local.db

    def _connect(self) -> sqlite3.Connection:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(self.path, timeout=self.busy_timeout_ms / 1000, isolation_level=None)
            db.execute(f"PRAGMA busy_timeout = {self.busy_timeout_ms}")
            if db.execute("PRAGMA journal_mode = WAL").fetchone()[0].lower() != "wal":
                raise StoreError("sessions", f"{self.path}: the filesystem does not support WAL mode")
            db.execute(f"PRAGMA synchronous = {self.synchronous.upper()}")  # see the module docstring
        except sqlite3.Error as exc:
            raise StoreError("sessions", f"cannot open session database {self.path}: {exc}") from None
        db.row_factory = sqlite3.Row
        return db

    def close(self) -> None:
        db = getattr(self._local, "db", None)
        if db is not None and getattr(self._local, "pid", None) == os.getpid():
            db.close()
        self._local = threading.local()

    def _transaction(self) -> "_Transaction":
        return _Transaction(self._connection())

    # -- records --------------------------------------------------------------------
    def create(self, model_id: str, method: str, state: dict[str, Any],
               initial_response: dict[str, Any] | None = None) -> str:
        """A new session at seq 0; returns its random url-safe id."""
        state_text = _dumps(state, "state")
        initial_text = _dumps(initial_response or {}, "initial_response")
        session_id = secrets.token_urlsafe(16)
        now = _utc_now()
        step, t, loglik = _progress(state, initial_response or {}, (0, 0.0, None))
        with self._transaction() as db:
            db.execute("INSERT INTO sessions VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                       (session_id, str(model_id), str(method), state_text, initial_text, 0, step, t,
                        loglik, now, now, 0))
        return session_id

    def get(self, session_id: str) -> SessionRecord:
        row = self._read(session_id)
        if row is None:
            raise NotFound("session", f"no session {session_id!r}")
        return row

    def _read(self, session_id: str) -> SessionRecord | None:
        try:
            query = self._connection().execute("SELECT * FROM sessions WHERE id = ?", (str(session_id),))
            row = query.fetchone()
        except sqlite3.Error as exc:
            raise StoreError("sessions", f"cannot read session: {exc}") from None
        if row is None:
            return None
        return SessionRecord(
            id=row["id"], model_id=row["model_id"], method=row["method"], state=orjson.loads(row["state"]),
            initial_response=orjson.loads(row["initial_response"]), next_seq=row["next_seq"],
            step=row["step"],
            t=row["t"], loglik=row["loglik"], created=row["created"], updated=row["updated"],
            version=row["version"])

    def delete(self, session_id: str) -> None:
        with self._transaction() as db:
            deleted = db.execute("DELETE FROM sessions WHERE id = ?", (str(session_id),)).rowcount
            db.execute("DELETE FROM chunks WHERE session_id = ?", (str(session_id),))
        if not deleted:
            raise NotFound("session", f"no session {session_id!r}")

    def count(self) -> int:
        return int(self._connection().execute("SELECT COUNT(*) FROM sessions").fetchone()[0])

    def ids(self) -> list[str]:
        return [r[0] for r in self._connection().execute("SELECT id FROM sessions ORDER BY created")]

    # -- chunks ---------------------------------------------------------------------
    def stored_response(self, session_id: str, seq: int) -> dict[str, Any]:
        """The response of an applied chunk (Conflict if it is older than the retention window)."""
        return orjson.loads(self._stored_text(session_id, seq))

    def _stored_text(self, session_id: str, seq: int) -> str:
        row = self._connection().execute("SELECT response FROM chunks WHERE session_id = ? AND seq = ?",
                                         (str(session_id), seq)).fetchone()
        if row is None:
            oldest = self._connection().execute("SELECT MIN(seq) FROM chunks WHERE session_id = ?",
                                                (str(session_id),)).fetchone()[0]
            raise Conflict("seq", f"chunk {seq} was applied but its response is no longer kept "
                                  f"(the last {self.retention} are; oldest kept: {oldest})")
        return row[0]

    def apply_chunk(self, session_id: str, seq: int, compute: Compute,
                    encoded: bool = False) -> tuple[Any, bool]:
        """Apply chunk ``seq`` exactly once; returns (response, replayed).

        ``encoded``: the response as the JSON text that is stored (a replay sends the same bytes)."""
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise StoreError("seq", f"must be a non-negative integer, got {seq!r}")
        for _ in range(_MAX_ATTEMPTS):
            record = self.get(session_id)
            if seq < record.next_seq:
                text = self._stored_text(session_id, seq)
                return (text if encoded else orjson.loads(text)), True
            if seq > record.next_seq:
                raise Conflict("seq", f"expected seq {record.next_seq} (the next chunk), got {seq}; "
                                      "nothing was applied")
            new_state, response = compute(record.state)  # outside any lock: sessions run in parallel
            text = self._commit(record, seq, new_state, response)
            if text is not None:
                if encoded:
                    return text, False
                return (orjson.loads(text) if isinstance(response, str) else response), False
        raise Conflict("session", f"session {session_id} is updated too often concurrently; retry")

    def _commit(self, old: SessionRecord, seq: int, new_state: dict, response: dict | str) -> str | None:
        """The stored response text, or None when another writer moved the session on."""
        state_text = _dumps(new_state, "state")
        if isinstance(response, str):
            response_text, response = response, {}  # encoded by the caller, who vouches for it
        else:
            response_text = _dumps(response, "response")
        step, t, loglik = _progress(new_state, response, (old.step, old.t, old.loglik))
        with self._transaction() as db:
            changed = db.execute(
                "UPDATE sessions SET state = ?, next_seq = ?, step = ?, t = ?, loglik = ?, updated = ?, "
                "version = version + 1 WHERE id = ? AND version = ?",
                (state_text, seq + 1, step, t, loglik, _utc_now(), old.id, old.version),
            ).rowcount
            if not changed:
                return None  # someone else moved the session on: re-read
            db.execute("INSERT OR REPLACE INTO chunks VALUES (?,?,?)", (old.id, seq, response_text))
            db.execute("DELETE FROM chunks WHERE session_id = ? AND seq <= ?", (old.id, seq - self.retention))
        return response_text


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT (ROLLBACK on error); sqlite errors become StoreError."""

    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self) -> sqlite3.Connection:
        try:
            self.db.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as exc:
            raise StoreError("sessions", f"cannot start a transaction: {exc}") from None
        return self.db

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                self.db.execute("COMMIT")
                return False
            except sqlite3.Error as err:
                self.db.execute("ROLLBACK")
                raise StoreError("sessions", f"cannot commit: {err}") from None
        self.db.execute("ROLLBACK")
        if isinstance(exc, sqlite3.Error):
            raise StoreError("sessions", f"database error: {exc}") from None
        return False
