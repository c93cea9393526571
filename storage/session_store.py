"""SQLite session store (the embedded default :class:`storage.protocols.SessionStore`): filter states
advanced by numbered chunks, each applied exactly once.

A session holds the filter state (any JSON-able dict), ``next_seq`` (the seq the next chunk must
carry; the first chunk is seq 0), a ``version`` and its ``options`` (a JSON object the service
gives at creation, e.g. its policy on degeneracy and its outlier gate; a file written before the
column existed gets it, ``{}``, when opened).  ``apply_chunk(id, seq, compute)``:

* seq == next_seq: ``compute(state) -> (new_state, response)`` runs outside any lock, then the new
  state and the response are written in ONE transaction, only if the version is unchanged
  (optimistic concurrency); on a clash the row is re-read and either the response stored by the
  winner is returned (replayed) or the chunk is recomputed on the new state;
* seq <  next_seq: the stored response is returned (replayed, nothing applied);
* seq >  next_seq: :class:`Conflict` naming the expected seq, nothing changed.

Replays need the responses of the last few chunks only (a client that lost an answer re-sends the
chunk it sent last): per session the store keeps at most ``retention`` responses (default 16),
at most ``retention_bytes`` of them (default 256 KiB) and none older than ``retention_seconds``
(default one day), always the newest one.  Each stored chunk keeps a digest of its request, so a
re-sent seq with *different* data is refused (Conflict) instead of silently answered with the first
response.  Deleted sessions give their pages back to the file system (``auto_vacuum =
INCREMENTAL`` and an incremental vacuum after each delete).  The file is shared by several
processes (WAL mode, busy timeout); each thread of each process has its own connection.

Faults (docs/reliability.md).  A full disk makes the transaction fail and roll back: nothing is
stored, :class:`Unavailable` (with retry_after) is raised and the next attempt succeeds once there
is space.  The file removed, replaced, truncated or its write-ahead log overwritten under a running
server is detected (the file's identity, the header's page count against the file size and the
WAL header's checksum after every commit; a generation counter that must never go back at the
start of every write; SQLite's corruption errors): the store then refuses every operation
(:class:`Unavailable` without retry_after) and :meth:`health` reports why, so that no chunk is
acknowledged that a restart would lose.
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
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import orjson

from .errors import Conflict, NotFound, StoreError, Unavailable

Compute = Callable[[dict[str, Any]], tuple[dict[str, Any], dict[str, Any] | str]]
# compute_many([(index, state)]) -> per pair (new state, response) or the exception that is its answer
ComputeMany = Callable[[list[tuple[int, dict[str, Any]]]], list[Any]]

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
    version INTEGER NOT NULL,
    options TEXT NOT NULL DEFAULT '{}'
);
CREATE TABLE IF NOT EXISTS chunks (
    session_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    size INTEGER,
    digest TEXT,
    stored REAL,
    response TEXT NOT NULL,
    PRIMARY KEY (session_id, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value INTEGER NOT NULL
);
INSERT OR IGNORE INTO meta VALUES ('generation', 0);
CREATE INDEX IF NOT EXISTS sessions_updated ON sessions (updated);
"""
# added to files written before they existed (ALTER TABLE ... ADD COLUMN, in one transaction).  In a
# new file the response comes last: the retention trims read size, seq and stored of every kept
# response, and a column after a long response would be read through its overflow pages.
_CHUNK_COLUMNS = {"digest": "TEXT", "stored": "REAL", "size": "INTEGER"}
_SESSION_COLUMNS = {"options": "TEXT NOT NULL DEFAULT '{}'"}  # older sessions: no options (the defaults)
_SESSION_FIELDS = ("id", "model_id", "method", "state", "initial_response", "next_seq", "step", "t", "loglik",
                   "created", "updated", "version", "options")
