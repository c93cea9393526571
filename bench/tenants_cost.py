"""What tenants cost a chunk: one stream of 100-increment chunks over loopback, side by side.

    python -m bench.tenants_cost [--baseline REV] [--chunks N] [--rounds R]

Serves, interleaved round by round so that they share the machine's load: git revision REV (default
main: no Host check, no tenants), the working tree without a tenants file (the Host check), and the
working tree with a tenants file of 100 tenants (the Host check, a bearer token hashed and compared
with all 100 hashes, the owner checked on every chunk).  One keep-alive ``http.client`` connection
posts N chunks back to back; reported: the median and p90 latency per chunk and the server's CPU
time per chunk (from /proc, steadier than wall time on a shared machine).
"""

from __future__ import annotations

import argparse
import hashlib
import http.client
import json
import statistics
import tempfile
import time
from pathlib import Path

from .load import CHUNK, ROOT, Server, _baseline_tree, _group_cpu_seconds, _prepare_store

TOKEN = "bench-token-of-tenant-99"


def _tenants_file(path: Path, count: int = 100) -> Path:
    lines = []
    for i in range(count):
        digest = hashlib.sha256(f"bench-token-of-tenant-{i}".encode()).hexdigest()
        lines.append(f'[[tenant]]\nname = "t{i}"\ntoken_sha256 = "{digest}"\n')
    path.write_text("\n".join(lines))
    return path


def _stream(server: Server, model_id: str, bodies: list[bytes], chunks: int,
            token: str | None) -> tuple[list[float], float]:
    """Latencies of ``chunks`` chunks of one session, and the server's CPU seconds meanwhile."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=120)
    headers = {"Content-Type": "application/json"}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    conn.request("POST", "/v1/sessions", json.dumps({"model": model_id}), headers)
    sid = json.loads(conn.getresponse().read())["id"]
    path, took = f"/v1/sessions/{sid}/observations", []
    cpu = _group_cpu_seconds(server.proc.pid)
    for seq in range(chunks):
        start = time.perf_counter()
        conn.request("POST", path, b'{"seq":%d,"increments":%s}' % (seq, bodies[seq % len(bodies)]), headers)
        response = conn.getresponse()
        text = response.read()
        took.append(time.perf_counter() - start)
        if response.status != 200:
            raise RuntimeError(f"chunk {seq}: {response.status} {text[:200]!r}")
    cpu = _group_cpu_seconds(server.proc.pid) - cpu
    conn.request("DELETE", f"/v1/sessions/{sid}", headers=headers)
    conn.getresponse().read()
    conn.close()
    return took, cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="git revision served as the baseline")
    parser.add_argument("--chunks", type=int, default=400, help="chunks per stream and round")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="yauyau-tenants-cost-") as tmp:
        tmp = Path(tmp)
        store = tmp / "store"
        _, _, model_id, increments = _prepare_store(store, ROOT / "examples" / "cubic_sensor.toml")
        bodies = [json.dumps(increments[i * CHUNK:(i + 1) * CHUNK].tolist(), separators=(",", ":")).encode()
                  for i in range(len(increments) // CHUNK)]
        tenants = _tenants_file(tmp / "tenants.toml")
        configs = {f"{args.baseline} (no checks)": (_baseline_tree(args.baseline, tmp / "base"), {}, None),
                   "tree, no tenants (Host check)": (ROOT, {}, None),
                   "tree, 100 tenants (Host + token + owner)": (ROOT, {"YAUYAU_TENANTS_FILE": str(tenants)},
                                                                TOKEN)}
        servers = {name: Server(tree, store, tmp / f"s{i}.sqlite3", 1, env)
                   for i, (name, (tree, env, _)) in enumerate(configs.items())}
        results: dict[str, tuple[list[float], float]] = {name: ([], 0.0) for name in configs}
        try:
            for name, server in servers.items():  # warm-up: models loaded, code paths taken
                _stream(server, model_id, bodies, 20, configs[name][2])
            for _ in range(args.rounds):
                for name, server in servers.items():
                    took, cpu = _stream(server, model_id, bodies, args.chunks, configs[name][2])
                    results[name] = (results[name][0] + took, results[name][1] + cpu)
        finally:
            for server in servers.values():
                server.stop()
    base = None
    print(f"one stream, {CHUNK} increments per chunk, {args.rounds} x {args.chunks} chunks per configuration")
    print(f"{'configuration':44} {'median ms':>10} {'p90 ms':>8} {'server CPU ms/chunk':>20} "
          f"{'vs baseline':>12}")
    for name, (took, cpu) in results.items():
        median = statistics.median(took) * 1e3
        p90 = sorted(took)[int(0.9 * len(took))] * 1e3
        per_chunk = cpu / len(took) * 1e3
        base = base or median
        print(f"{name:44} {median:10.3f} {p90:8.3f} {per_chunk:20.3f} {median / base - 1:+11.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
