"""HTTP load benchmark: observations/s and latency per 100-observation chunk over loopback.

    python -m bench.load [--quick] [--seconds S] [--workers K] [--baseline REV] [--rounds R]
                         [--example 1d|2d] [--unbatched] [--streams 1,8,64]

Starts `yauyau serve` itself (the 1-D cubic-sensor example, precomputed into a temporary store),
then drives 1, 8 and 64 concurrent sessions, each posting chunks of 100 increments back to back
for a bounded time (and at most ``MAX_CHUNKS`` chunks per stream).  The client runs in its own
process so that its CPU is measured apart from the server's (both share the machine's cores):

* ``lean``: one thread per stream, each with a keep-alive ``http.client`` connection and the
  request bodies encoded once (what a production client can do);
* ``httpx``: httpx's asyncio client in the same style as a typical Python application (the
  client the first version of this benchmark used);
* ``urllib``: the standard library's ``urllib.request``, one thread per stream, a new connection per
  chunk (no keep-alive: the plainest client);
* ``ws``: one WebSocket per stream (``WS /v1/sessions/{id}/stream``, websocket-client), a chunk sent
  and its answer read.

``--baseline REV`` also serves git revision REV (its solver/, service/ and storage/) in the same
run, interleaved with the working tree, so that before/after figures
share the machine's load.  The server's CPU time per chunk (from /proc) is reported too: on a
noisy shared machine it varies far less than wall-clock rates.  The engine alone on the same
chunks is timed in the same run.  ``--unbatched`` also serves the working tree with micro-batching
off (``YAUYAU_MAX_BATCH=1``: every chunk stepped and committed alone), side by side.  ``--example 2d``
drives the 2-D rotation example (examples/range_2d.toml) instead of the 1-D cubic sensor.
``--stores`` compares the session stores instead: SQLite and PostgreSQL (a server of its own,
scripts/pg_server.py), each with one and two server processes (``--workers``).
Writes bench/results/load.md (bench/results/load-2d.md for the 2-D example, bench/results/load-stores.md for
``--stores``).
Targets (issue "Many streams at once"): 1-D, 64 streams >= 100 000 observations/s with p99 <= 50 ms,
one stream >= 2x the previous revision's throughput; 2-D, 64 streams batched >= 2.5x unbatched.
"""

from __future__ import annotations

import argparse
import asyncio
import http.client
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
SPECS = {"1d": ROOT / "examples" / "cubic_sensor.toml", "2d": ROOT / "examples" / "range_2d.toml"}
RESULTS = ROOT / "bench" / "results"
DOCS = {"1d": RESULTS / "load.md", "2d": RESULTS / "load-2d.md", "stores": RESULTS / "load-stores.md",
        "windows": RESULTS / "load-windows.md"}
CHUNK = 100
MAX_CHUNKS = 20_000  # per stream and row: bounds the work however fast the server is
STREAMS = (1, 8, 64)
TARGET_RATE, TARGET_P99_MS = 100_000, 50.0  # 64 streams, one worker
TARGET_SINGLE, TARGET_2D = 2.0, 2.5  # one stream against --baseline; 2-D batched against unbatched
# every client sends a bearer token: a server with --tenants checks it, the others ignore the header
TOKEN = "bench-load-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _tenants_file(directory: Path, count: int = 100) -> Path:
    """A tenants file (issue "Trust") of ``count`` tenants, the last one's token the clients' (a token
    is compared with every tenant's hash, in constant time)."""
    import hashlib

    path = directory / "tenants.toml"
    tokens = [f"other-token-{k}" for k in range(count - 1)] + [TOKEN]
    path.write_text("".join(f'[[tenant]]\nname = "tenant-{k}"\n'
                            f'token_sha256 = "{hashlib.sha256(t.encode()).hexdigest()}"\n\n'
                            for k, t in enumerate(tokens)))
    return path


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _prepare_store(store: Path, spec_path: Path):
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline.pipeline import precompute
    from yauyau.solver.simulate import simulate
    from yauyau.solver.spec import load_spec
    from yauyau.storage.model_store import ModelStore

    spec = load_spec(spec_path)
    model = compile_model(spec)
    offline = precompute(model)
    model_id = ModelStore(store).save(spec.canonical_json(), offline.to_arrays(), {})
    increments = simulate(model, 20 * CHUNK, np.random.default_rng(0)).increments
    return model, offline, model_id, increments


