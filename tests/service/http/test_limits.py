"""Limits on everything a client can make the server hold (issue "Trust", item 3), each against a real
`yauyau serve` process: half-open connections (a header-read deadline and a connection cap per
worker), precompute jobs (a bounded queue shared through the model store), /events listeners (per
session and per worker) and request rates per client (token buckets).  Each test failed on the
revision before these limits; docs/reliability.md ("Limits") lists what each one proves."""

from __future__ import annotations

import errno
import math
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
from helpers.server import Server

PROBLEM = "application/problem+json"
HALF_HEAD = b"GET /livez HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "  # never finished


class LimitedServer(Server):
    """`yauyau serve` (one worker) started with RLIMIT_NOFILE set to ``nofile`` in the child."""

    def __init__(self, store, db, nofile=None, env=None, args=()):
        def limit():
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        super().__init__(store, db, env=env, args=args, preexec_fn=limit)

    def descriptors(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))


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
@pytest.mark.service
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


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    """Whether the server closes ``sock`` within ``seconds`` (what it sends before is read and dropped)."""
    sock.settimeout(seconds)
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            if sock.recv(65536) == b"":
                return True
    except (TimeoutError, socket.timeout):
        return False
    except OSError:
        return True
    return False


@pytest.mark.service
@pytest.mark.slow
def test_a_request_head_that_stalls_is_closed_at_the_header_timeout(tmp_path, example_store):
    """A connection that sends nothing, one that sends half a head, and a kept-alive one that starts its
    next head and stalls are all closed about header_timeout later; a whole request is still served."""
    store, _ = example_store
    header_timeout = 2.0
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_HEADER_TIMEOUT": str(header_timeout)})
    try:
        silent = socket.create_connection(("127.0.0.1", server.port))
        half = socket.create_connection(("127.0.0.1", server.port))
        half.sendall(HALF_HEAD)
        kept = socket.create_connection(("127.0.0.1", server.port))
        kept.sendall(b"GET /livez HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        kept.settimeout(30)
        assert kept.recv(65536).startswith(b"HTTP/1.1 200")
        kept.sendall(HALF_HEAD)  # the next request on the same connection: its head stalls
        for sock in (silent, half, kept):
            assert _closed_within(sock, header_timeout + 20)
            sock.close()
        assert httpx.get(server.url + "/livez", timeout=30).status_code == 200
    finally:
        stderr = server.kill()
    warnings = [line for line in stderr.splitlines() if "connections closed" in line]
    assert len(warnings) <= 2 and "Traceback" not in stderr, stderr  # a line every 10 s, not a connection


@pytest.mark.service
@pytest.mark.slow
def test_at_the_cap_with_every_connection_busy_a_newcomer_gets_503(tmp_path, example_store):
    """max_connections = 3 held by three /events listeners (requests that last): a fourth connection is
    answered 503 problem+json with Retry-After; once a listener leaves, requests are served again."""
    store, ids = example_store
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_MAX_CONNECTIONS": "3"})
    created = httpx.post(server.url + "/v1/sessions", json={"model": ids["cubic_sensor"]}, timeout=30)
    sid = created.json()["id"]
    clients, streams = [], []
    try:
        for _ in range(3):
            client = httpx.Client(timeout=30)
            stream = client.stream("GET", f"{server.url}/v1/sessions/{sid}/events")
            response = stream.__enter__()
            assert response.status_code == 200
            lines = response.iter_lines()  # kept: a line iterator dropped closes its response
            assert next(lines) == "event: frame"  # the first frame: the listener is in
            clients.append((client, lines))
            streams.append(stream)
        refused = httpx.get(server.url + "/livez", timeout=30)
        assert refused.status_code == 503, refused.text
        assert refused.headers["content-type"].startswith(PROBLEM)
        assert refused.json()["field"] == "connections" and int(refused.headers["retry-after"]) >= 1
        streams.pop().__exit__(None, None, None)
        clients.pop()[0].close()
        deadline, status = time.monotonic() + 30, None
        while time.monotonic() < deadline and status != 200:
            time.sleep(0.2)
            status = httpx.get(server.url + "/livez", timeout=30).status_code
        assert status == 200
    finally:
        for stream in streams:
            stream.__exit__(None, None, None)
        for client, _ in clients:
            client.close()
        server.kill()


# -- 2. precompute jobs: a bounded queue shared through the model store -------------------------------
def _ou_spec(k: int) -> dict:
    """A small linear spec, distinct for each k (a job of a few seconds)."""
    return {"name": f"ou-queue-{k}", "state": ["x"], "drift": [f"-{0.3 + 0.01 * k:.2f}*x"],
            "observation": ["x"], "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[0.5]]},
            "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 48}, "method": "yau-yau"}


def _job_processes(store) -> list[int]:
    """The pids of the precompute processes working on ``store`` (from /proc: what really runs)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as handle:
                    argv = handle.read().split(b"\0")
                with open(f"/proc/{entry}/stat") as handle:
                    state = handle.read().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if b"yauyau.service.models.jobs" in argv and str(store).encode() in argv and state != "Z":
                pids.append(int(entry))
    return pids


class _Watch:
    """The most job processes seen at once, sampled from /proc every 20 ms in a thread."""

    def __init__(self, store):
        import threading

        self.store, self.most, self._stop = store, 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(0.02):
            pids = _job_processes(self.store)
            self.most = max(self.most, len(pids))

    def stop(self) -> int:
        self._stop.set()
        self._thread.join()
        return self.most


@pytest.mark.service
@pytest.mark.slow
def test_precompute_jobs_wait_in_a_bounded_queue(tmp_path):
    """max_jobs = 2, max_queued_jobs = 3, seven distinct specs posted at once: two processes run (never
    more, counted in /proc), three wait with positions 1, 2, 3, two are refused 503 with Retry-After;
    every accepted job then finishes and its model is served."""
    from yauyau.solver.spec import spec_from_dict
    from yauyau.storage.model_store import model_id

    store = tmp_path / "store"
    store.mkdir()
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_MAX_JOBS": "2",
                                                               "YAUYAU_MAX_QUEUED_JOBS": "3"})
    watch = _Watch(store)
    stopped: list[int] = []
    try:
        answers = []
        for k in range(7):
            answers.append(httpx.post(server.url + "/v1/models", json={"spec": _ou_spec(k)}, timeout=60))
            if k == 1:  # the two running jobs are held still while the others are posted (no race)
                deadline = time.monotonic() + 60
                while len(stopped) < 2 and time.monotonic() < deadline:
                    stopped = _job_processes(store)
                    time.sleep(0.01)
                for pid in stopped:
                    os.kill(pid, signal.SIGSTOP)
        statuses = [(a.status_code, a.json().get("status")) for a in answers]
        assert statuses[:5] == [(202, "running")] * 2 + [(202, "queued")] * 3, statuses
        assert [a.json()["position"] for a in answers[2:5]] == [1, 2, 3]
        for refused in answers[5:]:
            assert refused.status_code == 503 and refused.headers["content-type"].startswith(PROBLEM)
            assert int(refused.headers["retry-after"]) >= 1
            assert "YAUYAU_MAX_QUEUED_JOBS" in refused.json()["detail"]
        accepted = [a.json()["id"] for a in answers[:5]]
        assert accepted == [model_id(spec_from_dict(_ou_spec(k)).canonical_json()) for k in range(5)]
        assert httpx.get(f"{server.url}/v1/jobs/{accepted[2]}", timeout=30).json()["position"] == 1
        assert len(_job_processes(store)) == 2  # the queued ones have no process
        for pid in stopped:
            os.kill(pid, signal.SIGCONT)
        deadline, pending = time.monotonic() + 300, set(accepted)
        while pending and time.monotonic() < deadline:
            for mid in sorted(pending):
                job = httpx.get(f"{server.url}/v1/jobs/{mid}", timeout=30).json()
                assert job["status"] in ("queued", "running", "done"), job
                if job["status"] == "done":
                    pending.discard(mid)
            time.sleep(0.2)
        assert not pending, f"jobs not done: {pending}"
        stored = {m["id"] for m in httpx.get(server.url + "/v1/models", timeout=30).json()}
        assert set(accepted) <= stored
        refused_id = model_id(spec_from_dict(_ou_spec(5)).canonical_json())
        assert httpx.get(f"{server.url}/v1/jobs/{refused_id}", timeout=30).status_code == 404
    finally:
        for pid in stopped:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        most = watch.stop()
        server.kill()
        for pid in _job_processes(store):
            os.kill(pid, signal.SIGKILL)
    assert most == 2, most


# -- 3. /events listeners: capped per session and per worker, fed by one poll a session --------------
class _Listener:
    """A GET /events stream read line by line (its own connection)."""

    def __init__(self, url: str):
        self.client = httpx.Client(timeout=60)
        self._stream = self.client.stream("GET", url)
        self.response = self._stream.__enter__()
        self._lines = self.response.iter_lines() if self.response.status_code == 200 else None
        if self._lines is None:
            self.response.read()  # a refusal: its problem+json body

    def frame(self) -> dict:
        """The next frame event: {'id': ..., 'data': ...}."""
        event: dict = {}
        for line in self._lines:
            if not line:
                if event.get("event") == "frame":
                    return event
                event = {}
            else:
                name, _, value = line.partition(": ")
                event[name] = value
        raise AssertionError("the stream ended")

    def close(self):
        self._stream.__exit__(None, None, None)
        self.client.close()


@pytest.mark.service
@pytest.mark.slow
def test_events_listeners_are_capped_per_session_and_per_worker(tmp_path, example_store):
    """max_session_listeners = 2, max_listeners = 3: a third listener of a session gets 429, a fourth
    of the worker 503 (problem+json, Retry-After); the listeners get every chunk's frame and the chunks
    are served; a listener that leaves frees its slot."""
    import json

    store, ids = example_store
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={
        "YAUYAU_MAX_SESSION_LISTENERS": "2", "YAUYAU_MAX_LISTENERS": "3", "YAUYAU_EVENTS_POLL": "0.05"})
    listeners: list[_Listener] = []
    try:
        created = [httpx.post(server.url + "/v1/sessions", json={"model": ids["cubic_sensor"]}, timeout=30)
                   for _ in range(2)]
        assert all(r.status_code == 201 for r in created), [(r.status_code, r.text) for r in created]
        a, b = (r.json()["id"] for r in created)
        events = f"{server.url}/v1/sessions/{{}}/events"
        for sid in (a, a, b):
            listeners.append(_Listener(events.format(sid)))
            assert listeners[-1].response.status_code == 200
            assert listeners[-1].frame()["id"] == "0"
        for sid, status, cap in ((a, 429, "YAUYAU_MAX_SESSION_LISTENERS"), (b, 503, "YAUYAU_MAX_LISTENERS")):
            listener = _Listener(events.format(sid))
            listeners.append(listener)  # closed at the end, whatever it is
            refused = listener.response
            assert refused.status_code == status, refused.status_code
            assert refused.headers["content-type"].startswith(PROBLEM) and cap in refused.json()["detail"]
            assert int(refused.headers["retry-after"]) >= 1
            listeners.pop().close()
        rows = [[0.01 * ((i * 7) % 5 - 2)] for i in range(50)]
        for seq in range(3):
            chunk = httpx.post(f"{server.url}/v1/sessions/{a}/observations",
                               json={"seq": seq, "increments": rows}, timeout=60)
            assert chunk.status_code == 200, chunk.text
            mean = chunk.json()["estimates"][-1]["mean"][0]
            for listener in listeners[:2]:  # each listener of a: a frame of this version, this estimate
                frame = listener.frame()
                while frame["id"] != str(seq + 1):
                    frame = listener.frame()
                data = json.loads(frame["data"])
                assert data["next_seq"] == seq + 1 and data["mean"][0] == pytest.approx(mean, abs=1e-9)
        listeners.pop(0).close()
        deadline, status = time.monotonic() + 30, None
        while status != 200 and time.monotonic() < deadline:
            again = _Listener(events.format(a))
            status = again.response.status_code
            if status == 200:
                listeners.append(again)
            else:  # the slot is given back once the server has seen the disconnect
                again.close()
                time.sleep(0.1)
        assert status == 200 and listeners[-1].frame()["id"] == "3"
    finally:
        for listener in listeners:
            listener.close()
        server.kill()


# -- 4. rates per client: token buckets, 429 with Retry-After ----------------------------------------
def _until_refused(call, most: int = 40) -> tuple[int, httpx.Response]:
    """Call until a 429: (how many succeeded before, the 429)."""
    for done in range(most):
        response = call()
        if response.status_code == 429:
            return done, response
    raise AssertionError(f"no 429 in {most} calls")


def _is_rate_problem(response: httpx.Response, setting: str, period: float) -> int:
    assert response.headers["content-type"].startswith(PROBLEM)
    assert setting in response.json()["detail"]
    retry = int(response.headers["retry-after"])
    assert 1 <= retry <= math.ceil(period)  # at most the time one token takes to come back
    return retry


@pytest.mark.service
@pytest.mark.slow
def test_session_creation_past_its_burst_is_429_until_retry_after(tmp_path, example_store):
    """rate_sessions = 0.2/s with a burst of 3: three creations (after refused ones, which cost no
    token) and then 429 with Retry-After; the rest of the API, /livez, /readyz and /metrics still
    answer; after Retry-After seconds a session is created again."""
    store, ids = example_store
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_RATE_SESSIONS": "0.2",
                                                               "YAUYAU_RATE_SESSIONS_BURST": "3"})
    try:
        def create(model=ids["cubic_sensor"]):
            return httpx.post(server.url + "/v1/sessions", json={"model": model}, timeout=30)

        assert all(create("no-such-model").status_code == 404 for _ in range(5))  # no session: no token
        created, refused = _until_refused(create)
        assert created >= 3
        retry = _is_rate_problem(refused, "YAUYAU_RATE_SESSIONS", 1 / 0.2)
        assert httpx.get(server.url + "/v1/models", timeout=30).status_code == 200
        for path in ("/livez", "/readyz", "/metrics"):
            assert httpx.get(server.url + path, timeout=30).status_code == 200
        time.sleep(retry)
        assert create().status_code == 201
    finally:
        server.kill()


@pytest.mark.service
@pytest.mark.slow
def test_requests_past_their_burst_are_429_until_retry_after(tmp_path, example_store):
    """rate_requests = 0.5/s with a burst of 6: /v1 requests beyond are 429 with Retry-After while the
    health routes and /metrics never are; after Retry-After seconds requests are served again."""
    store, _ = example_store
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_RATE_REQUESTS": "0.5",
                                                               "YAUYAU_RATE_REQUESTS_BURST": "6"})
    try:
        served, refused = _until_refused(lambda: httpx.get(server.url + "/v1/models", timeout=30))
        assert served >= 6
        retry = _is_rate_problem(refused, "YAUYAU_RATE_REQUESTS", 1 / 0.5)
        for path in ("/livez", "/readyz", "/metrics") * 10:
            assert httpx.get(server.url + path, timeout=30).status_code == 200
        time.sleep(retry)
        assert httpx.get(server.url + "/v1/models", timeout=30).status_code == 200
    finally:
        server.kill()


@pytest.mark.service
@pytest.mark.slow
def test_rates_are_kept_per_tenant(tmp_path, example_store):
    """With a tenants file each tenant has its own buckets, though all come from one address:
    rate_sessions_burst = 2 lets each tenant create two sessions at once, then 429 for that tenant
    only."""
    import hashlib

    store, ids = example_store
    tokens = {"alice": "alice-token-" + "a" * 20, "bob": "bob-token-" + "b" * 20}
    tenants = tmp_path / "tenants.toml"
    tenants.write_text("".join(f'[[tenant]]\nname = "{name}"\n'
                               f'token_sha256 = "{hashlib.sha256(token.encode()).hexdigest()}"\n'
                               for name, token in tokens.items()))
    server = LimitedServer(store, tmp_path / "s.sqlite3", env={"YAUYAU_TENANTS_FILE": str(tenants),
                                                               "YAUYAU_RATE_SESSIONS": "0.01",
                                                               "YAUYAU_RATE_SESSIONS_BURST": "2"})
    try:
        def create(tenant):
            return httpx.post(server.url + "/v1/sessions", json={"model": ids["cubic_sensor"]}, timeout=30,
                              headers={"Authorization": f"Bearer {tokens[tenant]}"}).status_code

        assert [create("alice") for _ in range(3)] == [201, 201, 429]
        assert [create("bob") for _ in range(3)] == [201, 201, 429]
        assert create("alice") == 429
    finally:
        server.kill()


@pytest.mark.parametrize("flag, value, field", [
    ("--header-timeout", "0", "header_timeout"), ("--max-connections", "0", "max_connections"),
    ("--max-jobs", "0", "max_jobs"), ("--max-queued-jobs", "-1", "max_queued_jobs"),
    ("--max-listeners", "0", "max_listeners"), ("--max-session-listeners", "0", "max_session_listeners"),
    ("--rate-requests", "-1", "rate_requests"), ("--rate-sessions", "-1", "rate_sessions"),
])
def test_a_limit_flag_out_of_range_is_one_line_naming_it(tmp_path, flag, value, field):
    """Each limit's `yauyau serve` flag reaches its setting: a value out of range exits 2 naming it."""
    (tmp_path / "store").mkdir()
    store = tmp_path / "store"
    cmd = [sys.executable, "-m", "yauyau.service.cli", "serve", "--store", str(store), flag, value]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and out.stderr.startswith(f"yauyau serve: error: {field}:"), out.stderr
    assert len(out.stderr.splitlines()) == 1
