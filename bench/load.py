"""HTTP load benchmark: observations/s and latency per 100-observation chunk over loopback.

    python -m bench.load [--quick] [--seconds S] [--workers K]

Starts `yauyau serve` itself (the 1-D cubic-sensor example, precomputed into a temporary store),
then drives 1, 8 and 64 concurrent sessions, each posting chunks of 100 increments back to back
(httpx, asyncio) for a bounded time.  The engine alone on the same chunks is timed in the same run
so that the HTTP + SQLite overhead shows as a ratio.  Writes docs/bench-load.md.
Targets: >= 20 000 observations/s with one worker, p99 <= 10 ms per 100-observation chunk.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "examples" / "cubic_sensor.toml"
DOC = ROOT / "docs" / "bench-load.md"
CHUNK = 100
TARGET_RATE, TARGET_P99_MS = 20_000, 10.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _prepare_store(store: Path):
    from solver.model import compile_model
    from solver.offline import precompute
    from solver.simulate import simulate
    from solver.spec import load_spec
    from storage.model_store import ModelStore

    spec = load_spec(SPEC)
    model = compile_model(spec)
    offline = precompute(model)
    model_id = ModelStore(store).save(spec.canonical_json(), offline.to_arrays(), {})
    increments = simulate(model, 20 * CHUNK, np.random.default_rng(0)).increments
    return model, offline, model_id, increments


def _start_server(store: Path, workers: int) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    cmd = [sys.executable, "-m", "service.cli", "serve", "--store", str(store), "--port", str(port),
           "--workers", str(workers), "--log-level", "warning"]
    proc = subprocess.Popen(cmd, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    raise RuntimeError("server did not start")


async def _stream(client, url, model_id, chunks, stop_at, latencies):
    sid = (await client.post(url + "/v1/sessions", json={"model": model_id})).json()["id"]
    seq = 0
    while time.perf_counter() < stop_at:
        rows = chunks[seq % len(chunks)]
        start = time.perf_counter()
        r = await client.post(f"{url}/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows})
        latencies.append(time.perf_counter() - start)
        if r.status_code != 200:
            raise RuntimeError(f"chunk {seq}: {r.status_code} {r.text[:200]}")
        seq += 1
    await client.delete(f"{url}/v1/sessions/{sid}")


async def _drive(url, model_id, chunks, streams, seconds) -> dict:
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=streams, max_keepalive_connections=streams)
    async with httpx.AsyncClient(limits=limits, timeout=60) as client:
        await _stream(client, url, model_id, chunks[:1], time.perf_counter() + 0.5, [])  # warm-up
        start = time.perf_counter()
        stop_at = start + seconds
        await asyncio.gather(*(_stream(client, url, model_id, chunks, stop_at, latencies)
                               for _ in range(streams)))
        elapsed = time.perf_counter() - start
    lat = np.array(latencies) * 1e3
    return {"streams": streams, "chunks": len(lat), "rate": len(lat) * CHUNK / elapsed,
            "p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99))}


def _engine_ms(model, offline, increments) -> float:
    """Median ms of the filter alone on one 100-row chunk (state (de)serialised as the service does)."""
    from solver.methods import make_filter

    filt = make_filter(model, offline, None)
    state = filt.initial_state().to_dict()
    times = []
    for k in range(200):
        chunk = increments[(k % 20) * CHUNK:(k % 20 + 1) * CHUNK]
        start = time.perf_counter()
        new_state, _ = filt.run(filt.state_from_dict(state), chunk)
        state = new_state.to_dict()
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


def _write_doc(rows, engine_ms, workers, seconds, load, command) -> None:
    lines = ["## HTTP load (`yauyau serve`)", "", f"`{command}`", "",
             f"1-D cubic sensor (N = 128), chunks of {CHUNK} observations, {workers} uvicorn worker(s), "
             f"{seconds:g} s per row; client (httpx asyncio) and server share the 2 cores; "
             f"load average at the start {load:.1f}. The filter alone takes {engine_ms:.2f} ms per chunk "
             f"({CHUNK / engine_ms * 1e3:,.0f} obs/s) in the same run.", "",
             "| concurrent streams | chunks | observations/s | p50 ms / chunk | p99 ms / chunk "
             "| × filter alone (p50) |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['streams']} | {r['chunks']} | {r['rate']:,.0f} | {r['p50']:.2f} "
                     f"| {r['p99']:.2f} | {r['p50'] / engine_ms:.1f} |")
    best = max(r["rate"] for r in rows)
    single = rows[0]
    lines += ["", f"Targets (one worker): ≥ {TARGET_RATE:,} obs/s — best {best:,.0f} "
              f"({best / TARGET_RATE:.0%} of target); p99 ≤ {TARGET_P99_MS:g} ms per chunk — "
              f"{single['p99']:.2f} ms with one stream ({single['p99'] / TARGET_P99_MS:.0%} of the budget)."]
    DOC.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.load", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 s per row")
    parser.add_argument("--seconds", type=float, default=None, help="duration per concurrency (default 5)")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args(argv)
    seconds = args.seconds or (1.0 if args.quick else 5.0)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="yauyau-load-") as tmp:
        store = Path(tmp) / "store"
        model, offline, model_id, increments = _prepare_store(store)
        chunks = [[[float(v) for v in row] for row in increments[i:i + CHUNK]]
                  for i in range(0, len(increments), CHUNK)]
        engine_ms = _engine_ms(model, offline, increments)
        proc, url = _start_server(store, args.workers)
        try:
            rows = [asyncio.run(_drive(url, model_id, chunks, streams, seconds)) for streams in (1, 8, 64)]
        finally:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=30)
    for r in rows:
        print(f"{r['streams']:>3} streams: {r['rate']:>9,.0f} obs/s  "
              f"p50 {r['p50']:.2f} ms  p99 {r['p99']:.2f} ms")
    command = "python -m bench.load" + (f" --workers {args.workers}" if args.workers != 1 else "")
    _write_doc(rows, engine_ms, args.workers, seconds, load, command)
    print(f"filter alone: {engine_ms:.2f} ms per chunk; wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
