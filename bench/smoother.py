"""The optimal smoother's cost per row beside the filter's, FilterPy's RTS and `particles`' FFBS (issue 38).

    .venv/bin/python -m bench.smoother [--quick]     # writes bench/results/smoother.md

CPU time (``time.process_time``), one BLAS thread, medians of interleaved repeats, on the engine:
the fused filter (``run_arrays``) and the fixed-interval smoother (``smooth_arrays``) over the same rows,
on examples/ou.toml (1-D, continuous increments, Q = 195) at a chunk whose forward pass is kept whole and
at one beyond solver/engine/smoother.py's KEEP (checkpointed blocks: the forward pass runs twice), and
on a 2-D linear model (tests/solver/engine/test_smoother.py's, 200 basis functions).  The peers run in
their own venv (bench/out/peers-venv, ``python -m bench.measurements --setup-peers``) as a subprocess
(bench/peer_smoothers.py) on the same increments read as the exactly sampled model: FilterPy's
``batch_filter`` + ``rts_smoother`` and particles' bootstrap filter with its history and
``backward_sampling_ON2`` (N = M = 1 000: the O(N²) backward pass) on the first rows.  Each smoothed
mean is compared with an exact RTS on the sampled model computed here.  Memory: the peak RSS of a
subprocess smoothing 10⁶ rows of ou.toml, beside one that only builds the engine and the rows.
"""

from __future__ import annotations

import argparse
import math
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from yauyau.solver import compile_model, spec_from_dict  # noqa: E402
from yauyau.solver.engine import smoother  # noqa: E402
from yauyau.solver.engine.filter import YauYauFilter  # noqa: E402
from yauyau.solver.offline.pipeline import precompute  # noqa: E402

from .fragments import RESULTS, ROOT, write_fragment  # noqa: E402

PEER_PYTHON = ROOT / "bench" / "out" / "peers-venv" / "bin" / "python"
PEER_SCRIPT = ROOT / "bench" / "peer_smoothers.py"
TWO_D = {"name": "linear-2d", "state": ["p", "q"], "drift": ["-p", "-0.5*q"],
         "observation": ["p + 0.5*q", "q"],
         "initial": {"kind": "gaussian", "mean": [0.3, -0.2], "cov": [[0.5, 0.0], [0.0, 0.5]]},
         "domain": {"radius": 4.0}, "discretization": {"dt": 0.02, "basis": 200, "mesh": 16}}
THETA, A, R, M0, P0 = 0.5, 1.0, 1.0, 1.0, 0.5  # examples/ou.toml with its diffusion and noise written out


def ou_engine() -> YauYauFilter:
    doc = tomllib.loads((ROOT / "examples" / "ou.toml").read_text())
    doc["diffusion"], doc["observation_noise"] = [[A]], [[R]]
    model = compile_model(spec_from_dict(doc))
    return YauYauFilter(model, precompute(model))