def _postgres():
    """A PostgreSQL server of its own (scripts/pg_server.py), for --stores."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from pg_server import PostgresServer

    return PostgresServer()


def _baseline_tree(rev: str, into: Path) -> Path:
    """yauyau/, solver/, service/ and storage/ of git revision ``rev``: the whole previous revision
    (revisions from 0.2 on: before, the packages were top-level and used another import name)."""
    into.mkdir(parents=True)
    packages = ["yauyau", "solver", "service", "storage"]
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, *packages],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


class Server:
    """`python -m yauyau.service.cli serve` run from ``tree`` (its service/ and storage/ come first)."""

    def __init__(self, tree: Path, store: Path, db: Path | str, workers: int, env: dict | None = None):
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "yauyau.service.cli", "serve", "--store", str(store),
               "--port", str(self.port), "--session-db", str(db), "--workers", str(workers),
               "--log-level", "warning"]
        env = dict(os.environ, PYTHONPATH=str(tree), **(env or {}))
        self.proc = subprocess.Popen(cmd, cwd=tree, env=env, start_new_session=True)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server in {tree} exited with {self.proc.returncode}")
            try:
                if _get(self.port, "/readyz")[0] == 200:
                    return
            except OSError:
                time.sleep(0.2)
        self.stop()
        raise RuntimeError("server did not start")

    def stop(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGTERM)
            self.proc.wait(timeout=30)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)


def _wait_idle(server: Server, timeout: float = 180.0) -> None:
    """Until the server's start-up work in the background (the compiled loops made ready, the analysis
    process) is done: less than 0.05 s of CPU in a second.  Otherwise the configuration measured first
    pays for it (a 1-stream row at 3x the server CPU per chunk of the same revision measured later)."""
    deadline = time.monotonic() + timeout
    before = _group_cpu_seconds(server.proc.pid)
    while time.monotonic() < deadline:
        time.sleep(1.0)
        now = _group_cpu_seconds(server.proc.pid)
        if now - before < 0.05:
            return
        before = now


def _get(port: int, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=2)
    try:
        conn.request("GET", path)
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def _group_cpu_seconds(pgid: int) -> float:
    """User + system CPU of every process in the process group (the server and its workers)."""
    total, tick = 0.0, os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:  # fields after the name: state ppid pgrp ...
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


# -- the clients (run in a process of their own: python -m bench.load --drive ...) ------------
def _lean_stream(port: int, model_id: str, bodies: list[bytes], stop_at: float, out: list[float],
                 resent: list[int]) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    headers = {"Content-Type": "application/json", **AUTH}
    conn.request("POST", "/v1/sessions", json.dumps({"model": model_id}), headers)
    sid = json.loads(conn.getresponse().read())["id"]
    path = f"/v1/sessions/{sid}/observations"
    seq = 0
    while seq < MAX_CHUNKS and (seq == 0 or time.perf_counter() < stop_at):  # one chunk at least
        body = b'{"seq":%d,"increments":%s}' % (seq, bodies[seq % len(bodies)])
        start = time.perf_counter()
        try:
            conn.request("POST", path, body, headers)
            response = conn.getresponse()
            text = response.read()
        except (ConnectionError, http.client.HTTPException):  # e.g. a keep-alive closed by the server
            conn.close()
            resent.append(seq)  # the same seq again: the service applies a chunk exactly once
            continue
        out.append(time.perf_counter() - start)
        if response.status != 200:
            raise RuntimeError(f"chunk {seq}: {response.status} {text[:200]!r}")
        seq += 1
    conn.request("DELETE", f"/v1/sessions/{sid}")
    conn.getresponse().read()
    conn.close()


def _new_session(port: int, model_id: str) -> str:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    conn.request("POST", "/v1/sessions", json.dumps({"model": model_id}), {"Content-Type": "application/json",
                                                                          **AUTH})
    sid = json.loads(conn.getresponse().read())["id"]
    conn.close()
    return sid


def _ws_stream(port: int, model_id: str, bodies: list[bytes], stop_at: float, out: list[float],
               resent: list[int]) -> None:
    """One WebSocket per stream (WS /v1/sessions/{id}/stream): a chunk sent, its answer read."""
    import websocket

    sid = _new_session(port, model_id)
    url = f"ws://127.0.0.1:{port}/v1/sessions/{sid}/stream"
    # skip_utf8_validation: websocket-client checks UTF-8 in Python, 4.4 ms of client CPU per 9 KB answer
    # (the answers are orjson's ASCII)
    connect = dict(header=[f"Authorization: Bearer {TOKEN}"], timeout=120, skip_utf8_validation=True)
    ws = websocket.create_connection(url, **connect)
    seq = 0
    while seq < MAX_CHUNKS and (seq == 0 or time.perf_counter() < stop_at):  # one chunk at least
        body = b'{"seq":%d,"increments":%s}' % (seq, bodies[seq % len(bodies)])
        start = time.perf_counter()
        try:
            ws.send(body, websocket.ABNF.OPCODE_TEXT)
            text = ws.recv()
        except (websocket.WebSocketException, OSError):  # the socket dropped: again, same seq
            ws = websocket.create_connection(url, **connect)
            resent.append(seq)
            continue
        out.append(time.perf_counter() - start)
        if not text.startswith('{"seq":'):
            raise RuntimeError(f"chunk {seq}: {text[:200]}")
        seq += 1
    ws.close()


def _urllib_stream(port: int, model_id: str, bodies: list[bytes], stop_at: float, out: list[float],
                   resent: list[int]) -> None:
    """The plainest client: urllib.request, a new connection per chunk (no keep-alive)."""
    import urllib.error
    import urllib.request

    sid = _new_session(port, model_id)
    url = f"http://127.0.0.1:{port}/v1/sessions/{sid}/observations"
    headers = {"Content-Type": "application/json", **AUTH}
    seq = 0
    while seq < MAX_CHUNKS and (seq == 0 or time.perf_counter() < stop_at):  # one chunk at least
        body = b'{"seq":%d,"increments":%s}' % (seq, bodies[seq % len(bodies)])
        start = time.perf_counter()
        try:
            with urllib.request.urlopen(urllib.request.Request(url, body, headers), timeout=120) as r:
                r.read()
        except urllib.error.HTTPError as exc:
            raise RuntimeError(f"chunk {seq}: {exc.code} {exc.read()[:200]!r}") from None
        except OSError:
            resent.append(seq)
            continue
        out.append(time.perf_counter() - start)
        seq += 1


def _drive_lean(port, model_id, chunks, streams, stop_at, resent, stream=None) -> list[list[float]]:
    bodies = [json.dumps(c, separators=(",", ":")).encode() for c in chunks]
    outs: list[list[float]] = [[] for _ in range(streams)]
    threads = [threading.Thread(target=stream or _lean_stream,
                                args=(port, model_id, bodies, stop_at, out, resent))
               for out in outs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return outs


async def _httpx_stream(client, url, model_id, chunks, stop_at, out, resent):
    import httpx

    sid = (await client.post(url + "/v1/sessions", json={"model": model_id})).json()["id"]
    seq = 0
    while seq < MAX_CHUNKS and (seq == 0 or time.perf_counter() < stop_at):  # one chunk at least
        start = time.perf_counter()
        try:
            r = await client.post(f"{url}/v1/sessions/{sid}/observations",
                                  json={"seq": seq, "increments": chunks[seq % len(chunks)]})
        except httpx.TransportError:
            resent.append(seq)  # the same seq again: the service applies a chunk exactly once
            continue
        out.append(time.perf_counter() - start)
        if r.status_code != 200:
            raise RuntimeError(f"chunk {seq}: {r.status_code} {r.text[:200]}")
        seq += 1
    await client.delete(f"{url}/v1/sessions/{sid}")


async def _drive_httpx(port, model_id, chunks, streams, stop_at, resent) -> list[list[float]]:
    import httpx

    url = f"http://127.0.0.1:{port}"
    outs: list[list[float]] = [[] for _ in range(streams)]
    limits = httpx.Limits(max_connections=streams, max_keepalive_connections=streams)
    async with httpx.AsyncClient(limits=limits, timeout=120, headers=AUTH) as client:
        await asyncio.gather(*(_httpx_stream(client, url, model_id, chunks, stop_at, out, resent)
                               for out in outs))
    return outs


def _drive(args) -> None:
    """Client process: warm up, drive the streams, print one JSON line of results."""
    chunks = json.loads(Path(args.chunks).read_text())
    drive = {"lean": _drive_lean, "httpx": lambda *a: asyncio.run(_drive_httpx(*a)),
             "ws": lambda *a: _drive_lean(*a, stream=_ws_stream),
             "urllib": lambda *a: _drive_lean(*a, stream=_urllib_stream)}[args.client]
    resent: list[int] = []
    # warm-up: one chunk at least per stream (a model loaded and its loops compiled outlast the 0.3 s)
    drive(args.port, args.model, chunks[:1], 1, time.perf_counter() + 0.3, [])
    cpu0, server0 = resource.getrusage(resource.RUSAGE_SELF), _group_cpu_seconds(args.server_pgid)
    start = time.perf_counter()
    outs = drive(args.port, args.model, chunks, args.streams, start + args.seconds, resent)
    elapsed = time.perf_counter() - start
    cpu1, server1 = resource.getrusage(resource.RUSAGE_SELF), _group_cpu_seconds(args.server_pgid)
    latencies = [x for out in outs for x in out]
    client_cpu = cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime
    print(json.dumps({"chunks": len(latencies), "elapsed": elapsed, "latencies": latencies,
                      "client_cpu": client_cpu, "server_cpu": server1 - server0, "resent": len(resent)}))


def _run_client(server: Server, kind: str, model_id: str, chunks_file: Path, streams: int,
                seconds: float) -> dict:
    cmd = [sys.executable, "-m", "bench.load", "--drive", "--client", kind, "--port", str(server.port),
           "--model", model_id, "--chunks", str(chunks_file), "--streams", str(streams),
           "--seconds", str(seconds), "--server-pgid", str(server.proc.pid)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{kind} client, {streams} streams: {done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _summary(runs: list[dict]) -> dict:
    lat = np.array([x for r in runs for x in r["latencies"]]) * 1e3
    elapsed = sum(r["elapsed"] for r in runs)
    chunks = len(lat)
    return {"chunks": chunks, "rate": chunks * CHUNK / elapsed, "p50": float(np.percentile(lat, 50)),
            "p99": float(np.percentile(lat, 99)),
            "server_ms": sum(r["server_cpu"] for r in runs) / chunks * 1e3,
            "client_cores": sum(r["client_cpu"] for r in runs) / elapsed,
            "resent": sum(r["resent"] for r in runs)}


def _engine_ms(model, offline, increments) -> float:
    """Median ms of the filter alone on one 100-row chunk (state (de)serialised as the service does), with
    one BLAS thread as a worker runs it."""
    from yauyau.solver.blas import limited_blas
    from yauyau.solver.methods import make_filter

    filt = make_filter(model, offline, None)
    state = filt.initial_state().to_dict()
    times = []
    with limited_blas(1):
        for k in range(200):
            chunk = increments[(k % 20) * CHUNK:(k % 20 + 1) * CHUNK]
            start = time.perf_counter()
            new_state, _ = filt.run(filt.state_from_dict(state), chunk)
            state = new_state.to_dict()
            times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


def _commit_ms(directory: Path, state: dict, response: dict, count: int = 300) -> dict[str, tuple]:
    """p50/p99 ms of one chunk's store round (read, write state + response, commit) per durability."""
    from yauyau.storage.session_store import SqliteSessionStore

    out = {}
    for level in ("normal", "full"):
        store = SqliteSessionStore(directory / f"commit-{level}.sqlite3", synchronous=level)
        sid = store.create("m", "yau-yau", state)
        times = []
        for seq in range(count):
            start = time.perf_counter()
            store.apply_chunk(sid, seq, lambda s: (state, response), encoded=True)
            times.append(time.perf_counter() - start)
        out[level] = (float(np.percentile(times, 50) * 1e3), float(np.percentile(times, 99) * 1e3))
    return out