_SQLITE_MAGIC = b"SQLite format 3\x00"
_WAL_MAGIC = (0x377F0682, 0x377F0683)  # little- / big-endian checksums
DISK_FULL_RETRY_S = 10
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
    options: dict[str, Any] = field(default_factory=dict)  # per-session settings, as the service stored them


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

    def __init__(self, path: str | os.PathLike, retention: int = 16, busy_timeout_ms: int = 30_000,
                 synchronous: str = "normal", retention_bytes: int = 256 * 1024,
                 retention_seconds: float = 86_400.0, idle_expiry: float | None = None):
        for name, value in (("retention", retention), ("retention_bytes", retention_bytes)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise StoreError(name, "must be a positive integer")
        if not retention_seconds > 0:
            raise StoreError("retention_seconds", "must be positive")
        if idle_expiry is not None and not idle_expiry > 0:
            raise StoreError("idle_expiry", "must be positive seconds (or None: sessions never expire)")
        self.idle_expiry = None if idle_expiry is None else float(idle_expiry)
        if synchronous not in _SYNCHRONOUS:
            raise StoreError("synchronous", f"must be one of {', '.join(_SYNCHRONOUS)}, got {synchronous!r}")
        self.synchronous = synchronous
        self.path = Path(path)
        self.retention = retention
        self.retention_bytes = retention_bytes
        self.retention_seconds = float(retention_seconds)
        self.busy_timeout_ms = int(busy_timeout_ms)
        self._local = threading.local()
        self._failure: str | None = None  # why the store refuses everything (removed, damaged)
        self._generation = 0  # the highest generation this process has seen committed
        self._identity: tuple[int, int] | None = None
        self._create_schema()
        self._identity = self._file_identity()
        self._generation = self._read_generation(self._connection())

    def _create_schema(self) -> None:
        db = self._connection()
        try:
            if db.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()[0] == 0:
                db.execute("PRAGMA auto_vacuum = INCREMENTAL")  # only takes effect on an empty file
                db.execute("VACUUM")
        except sqlite3.Error as exc:
            raise _as_store_error(exc, "cannot create the session database") from None
        with self._transaction(write=False) as db:
            for statement in filter(str.strip, _SCHEMA.split(";")):
                db.execute(statement)
            for table, columns in (("chunks", _CHUNK_COLUMNS), ("sessions", _SESSION_COLUMNS)):
                present = {row[1] for row in db.execute(f"PRAGMA table_info({table})")}
                for column, kind in columns.items():
                    if column not in present:
                        db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {kind}")

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

    def _transaction(self, write: bool = True) -> "_Transaction":
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)
        return _Transaction(self, self._connection(), write)

    # -- integrity ------------------------------------------------------------------
    def _file_identity(self) -> tuple[int, int]:
        st = os.stat(self.path)
        return st.st_dev, st.st_ino

    @staticmethod
    def _read_generation(db: sqlite3.Connection) -> int:
        row = db.execute("SELECT value FROM meta WHERE key = 'generation'").fetchone()
        return int(row[0]) if row is not None else 0

    def fail(self, reason: str) -> Unavailable:
        """Refuse every operation from now on (the file cannot be trusted); the error to raise."""
        if self._failure is None:
            self._failure = (f"the session database {self.path} {reason}; no chunk is acknowledged until it "
                             "is restored and the server restarted")
            _log_critical(self._failure)
        return Unavailable("sessions", self._failure)

    def verify_file(self) -> None:
        """Cheap checks of the file after a commit (µs): still the file we opened, not truncated below
        the page count its header states, the write-ahead log's header intact.  Raises Unavailable."""
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)
        problem = self._file_problem()
        if problem is not None:
            time.sleep(0.05)  # a checkpoint of another process may be half-way: look again once
            problem = self._file_problem()
        if problem is not None:
            raise self.fail(problem)

    def _file_problem(self) -> str | None:
        try:
            st = os.stat(self.path)
            with open(self.path, "rb") as fh:
                header = fh.read(100)
        except FileNotFoundError:
            return "was removed"
        except OSError as exc:
            return f"cannot be read ({exc})"
        if (st.st_dev, st.st_ino) != self._identity:
            return "was replaced by another file"
        if len(header) < 100 or not header.startswith(_SQLITE_MAGIC):
            return "was truncated or overwritten (no SQLite header)"
        page_size = struct.unpack(">H", header[16:18])[0]
        page_size = 65536 if page_size == 1 else page_size
        pages = struct.unpack(">I", header[28:32])[0]
        if st.st_size < pages * page_size:
            return f"was truncated ({st.st_size} bytes, its header says {pages * page_size})"
        return _wal_problem(Path(f"{self.path}-wal"))

    def health(self, deep: bool = False) -> str | None:
        """None when the store is usable, else why not.  ``deep`` adds SQLite's quick_check on a
        connection of its own (reads every page: for /readyz, not per request)."""
        if self._failure is not None:
            return self._failure
        problem = self._file_problem() or (self._quick_check() if deep else None)
        if problem is not None:
            self.fail(problem)
            return self._failure
        try:
            self._check_generation(self._connection())  # a read: the generation must not have gone back
        except Unavailable:
            pass  # marked failed: reported below
        except sqlite3.Error as exc:
            return self._error(exc, "cannot read the store's generation").message
        return self._failure

    def _quick_check(self) -> str | None:
        try:
            db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, timeout=self.busy_timeout_ms / 1000)
            try:
                result = [r[0] for r in db.execute("PRAGMA quick_check")]
            finally:
                db.close()
        except sqlite3.Error as exc:
            return f"fails SQLite's integrity check ({exc})"
        return None if result == ["ok"] else f"fails SQLite's integrity check ({'; '.join(result[:3])})"

    def _check_generation(self, db: sqlite3.Connection) -> None:
        generation = self._read_generation(db)
        if generation < self._generation:
            raise self.fail(f"lost committed transactions (generation {generation} < {self._generation} "
                            "seen): it was replaced, truncated or its write-ahead log overwritten")

    def _committed(self, generation: int) -> None:
        self._generation = max(self._generation, generation)

    # -- records --------------------------------------------------------------------
    def create(self, model_id: str, method: str, state: dict[str, Any],
               initial_response: dict[str, Any] | None = None, options: dict[str, Any] | None = None) -> str:
        """A new session at seq 0; returns its random url-safe id.  ``options``: the session's own
        settings (a JSON object with finite numbers), kept with it and returned by :meth:`get`."""
        state_text = _dumps(state, "state")
        initial_text = _dumps(initial_response or {}, "initial_response")
        options_text = _dumps(options or {}, "options")
        session_id = secrets.token_urlsafe(16)
        now = _utc_now()
        step, t, loglik = _progress(state, initial_response or {}, (0, 0.0, None))
        columns = ", ".join(_SESSION_FIELDS)
        with self._transaction() as db:
            db.execute(f"INSERT INTO sessions ({columns}) VALUES ({', '.join('?' * len(_SESSION_FIELDS))})",
                       (session_id, str(model_id), str(method), state_text, initial_text, 0, step, t,
                        loglik, now, now, 0, options_text))
        return session_id

    def get(self, session_id: str) -> SessionRecord:
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)
        row = self._read(session_id)
        if row is None:
            raise NotFound("session", f"no session {session_id!r}")
        return row

    def _read(self, session_id: str) -> SessionRecord | None:
        try:
            query = self._connection().execute("SELECT * FROM sessions WHERE id = ?", (str(session_id),))
            row = query.fetchone()
        except sqlite3.Error as exc:
            raise self._error(exc, "cannot read session") from None
        if row is None:
            return None
        return SessionRecord(
            id=row["id"], model_id=row["model_id"], method=row["method"], state=orjson.loads(row["state"]),
            initial_response=orjson.loads(row["initial_response"]), next_seq=row["next_seq"],
            step=row["step"],
            t=row["t"], loglik=row["loglik"], created=row["created"], updated=row["updated"],
            version=row["version"], options=orjson.loads(row["options"] or "{}"))

    def delete(self, session_id: str) -> None:
        with self._transaction() as db:
            deleted = db.execute("DELETE FROM sessions WHERE id = ?", (str(session_id),)).rowcount
            db.execute("DELETE FROM chunks WHERE session_id = ?", (str(session_id),))
        if not deleted:
            raise NotFound("session", f"no session {session_id!r}")
        self.reclaim()

    def reclaim(self, pages: int = 0) -> None:
        """Give free pages back to the file system (all of them when ``pages`` is 0); the file
        shrinks at the next checkpoint of the write-ahead log."""
        try:
            # executescript steps the pragma to completion (execute frees one page per step taken)
            self._connection().executescript(f"PRAGMA incremental_vacuum({int(pages)});")
        except sqlite3.Error as exc:
            raise self._error(exc, "cannot reclaim free pages") from None

    def _error(self, exc: sqlite3.Error, what: str) -> StoreError:
        error = _as_store_error(exc, what)
        if isinstance(error, Unavailable) and error.retry_after is None:
            return self.fail(f"is damaged ({exc})")
        return error

    def count(self) -> int:
        return int(self._connection().execute("SELECT COUNT(*) FROM sessions").fetchone()[0])

    def ids(self) -> list[str]:
        return [r[0] for r in self._connection().execute("SELECT id FROM sessions ORDER BY created")]

    # -- lifecycle ------------------------------------------------------------------
    def list_sessions(self, limit: int = 100, after: str | None = None,
                      model_id: str | None = None) -> list[dict[str, Any]]:
        """A page of sessions (no states), by id: those after ``after`` (the last id of the previous
        page), of ``model_id`` if given."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= 10_000:
            raise StoreError("limit", f"must be an integer in [1, 10000], got {limit!r}")
        which = " AND model_id = ?" if model_id is not None else ""
        query = ("SELECT id, model_id, method, next_seq, step, t, loglik, created, updated FROM sessions "
                 f"WHERE id > ?{which} ORDER BY id LIMIT ?")
        args = (after or "", *([str(model_id)] if model_id is not None else []), limit)
        try:
            rows = self._connection().execute(query, args).fetchall()
        except sqlite3.Error as exc:
            raise self._error(exc, "cannot list sessions") from None
        return [dict(row) for row in rows]

    def expire(self, idle_seconds: float | None = None, now: float | None = None) -> int:
        """Delete the sessions not updated for ``idle_seconds`` (default: the store's ``idle_expiry``)
        with their stored responses, give the pages back; how many went.  A session that a chunk is
        being applied to is never among them: a chunk that finds its session older than half the
        expiry touches it before computing (:meth:`_keep_alive`)."""
        idle = self.idle_expiry if idle_seconds is None else float(idle_seconds)
        if idle is None:
            return 0
        cutoff = _dt.datetime.fromtimestamp((time.time() if now is None else now) - idle, _dt.timezone.utc)
        stamp = cutoff.isoformat(timespec="milliseconds")
        with self._transaction() as db:
            db.execute("DELETE FROM chunks WHERE session_id IN (SELECT id FROM sessions WHERE updated < ?)",
                       (stamp,))
            gone = db.execute("DELETE FROM sessions WHERE updated < ?", (stamp,)).rowcount
        if gone:
            self.reclaim()
        return int(gone)

    def _keep_alive(self, record: SessionRecord) -> None:
        """Touch a session that is older than half the idle expiry before a chunk computes on it, so
        that :meth:`expire` cannot remove it mid-chunk (NotFound if it expired just before)."""
        if self.idle_expiry is None:
            return
        updated = _dt.datetime.fromisoformat(record.updated).timestamp()
        if time.time() - updated <= self.idle_expiry / 2:
            return
        with self._transaction() as db:
            touched = db.execute("UPDATE sessions SET updated = ? WHERE id = ?",
                                 (_utc_now(), record.id)).rowcount
        if not touched:
            raise NotFound("session", f"no session {record.id!r} (it expired)")

    # -- chunks ---------------------------------------------------------------------
    def stored_response(self, session_id: str, seq: int) -> dict[str, Any]:
        """The response of an applied chunk (Conflict if it is older than the retention window)."""
        return orjson.loads(self._stored_text(session_id, seq))

    def _stored_text(self, session_id: str, seq: int, digest: str | None = None) -> str:
        query = "SELECT response, digest FROM chunks WHERE session_id = ? AND seq = ?"
        row = self._connection().execute(query, (str(session_id), seq)).fetchone()
        if row is not None and digest is not None and row[1] is not None and row[1] != digest:
            raise Conflict("seq", f"chunk {seq} was already applied with different data; nothing was applied "
                                  "(send new data with the next seq, or re-send chunk {seq} unchanged)"
                           .replace("{seq}", str(seq)))
        if row is None:
            oldest = self._connection().execute("SELECT MIN(seq) FROM chunks WHERE session_id = ?",
                                                (str(session_id),)).fetchone()[0]
            raise Conflict("seq", f"chunk {seq} was applied but its response is no longer kept "
                                  f"(replays are kept for the last {self.retention} chunks, at most "
                                  f"{self.retention_bytes} bytes and {self.retention_seconds:g} s; "
                                  f"oldest kept: {oldest})")
        return row[0]

    def apply_chunk(self, session_id: str, seq: int, compute: Compute,
                    encoded: bool = False, digest: str | None = None) -> tuple[Any, bool]:
        """Apply chunk ``seq`` exactly once; returns (response, replayed).

        ``encoded``: the response as the JSON text that is stored (a replay sends the same bytes).
        ``digest``: a digest of the request; a replay whose digest differs is a Conflict."""
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise StoreError("seq", f"must be a non-negative integer, got {seq!r}")
        for _ in range(_MAX_ATTEMPTS):
            record = self.get(session_id)
            if seq < record.next_seq:
                text = self._stored_text(session_id, seq, digest)
                return (text if encoded else orjson.loads(text)), True
            if seq > record.next_seq:
                raise Conflict("seq", f"expected seq {record.next_seq} (the next chunk), got {seq}; "
                                      "nothing was applied")
            self._keep_alive(record)
            new_state, response = compute(record.state)  # outside any lock: sessions run in parallel
            text = self._commit(record, seq, new_state, response, digest)
            if text is not None:
                if encoded:
                    return text, False
                return (orjson.loads(text) if isinstance(response, str) else response), False
        raise Conflict("session", f"session {session_id} is updated too often concurrently; retry")

    def apply_chunks(self, requests: list[tuple[str, int, str | None]], compute_many: ComputeMany,
                     encoded: bool = False, records: list[Any] | None = None) -> list[Any]:
        """Several chunks of *different* sessions at once, each exactly as :meth:`apply_chunk` would
        apply it: [(response, replayed) or the StoreError of that chunk].

        ``requests`` are (session id, seq, digest).  Replays and gaps are answered per chunk; the
        others' (index in ``requests``, state) pairs go to ``compute_many(pairs) -> [(new state,
        response) or an exception]`` in one call (what lets the service step them together), and
        their results are written in ONE transaction (one commit for the lot).  An exception that
        ``compute_many`` returns for a chunk is that chunk's answer (nothing stored for it); a chunk
        whose session another writer moved on meanwhile is applied again alone.  A failed
        transaction fails every chunk it held (nothing stored, each raises as apply_chunk would).
        ``records``: the sessions as the caller just read them (:meth:`get`), to save a read each; a
        stale one is harmless (a gap it shows is read again, a session moved on is a clash)."""
        out: list[Any] = [None] * len(requests)
        pending: list[tuple[int, SessionRecord]] = []
        seen: set[str] = set()
        for i, (session_id, seq, digest) in enumerate(requests):
            if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
                out[i] = StoreError("seq", f"must be a non-negative integer, got {seq!r}")
                continue
            if session_id in seen:
                raise StoreError("requests", f"session {session_id} appears twice: one chunk per session")
            seen.add(session_id)
            try:
                given = records[i] if records is not None else None
                record = given if given is not None else self.get(session_id)
                if seq > record.next_seq and given is not None:  # maybe stale: read it again
                    record = self.get(session_id)
                if seq < record.next_seq:
                    text = self._stored_text(session_id, seq, digest)
                    out[i] = (text if encoded else orjson.loads(text)), True
                elif seq > record.next_seq:
                    raise Conflict("seq", f"expected seq {record.next_seq} (the next chunk), got {seq}; "
                                          "nothing was applied")
                else:
                    self._keep_alive(record)
                    pending.append((i, record))
            except StoreError as exc:
                out[i] = exc
        if not pending:
            return out
        computed = compute_many([(i, record.state) for i, record in pending])
        rows: list[tuple[int, SessionRecord, tuple, Any]] = []
        for (i, record), result in zip(pending, computed, strict=True):
            if isinstance(result, BaseException):
                out[i] = result
                continue
            try:
                rows.append((i, record, self._row(record, result[0], result[1]), result[1]))
            except StoreError as exc:
                out[i] = exc
        clashes: list[int] = []
        try:
            with self._transaction() as db:
                for i, record, row, _ in rows:
                    seq, digest = requests[i][1], requests[i][2]
                    if not self._write(db, record, seq, row, digest):
                        clashes.append(i)
        except StoreError as exc:
            for i, _, _, _ in rows:
                out[i] = exc
            return out
        for i, _, row, response in rows:
            if i not in clashes:
                text = row[1]
                out[i] = (text if encoded else orjson.loads(text) if isinstance(response, str) else response,
                          False)
        for i in clashes:  # another writer moved the session on: again, alone
            session_id, seq, digest = requests[i]

            def compute(state: dict[str, Any], i: int = i) -> tuple[dict[str, Any], Any]:
                result = compute_many([(i, state)])[0]
                if isinstance(result, BaseException):
                    raise result
                return result

            try:
                out[i] = self.apply_chunk(session_id, seq, compute, encoded=encoded, digest=digest)
            except Exception as exc:  # noqa: BLE001 - the chunk's own answer, as compute_many gives it
                out[i] = exc
        return out

    def _row(self, old: SessionRecord, new_state: dict, response: dict | str) -> tuple:
        """(state text, response text, step, t, loglik) of a chunk's result (StoreError if not storable)."""
        state_text = _dumps(new_state, "state")
        if isinstance(response, str):
            response_text, response = response, {}  # encoded by the caller, who vouches for it
        else:
            response_text = _dumps(response, "response")
        step, t, loglik = _progress(new_state, response, (old.step, old.t, old.loglik))
        return state_text, response_text, step, t, loglik

    def _write(self, db: sqlite3.Connection, old: SessionRecord, seq: int, row: tuple,
               digest: str | None) -> bool:
        """Store a chunk's row in the open transaction; False when another writer moved the session on."""
        state_text, response_text, step, t, loglik = row
        changed = db.execute(
            "UPDATE sessions SET state = ?, next_seq = ?, step = ?, t = ?, loglik = ?, updated = ?, "
            "version = version + 1 WHERE id = ? AND version = ?",
            (state_text, seq + 1, step, t, loglik, _utc_now(), old.id, old.version),
        ).rowcount
        if not changed:
            return False
        now = time.time()
        db.execute("INSERT OR REPLACE INTO chunks (session_id, seq, response, digest, stored, size) "
                   "VALUES (?,?,?,?,?,?)", (old.id, seq, response_text, digest, now, len(response_text)))
        self._trim(db, old.id, seq, now)
        return True

    def _commit(self, old: SessionRecord, seq: int, new_state: dict, response: dict | str,
                digest: str | None = None) -> str | None:
        """The stored response text, or None when another writer moved the session on."""
        row = self._row(old, new_state, response)
        with self._transaction() as db:
            if not self._write(db, old, seq, row, digest):
                return None  # someone else moved the session on: re-read
        return row[1]

    def _trim(self, db: sqlite3.Connection, session_id: str, seq: int, now: float) -> None:
        """Keep the newest chunk and, before it, what fits in retention (count), retention_bytes
        (the newest first) and retention_seconds."""
        db.execute("DELETE FROM chunks WHERE session_id = ? AND seq < ? AND (seq <= ? OR stored < ?)",
                   (session_id, seq, seq - self.retention, now - self.retention_seconds))
        db.execute(
            "DELETE FROM chunks WHERE session_id = ? AND seq < ? AND seq IN (SELECT seq FROM (SELECT seq, "
            "SUM(COALESCE(size, LENGTH(response))) OVER (ORDER BY seq DESC) AS total FROM chunks "
            "WHERE session_id = ?) "
            "WHERE total > ?)", (session_id, seq, session_id, self.retention_bytes))


