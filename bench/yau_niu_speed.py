"""The Yau–Niu rows (independent sensors, a coupled ring): compiled, the numpy path, a previous revision.

    python -m bench.yau_niu_speed [--against REV] [--rounds R]   # writes bench/results/yau-niu-speed.md

n independent cubic sensors (bench/yau_niu.py's model: dx_i = −0.5x_i dt + dW_i, dy_i = x_i³dt + dw_i, dt
= 0.01) at 4096 points, and the coupled 4-state ring (bench/yau_niu.py's RING: one block, the kernels of
solver/qmc/coupled.py) at 8192 and 65 536 points, K rows of one simulated path. Each round runs, each in
a fresh process and alternating: this tree with ``YAUYAU_KERNEL`` = compiled (solver/qmc/kernels.py) and
= numpy (the reference path), and revision REV with its default kernels (default d02c22d, before the
kernels: an n-dimensional Sobol row of noise a row, numpy throughout; 09770ad: before the coupled
block's) from a temporary ``git worktree``. Cost: process CPU time of ``run_arrays`` per row (after a
5-row warm-up that pays numba's load), one BLAS thread, medians over the rounds; gap: rms distance of the
means to the n 1-D point-mass filters (the ring: to a 10⁶-particle filter, bench/yau_niu.py); real time
means a row's CPU under dt = 10 ms.
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

import numpy as np

from .fragments import write_fragment
from .yau_niu import DT, RING, point_mass, ring_reference

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "yau-niu-speed.md"
CASES = ((10, 4096, False), (100, 4096, False), (4, 8192, True), (4, 65536, True))
ROUND = """
import json, os, sys, time
os.chdir({tree!r}); sys.path.insert(0, {tree!r})
import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver.model import compile_model
from yauyau.solver.spec import spec_from_dict
import yauyau.solver.qmc.yau_niu as niu
assert niu.__file__.startswith({tree!r}), niu.__file__
n, points = {n}, {points}
doc = {{"name": "cubic", "state": [f"x{{i}}" for i in range(n)], "drift": {drift!r},
       "observation": [f"x{{i}}**3" for i in range(n)], "observation_noise": np.eye(n).tolist(),
       "initial": {{"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()}},
       "method": "yau-niu", "domain": {{"radius": 8.0}},
       "discretization": {{"dt": {dt}, "basis": 64, "points": points}}}}
model = compile_model(spec_from_dict(doc))
rows = np.load({rows!r})
with threadpool_limits(1):
    flt = niu.YauNiuFilter(model)
    flt.run_arrays(flt.initial_state(), rows[:5])
    flt = niu.YauNiuFilter(model)
    start = time.process_time()
    _, result = flt.run_arrays(flt.initial_state(), rows)
    seconds = time.process_time() - start
np.save({means!r}, result.mean)
print(json.dumps({{"ms": 1e3 * seconds / len(rows)}}))
"""


def _run(tree: Path, kernel: str, n: int, points: int, drift: list[str], rows: Path, means: Path) -> float:
    env = dict(os.environ, YAUYAU_KERNEL=kernel, OPENBLAS_NUM_THREADS="1")
    script = ROUND.format(tree=str(tree), n=n, points=points, drift=drift, dt=DT, rows=str(rows),
                          means=str(means))
    done = subprocess.run([sys.executable, "-c", script], env=env, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["ms"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_niu_speed",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="d02c22d",
                        help="the earlier revision (default: before the kernels)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rows", type=int, default=200)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from yauyau.solver.model import compile_model
    from yauyau.solver.simulate import simulate
    from yauyau.solver.spec import spec_from_dict

    runs = (("compiled", "compiled", None), ("numpy path", "numpy", None), (args.against, "compiled", "old"))
    found, truths = [], {}
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(old), args.against],
                       check=True)
        try:
            for n, points, ring in CASES:
                drift = RING if ring else [f"-0.5*x{i}" for i in range(n)]
                doc = {"name": "cubic", "state": [f"x{i}" for i in range(n)], "drift": drift,
                       "observation": [f"x{i}**3" for i in range(n)],
                       "observation_noise": np.eye(n).tolist(),
                       "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
                       "method": "yau-niu", "discretization": {"dt": DT, "points": points}}
                increments = simulate(compile_model(spec_from_dict(doc)), args.rows,
                                      np.random.default_rng(5)).increments
                if (n, ring) not in truths:
                    truths[n, ring] = (ring_reference(increments) if ring else
                                       np.stack([point_mass(increments[:, i]) for i in range(n)], axis=1))
                truth = truths[n, ring]
                rows = Path(tmp) / f"rows{n}.npy"
                np.save(rows, increments)
                costs: dict[str, list[float]] = {name: [] for name, *_ in runs}
                gaps: dict[str, float] = {}
                for _ in range(args.rounds):
                    for name, kernel, where in runs:
                        means = Path(tmp) / f"means-{n}-{points}-{kernel}-{where}.npy"
                        tree = old if where else ROOT
                        costs[name].append(_run(tree, kernel, n, points, drift, rows, means))
                        gaps[name] = float(np.sqrt(np.mean((np.load(means) - truth) ** 2)))
                    loads.append(os.getloadavg()[0])
                for name, *_ in runs:
                    found.append((n, "ring" if ring else "independent", points, name,
                                  statistics.median(costs[name]), gaps[name]))
                print(found[-3:], flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    lines = ["## Yau-Niu: the compiled rows", "",
             f"`python -m bench.yau_niu_speed --against {args.against}`: {args.rows} rows, "
             f"{args.rounds} rounds, "
             f"load average {min(loads):.1f}–{max(loads):.1f} on 2 cores. "
             + " ".join(__doc__.split("\n\n")[2].split()), "",
             "| states | model | points | run | ms/row (CPU) | gap | real time at dt = 10 ms |",
             "|---:|---|---:|---|---:|---:|---|"]
    lines += [f"| {n} | {model} | {points} | {name} | {ms:.2f} | {gap:.4f} | {'yes' if ms < 10.0 else 'no'} |"
              for n, model, points, name, ms, gap in found]
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
