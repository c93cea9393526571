"""What every session store does, whatever holds its rows: filter states advanced by numbered
chunks, each applied exactly once (:class:`SessionStoreBase`).

A session holds the filter state (any JSON-able dict), ``next_seq`` (the seq the next chunk must
carry; the first chunk is seq 0), a ``version`` and its ``options`` (a JSON object the service
gives at creation, e.g. its policy on degeneracy and its outlier gate).  ``apply_chunk(id, seq,
compute)``:

* seq == next_seq: ``compute(state) -> (new_state, response)`` runs outside any lock, then the new
  state and the response are written in ONE transaction, only if the version is unchanged
  (optimistic concurrency: no lost update, whichever process or host wrote meanwhile); on a clash
  the row is re-read and either the response stored by the winner is returned (replayed) or the
  chunk is recomputed on the new state;
* seq <  next_seq: the stored response is returned (replayed, nothing applied);
* seq >  next_seq: :class:`Conflict` naming the expected seq, nothing changed.

``apply_chunks`` does the same for chunks of several sessions with one ``compute_many`` call and one
transaction (the service's micro-batches).  Replays need the responses of the last few chunks only:
per session the store keeps at most ``retention`` responses (default 16), at most
``retention_bytes`` of them (default 256 KiB) and none older than ``retention_seconds`` (default one
day), always the newest one.  Each stored chunk keeps a digest of its request, so a re-sent seq
with *different* data is refused (Conflict).  Sessions idle for ``idle_expiry`` seconds are deleted
by :meth:`expire` (never one a chunk is being applied to).  ``apply_chunk(..., encoded=True)``
returns the response as the JSON text stored; ``compute`` may also return the response already
encoded (a ``str`` of a JSON object with finite numbers, stored as given).

A store is this class plus how it reaches its rows: ``_transaction()`` (a context giving an object
with ``execute(sql, args)``), ``_query(sql, args)`` for reads (rows by column name), ``_db_errors``,
``_error``, ``_INSERT_CHUNK`` and ``reclaim``.  The SQL here uses ``?`` placeholders and the columns
of storage/session_store.py's schema.  Storage knows files and rows, not math.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import logging
import math
import secrets
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import orjson

from .errors import Conflict, NotFound, StoreError, Unavailable

Compute = Callable[[dict[str, Any]], tuple[dict[str, Any], dict[str, Any] | str]]
# compute_many([(index, state)]) -> per pair (new state, response) or the exception that is its answer
ComputeMany = Callable[[list[tuple[int, dict[str, Any]]]], list[Any]]
SESSION_FIELDS = ("id", "model_id", "method", "state", "initial_response", "next_seq", "step", "t", "loglik",
                  "created", "updated", "version", "options", "owner", "checksum")
# columns added after a store's first release: (table, column, SQL type), added when a store opens a
# database written before them (a row written before has NULL there: it cannot be verified)
ADDED_COLUMNS = (("chunks", "digest", "TEXT"), ("chunks", "stored", "REAL"), ("chunks", "size", "INTEGER"),
                 ("chunks", "checksum", "TEXT"), ("sessions", "options", "TEXT NOT NULL DEFAULT '{}'"),
                 ("sessions", "owner", "TEXT"), ("sessions", "checksum", "TEXT"))
MAX_ATTEMPTS = 100


def schema(integer: str, real: str, chunks_suffix: str = "") -> str:
    """The two tables every store keeps (statements separated by ``;``), in its SQL types.  The
    response comes last in a chunk row: the retention trims read size, seq and stored of every kept
    response, and a column after a long text may be read through its overflow pages."""
    return f"""
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    model_id TEXT NOT NULL,
    method TEXT NOT NULL,
    state TEXT NOT NULL,
    initial_response TEXT NOT NULL,
    next_seq {integer} NOT NULL,
    step {integer} NOT NULL,
    t {real} NOT NULL,
    loglik {real},
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    version {integer} NOT NULL,
    options TEXT NOT NULL DEFAULT '{{}}',
    owner TEXT,
    checksum TEXT
);
CREATE TABLE IF NOT EXISTS chunks (
    session_id TEXT NOT NULL,
    seq {integer} NOT NULL,
    size INTEGER,
    digest TEXT,
    stored {real},
    checksum TEXT,
    response TEXT NOT NULL,
    PRIMARY KEY (session_id, seq)
){chunks_suffix};
CREATE INDEX IF NOT EXISTS sessions_updated ON sessions (updated)
"""


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
    owner: str | None = None  # the tenant that created it (None: no tenant, e.g. made before tenants)


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


def checksum(*texts: str) -> str:
    """The checksum a row is stored with (BLAKE2b, 128 bits, of its texts in order): a row changed
    outside the store (an edit, a bad restore, a flipped byte) no longer matches it."""
    h = hashlib.blake2b(digest_size=16)
    for text in texts:
        h.update(text.encode())
        h.update(b"\x00")
    return h.hexdigest()


def session_checksum(session_id: str, model_id: str, method: str, next_seq: int, state_text: str,
                     options_text: str, owner: str | None) -> str:
    """A session row's checksum: its state bound to the session, its model, method, options and owner
    and to the seq it is at (an older state written back, another session's, or the session handed to
    another tenant fails it too)."""
    return checksum(session_id, model_id, method, str(int(next_seq)), state_text, options_text,
                    "no owner" if owner is None else f"owner {owner}")


def _damaged(what: str) -> Unavailable:
    """A row that fails its checksum or is not JSON: 503 (no retry: an operator must restore it) and
    the store's critical log; the other sessions go on."""
    logging.getLogger("yauyau.storage").critical("SESSION STORE DAMAGED: %s", what)
    return Unavailable("sessions", f"{what}; it is not used (restore the database from a backup, or delete "
                                   "the session and start a new one)")