def _store_round(model, offline, increments, directory: Path) -> dict[str, tuple]:
    from yauyau.service.sessions.chunks import chunk_response
    from yauyau.solver.methods import make_filter

    filt = make_filter(model, offline, None)
    state, _, response = chunk_response(0, filt.initial_state(), increments[:CHUNK], filt)
    return _commit_ms(directory, state.to_dict(), response)


def _write_doc(rows, engine_ms, commits, args, load, command, model) -> Path:
    doc = DOCS["stores"] if args.stores else DOCS["windows"] if args.windows else DOCS[args.example]
    what = ("1-D cubic sensor" if args.example == "1d" else "2-D rotation with a cubic sensor") + \
        f" (N = {model.spec.discretization.basis})"
    title = (", session stores" if args.stores else ", batch windows" if args.windows
             else "" if args.example == "1d" else ", 2-D")
    lines = ["## HTTP load (`yauyau serve`)" + title, "",
             f"`{command}`", "",
             f"{what}, chunks of {CHUNK} observations, {args.workers} uvicorn worker(s), "
             f"{args.seconds:g} s per row × {args.rounds} round(s), configurations interleaved; client "
             f"(its own process) and server share the machine's {os.cpu_count()} cores; load average at "
             f"the start {load:.1f}. The filter alone takes {engine_ms:.2f} ms per chunk "
             f"({CHUNK / engine_ms * 1e3:,.0f} obs/s) in the same run. Server CPU: ms of CPU time "
             "(all threads) per chunk; client CPU: cores the client process used; resent: chunks sent again "
             "after a transport error (same seq). *unbatched*: the working tree with micro-batching off "
             "(`YAUYAU_MAX_BATCH=1`). One chunk's session-store "
             "round (read, write state and response, commit) alone: "
             + "; ".join(f"synchronous={k} p50 {v[0]:.2f} ms, p99 {v[1]:.2f} ms" for k, v in commits.items())
             + ".", "",
             "| server | client | streams | chunks | observations/s | p50 ms | p99 ms "
             "| server CPU ms / chunk | client CPU cores | resent |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['server']} | {r['client']} | {r['streams']} | {r['chunks']} | {r['rate']:,.0f} "
                     f"| {r['p50']:.2f} | {r['p99']:.2f} | {r['server_ms']:.2f} | {r['client_cores']:.2f} "
                     f"| {r['resent']} |")
    lines += ["", *_verdicts(rows, args)]
    write_fragment(doc, lines)
    return doc


