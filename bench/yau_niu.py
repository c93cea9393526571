"""The Yau–Niu filter (method "yau-niu") on n-state cubic sensors (4, 10, 100 states) and a coupled
4-state ring, against the peers users would pick: `particles`' bootstrap filter and FilterPy's UKF.

    .venv/bin/python -m bench.measurements --setup-peers   # once: the peers' venv
    python -m bench.yau_niu [--quick]                      # writes bench/results/yau-niu.md

Independent sensors: dx_i = −0.5x_i dt + dW_i, dy_i = x_i³dt + dw_i, x(0) ~ N(0.5, I), dt = 0.01, K rows
of one simulated path.  The exact filter factorises into n 1-D filters: the truth is n runs of the
library's 1-D fine-grid reference (solver/reference/pointmass.py; exact in time, so the gap includes
yau-niu's Euler step).  The ring: dx_i = (−x_i + 0.5 tanh x_{i+1}) dt + dW_i (indices mod 4), the same
cubic sensors, one coupled block for yau-niu; its truth is a 10⁶-particle bootstrap filter written here
in numpy (Euler–Maruyama, SUBSTEPS steps a row, fixed seed).  Gap: the rms over rows and coordinates of
the mean's distance to the truth.

The peers run in their own venv (bench/out/peers-venv: particles pins numpy < 2) through
bench/peer_cubic_nd.py, one subprocess per model: `particles`' bootstrap filter with N = 10 000 (the
EXACT Ornstein–Uhlenbeck transition on the independent sensors, Euler–Maruyama with the reference's
substeps on the ring, which has no exact one; warmed up on 5 rows first: imports and numba's
compilation), on SEEDS seeds (median gap and cost), and FilterPy's UKF (Merwe points, α = 0.1).  Cost:
process CPU time per row, one BLAS thread, with the load average; yau-niu's gap and cost are medians over
as many of its own seeds (0, 1, 2; one run at 100 states), as the peer's over its seeds.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .fragments import RESULTS, ROOT, write_fragment

FRAGMENT = RESULTS / "yau-niu.md"
DT = 0.01
SUBSTEPS = 4  # Euler–Maruyama steps a row for the ring (its reference and `particles`)
SEEDS = (1, 2, 3)  # the peer bootstrap filter's seeds
PEER_PYTHON = ROOT / "bench" / "out" / "peers-venv" / "bin" / "python"
PEER_SCRIPT = Path(__file__).resolve().parent / "peer_cubic_nd.py"
RING = [f"-x{i} + 0.5*tanh(x{(i + 1) % 4})" for i in range(4)]


def cubic_model(n: int, points: int, ring: bool = False):
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import spec_from_dict

    doc = {"name": f"{'ring' if ring else 'cubic'}{n}", "state": [f"x{i}" for i in range(n)],
           "drift": RING if ring else [f"-0.5*x{i}" for i in range(n)],
           "observation": [f"x{i}**3" for i in range(n)],
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


def ring_reference(increments: np.ndarray, N: int = 10**6, seed: int = 0) -> np.ndarray:
    """Means of a bootstrap filter of the ring (Euler–Maruyama, SUBSTEPS steps a row, systematic
    resampling below half the particles): the ring's truth at N = 10⁶."""
    rng = np.random.default_rng(seed)
    K, n = increments.shape
    small = DT / SUBSTEPS
    X = 0.5 + rng.standard_normal((N, n))
    logw = np.zeros(N)
    means = np.empty((K, n))
    for k in range(K):
        for _ in range(SUBSTEPS):
            X += (0.5 * np.tanh(np.roll(X, -1, axis=1)) - X) * small
            X += math.sqrt(small) * rng.standard_normal((N, n))
        h = X**3
        logw += h @ increments[k] - 0.5 * DT * (h * h).sum(axis=1)
        w = np.exp(logw - logw.max())
        w /= w.sum()
        means[k] = w @ X
        if 1.0 / (w @ w) < N / 2:
            picks = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(N)) / N), N - 1)
            X, logw = X[picks], np.zeros(N)
    return means


def peers(increments: np.ndarray, ring: bool, N: int = 10**4) -> dict | None:
    """particles' bootstrap filter (N particles, SEEDS) and FilterPy's UKF on the rows, in the peers'
    venv; None when that venv is missing."""
    if not PEER_PYTHON.exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, model="ring" if ring else "ou", increments=increments, seeds=np.array(SEEDS), dt=DT,
                 substeps=SUBSTEPS, c1=0.0, c3=1.0, prior_mean=0.5, particles=N, ukf=1)
        subprocess.run(["nice", "-n", "5", str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst)],
                       check=True)
        out = np.load(dst)
        return {k: out[k] for k in out.files}


