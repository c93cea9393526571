"""A real `yauyau serve` process for the tests, and the client calls they share."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from contextlib import contextmanager

import httpx

from helpers import free_port

ROWS = [[0.01 * ((i * 7) % 5 - 2)] for i in range(50)]  # a chunk of 50 small increments (1-D models)


class Server:
    """`python -m yauyau.service.cli serve` in its own process group (SIGKILL takes the workers too)."""

    def __init__(self, store, db, workers=1, env=None, args=(), preexec_fn=None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "yauyau.service.cli", "serve", "--store", str(store),
               "--session-db", str(db), "--port", str(self.port), "--workers", str(workers),
               "--log-level", "warning", *map(str, args)]
        env = {k: v for k, v in {**os.environ, **(env or {})}.items() if v is not None}  # None: unset
        self.proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, env=env, preexec_fn=preexec_fn)
        self._wait_ready()

    def _wait_ready(self, timeout=90.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.proc.stderr.read().decode()[-2000:]}")
            try:
                if httpx.get(self.url + "/readyz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.kill()
        raise RuntimeError("server did not become ready")

    def kill(self) -> str:
        """SIGKILL the process group; what the server wrote to stderr (again: nothing)."""
        if self.proc.stderr.closed:
            return ""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=30)
        err = self.proc.stderr.read().decode(errors="replace")
        self.proc.stderr.close()
        return err


@contextmanager
def running(store, db, **kwargs):
    """A Server for the ``with`` block; ``log["stderr"]`` holds what it wrote once the block ends."""
    server = Server(store, db, **kwargs)
    log = {"stderr": ""}
    try:
        yield server, log
    finally:
        log["stderr"] = server.kill()


def session_db(kind: str, request, tmp_path) -> str:
    """Where the servers keep their sessions: a SQLite file, or a fresh database on the test
    PostgreSQL server (the ``postgres`` fixture of tests/conftest.py)."""
    if kind == "sqlite":
        return str(tmp_path / "sessions.sqlite3")
    return request.getfixturevalue("postgres").database(f"t{uuid.uuid4().hex}")


def new_session(url: str, model_id: str, **body) -> str:
    r = httpx.post(f"{url}/v1/sessions", json={"model": model_id, **body}, timeout=30)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def chunk(url: str, sid: str, seq: int, rows, **extra) -> httpx.Response:
    return httpx.post(f"{url}/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows, **extra},
                      timeout=60)
