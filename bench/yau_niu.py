"""The Yau–Niu filter (method "yau-niu") on independent cubic sensors at 4, 10 and 100 states.

    python -m bench.yau_niu [--quick]     # writes bench/results/yau-niu.md

dx_i = −0.5x_i dt + dW_i, dy_i = x_i³dt + dw_i, x(0) ~ N(0.5, I), dt = 0.01, K rows of one simulated
path.  The exact filter factorises into n 1-D filters: the truth is n runs of the library's 1-D
fine-grid reference (solver/reference/pointmass.py; exact in time, so the gap includes yau-niu's Euler
step).  Gap: the rms over rows and coordinates of
the mean's distance to it.  Beside it, a 10 000-particle bootstrap filter written here in numpy
(exact Ornstein–Uhlenbeck transitions, systematic resampling below half the particles, the same
data); the particles library's and FilterPy's peers are not wired to this model yet.  Cost: process
CPU time per row, one BLAS thread, with the load average beside it.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from threadpoolctl import threadpool_limits

from .fragments import RESULTS, write_fragment

FRAGMENT = RESULTS / "yau-niu.md"
DT = 0.01


def cubic_model(n: int, points: int):
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import spec_from_dict

    doc = {"name": f"cubic{n}", "state": [f"x{i}" for i in range(n)],
           "drift": [f"-0.5*x{i}" for i in range(n)], "observation": [f"x{i}**3" for i in range(n)],
           "method": "yau-niu", "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
           "domain": {"radius": 8.0}, "discretization": {"dt": DT, "basis": 64, "points": points}}
    return compile_model(spec_from_dict(doc))


def point_mass(dy: np.ndarray) -> np.ndarray:
    """Means of the 1-D cubic-sensor filter by the library's fine-grid reference
    (solver/reference/pointmass.py: finite volumes, TR-BDF2 over each dt, the update in log scale)."""
    from yauyau.solver.reference.pointmass import PointMassFilter

    reference = PointMassFilter(one_dimensional())
    return np.array([e.mean[0] for e in reference.run(reference.initial_state(), dy[:, None])[1]])


def one_dimensional():
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import spec_from_dict

    doc = {"name": "cubic1", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x**3"],
           "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]},
           "domain": {"radius": 6.0}, "discretization": {"dt": DT, "basis": 64}}
    return compile_model(spec_from_dict(doc))


def bootstrap(increments: np.ndarray, N: int = 10_000, seed: int = 0) -> np.ndarray:
    """Means of a bootstrap particle filter with exact OU transitions."""
    rng = np.random.default_rng(seed)
    K, n = increments.shape
    decay, spread = np.exp(-0.5 * DT), np.sqrt(1.0 - np.exp(-DT))
    X = 0.5 + rng.standard_normal((N, n))
    logw = np.zeros(N)
    means = np.empty((K, n))
    for k in range(K):
        X = decay * X + spread * rng.standard_normal((N, n))
        h = X**3
        logw += h @ increments[k] - 0.5 * DT * (h * h).sum(axis=1)
        w = np.exp(logw - logw.max())
        w /= w.sum()
        means[k] = w @ X
        if 1.0 / (w @ w) < N / 2:
            picks = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(N)) / N), N - 1)
            X, logw = X[picks], np.zeros(N)
    return means


def measure(n: int, points: int, K: int) -> dict:
    from yauyau.solver.qmc.yau_niu import YauNiuFilter
    from yauyau.solver.simulate import simulate

    model = cubic_model(n, points)
    rows = simulate(model, K, np.random.default_rng(5)).increments
    truth = np.stack([point_mass(rows[:, i]) for i in range(n)], axis=1)
    flt = YauNiuFilter(model)
    start = time.process_time()
    _, result = flt.run_arrays(flt.initial_state(), rows)
    ours = (time.process_time() - start) / K
    start = time.process_time()
    pf = bootstrap(rows)
    theirs = (time.process_time() - start) / K
    gap = lambda means: float(np.sqrt(np.mean((means - truth) ** 2)))  # noqa: E731
    return {"n": n, "points": points, "ours_gap": gap(result.mean), "ours_ms": 1e3 * ours,
            "pf_gap": gap(pf), "pf_ms": 1e3 * theirs}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_niu", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100 rows, no 100-D case")
    args = parser.parse_args(argv)
    K = 100 if args.quick else 300
    cases = [(4, 4096), (10, 1024), (10, 4096), (10, 8192)] + ([] if args.quick else [(100, 4096)])
    rows = []
    with threadpool_limits(1):
        for n, points in cases:
            found = measure(n, points, K)
            found["load"] = os.getloadavg()[0]
            rows.append(found)
            print(found, flush=True)
    lines = ["## Yau-Niu: cubic sensors at 4, 10 and 100 states", "",
             f"`python -m bench.yau_niu{' --quick' if args.quick else ''}`: {K} rows of dt = {DT}, one path, "
             "gap = rms distance of the mean to n 1-D point-mass filters; cost = CPU per row, one BLAS "
             "thread. The bootstrap columns are a yardstick written here in numpy (exact OU transitions), "
             "not a peer library: no peer ratio is quoted from them (the `particles` library and FilterPy's "
             "UKF on these data: not measured yet).", "",
             "| states | points | yau-niu gap | yau-niu ms/row | own numpy 10k bootstrap gap | its ms/row "
             "| load |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['n']} | {r['points']} | {r['ours_gap']:.4f} | {r['ours_ms']:.1f} | {r['pf_gap']:.4f} | "
              f"{r['pf_ms']:.1f} | {r['load']:.1f} |" for r in rows]
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