class SessionStoreBase:
    """The exactly-once semantics over any SQL store (module docstring)."""

    retention: int
    retention_bytes: int
    retention_seconds: float
    idle_expiry: float | None
    _db_errors: tuple[type[BaseException], ...] = ()
    _INSERT_CHUNK = ""

    def _configure(self, retention: int, retention_bytes: int, retention_seconds: float,
                   idle_expiry: float | None) -> None:
        """Check and keep the retention of stored responses and the idle expiry of sessions."""
        for name, value in (("retention", retention), ("retention_bytes", retention_bytes)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise StoreError(name, "must be a positive integer")
        if not retention_seconds > 0:
            raise StoreError("retention_seconds", "must be positive")
        if idle_expiry is not None and not idle_expiry > 0:
            raise StoreError("idle_expiry", "must be positive seconds (or None: sessions never expire)")
        self.retention, self.retention_bytes = retention, retention_bytes
        self.retention_seconds = float(retention_seconds)
        self.idle_expiry = None if idle_expiry is None else float(idle_expiry)

    def _check_available(self) -> None:
        """Raise Unavailable when the store refuses everything (a damaged file); else nothing."""

    def reclaim(self, pages: int = 0) -> None:
        """Give the space of deleted rows back (where the store can)."""

    # -- records --------------------------------------------------------------------
    def create(self, model_id: str, method: str, state: dict[str, Any],
               initial_response: dict[str, Any] | None = None, options: dict[str, Any] | None = None,
               owner: str | None = None) -> str:
        """A new session at seq 0; returns its random url-safe id.  ``options``: the session's own
        settings (a JSON object with finite numbers), kept with it and returned by :meth:`get`;
        ``owner``: the tenant it belongs to (None: no tenant)."""
        if owner is not None and not isinstance(owner, str):
            raise StoreError("owner", f"must be a tenant's name (text) or None, got {type(owner).__name__}")
        state_text = _dumps(state, "state")
        initial_text = _dumps(initial_response or {}, "initial_response")
        options_text = _dumps(options or {}, "options")
        session_id = secrets.token_urlsafe(16)
        now = _utc_now()
        step, t, loglik = _progress(state, initial_response or {}, (0, 0.0, None))
        columns = ", ".join(SESSION_FIELDS)
        sealed = session_checksum(session_id, str(model_id), str(method), 0, state_text, options_text, owner)
        with self._transaction() as db:
            db.execute(f"INSERT INTO sessions ({columns}) VALUES ({', '.join('?' * len(SESSION_FIELDS))})",
                       (session_id, str(model_id), str(method), state_text, initial_text, 0, step, t,
                        loglik, now, now, 0, options_text, owner, sealed))
        return session_id

    def get(self, session_id: str) -> SessionRecord:
        self._check_available()
        row = self._read(session_id)
        if row is None:
            raise NotFound("session", f"no session {session_id!r}")
        return row

    def _read(self, session_id: str) -> SessionRecord | None:
        try:
            row = self._query("SELECT * FROM sessions WHERE id = ?", (str(session_id),)).fetchone()
        except self._db_errors as exc:
            raise self._error(exc, "cannot read session") from None
        if row is None:
            return None
        options_text = row["options"] or "{}"
        sealed = row["checksum"]
        sid = row["id"]
        expected = session_checksum(sid, row["model_id"], row["method"], row["next_seq"], row["state"],
                                    options_text, row["owner"])
        if sealed is not None and sealed != expected:
            raise _damaged(f"session {sid} was changed outside the service (its row fails its checksum)")
        try:
            return SessionRecord(
                id=sid, model_id=row["model_id"], method=row["method"], state=orjson.loads(row["state"]),
                initial_response=orjson.loads(row["initial_response"]), next_seq=row["next_seq"],
                step=row["step"],
                t=row["t"], loglik=row["loglik"], created=row["created"], updated=row["updated"],
                version=row["version"], options=orjson.loads(options_text), owner=row["owner"])
        except orjson.JSONDecodeError:
            raise _damaged(f"session {sid} is damaged in the store (its row is not valid JSON)") from None

    def delete(self, session_id: str) -> None:
        with self._transaction() as db:
            deleted = db.execute("DELETE FROM sessions WHERE id = ?", (str(session_id),)).rowcount
            db.execute("DELETE FROM chunks WHERE session_id = ?", (str(session_id),))
        if not deleted:
            raise NotFound("session", f"no session {session_id!r}")
        self.reclaim()

    def count(self) -> int:
        return int(self._query("SELECT COUNT(*) AS n FROM sessions").fetchone()["n"])

    def ids(self) -> list[str]:
        return [r["id"] for r in self._query("SELECT id FROM sessions ORDER BY created").fetchall()]

    # -- lifecycle ------------------------------------------------------------------
    def list_sessions(self, limit: int = 100, after: str | None = None,
                      model_id: str | None = None, owner: str | None = None) -> list[dict[str, Any]]:
        """A page of sessions (no states), by id: those after ``after`` (the last id of the previous
        page), of ``model_id`` if given, of the tenant ``owner`` if given (None: every session's)."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= 10_000:
            raise StoreError("limit", f"must be an integer in [1, 10000], got {limit!r}")
        filters = [(column, str(value)) for column, value in (("model_id", model_id), ("owner", owner))
                   if value is not None]
        which = "".join(f" AND {column} = ?" for column, _ in filters)
        query = ("SELECT id, model_id, method, next_seq, step, t, loglik, created, updated FROM sessions "
                 f"WHERE id > ?{which} ORDER BY id LIMIT ?")
        args = (after or "", *(value for _, value in filters), limit)
        try:
            rows = self._query(query, args).fetchall()
        except self._db_errors as exc:
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
        with self._transaction() as db:  # the sessions first: a session touched meanwhile keeps its chunks
            ids = [row["id"] for row in db.execute("DELETE FROM sessions WHERE updated < ? RETURNING id",
                                                   (stamp,)).fetchall()]
            for start in range(0, len(ids), 500):
                part = ids[start:start + 500]
                marks = ", ".join("?" * len(part))
                db.execute(f"DELETE FROM chunks WHERE session_id IN ({marks})", tuple(part))
            gone = len(ids)
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
        query = "SELECT response, digest, checksum FROM chunks WHERE session_id = ? AND seq = ?"
        try:
            row = self._query(query, (str(session_id), seq)).fetchone()
        except self._db_errors as exc:
            raise self._error(exc, "cannot read a stored response") from None
        if row is not None and digest is not None and row["digest"] is not None and row["digest"] != digest:
            raise Conflict("seq", f"chunk {seq} was already applied with different data; nothing was applied "
                                  "(send new data with the next seq, or re-send chunk {seq} unchanged)"
                           .replace("{seq}", str(seq)))
        if row is None:
            try:
                oldest = self._query("SELECT MIN(seq) AS oldest FROM chunks WHERE session_id = ?",
                                     (str(session_id),)).fetchone()["oldest"]
            except self._db_errors as exc:
                raise self._error(exc, "cannot read a stored response") from None
            raise Conflict("seq", f"chunk {seq} was applied but its response is no longer kept "
                                  f"(replays are kept for the last {self.retention} chunks, at most "
                                  f"{self.retention_bytes} bytes and {self.retention_seconds:g} s; "
                                  f"oldest kept: {oldest})")
        sealed = row["checksum"]
        if sealed is not None and sealed != checksum(str(session_id), str(seq), row["response"]):
            raise _damaged(f"the stored response of chunk {seq} of session {session_id} was changed outside "
                           "the service (it fails its checksum)")
        return row["response"]

    def apply_chunk(self, session_id: str, seq: int, compute: Compute,
                    encoded: bool = False, digest: str | None = None) -> tuple[Any, bool]:
        """Apply chunk ``seq`` exactly once; returns (response, replayed).

        ``encoded``: the response as the JSON text that is stored (a replay sends the same bytes).
        ``digest``: a digest of the request; a replay whose digest differs is a Conflict."""
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise StoreError("seq", f"must be a non-negative integer, got {seq!r}")
        for _ in range(MAX_ATTEMPTS):
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
            with self._transaction() as db:  # in id order: two hosts' batches never lock in a cycle
                for i, record, row, _ in sorted(rows, key=lambda r: r[1].id):
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

    def _write(self, db: Any, old: SessionRecord, seq: int, row: tuple,
               digest: str | None) -> bool:
        """Store a chunk's row in the open transaction; False when another writer moved the session on."""
        state_text, response_text, step, t, loglik = row
        sealed = session_checksum(old.id, old.model_id, old.method, seq + 1, state_text,
                                  _dumps(old.options, "options"), old.owner)
        changed = db.execute(
            "UPDATE sessions SET state = ?, next_seq = ?, step = ?, t = ?, loglik = ?, updated = ?, "
            "version = version + 1, checksum = ? WHERE id = ? AND version = ?",
            (state_text, seq + 1, step, t, loglik, _utc_now(), sealed, old.id, old.version),
        ).rowcount
        if not changed:
            return False
        now = time.time()
        db.execute(self._INSERT_CHUNK, (old.id, seq, response_text, digest, now, len(response_text),
                                        checksum(old.id, str(seq), response_text)))
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

    def _trim(self, db: Any, session_id: str, seq: int, now: float) -> None:
        """Keep the newest chunk and, before it, what fits in retention (count), retention_bytes
        (the newest first) and retention_seconds."""
        db.execute("DELETE FROM chunks WHERE session_id = ? AND seq < ? AND (seq <= ? OR stored < ?)",
                   (session_id, seq, seq - self.retention, now - self.retention_seconds))
        db.execute(
            "DELETE FROM chunks WHERE session_id = ? AND seq < ? AND seq IN (SELECT seq FROM (SELECT seq, "
            "SUM(COALESCE(size, LENGTH(response))) OVER (ORDER BY seq DESC) AS total FROM chunks "
            "WHERE session_id = ?) AS kept "
            "WHERE total > ?)", (session_id, seq, session_id, self.retention_bytes))