def _verdicts(rows, args) -> list[str]:
    """The issue's targets against this run (lean client)."""
    def row(server, streams):
        return next((r for r in rows if r["server"] == server and r["client"] == "lean"
                     and r["streams"] == streams), None)

    out = []
    most = max(r["streams"] for r in rows)
    ours = row("working tree", most)
    if args.example == "1d" and ours is not None:
        out.append(f"- {most} streams: {ours['rate']:,.0f} obs/s ({ours['rate'] / TARGET_RATE:.0%} of the "
                   f"{TARGET_RATE:,} target), p99 {ours['p99']:.1f} ms (target ≤ {TARGET_P99_MS:g} ms).")
    base = next((r["server"] for r in rows if r["server"].startswith("baseline")), None)
    if base is not None and row(base, 1) and row("working tree", 1):
        ratio = row("working tree", 1)["rate"] / row(base, 1)["rate"]
        out.append(f"- one stream: {ratio:.2f}× {base}'s throughput (target ≥ {TARGET_SINGLE:g}×).")
    for streams in sorted({r["streams"] for r in rows}):
        if row("unbatched", streams) and row("working tree", streams):
            ratio = row("working tree", streams)["rate"] / row("unbatched", streams)["rate"]
            target = f" (target ≥ {TARGET_2D:g}× at 64)" if args.example == "2d" and streams == 64 else ""
            out.append(f"- {streams} streams: batched {ratio:.2f}× unbatched throughput{target}.")
    return out


