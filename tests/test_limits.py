"""Limits on everything a client can make the server hold (issue "Trust", item 3), each against a real
`yauyau serve` process: half-open connections (a header-read deadline and a connection cap per
worker), precompute jobs (a bounded queue shared through the model store), /events listeners (per
session and per worker) and request rates per client (token buckets).  Each test failed on the
revision before these limits; docs/reliability.md ("Limits") lists what each one proves."""

from __future__ import annotations

import errno
import os
import resource
import selectors
import signal
import socket
import subprocess
import sys
import time

import httpx
import pytest
from conftest import free_port

PROBLEM = "application/problem+json"
HALF_HEAD = b"GET /livez HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "  # never finished


class LimitedServer:
    """`yauyau serve` (one worker) started with RLIMIT_NOFILE set to ``nofile`` in the child."""

    def __init__(self, store, db, nofile=None, env=None, args=()):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "yauyau.service.cli", "serve", "--store", str(store), "--session-db",
               str(db), "--port", str(self.port), "--log-level", "warning", *map(str, args)]

        def limit():
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, env={**os.environ, **(env or {})},
                                     preexec_fn=limit)
        deadline = time.monotonic() + 90
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

    def descriptors(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))

    def kill(self) -> str:
        """SIGKILL the process group; what the server wrote to stderr."""
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


def _raise_own_descriptor_limit(wanted: int) -> int:
    """Raise this process's soft RLIMIT_NOFILE to its hard limit; how many sockets it may then open."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        soft = hard
    return min(wanted, soft - 200 if soft != resource.RLIM_INFINITY else wanted)


def _half_open(port: int, count: int, deadline_s: float = 120.0) -> list[socket.socket]:
    """``count`` sockets, in order, each sending half a request head once connected (as fast as the
    server's listen queue takes them); the sockets stay open."""
    socks, selector = [], selectors.DefaultSelector()
    for _ in range(count):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.connect_ex(("127.0.0.1", port))
        selector.register(sock, selectors.EVENT_WRITE)
        socks.append(sock)
    pending, deadline = count, time.monotonic() + deadline_s
    while pending and time.monotonic() < deadline:
        for key, _ in selector.select(timeout=1.0):
            try:
                key.fileobj.send(HALF_HEAD)
            except OSError:  # refused or reset: the server closed it at once
                pass
            selector.unregister(key.fileobj)
            pending -= 1
    selector.close()
    return socks


def _closed_by_server(sock: socket.socket) -> bool:
    try:
        return sock.recv(1024) == b""
    except BlockingIOError:
        return False
    except OSError as exc:
        return exc.errno in (errno.ECONNRESET, errno.EPIPE, errno.ENOTCONN, errno.ECONNREFUSED)


# -- 1. connections: a cap per worker and a deadline for the request head --------------------------
@pytest.mark.slow
def test_half_open_connections_leave_the_server_answering(tmp_path, example_store):
    """5 000 sockets that send half a request head against a worker limited to 4 096 descriptors: the
    oldest are closed to make room, /livez answers, the log holds no line per connection."""
    store, _ = example_store
    nofile, header_timeout = 4096, 60.0  # a long deadline: the cap alone has to keep the server up
    count = _raise_own_descriptor_limit(5000)
    assert count > nofile, f"this machine lets a process open only {count + 200} descriptors"
    server = LimitedServer(store, tmp_path / "s.sqlite3", nofile=nofile,
                           env={"YAUYAU_HEADER_TIMEOUT": str(header_timeout)})
    socks = []
    try:
        socks = _half_open(server.port, count)
        livez = httpx.get(server.url + "/livez", timeout=header_timeout + 30)
        assert livez.status_code == 200 and livez.json() == {"status": "ok"}
        assert server.descriptors() < nofile
        time.sleep(1.0)
        closed = [i for i, sock in enumerate(socks) if _closed_by_server(sock)]
        kept = sorted(set(range(count)) - set(closed))
        assert len(closed) >= count - nofile, (len(closed), count)  # what could not be held was closed...
        assert sum(closed) / len(closed) < sum(kept) / len(kept)  # ...the oldest first
        chunked = httpx.post(server.url + "/v1/sessions", json={"model": "nope"}, timeout=30)
        assert chunked.status_code == 404  # the application itself still answers
    finally:
        for sock in socks:
            sock.close()
        stderr = server.kill()
    lines = stderr.splitlines()
    assert len(lines) < 50, "\n".join(lines[:20])
