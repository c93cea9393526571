"""The engine's cost per row by chunk size, this tree against an earlier revision, side by side in one run.

    python -m bench.chunk_overhead [--against REV] [--rounds 5]

The bundled 1-D cubic sensor (``examples/cubic_sensor.toml``, N = 128): µs of process CPU time per row
through ``OnlineFilter.run`` in chunks of 100 and of 1000 rows, ``YauYauFilter.run_arrays`` in chunks
of 100, and ``run_batch`` of 64 states with a 100-row chunk each (the service's batcher), one BLAS
thread.  Each round runs each revision in a fresh process (the earlier one from a temporary
``git worktree``), alternating; the table gives the medians over rounds.  The difference between the
chunk sizes is the fixed cost of a chunk (the Python around the compiled rows).  Prints the table; it
writes no fragment.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ROUND = """
import json, sys, tempfile, time
sys.meta_path[:] = [f for f in sys.meta_path if "ditable" not in repr(f)]  # not the installed checkout
sys.path.insert(0, {tree!r})
import numpy as np
import yauyau
assert yauyau.__file__.startswith({tree!r}), yauyau.__file__
spec = yauyau.load_spec({tree!r} + "/examples/cubic_sensor.toml")
folder = tempfile.mkdtemp()
flt = yauyau.open_filter(folder, yauyau.precompute(spec, folder))
rows = yauyau.simulate(spec, steps=20000, seed=1).increments
engine, out = flt.filter, {{}}
from yauyau.solver.warm import warm_kernels
warm_kernels()  # every compiled loop typed before the timing (a fresh worktree's numba cache is cold)

def per_row(run, size, reset, total=20000):
    run(0, size)  # warm: the first chunk of its size, then from the start again
    reset()
    started = time.process_time()
    for start in range(0, total, size):
        run(start, size)
    return (time.process_time() - started) / total * 1e6

for size in (100, 1000):
    out[f"run {{size}}"] = per_row(lambda s, k: flt.run(rows[s:s + k]), size, flt.reset)
box = [None]
def arrays(s, k):
    box[0] = engine.run_arrays(box[0], rows[s:s + k])[0]
def fresh():
    box[0] = engine.initial_state()
fresh()
out["run_arrays 100"] = per_row(arrays, 100, fresh)
streams = [yauyau.simulate(spec, steps=2000, seed=s).increments for s in range(64)]
states = []
def batch(s, k):
    states[:] = [r[0] for r in engine.run_batch(states, [x[s:s + k] for x in streams])]
def fresh_states():
    states[:] = [engine.initial_state() for _ in streams]
fresh_states()
out["run_batch 64 x 100"] = per_row(batch, 100, fresh_states, 2000) / 64
print(json.dumps(out))
"""


def _round(tree: str) -> dict[str, float]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", ROUND.format(tree=tree)], capture_output=True, text=True,
                          check=True, env=env, cwd=tempfile.gettempdir())
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.chunk_overhead",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="d02c22d", help="the earlier revision")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as folder:
        earlier = str(Path(folder) / "earlier")
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", earlier, args.against],
                       check=True, capture_output=True)
        try:
            figures: dict[str, list[dict[str, float]]] = {"earlier": [], "this": []}
            for _ in range(args.rounds):
                figures["earlier"].append(_round(earlier))
                figures["this"].append(_round(str(ROOT)))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", earlier], check=False)
    print(f"{args.rounds} rounds, load average {load:.1f} at the start; µs per row, medians")
    print(f"| µs per row | {args.against} | this tree | ratio |\n|---|---:|---:|---:|")
    for key in figures["this"][0]:
        before = statistics.median(r[key] for r in figures["earlier"])
        after = statistics.median(r[key] for r in figures["this"])
        print(f"| {key} | {before:.2f} | {after:.2f} | {after / before:.3f} |")


if __name__ == "__main__":
    main()
