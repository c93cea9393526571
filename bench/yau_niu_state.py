"""The Yau–Niu session state's stored form: its size and what it costs a chunk over HTTP.

    python -m bench.yau_niu_state [--against REV] [--rounds R]   # writes bench/results/yau-niu-state.md

Two parts.  (1) The codecs of the points and log weights (solver/qmc/packed.py) on the states after 57
rows of the 4-D linear ring at 8192 points (one block) and of 100 independent cubic sensors at 4096
points (100 blocks): stored bytes and the CPU of encode + orjson dumps + loads + decode, medians of 7,
for the JSON lists states were stored as before, the base64 of the raw float64 bytes (this tree's
form), zlib (level 1) of them in base64, and byte-shuffled + zlib in base64.  (2) A 100-state session
(the cubic sensors, 4096 points) over HTTP, in process (FastAPI's TestClient, SQLite store): the
process CPU and wall time a chunk of 1 and of 10 rows (20 chunks, medians of the last 14), in a fresh
process per tree, this tree and REV (default db398ce, the list form; a ``git archive`` of it in a
temporary folder, run once uncounted first: its numba cache is empty, and the warm-up thread's
compiling doubled its first figures), alternating, R rounds.  One BLAS thread.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "yau-niu-state.md"


def _cubic(n: int, points: int) -> dict:
    return {"name": f"cubic{n}", "state": [f"x{i}" for i in range(n)],
            "drift": [f"-0.5*x{i}" for i in range(n)], "observation": [f"x{i}**3" for i in range(n)],
            "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n, dtype=int).tolist()},
            "method": "yau-niu", "discretization": {"dt": 0.01, "points": points}}


def _ring(n: int, points: int) -> dict:
    drift = [f"-0.5*x{i}" + (f" + 0.3*x{i + 1}" if i + 1 < n else "") + (f" - 0.3*x{i - 1}" if i else "")
             for i in range(n)]
    return {"name": "ring", "state": [f"x{i}" for i in range(n)], "drift": drift,
            "observation": ["x0 + 0.2*x1", "x1 + 0.2*x2"], "observation_noise": (0.1 * np.eye(2)).tolist(),
            "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
            "method": "yau-niu", "discretization": {"dt": 0.01, "points": points}}


def _shuffled(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, 8).T).tobytes()


def _unshuffled(raw: bytes, shape: list[int]) -> np.ndarray:
    return np.frombuffer(raw, np.uint8).reshape(8, -1).T.copy().view("<f8").reshape(shape)


def _codecs() -> dict:
    from yauyau.solver.qmc.packed import pack, unpack

    def z64(raw: bytes) -> str:
        return base64.b64encode(zlib.compress(raw, 1)).decode("ascii")

    return {
        "JSON lists (before)": (lambda a: a.tolist(), lambda v, s: np.asarray(v, float)),
        "base64 of the bytes (this tree)": (pack, lambda v, s: unpack(v, "x", tuple(s))),
        "zlib + base64": (lambda a: z64(a.tobytes()),
                          lambda v, s: np.frombuffer(zlib.decompress(base64.b64decode(v)), "<f8").reshape(s)),
        "byte-shuffled + zlib + base64": (lambda a: z64(_shuffled(a)),
                                          lambda v, s: _unshuffled(zlib.decompress(base64.b64decode(v)), s)),
    }


def codec_rows() -> list[tuple[str, str, int, float]]:
    import orjson
    from yauyau.solver.model import compile_model
    from yauyau.solver.qmc.yau_niu import YauNiuFilter
    from yauyau.solver.simulate import simulate
    from yauyau.solver.spec import spec_from_dict

    out = []
    cases = (("4-D ring, 8192 points", _ring(4, 8192)), ("100 sensors, 4096 points", _cubic(100, 4096)))
    for label, doc in cases:
        model = compile_model(spec_from_dict(doc))
        flt = YauNiuFilter(model)
        rows = simulate(model, 57, np.random.default_rng(1)).increments
        state, _ = flt.run_arrays(flt.initial_state(), rows)
        numbers = state.points.size + state.log_weights.size
        for name, (encode, decode) in _codecs().items():
            times = []
            for _ in range(7):
                start = time.process_time()
                data = {"points": encode(state.points), "log_weights": encode(state.log_weights)}
                text = orjson.dumps(data)
                back = orjson.loads(text)
                X = decode(back["points"], list(state.points.shape))
                L = decode(back["log_weights"], list(state.log_weights.shape))
                times.append(time.process_time() - start)
            assert np.array_equal(X, state.points) and np.array_equal(L, state.log_weights)
            out.append((f"{label} ({numbers} numbers)", name, len(text), 1e3 * statistics.median(times)))
            print(out[-1], flush=True)
    return out


CHUNKS = """
import json, statistics, sys, tempfile, time
tree = {tree!r}
sys.path.insert(0, tree)
from pathlib import Path
import numpy as np
from fastapi.testclient import TestClient
from threadpoolctl import threadpool_limits
import yauyau
import yauyau.solver.qmc.yau_niu as niu
assert niu.__file__.startswith(tree), niu.__file__
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings
from yauyau.solver.spec import spec_from_dict
tmp = Path(tempfile.mkdtemp())
spec = spec_from_dict(json.loads({doc!r}))
mid = yauyau.precompute(spec, tmp / "store")
rows = np.load({rows!r})
app = create_app(Settings(store=tmp / "store", session_db=tmp / "s.sqlite3"))
out = {{}}
with threadpool_limits(1), TestClient(app, base_url="http://localhost") as client:
    time.sleep(6)  # the warm-up thread
    for K in (1, 10):
        made = client.post("/v1/sessions", json={{"model": mid}})
        assert made.status_code == 201, made.text
        sid, cpu, wall = made.json()["id"], [], []
        for seq in range(20):
            body = {{"seq": seq, "increments": rows[K * seq:K * (seq + 1)].tolist()}}
            c0, w0 = time.process_time(), time.perf_counter()
            r = client.post(f"/v1/sessions/{{sid}}/observations", json=body)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            assert r.status_code == 200, r.text
        out[K] = (1e3 * statistics.median(cpu[6:]), 1e3 * statistics.median(wall[6:]))