def _log_critical(message: str) -> None:
    import logging

    logging.getLogger("yauyau.storage").critical("SESSION STORE UNUSABLE: %s", message)


def _as_store_error(exc: sqlite3.Error, what: str) -> StoreError:
    """A full disk is Unavailable with retry_after (space may come back); corruption is Unavailable
    without (an operator must act); anything else a StoreError."""
    code = getattr(exc, "sqlite_errorcode", None)
    text = str(exc)
    if code == sqlite3.SQLITE_FULL or "disk is full" in text or "No space left" in text:
        return Unavailable("sessions", f"{what}: the disk is full (nothing was stored; retry when there is "
                                       "space)", retry_after=DISK_FULL_RETRY_S)
    damaged = "malformed" in text or "not a database" in text
    if code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB) or damaged:
        return Unavailable("sessions", f"{what}: the database is damaged ({text})")
    if code == sqlite3.SQLITE_IOERR or (code is not None and code & 0xFF == sqlite3.SQLITE_IOERR):
        return Unavailable("sessions", f"{what}: input/output error ({text}); nothing was stored",
                           retry_after=DISK_FULL_RETRY_S)
    return StoreError("sessions", f"{what}: {text}")


def _wal_problem(wal: Path) -> str | None:
    """The write-ahead log's 32-byte header: magic, and its checksum (SQLite's wal.c algorithm)."""
    try:
        with open(wal, "rb") as fh:
            header = fh.read(32)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"has an unreadable write-ahead log ({exc})"
    if len(header) == 0:
        return None  # reset after a checkpoint
    if len(header) < 32:
        return "has a truncated write-ahead log header"
    magic = struct.unpack(">I", header[:4])[0]
    if magic not in _WAL_MAGIC:
        return "has an overwritten write-ahead log (bad magic number)"
    order = ">" if magic & 1 else "<"
    words = struct.unpack(f"{order}6I", header[:24])
    s0 = s1 = 0
    for i in range(0, 6, 2):
        s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
        s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
    if (s0, s1) != struct.unpack(">2I", header[24:32]):
        return "has an overwritten write-ahead log (header checksum)"
    return None


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT (ROLLBACK on error); sqlite errors become StoreError.

    A write transaction checks that the store's generation did not go back, bumps it, and after
    the COMMIT verifies the file (:meth:`SqliteSessionStore.verify_file`) before the caller may
    acknowledge anything."""

    def __init__(self, store: SqliteSessionStore, db: sqlite3.Connection, write: bool = True):
        self.store, self.db, self.write = store, db, write
        self.generation = 0

    def __enter__(self) -> sqlite3.Connection:
        try:
            self.db.execute("BEGIN IMMEDIATE")
            if self.write:
                self.store._check_generation(self.db)
                bump = "UPDATE meta SET value = value + 1 WHERE key = 'generation' RETURNING value"
                self.generation = self.db.execute(bump).fetchone()[0]
        except sqlite3.Error as exc:
            self._rollback()
            raise self.store._error(exc, "cannot start a transaction") from None
        except BaseException:
            self._rollback()
            raise
        return self.db

    def _rollback(self) -> None:
        if self.db.in_transaction:  # SQLite already rolled back after SQLITE_FULL and some I/O errors
            try:
                self.db.execute("ROLLBACK")
            except sqlite3.Error:
                pass

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                self.db.execute("COMMIT")
            except sqlite3.Error as err:
                self._rollback()
                raise self.store._error(err, "cannot commit") from None
            if self.write:
                self.store._committed(self.generation)
                self.store.verify_file()
            return False
        self._rollback()
        if isinstance(exc, sqlite3.Error):
            raise self.store._error(exc, "database error") from None
        return False
