"""SQLite session store (the embedded default :class:`storage.protocols.SessionStore`): filter states
advanced by numbered chunks, each applied exactly once — the semantics (replays, gaps, retention,
batches of chunks, idle expiry) are storage/session_base.py's; this module is how SQLite holds the
rows.  A file written before a column existed gets it when opened (``options`` ``{}``, a stored
response's ``size`` computed when needed).  Deleted sessions give their pages back to the file
system (``auto_vacuum = INCREMENTAL`` and an incremental vacuum after each delete).  The file is
shared by several processes (WAL mode, busy timeout); each thread of each process has its own
connection.

Faults (docs/reliability.md).  A full disk makes the transaction fail and roll back: nothing is
stored, :class:`Unavailable` (with retry_after) is raised and the next attempt succeeds once there
is space.  The file removed, replaced, truncated or its write-ahead log overwritten under a running
server is detected (the file's and the log's identity, the header's page count against the file size and
the WAL header's checksum after every commit, read through descriptors kept open so that no lock
of SQLite's is ever dropped (storage/sqlite_files.py); a generation counter that must never go back
at the start of every write; SQLite's corruption errors): the store then refuses every operation
(:class:`Unavailable` without retry_after) and :meth:`health` reports why, so that no chunk is
acknowledged that a restart would lose.  A look that a checkpoint in flight can explain is looked at
again and, for a short file, judged by SQLite's quick_check before anything is declared: a healthy
database under load never fails (a doubt SQLite cannot settle at once costs a 503 with Retry-After).
The store holds one connection for its whole life, so another process closing its own connection
never takes itself for the last one and deletes the log; a log that vanishes anyway is damage.
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

import logging
import os
import sqlite3
import threading
import time
from pathlib import Path

from .errors import StoreError, Unavailable
from .session_base import (  # noqa: F401 - re-exported: what callers imported from here before
    ADDED_COLUMNS,
    SESSION_FIELDS,
    Compute,
    ComputeMany,
    SessionRecord,
    SessionStoreBase,
    schema,
)
from .sqlite_files import FileWatch, Finding

_SCHEMA = schema("INTEGER", "REAL", " WITHOUT ROWID") + """;
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value INTEGER NOT NULL
);
INSERT OR IGNORE INTO meta VALUES ('generation', 0);
"""
_DOUBT_PAUSES = (0.01, 0.05, 0.25)  # seconds between looks at a doubt before it is taken as real
DISK_FULL_RETRY_S = 10
_SYNCHRONOUS = ("normal", "full")


class SqliteSessionStore(SessionStoreBase):
    """Sessions in one SQLite file; safe to share between threads and processes."""

    _db_errors = (sqlite3.Error,)
    _INSERT_CHUNK = ("INSERT OR REPLACE INTO chunks (session_id, seq, response, digest, stored, size, "
                     "checksum) VALUES (?,?,?,?,?,?,?)")

    def __init__(self, path: str | os.PathLike, retention: int = 16, busy_timeout_ms: int = 30_000,
                 synchronous: str = "normal", retention_bytes: int = 256 * 1024,
                 retention_seconds: float = 86_400.0, idle_expiry: float | None = None):
        self._configure(retention, retention_bytes, retention_seconds, idle_expiry)
        if synchronous not in _SYNCHRONOUS:
            raise StoreError("synchronous", f"must be one of {', '.join(_SYNCHRONOUS)}, got {synchronous!r}")
        self.synchronous = synchronous
        self.path = Path(path)
        self.busy_timeout_ms = int(busy_timeout_ms)
        self._local = threading.local()
        self._failure: str | None = None  # why the store refuses everything (removed, damaged)
        self._generation = 0  # the highest generation this process has seen committed
        self._watch: FileWatch | None = None
        self._create_schema()
        # One connection held for the store's life: while it is open, no other process can be "the last
        # connection" that checkpoints and deletes the write-ahead log under this one.
        self._anchor: sqlite3.Connection | None = self._connect()
        self._watch = FileWatch(self.path)
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
            # columns added since a file was written (ALTER TABLE ... ADD COLUMN, in this transaction)
            for table, column, kind in ADDED_COLUMNS:
                present = {row[1] for row in db.execute(f"PRAGMA table_info({table})")}
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
        """Close this thread's connection, the anchor and (when no other store of this process watches
        the file) the watch's descriptors."""
        db = getattr(self._local, "db", None)
        if db is not None and getattr(self._local, "pid", None) == os.getpid():
            db.close()
        self._local = threading.local()
        if self._anchor is not None:
            self._anchor.close()
            self._anchor = None
        if self._watch is not None:
            self._watch.release()
            self._watch = None

    def _query(self, sql: str, args: tuple = ()) -> sqlite3.Cursor:
        return self._connection().execute(sql, args)

    def _check_available(self) -> None:
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)

    def _transaction(self, write: bool = True) -> "_Transaction":
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)
        return _Transaction(self, self._connection(), write)

    # -- integrity ------------------------------------------------------------------
    def _watched(self) -> FileWatch:
        """The watch of the database file and its log (opened again after :meth:`close`)."""
        if self._watch is None:
            self._watch = FileWatch(self.path)
        return self._watch

    @staticmethod
    def _read_generation(db: sqlite3.Connection) -> int:
        row = db.execute("SELECT value FROM meta WHERE key = 'generation'").fetchone()
        return int(row[0]) if row is not None else 0

    def fail(self, reason: str) -> Unavailable:
        """Refuse every operation from now on (the file cannot be trusted); the error to raise.  The
        message a client sees names no server path; the critical log line does."""
        if self._failure is None:
            self._failure = (f"the session database {reason}; no chunk is acknowledged until it is restored "
                             "and the server restarted")
            _log_critical(f"{self.path}: {self._failure}")
        return Unavailable("sessions", self._failure)

    def verify_file(self) -> None:
        """Cheap checks of the files after a commit (a few µs, no descriptor opened or closed): still
        the files we opened, the database not shorter than its header's page count, the write-ahead
        log's header intact.  A certain finding fails the store; a doubt is confirmed first
        (:meth:`_settle`).  Raises Unavailable."""
        if self._failure is not None:
            raise Unavailable("sessions", self._failure)
        finding = self._settle(self._watched().look())
        if finding is not None:
            raise self.fail(finding.text)

    def _settle(self, finding: Finding | None) -> Finding | None:
        """A doubt looked at again: a checkpoint of another thread or process writes the header's new
        page count before it grows the file, and rewrites the log's header when it restarts it, so
        the same doubt must last ~0.3 s; a short file is then judged by SQLite's quick_check on a
        consistent snapshot (it reads every page).  None: healthy after all; else a certain
        finding.  Unavailable with retry_after when even SQLite cannot tell now (busy)."""
        for pause in _DOUBT_PAUSES:
            if finding is None or finding.certain:
                return finding
            time.sleep(pause)
            finding = self._watched().look()
        if finding is None or finding.certain or not finding.sqlite_decides:
            return None if finding is None else Finding(finding.text, True)
        verdict = self._quick_check()
        if verdict is None:
            _log.warning("%s: the file looked short (%s) for %.2f s but SQLite's quick_check passes: a long "
                         "checkpoint, not damage", self.path, finding.text, sum(_DOUBT_PAUSES))
            return None
        return Finding(verdict, True)

    def health(self, deep: bool = False) -> str | None:
        """None when the store is usable, else why not.  ``deep`` adds SQLite's quick_check on a
        connection of its own (reads every page: for /readyz, not per request)."""
        if self._failure is not None:
            return self._failure
        try:
            finding = self._settle(self._watched().look())
            if finding is None and deep:
                verdict = self._quick_check()
                finding = None if verdict is None else Finding(verdict, True)
        except Unavailable as exc:  # SQLite could not tell now: not ready for a moment, not failed
            return exc.message
        if finding is not None:
            self.fail(finding.text)
            return self._failure
        try:
            self._check_generation(self._connection())  # a read: the generation must not have gone back
        except Unavailable:
            pass  # marked failed: reported below
        except sqlite3.Error as exc:
            return self._error(exc, "cannot read the store's generation").message
        return self._failure

    def _quick_check(self) -> str | None:
        """None when SQLite's quick_check passes, else what it found.  Through SQLite only (the close of
        its connection keeps this process's locks: SQLite defers it).  Unavailable with retry_after
        when the database is busy or locked: that says nothing about damage."""
        try:
            db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, timeout=self.busy_timeout_ms / 1000)
            try:
                result = [r[0] for r in db.execute("PRAGMA quick_check")]
            finally:
                db.close()
        except sqlite3.Error as exc:
            code = getattr(exc, "sqlite_errorcode", None)
            if code in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED) or "locked" in str(exc):
                raise Unavailable("sessions", "the session database is busy being checked; retry",
                                  retry_after=1) from None
            return f"fails SQLite's integrity check ({exc})"
        return None if result == ["ok"] else f"fails SQLite's integrity check ({'; '.join(result[:3])})"

    def _check_generation(self, db: sqlite3.Connection) -> None:
        # what this process saw committed *before* the read: a commit of another thread that lands
        # between the read and the comparison raised the seen generation after the read's snapshot
        # was taken, and was reported as lost transactions (a CI run's burst of session creation)
        seen = self._generation
        generation = self._read_generation(db)
        if generation < seen:
            raise self.fail(f"lost committed transactions (generation {generation} < {seen} "
                            "seen): it was replaced, truncated or its write-ahead log overwritten")

    def _committed(self, generation: int) -> None:
        self._generation = max(self._generation, generation)

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

_log = logging.getLogger("yauyau.storage")


def _log_critical(message: str) -> None:
    _log.critical("SESSION STORE UNUSABLE: %s", message)


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
