"""What the limits on what clients hold cost one stream (issue "Trust", item 3): the rate limiter and the
connection bookkeeping are on every request's path.

    python -m bench.limits_cost [--against main] [--rounds 5] [--chunks 500]

Serves revision ``--against`` (its solver/, service/, storage/) and this tree side by side, each with one
worker, and posts ``--chunks`` chunks of 100 increments of the 1-D cubic sensor over one keep-alive
connection (``http.client``, bodies encoded beforehand), to each server in turn (the first of a round
alternating), ``--rounds`` times.
Prints each round's median latency and the server's CPU per chunk (from /proc), then the medians over
rounds.  On a shared machine these vary by more than what is measured, so the added work is also timed
alone, in-process: the RateLimits middleware around an application that does nothing (a client's two
buckets, a session creation's give-back), and one request's connection bookkeeping (a deadline armed
and cancelled, the waiting list entered and left).  Prints only: nothing is written.
"""

from __future__ import annotations

import argparse
import http.client
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from .load import CHUNK, ROOT, SPECS, Server, _baseline_tree, _group_cpu_seconds, _prepare_store


def _one_stream(port: int, model_id: str, bodies: list[bytes]) -> list[float]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    headers = {"Content-Type": "application/json"}
    conn.request("POST", "/v1/sessions", json.dumps({"model": model_id}), headers)
    sid = json.loads(conn.getresponse().read())["id"]
    out = []
    for seq, body in enumerate(bodies):
        start = time.perf_counter()
        conn.request("POST", f"/v1/sessions/{sid}/observations", body.replace(b'"SEQ"', str(seq).encode()),
                     headers)
        response = conn.getresponse()
        response.read()
        out.append(time.perf_counter() - start)
        if response.status != 200:
            raise RuntimeError(f"chunk {seq}: {response.status}")
    conn.close()
    return out


def _per_call_us(call, count: int = 20_000) -> float:
    start = time.perf_counter()
    for _ in range(count):
        call()
    return (time.perf_counter() - start) / count * 1e6


def _micro() -> dict[str, float]:
    """Microseconds per request of what the limits add, each timed alone (medians of 5)."""
    import asyncio

    from yauyau.service.http.connections import ConnectionGuard
    from yauyau.service.http.limits import RateLimits, TokenBuckets

    async def nothing(scope, receive, send):
        await send({"type": "http.response.start", "status": 201, "headers": []})

    async def sink(message):
        pass

    limited = RateLimits(nothing, TokenBuckets(1e9, 1e9), TokenBuckets(1e9, 1e9))
    scope = {"type": "http", "method": "POST", "path": "/v1/sessions/abc/observations", "state": {},
             "client": ("127.0.0.1", 1)}
    create = {**scope, "path": "/v1/sessions"}
    loop = asyncio.new_event_loop()

    def requests(app, scope):
        async def many(count):
            for _ in range(count):
                await app(scope, None, sink)

        return lambda: loop.run_until_complete(many(1000))

    class Conn:
        def evict(self):
            pass

    guard = ConnectionGuard(loop, 10_000, 10.0)
    conns = [Conn() for _ in range(1000)]
    for conn in conns:
        guard.opened(conn)

    def kept_alive():  # 1000 requests on kept-alive connections: each head arrives, each response completes
        for conn in conns:
            guard.head_received(conn)
            guard.wait_for_head(conn)

    def connections():  # 1000 connections opened (a head deadline armed), served and closed
        for conn in conns:
            guard.closed(conn)
            guard.opened(conn)
            loop.call_later(10.0, print).cancel()

    runs = {"app alone": requests(nothing, scope), "rate limits, a chunk": requests(limited, scope),
            "rate limits, a creation": requests(limited, create), "bookkeeping, a request": kept_alive,
            "bookkeeping, a connection": connections}
    out = {name: statistics.median(_per_call_us(run, 20) / 1000 for _ in range(5))
           for name, run in runs.items()}
    loop.close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.limits_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="main")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--chunks", type=int, default=500)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="yauyau-limits-") as tmp:
        tmp = Path(tmp)
        _, _, model_id, increments = _prepare_store(tmp / "store", SPECS["1d"])
        rows = [increments[(k * CHUNK) % len(increments):][:CHUNK].tolist() for k in range(args.chunks)]
        bodies = [json.dumps({"seq": "SEQ", "increments": r}).encode() for r in rows]
        trees = {f"before ({args.against})": _baseline_tree(args.against, tmp / "before"), "this tree": ROOT}
        servers = {name: Server(tree, tmp / "store", tmp / f"{k}.sqlite3", 1)
                   for k, (name, tree) in enumerate(trees.items())}
        results: dict[str, list[tuple[float, float]]] = {name: [] for name in servers}
        try:
            for round_ in range(args.rounds):
                order = list(servers.items())
                for name, server in order if round_ % 2 == 0 else order[::-1]:  # who goes first alternates
                    cpu = _group_cpu_seconds(server.proc.pid)
                    latencies = _one_stream(server.port, model_id, bodies)
                    cpu_ms = (_group_cpu_seconds(server.proc.pid) - cpu) * 1000 / len(bodies)
                    p50 = statistics.median(latencies) * 1000
                    results[name].append((p50, cpu_ms))
                    print(f"round {round_ + 1} {name:>16}: p50 {p50:.3f} ms, "
                          f"server CPU {cpu_ms:.3f} ms/chunk", flush=True)
        finally:
            for server in servers.values():
                server.stop()
    micro = _micro()
    print("in-process, µs per request: " + ", ".join(f"{name} {us:.2f}" for name, us in micro.items()))
    print(f"medians over {args.rounds} rounds of {args.chunks} chunks:")
    for name, rounds in results.items():
        print(f"{name:>16}: p50 {statistics.median(r[0] for r in rounds):.3f} ms, "
              f"server CPU {statistics.median(r[1] for r in rounds):.3f} ms/chunk")
    return 0


if __name__ == "__main__":
    sys.exit(main())
