"""What the limits on what clients hold cost one stream (issue "Trust", item 3): the rate limiter and the
connection bookkeeping are on every request's path.

    python -m bench.limits_cost [--against main] [--rounds 5] [--chunks 500]

Serves revision ``--against`` (its solver/, service/, storage/) and this tree side by side, each with one
worker, and posts ``--chunks`` chunks of 100 increments of the 1-D cubic sensor over one keep-alive
connection (``http.client``, bodies encoded beforehand), to each server in turn, ``--rounds`` times.
Prints each round's median latency and the server's CPU per chunk (from /proc), then the medians over
rounds.  Prints only: nothing is written.
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
                for name, server in servers.items():
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
    print(f"medians over {args.rounds} rounds of {args.chunks} chunks:")
    for name, rounds in results.items():
        print(f"{name:>16}: p50 {statistics.median(r[0] for r in rounds):.3f} ms, "
              f"server CPU {statistics.median(r[1] for r in rounds):.3f} ms/chunk")
    return 0


if __name__ == "__main__":
    sys.exit(main())