print(json.dumps(out))
"""


def chunk_costs(tree: Path, rows: Path) -> dict[str, list[float]]:
    script = CHUNKS.format(tree=str(tree), doc=json.dumps(_cubic(100, 4096)), rows=str(rows))
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, cwd=tree)
    if done.returncode and not done.stdout.strip():
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])  # (numba may abort at exit: its output is in)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_niu_state",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="db398ce", help="the revision storing lists (default db398ce)")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from yauyau.solver.model import compile_model
    from yauyau.solver.simulate import simulate
    from yauyau.solver.spec import spec_from_dict

    loads = [os.getloadavg()[0]]
    codecs = codec_rows()
    loads.append(os.getloadavg()[0])
    costs: dict[str, dict[str, list[list[float]]]] = {"this tree": {}, args.against: {}}
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        old.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.against], check=True,
                                 capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive.stdout, check=True)
        rows = Path(tmp) / "rows.npy"
        np.save(rows, simulate(compile_model(spec_from_dict(_cubic(100, 4096))), 200,
                               np.random.default_rng(3)).increments)
        chunk_costs(old, rows)  # not counted: fills the new folder's numba cache (its warm-up compiles)
        for _ in range(args.rounds):
            for name, tree in ((args.against, old), ("this tree", ROOT)):
                for K, figures in chunk_costs(tree, rows).items():
                    costs[name].setdefault(K, []).append(figures)
                print(name, costs[name], flush=True)
                loads.append(os.getloadavg()[0])
    lines = ["## Yau-Niu: the session state's stored form", "",
             f"`python -m bench.yau_niu_state --against {args.against} --rounds {args.rounds}`: "
             f"load average {min(loads):.1f}–{max(loads):.1f} on 2 cores. "
             + " ".join(__doc__.split("\n\n")[2].split()), "",
             "| state | form | stored bytes | bytes a number | encode + decode, ms (CPU) |",
             "|---|---|---:|---:|---:|"]
    for label, name, size, ms in codecs:
        numbers = int(label.split("(")[1].split()[0])
        lines.append(f"| {label} | {name} | {size:,} | {size / numbers:.2f} | {ms:.1f} |")
    lines += ["", "| 100 sensors, 4096 points, over HTTP | rows a chunk | process CPU a chunk, ms "
                  "| wall a chunk, ms |", "|---|---:|---:|---:|"]
    for name, by_k in costs.items():
        for K, runs in by_k.items():
            cpu = statistics.median(r[0] for r in runs)
            wall = statistics.median(r[1] for r in runs)
            lines.append(f"| {name} | {K} | {cpu:.0f} | {wall:.0f} |")
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
