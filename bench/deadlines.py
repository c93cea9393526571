"""How long past their limits the analysis deadlines end, what two analyses cost a stream's chunks beside
them, and the per-request latency over keep-alive with two workers: the timings that the tests used to
assert (they now assert the mechanisms, which load does not change: the report of an analysis stopped
at its limit, TCP_NODELAY on the sockets a worker accepts).

    python -m bench.deadlines [--repeats 3] [--quick]

1. ``yauyau analyze --time-limit 1`` on the 3-D model of tests/service/cli/test_cli_analyze.py (without
   its bounds it ran for more than 5 minutes): the command's wall time and the report's elapsed_s,
   against the limit + the grace (2 s) after which its process is killed.
2. A real `yauyau serve` (one worker, YAUYAU_ANALYZE_TIME_LIMIT 0.2, YAUYAU_ANALYZE_GRACE 0.5) and the
   attack spec of issue "Hardening" (h = (x+y+z+1)^24): the first POST /v1/analyze (it starts the
   analysis forkserver), then two at once (the second waits for the one slot at most its limit: 503),
   while one stream posts chunks of 50 rows of the OU example; the chunks' median latency alone and
   beside the analyses.
3. Two workers, one keep-alive connection, 60 chunks of 5 rows: the median per request after 10 (without
   TCP_NODELAY on the accepted sockets each response waited for the client's delayed ACK: ~44 ms).

Writes bench/results/deadlines.md.
"""

from __future__ import annotations

import argparse
import http.client
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yauyau

from . import load
from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "bench" / "results" / "deadlines.md"
NASTY = {"name": "nasty", "state": ["x", "y", "z"],
         "drift": ["sin(x*y)*exp(z) + tanh(y)", "cos(x+z)**3 - y", "atan(x*y*z)"],
         "observation": ["x**3*y + sin(z)", "exp(-x**2)*y"],
         "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0],
                     "cov": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
         "domain": {"radius": 3.0}, "discretization": {"dt": 0.01, "basis": 20}}
ROWS = [[0.01 * ((i * 7) % 5 - 2)] for i in range(50)]


def attack_spec() -> dict:
    """tests/helpers/specs.py's dos_spec(24), the spec the hardening tests analyse."""
    sys.path.insert(0, str(ROOT / "tests"))  # lazy: the tests' helpers are not a package of the project
    from helpers.specs import dos_spec

    return dos_spec(24)


def analyze_cli(directory: Path, repeats: int) -> list[tuple[float, float, str]]:
    """(wall s, the report's elapsed_s, stopped_by) of ``yauyau analyze --time-limit 1`` on NASTY."""
    spec = directory / "nasty.json"
    spec.write_text(json.dumps(NASTY))
    out = []
    for _ in range(repeats):
        began = time.perf_counter()
        command = ["analyze", str(spec), "--time-limit", "1", "--max-size", "1000000",
                   "--max-dimension", "64", "--json"]
        done = subprocess.run([sys.executable, "-m", "yauyau.service.cli", *command], capture_output=True,
                              text=True, timeout=600, check=True)
        report = json.loads(done.stdout)
        out.append((time.perf_counter() - began, report["elapsed_s"],
                    report["estimation_algebra"]["stopped_by"]))
    return out


def post(conn: http.client.HTTPConnection, path: str, body: dict) -> tuple[int, dict, float]:
    """(status, JSON answer, seconds) of one POST on a kept-alive connection."""
    began = time.perf_counter()
    conn.request("POST", path, json.dumps(body), {"Content-Type": "application/json"})
    response = conn.getresponse()
    return response.status, json.loads(response.read()), time.perf_counter() - began


def chunk_latencies(port: int, session: str, seq0: int, count: int, rows: list) -> list[float]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    try:
        return [post(conn, f"/v1/sessions/{session}/observations", {"seq": seq0 + k, "increments": rows})[2]
                for k in range(count)]
    finally:
        conn.close()


def new_session(port: int, model_id: str) -> str:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    try:
        return post(conn, "/v1/sessions", {"model": model_id})[1]["id"]
    finally:
        conn.close()


def analyses_beside_chunks(store: Path, model_id: str, directory: Path) -> dict:
    """Part 2: the first analysis, then two at once beside a stream's chunks."""
    env = {"YAUYAU_ANALYZE_TIME_LIMIT": "0.2", "YAUYAU_ANALYZE_GRACE": "0.5"}
    server = load.Server(ROOT, store, directory / "s2.sqlite3", 1, env)
    try:
        session = new_session(server.port, model_id)

        def analyse(into: list):
            conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=600)
            into.append(post(conn, "/v1/analyze", attack_spec()))
            conn.close()

        first: list = []
        analyse(first)
        quiet = chunk_latencies(server.port, session, 0, 30, ROWS)
        answers: list = []
        threads = [threading.Thread(target=analyse, args=(answers,)) for _ in range(2)]
        for thread in threads:
            thread.start()
        busy = chunk_latencies(server.port, session, 30, 30, ROWS)
        for thread in threads:
            thread.join()
    finally:
        server.stop()
    return {"first": first[0], "answers": answers, "quiet": quiet, "busy": busy}


def keep_alive(store: Path, model_id: str, directory: Path) -> float:
    """Part 3: the median seconds per chunk of 5 rows over one keep-alive connection, two workers."""
    server = load.Server(ROOT, store, directory / "s3.sqlite3", 2)
    try:
        took = chunk_latencies(server.port, new_session(server.port, model_id), 0, 60, ROWS[:5])
    finally:
        server.stop()
    return statistics.median(took[10:])


def render(cli: list, served: dict, keep_alive_s: float, command: str) -> list[str]:
    first_status, _, first_s = served["first"]
    lines = ["## Deadlines and the chunk path beside them", "",
             f"`{command}`; one run, wall-clock times.", "",
             "| what | limit + grace | measured |", "|---|---|---|"]
    for wall, elapsed, stopped in cli:
        lines.append(f"| `yauyau analyze --time-limit 1` (stopped by {stopped}) | 1 + 2 s | "
                     f"{wall:.2f} s wall, elapsed_s {elapsed:.2f} |")
    lines.append(f"| first POST /v1/analyze (starts the forkserver): {first_status} | 0.2 + 0.5 s | "
                 f"{first_s:.2f} s |")
    for status, _, seconds in served["answers"]:
        lines.append(f"| POST /v1/analyze, two at once: {status} | 0.2 + 0.5 s (+ 0.2 s slot wait) | "
                     f"{seconds:.2f} s |")
    lines += ["", f"Chunks of 50 rows (OU), median: {statistics.median(served['quiet']) * 1e3:.1f} ms alone, "
              f"{statistics.median(served['busy']) * 1e3:.1f} ms beside the two analyses. Two workers, one "
              f"keep-alive connection, chunks of 5 rows: median {keep_alive_s * 1e3:.1f} ms per request "
              "(the delayed-ACK stall that TCP_NODELAY removes would show as ~44 ms)."]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.deadlines", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs of yauyau analyze")
    parser.add_argument("--quick", action="store_true", help="one run of yauyau analyze")
    args = parser.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        store = directory / "store"
        model_id = yauyau.precompute(ROOT / "examples" / "ou.toml", store)
        cli = analyze_cli(directory, repeats)
        served = analyses_beside_chunks(store, model_id, directory)
        keep_alive_s = keep_alive(store, model_id, directory)
    command = "python -m bench.deadlines" + (" --quick" if args.quick else f" --repeats {repeats}")
    lines = render(cli, served, keep_alive_s, command)
    print("\n".join(lines))
    write_fragment(DOC, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
