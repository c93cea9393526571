"""Trust in the session store (issue "Trust", items 1, 2 and the stored-state checksum): what an
operator's routine outside read, a burst of clients and a corrupted row do to a real `yauyau serve`
process over a real SQLite file (and PostgreSQL where the item concerns it).  Each test failed on
the revision before its fix."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
from helpers import EXAMPLES, precompute_into
from helpers.server import ROWS, chunk, new_session, running
from pg_server import PostgresServer

pytestmark = pytest.mark.service  # a real `yauyau serve` process

_OUTSIDE_READ = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1])
print(db.execute("SELECT count(*) FROM sessions").fetchone()[0])
db.close()
"""


def outside_read(db) -> int:
    """What an operator does: another process opens the file with SQLite, counts, closes."""
    out = subprocess.run([sys.executable, "-c", _OUTSIDE_READ, str(db)], capture_output=True, text=True,
                         check=True, timeout=60)
    return int(out.stdout)


def test_an_outside_read_loses_no_acknowledged_chunk(tmp_path, example_store):
    store, ids = example_store
    db = tmp_path / "s.sqlite3"
    with running(store, db) as (server, _):
        sid = new_session(server.url, ids["ou"])
        for seq in range(3):
            assert chunk(server.url, sid, seq, ROWS).status_code == 200
        assert outside_read(db) == 1
        for seq in range(3, 5):
            assert chunk(server.url, sid, seq, ROWS).status_code == 200
        assert httpx.get(server.url + "/readyz").status_code == 200
    # the server was SIGKILLed (running() kills its process group): every acknowledged chunk is there
    with running(store, db) as (server, _):
        info = httpx.get(f"{server.url}/v1/sessions/{sid}").json()
        assert info["next_seq"] == 5, info
        assert chunk(server.url, sid, 5, ROWS).status_code == 200


@pytest.fixture(scope="module")
def range_store(tmp_path_factory) -> tuple[Path, str]:
    """The 2-D range example (basis 850 on 1 801 nodes: ~40 KB a session state)."""
    store = tmp_path_factory.mktemp("range-store")
    return store, precompute_into(store, EXAMPLES / "range_2d.toml")


THREADS, PER_THREAD = 8, 400
_CHECKPOINTER = """
import sqlite3, sys, time
db = sqlite3.connect(sys.argv[1], timeout=30)
while True:
    db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
    time.sleep(0.005)
"""


@contextmanager
def checkpointer(db: Path):
    """What a replication tool beside the server does (litestream, a backup script): another process
    that keeps a connection open and checkpoints the write-ahead log every few milliseconds."""
    proc = subprocess.Popen([sys.executable, "-c", _CHECKPOINTER, str(db)], stderr=subprocess.DEVNULL)
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait(timeout=30)