def sample_ou(K: int, dt: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    phi = math.exp(-THETA * dt)
    q = A * (1 - phi * phi) / (2 * THETA)
    x, dy = rng.normal(M0, math.sqrt(P0)), np.empty(K)
    for k in range(K):
        x = phi * x + rng.normal(0, math.sqrt(q))
        dy[k] = x * dt + rng.normal(0, math.sqrt(R * dt))
    return dy


def rts_exact(dy: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman + RTS of the exactly sampled OU model (the reference of every smoothed mean here)."""
    phi = math.exp(-THETA * dt)
    q = A * (1 - phi * phi) / (2 * THETA)
    K = len(dy)
    mf, Pf, mp, Pp = (np.empty(K) for _ in range(4))
    m, P = M0, P0
    for k in range(K):
        m, P = phi * m, phi * phi * P + q
        mp[k], Pp[k] = m, P
        G = P * dt / (dt * dt * P + R * dt)
        m, P = m + G * (dy[k] - dt * m), (1 - G * dt) * P
        mf[k], Pf[k] = m, P
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(K - 2, -1, -1):
        J = Pf[k] * phi / Pp[k + 1]
        ms[k] = mf[k] + J * (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + J * J * (Ps[k + 1] - Pp[k + 1])
    return ms, Ps


def per_row(engine: YauYauFilter, rows: np.ndarray, repeats: int) -> tuple[float, float, object]:
    """(filter µs a row, smoother µs a row, the smoothed result): interleaved, medians of CPU time."""
    state = engine.initial_state()
    engine.run_arrays(state, rows[:300])
    engine.smooth_arrays(state, rows[:300])  # warm: numba, the cached adjoint
    filt, smooth, result = [], [], None
    for _ in range(repeats):
        start = time.process_time()
        engine.run_arrays(state, rows)
        filt.append(time.process_time() - start)
        start = time.process_time()
        result = engine.smooth_arrays(state, rows)[1]
        smooth.append(time.process_time() - start)
    K = len(rows)
    return float(np.median(filt)) / K * 1e6, float(np.median(smooth)) / K * 1e6, result


def peers(dy: np.ndarray, dt: float, rows_ffbs: int, repeats: int) -> dict | str:
    if not PEER_PYTHON.exists():
        return "not run: no bench/out/peers-venv (python -m bench.measurements --setup-peers)"
    phi = math.exp(-THETA * dt)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, dy=dy, phi=phi, q=A * (1 - phi * phi) / (2 * THETA), dt=dt, r=R, m0=M0, P0=P0,
                 rows_ffbs=rows_ffbs, particles=1000, trajectories=1000, repeats=repeats)
        done = subprocess.run([str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst)], capture_output=True,
                              text=True)
        if done.returncode != 0:
            return "failed: " + done.stderr.strip().splitlines()[-1]
        return {k: v.item() if v.ndim == 0 else v for k, v in np.load(dst).items()}


MEMORY_CHILD = """
import os, resource, sys, numpy as np
sys.path.insert(0, {root!r})
from bench.smoother import ou_engine
K, smooth = int(sys.argv[1]), sys.argv[2] == "smooth"
engine = ou_engine()
rows = np.random.default_rng(0).normal(0.0, 0.1, (K, 1))
state = engine.initial_state()
engine.run_arrays(state, rows[:300])
if smooth:
    engine.smooth_arrays(state, rows)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def peak_rss_mb(K: int, smooth: bool) -> float:
    code = MEMORY_CHILD.format(root=str(ROOT))
    done = subprocess.run([sys.executable, "-c", code, str(K), "smooth" if smooth else "rows"],
                          capture_output=True, text=True, check=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    return int(done.stdout.split()[-1]) / 1024.0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.smoother", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    repeats, kept_rows, long_rows, two_rows, memory_rows, ffbs_rows = (
        (3, 5_000, 30_000, 1_000, 100_000, 10) if args.quick else (7, 20_000, 100_000, 5_000, 1_000_000, 30))
    wall, load = time.time(), os.getloadavg()[0]
    engine = ou_engine()
    dt, Q = engine.model.dt, len(engine.weights)
    dy = sample_ou(long_rows, dt, seed=1)
    lines_1d = []
    for K in (kept_rows, long_rows):
        f, s, result = per_row(engine, dy[:K, None], repeats if K == kept_rows else max(3, repeats // 2))
        ms, _ = rts_exact(dy[:K], dt)
        blocks = ("kept whole" if K * Q <= smoother.KEEP
                  else f"checkpointed (blocks of {max(256, smoother.KEEP // Q)})")
        lines_1d.append(f"| ou.toml, 1-D (Q = {Q}) | {K:,} | {blocks} | {f:.1f} | {s:.1f} | "
                        f"{s / f:.2f}× | {np.abs(result.mean[:, 0] - ms).max():.1e} |")
    engine2 = YauYauFilter(model := compile_model(spec_from_dict(TWO_D)), precompute(model))
    rng = np.random.default_rng(2)
    rows2 = rng.normal(0.0, math.sqrt(TWO_D["discretization"]["dt"]), (two_rows, 2))
    f2, s2, _ = per_row(engine2, rows2, repeats)
    Q2 = len(engine2.weights)
    line_2d = (f"| linear 2-D (Q = {Q2}) | {two_rows:,} | kept whole | {f2:.1f} | {s2:.1f} | {s2 / f2:.2f}× "
               "| — |")
    peer_rows = 2_000 if not args.quick else 500
    found = peers(dy[:peer_rows], dt, ffbs_rows, repeats=5)
    if isinstance(found, dict):
        ms, _ = rts_exact(dy[:peer_rows], dt)
        ms_f, _ = rts_exact(dy[:ffbs_rows], dt)
        peer_lines = [
            f"| FilterPy `batch_filter` + `rts_smoother` (1-D sampled OU) | {peer_rows:,} | "
            f"{found['rts_us']:.1f} | {np.abs(found['rts_mean'] - ms).max():.1e} |",
            f"| particles FFBS, N = M = 1 000 (`backward_sampling_ON2`) | {ffbs_rows} | "
            f"{found['ffbs_us']:,.0f} (forward {found['ffbs_forward_us']:,.0f}) | "
            f"{np.abs(found['ffbs_mean'] - ms_f).max():.1e} |"]
        versions = found["versions"]
    else:
        peer_lines, versions = [f"| peers | — | {found} | — |"], "—"
    base, peak = peak_rss_mb(memory_rows, False), peak_rss_mb(memory_rows, True)
    lines = [
        "## The optimal smoother", "",
        f"Generated by `python -m bench.smoother{' --quick' if args.quick else ''}` "
        f"(bench/smoother.py): CPU time a row, one BLAS thread, medians of interleaved repeats; 2 shared "
        f"cores, load average {load:.1f} at the start; {time.time() - wall:.0f} s wall.", "",
        "| model | rows | forward pass | filter µs/row | smoother µs/row | smoother / filter "
        "| max \\|mean − RTS\\| |",
        "|---|---:|---|---:|---:|---:|---:|", *lines_1d, line_2d, "",
        f"Peers on the same increments read as the exactly sampled model ({versions}; their own venv, a "
        "subprocess; the smoothed mean against an exact RTS over the same rows):", "",
        "| peer | rows | µs/row | max \\|mean − RTS\\| |", "|---|---:|---:|---:|", *peer_lines, "",
        f"Memory: smoothing {memory_rows:,} rows of ou.toml in one chunk peaks at {peak:.0f} MB RSS against "
        f"{base:.0f} MB for the engine and the rows alone (+{peak - base:.0f} MB: the result's mean, cov "
        f"and mode, the filter's per-row outputs and one checkpointed block).", ""]
    print("\n".join(lines))
    print(f"wrote {write_fragment(RESULTS / 'smoother.md', lines)}")


if __name__ == "__main__":
    main()