def ours(model, rows: np.ndarray, seeds: int, truth: np.ndarray) -> tuple[float, float]:
    """yau-niu's gap to ``truth`` and CPU seconds, medians over ``seeds`` runs of its seeds 0, 1, …
    (as the peer's over its SEEDS: one seed's gap moves by up to 2× on the coupled ring)."""
    from yauyau.solver.qmc.yau_niu import YauNiuFilter

    seconds, gaps = [], []
    for seed in range(seeds):
        flt = YauNiuFilter(model, seed=seed)
        start = time.process_time()
        _, result = flt.run_arrays(flt.initial_state(), rows)
        seconds.append(time.process_time() - start)
        gaps.append(float(np.sqrt(np.mean((result.mean - truth) ** 2))))
    return float(np.median(gaps)), float(np.median(seconds))


def measure(n: int, points: int, K: int, ring: bool, cache: dict) -> dict:
    from yauyau.solver.simulate import simulate

    model = cubic_model(n, points, ring)
    key = (n, ring)
    if key not in cache:
        rows = simulate(model, K, np.random.default_rng(5)).increments
        truth = ring_reference(rows) if ring else np.stack([point_mass(rows[:, i]) for i in range(n)], axis=1)
        cache[key] = rows, truth, peers(rows, ring)
    rows, truth, peer = cache[key]
    ours_gap, seconds = ours(model, rows, 1 if n >= 100 else len(SEEDS), truth)
    gap = lambda means: float(np.sqrt(np.mean((means - truth) ** 2)))  # noqa: E731
    found = {"n": n, "model": "ring" if ring else "independent", "points": points, "ours_gap": ours_gap,
             "ours_ms": 1e3 * seconds / K, "pf_gap": math.nan, "pf_ms": math.nan, "ukf_gap": math.nan,
             "ukf_ms": math.nan, "ukf_error": "", "versions": ""}
    if peer is not None:
        found.update(pf_gap=float(np.median([gap(m) for m in peer["pf_means"]])),
                     pf_ms=1e3 * float(np.median(peer["pf_seconds"])) / K,
                     ukf_gap=gap(peer["ukf_means"]) if np.isfinite(peer["ukf_means"]).all() else math.nan,
                     ukf_ms=1e3 * float(peer["ukf_seconds"]) / K, ukf_error=str(peer["ukf_error"]),
                     versions=", ".join(str(v) for v in peer["versions"]))
    return found


def _cell(value: float, digits: int) -> str:
    return "—" if not math.isfinite(value) else f"{value:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_niu", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100 rows, no 100-D case")
    args = parser.parse_args(argv)
    K = 100 if args.quick else 300
    cases = [(4, 4096, False), (10, 1024, False), (10, 4096, False), (10, 8192, False)]
    cases += [] if args.quick else [(100, 4096, False)]
    cases += [(4, 8192, True), (4, 32768, True), (4, 65536, True), (4, 131072, True)]
    found, cache = [], {}
    with threadpool_limits(1):
        for n, points, ring in cases:
            row = measure(n, points, K, ring, cache)
            row["load"] = os.getloadavg()[0]
            found.append(row)
            print(row, flush=True)
    versions = next((r["versions"] for r in found if r["versions"]), "")
    failed = sorted({f"{r['n']} states: {r['ukf_error']}" for r in found if r["ukf_error"]})
    lines = ["## Yau-Niu: cubic sensors at 4, 10 and 100 states, and a coupled 4-state ring", "",
             f"`python -m bench.yau_niu{' --quick' if args.quick else ''}`: {K} rows of dt = {DT}, one path; "
             "gap = rms distance of the mean to the truth (independent sensors: n 1-D point-mass filters; "
             f"ring: a 10⁶-particle bootstrap filter, Euler–Maruyama with {SUBSTEPS} steps a row); "
             "cost = CPU per row, one BLAS thread; yau-niu's gap and cost: medians over its seeds 0-2 (one "
             "run at 100 states). Peers: `particles`' bootstrap filter, N = 10 000 (exact "
             "Ornstein–Uhlenbeck transitions on the independent sensors; on the ring, which has no exact "
             f"transition, Euler–Maruyama with {SUBSTEPS} steps a row), warmed up, median of "
             f"{len(SEEDS)} seeds; FilterPy's UKF (Merwe points, α = 0.1). "
             f"Versions: {versions or 'peers not run (no bench/out/peers-venv)'}."
             + (f" UKF failures: {'; '.join(failed)}." if failed else ""), "",
             "| states | model | points | yau-niu gap | yau-niu ms/row | particles 10k gap | its ms/row "
             "| particles/yau-niu cost | UKF gap | UKF ms/row | load |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['n']} | {r['model']} | {r['points']} | {r['ours_gap']:.4f} | {r['ours_ms']:.1f} | "
              f"{_cell(r['pf_gap'], 4)} | {_cell(r['pf_ms'], 1)} | {_cell(r['pf_ms'] / r['ours_ms'], 2)} | "
              f"{_cell(r['ukf_gap'], 4)} | {_cell(r['ukf_ms'], 1)} | {r['load']:.1f} |" for r in found]
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