@pytest.mark.slow
def test_a_burst_of_session_creation_leaves_the_service_up(tmp_path, range_store):
    """8 clients create 400 sessions each on the 2-D model as fast as they can: every creation is
    answered 201 (or, at worst, a transient 503 with Retry-After that a retry gets past) and the
    store stays usable: /readyz 200 and chunks served afterwards."""
    store, mid = range_store
    answers: dict[int, int] = {}
    failures: list[str] = []
    lock = threading.Lock()

    def create(url: str) -> None:
        with httpx.Client(timeout=120) as client:
            for _ in range(PER_THREAD):
                r = client.post(f"{url}/v1/sessions", json={"model": mid})
                if r.status_code == 503 and "Retry-After" in r.headers:  # a transient doubt: once more
                    time.sleep(float(r.headers["Retry-After"]))
                    r = client.post(f"{url}/v1/sessions", json={"model": mid})
                with lock:
                    answers[r.status_code] = answers.get(r.status_code, 0) + 1
                    if r.status_code != 201:
                        failures.append(r.text)
                        return

    db = tmp_path / "s.sqlite3"
    unlimited = {"YAUYAU_RATE_SESSIONS": "0"}  # the store under a burst, not the rate limit (test_limits.py)
    with running(store, db, env=unlimited) as (server, log), checkpointer(db):
        threads = [threading.Thread(target=create, args=(server.url,)) for _ in range(THREADS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        ready = httpx.get(server.url + "/readyz", timeout=60)
        assert ready.status_code == 200, ready.text
        assert answers == {201: THREADS * PER_THREAD}, (answers, failures[:3])
        sid = new_session(server.url, mid)
        r = httpx.post(f"{server.url}/v1/sessions/{sid}/observations",
                       json={"seq": 0, "increments": [[0.01]] * 20}, timeout=60)
        assert r.status_code == 200, r.text
    assert "SESSION STORE UNUSABLE" not in log["stderr"]


def test_a_write_ahead_log_that_vanishes_is_damage_not_a_reason_to_go_on(tmp_path, example_store):
    store, ids = example_store
    db = tmp_path / "s.sqlite3"
    with running(store, db) as (server, log):
        sid = new_session(server.url, ids["ou"])
        assert chunk(server.url, sid, 0, ROWS).status_code == 200
        Path(f"{db}-wal").unlink()  # what a second process that took itself for the last user did
        r = chunk(server.url, sid, 1, ROWS)
        assert r.status_code == 503 and "write-ahead log" in r.json()["detail"], r.text
        ready = httpx.get(server.url + "/readyz")
        assert ready.status_code == 503 and "write-ahead log" in ready.json()["detail"]
        assert str(tmp_path) not in r.text + ready.text  # no server path in a 503 body
    assert "SESSION STORE UNUSABLE" in log["stderr"]


_EDIT_STATE = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1], isolation_level=None)
state = db.execute("SELECT state FROM sessions WHERE id = ?", (sys.argv[2],)).fetchone()[0]
db.execute("UPDATE sessions SET state = ? WHERE id = ?", (state.replace("0.", "0.9", 1), sys.argv[2]))
db.close()
"""


def test_a_state_edited_outside_the_service_answers_503_not_estimates(tmp_path, example_store):
    """A stored state changed into other valid JSON (one digit) was used as it was, and broken JSON gave
    a 500: now that session answers 503 naming the damage and the fix, the log says so, and the other
    sessions are served."""
    store, ids = example_store
    db = tmp_path / "s.sqlite3"
    with running(store, db) as (server, log):
        sid, other = (new_session(server.url, ids["cubic_sensor"]) for _ in range(2))
        for s in (sid, other):
            assert chunk(server.url, s, 0, ROWS).status_code == 200
        subprocess.run([sys.executable, "-c", _EDIT_STATE, str(db), sid], check=True, timeout=60)
        for r in (chunk(server.url, sid, 1, ROWS), httpx.get(f"{server.url}/v1/sessions/{sid}")):
            assert r.status_code == 503 and r.headers["content-type"].startswith("application/problem+json")
            assert "changed outside the service" in r.json()["detail"] and "Retry-After" not in r.headers
        assert chunk(server.url, other, 1, ROWS).status_code == 200
        assert httpx.get(server.url + "/readyz").status_code == 200  # one damaged row: the others go on
    assert "SESSION STORE DAMAGED" in log["stderr"]


# -- PostgreSQL: durable acknowledgements, a database that is down -------------------------------
@pytest.fixture
def own_postgres():
    """A PostgreSQL server of this test alone (it is crashed and restarted)."""
    server = PostgresServer()
    yield server
    server.stop()


def _eventually(call, timeout: float = 60.0):
    """call() until it returns a 200 (the store's pool reconnects after the database came back)."""
    deadline = time.monotonic() + timeout
    while True:
        r = call()
        if r.status_code == 200 or time.monotonic() > deadline:
            return r
        time.sleep(0.2)


@pytest.mark.postgres
@pytest.mark.slow
def test_postgres_acknowledged_chunks_survive_a_database_crash(tmp_path, example_store, own_postgres):
    """The test server commits asynchronously (synchronous_commit = off, as many tuned servers do): a
    chunk acknowledged just before the database host lost power was gone after its recovery.  The store
    asks for a synchronous commit in every write transaction."""
    store, ids = example_store
    dsn = own_postgres.database("sessions")
    with running(store, dsn) as (server, _), httpx.Client(timeout=60) as client:
        sids = [new_session(server.url, ids["ou"]) for _ in range(4)]
        for seq in range(5):
            for sid in sids:
                r = client.post(f"{server.url}/v1/sessions/{sid}/observations",
                                json={"seq": seq, "increments": ROWS})
                assert r.status_code == 200, r.text
        own_postgres.crash()  # at once after the last acknowledgement
        own_postgres.start()
        for sid in sids:
            r = _eventually(lambda sid=sid: client.get(f"{server.url}/v1/sessions/{sid}"))
            assert r.status_code == 200 and r.json()["next_seq"] == 5, r.text


@pytest.mark.postgres
@pytest.mark.slow
def test_postgres_down_is_answered_within_the_connect_timeout(tmp_path, example_store, own_postgres):
    """With the database down, a request waited 30 s for the pool (psycopg_pool's default) before its
    503; now the pool waits YAUYAU_SESSION_DB_TIMEOUT, which its error names (not a wall-clock
    measurement: load does not change it), the answer is 503 with Retry-After, and the service
    recovers by itself when the database is back."""
    store, ids = example_store
    dsn = own_postgres.database("sessions")
    with running(store, dsn, env={"YAUYAU_SESSION_DB_TIMEOUT": "2"}) as (server, _), \
            httpx.Client(timeout=120) as client:
        sid = new_session(server.url, ids["ou"])
        assert client.post(f"{server.url}/v1/sessions/{sid}/observations",
                           json={"seq": 0, "increments": ROWS}).status_code == 200
        own_postgres.crash()
        details = []
        for _ in range(3):
            r = client.post(f"{server.url}/v1/sessions/{sid}/observations",
                            json={"seq": 1, "increments": ROWS})
            assert r.status_code == 503 and "Retry-After" in r.headers, r.text
            details.append(r.json()["detail"])
        assert any("after 2.00 sec" in detail for detail in details), details  # the setting, not 30 s
        assert httpx.get(server.url + "/readyz", timeout=60).status_code == 503
        own_postgres.start()
        r = _eventually(lambda: client.post(f"{server.url}/v1/sessions/{sid}/observations",
                                            json={"seq": 1, "increments": ROWS}))
        assert r.status_code == 200, r.text