def _parse(argv):
    parser = argparse.ArgumentParser(prog="python -m bench.load", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 s per row")
    parser.add_argument("--seconds", type=float, default=None, help="duration per row (default 5)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=1, help="repeat every configuration (interleaved)")
    parser.add_argument("--baseline", metavar="REV",
                        help="also serve service/ and storage/ of this git revision")
    parser.add_argument("--clients", default="lean,httpx",
                        help="comma-separated: lean, httpx, urllib, ws (the WebSocket stream; not served by "
                             "a --baseline revision before it)")
    parser.add_argument("--example", choices=sorted(SPECS), default="1d",
                        help="the model served (default 1d)")
    parser.add_argument("--stores", action="store_true",
                        help="compare the session stores instead: SQLite and PostgreSQL (a server started "
                             "for the run), with one and two server processes")
    parser.add_argument("--windows", default="",
                        help="comma-separated batch windows in ms to compare instead (e.g. 0,1,2,5): the "
                             "working tree served once per window (YAUYAU_BATCH_WINDOW)")
    parser.add_argument("--tenants", action="store_true",
                        help="also serve the working tree with a tenants file (every request authenticated "
                             "and its session's owner checked)")
    parser.add_argument("--unbatched", action="store_true",
                        help="also serve the working tree with micro-batching off (YAUYAU_MAX_BATCH=1)")
    parser.add_argument("--streams-list", default=",".join(map(str, STREAMS)),
                        help="comma-separated concurrent streams per row (default 1,8,64)")
    parser.add_argument("--no-doc", action="store_true", help="print only; leave bench/results/load.md")
    # the client process (internal)
    parser.add_argument("--drive", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--client", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--model", help=argparse.SUPPRESS)
    parser.add_argument("--chunks", help=argparse.SUPPRESS)
    parser.add_argument("--streams", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--server-pgid", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.seconds = args.seconds or (1.0 if args.quick else 5.0)
    return args


def measure(args) -> tuple[list[dict], float, dict, dict, float]:
    """Serve every configuration the arguments name and drive it: (rows, engine ms per chunk, store
    round, the model, the load average before)."""
    load = os.getloadavg()[0]
    clients = [c for c in args.clients.split(",") if c]
    clients = [c for c in args.clients.split(",") if c]
    with tempfile.TemporaryDirectory(prefix="yauyau-load-") as tmp:
        tmp = Path(tmp)
        model, offline, model_id, increments = _prepare_store(tmp / "store", SPECS[args.example])
        chunks = [[[float(v) for v in row] for row in increments[i:i + CHUNK]]
                  for i in range(0, len(increments), CHUNK)]
        chunks_file = tmp / "chunks.json"
        chunks_file.write_text(json.dumps(chunks))
        engine_ms = _engine_ms(model, offline, increments)
        commits = _store_round(model, offline, increments, tmp)
        # name -> (tree, env, session db or None for a SQLite file of its own, workers)
        trees = {"working tree": (ROOT, {}, None, args.workers)}
        if args.unbatched:
            trees["unbatched"] = (ROOT, {"YAUYAU_MAX_BATCH": "1"}, None, args.workers)
        if args.tenants:
            env = {"YAUYAU_TENANTS_FILE": str(_tenants_file(tmp))}
            trees["working tree, tenants"] = (ROOT, env, None, args.workers)
        if args.baseline:
            baseline = _baseline_tree(args.baseline, tmp / "baseline")
            trees = {f"baseline {args.baseline}": (baseline, {}, None, args.workers), **trees}
        postgres = None
        servers = {}
        try:
            if args.windows:
                trees = {f"window {w} ms": (ROOT, {"YAUYAU_BATCH_WINDOW": str(float(w) / 1000)}, None,
                                            args.workers) for w in args.windows.split(",")}
            if args.stores:
                postgres = _postgres()
                trees = {f"{kind}, {w} process{'es' if w > 1 else ''}":
                         (ROOT, {}, postgres.database(f"load{w}") if kind == "postgres" else None, w)
                         for kind in ("sqlite", "postgres") for w in (1, 2)}
            for k, (name, (tree, env, db, workers)) in enumerate(trees.items()):
                db = db or tmp / f"sessions{k}.sqlite3"
                servers[name] = Server(tree, tmp / "store", db, workers, env)
            for server in servers.values():
                _wait_idle(server)
            runs: dict[tuple, list[dict]] = {}
            for _ in range(args.rounds):
                for streams in [int(v) for v in args.streams_list.split(",")]:
                    for name, server in servers.items():
                        for kind in clients:
                            if kind == "ws" and name.startswith("baseline"):
                                continue  # a revision before the WebSocket stream
                            result = _run_client(server, kind, model_id, chunks_file, streams, args.seconds)
                            runs.setdefault((name, kind, streams), []).append(result)
        finally:
            for server in servers.values():
                server.stop()
            if postgres is not None:
                postgres.stop()
    rows = [{"server": name, "client": kind, "streams": streams, **_summary(r)}
            for (name, kind, streams), r in runs.items()]
    order = {name: k for k, name in enumerate(servers)}
    rows.sort(key=lambda r: (r["client"] != "lean", r["streams"], order[r["server"]]))
    return rows, engine_ms, commits, model, load


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    if args.drive:
        _drive(args)
        return 0
    clients = [c for c in args.clients.split(",") if c]
    rows, engine_ms, commits, model, load = measure(args)
    for r in rows:
        print(f"{r['server'][:22]:>22} {r['client']:>5} {r['streams']:>3} streams: {r['rate']:>9,.0f} obs/s  "
              f"p50 {r['p50']:7.2f} ms  p99 {r['p99']:7.2f} ms  server {r['server_ms']:.2f} ms CPU/chunk  "
              f"client {r['client_cores']:.2f} cores")
    command = "python -m bench.load" + "".join(
        f" {flag}" for flag, on in ((f"--workers {args.workers}", args.workers != 1),
                                    (f"--seconds {args.seconds:g}", args.seconds != 5.0 and not args.quick),
                                    ("--quick", args.quick), (f"--rounds {args.rounds}", args.rounds != 1),
                                    (f"--baseline {args.baseline}", bool(args.baseline)),
                                    (f"--example {args.example}", args.example != "1d"),
                                    ("--unbatched", args.unbatched), ("--stores", args.stores),
                                    ("--tenants", args.tenants),
                                    (f"--windows {args.windows}", bool(args.windows)),
                                    (f"--streams-list {args.streams_list}",
                                     args.streams_list != ",".join(map(str, STREAMS))),
                                    (f"--clients {args.clients}", args.clients != "lean,httpx")) if on)
    for line in _verdicts(rows, args):
        print(line)
    if not args.no_doc and "lean" in clients:
        print(f"wrote {_write_doc(rows, engine_ms, commits, args, load, command, model)}")
    print(f"filter alone: {engine_ms:.2f} ms per chunk; store round {commits}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
