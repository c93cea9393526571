"""3-D through the general engine (issue 10 part 6): a fixed ball against one that follows the state.

    python -m bench.three_d [--quick]     # writes bench/results/3d.md

The issue's model f = (−x1 + 0.5x2, −x2, −0.5x3), h = (x1, x3), a = R = I, dt = 0.02, prior N(0, ½I),
``method = "yau-yau"``, on the default 3-D mesh for the basis (refinement 4 of scikit-fem's ball,
Q = 4991 P1 nodes), against the exact Kalman filter of the sampled model over 500 steps, seeds 5 and 6:

* the issue's starting point: a fixed ball of radius 4 and N = 500;
* the same ball with N = 1500 (the dense eigensolver's cost grows with Q, not N);
* a ball of radius 3.5 that follows the posterior in the frame of ċ = Ac (solver/engine/frame.py), N = 1000,
  its moves carried by P1 interpolation.  (A local spline carry was measured on 2026-11-24 and
  dropped: bench/results/3d.md's analysis has its figures.)
* the same following ball on the ball refined five times (``mesh = 5``, Q = 41727: the basis from
  shift-invert Lanczos, solver/offline/basis.py).  Its precompute takes ~25 min and 3.5 GB on one process;
* the same following ball with ``element = "bubble"`` (P2 plus face and interior bubbles, the
  15-node mass-lumped tetrahedron, solver/offline/fem.py) on the ball refined twice (Q = 2047) and three
  times (Q = 17023, a Lanczos basis; N = 600 and 1000).

``--only WORD ...`` runs the rows whose name contains one of the WORDs (``--only bubbles``); the others
are kept from the fragment as it was (their figures are then from the run that wrote them).

Precompute seconds and peak memory of the process; µs per observation with one BLAS thread (one run
each: the runs take minutes).
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "3d.md"


def spec_doc(radius: float, basis: int, follow: bool, mesh: int | None = None,
             element: str | None = "lagrange") -> dict:
    """The issue's 3-D linear model on this discretisation (``mesh``, ``element`` None: left out)."""
    return {"name": "linear-3d", "state": ["x1", "x2", "x3"], "method": "yau-yau",
            "drift": ["-x1 + 0.5*x2", "-x2", "-0.5*x3"], "observation": ["x1", "x3"],
            "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": (0.5 * np.eye(3)).tolist()},
            "domain": {"radius": radius, **({"follow": True} if follow else {})},
            "discretization": {"dt": 0.02, "basis": basis, **({"element": element} if element else {}),
                               **({"mesh": mesh} if mesh else {})}}


def against_kalman(model, offline, steps: int, seeds) -> tuple:
    """(rms mean gap, largest mean gap, median and largest relative variance error, moves, seconds per
    observation) of the engine against the exact Kalman filter on ``steps`` simulated steps per seed."""
    gaps, variances, moves, seconds = [], [], 0, []
    for seed in seeds:
        increments = simulate(model, steps, np.random.default_rng(seed)).increments
        flt = build(model, offline)
        start = time.perf_counter()
        with threadpool_limits(limits=1, user_api="blas"):
            _, ours = flt.run_arrays(flt.initial_state(), increments)
        seconds.append((time.perf_counter() - start) / steps)
        kalman = KalmanBucyFilter(model, kind="discrete")
        _, ref = kalman.run_arrays(kalman.initial_state(), increments)
        gaps.append(ours.mean - ref.mean)
        variances.append(np.abs(np.diagonal(ours.cov, axis1=1, axis2=2)
                                / np.diagonal(ref.cov, axis1=1, axis2=2) - 1))
        moves += 0 if ours.recentred is None else int(ours.recentred.sum())
        if ours.degenerate.any():
            raise SystemExit(f"degenerate: {ours.reason}")
    gap, var = np.concatenate(gaps), np.concatenate(variances)
    return (np.sqrt(np.mean(gap ** 2)), np.abs(gap).max(), np.median(var), var.max(), moves,
            float(np.median(seconds)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.three_d", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller bases, fewer steps")
    parser.add_argument("--only", nargs="+", metavar="WORD", help="run only the rows whose name has a WORD")
    args = parser.parse_args(argv)
    steps, seeds = (100, (5,)) if args.quick else (500, (5, 6))
    scale = 0.4 if args.quick else 1.0
    configs = [("fixed ball (the issue's)", 4.0, 500, False, None, "lagrange"),
               ("fixed ball", 4.0, 1500, False, None, "lagrange"),
               ("following ball", 3.5, 1000, True, None, "lagrange")]
    if not args.quick:
        configs += [("following ball, mesh 5", 3.5, 1000, True, 5, "lagrange"),
                    ("following ball, P2 + bubbles, mesh 2", 3.5, 1000, True, 2, "bubble"),
                    ("following ball, P2 + bubbles, mesh 3", 3.5, 600, True, 3, "bubble"),
                    ("following ball, P2 + bubbles, mesh 3, N = 1000", 3.5, 1000, True, 3, "bubble")]
    kept = _previous_rows() if args.only else {}
    lines = ["## 3-D: a fixed ball against one that follows the state", "",
             "`python -m bench.three_d" + (" --quick" if args.quick else "") + "`", "",
             "f = (−x1 + 0.5x2, −x2, −0.5x3), h = (x1, x3), a = R = I, dt = 0.02, through the general "
             "engine on the default 3-D mesh (or the one named), against the exact Kalman filter of the "
             f"sampled model, {steps} steps, seeds {', '.join(map(str, seeds))}. The following ball rides "
             "the frame of ċ = Ac (solver/engine/frame.py). Peak memory is the process's so far; µs per "
             "observation with one BLAS thread, one run each.", "",
             "| ball | radius | N | Q | precompute s | peak MB | rms mean gap | max mean gap "
             "| variance error median | variance error max | moves | µs/obs |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, radius, basis, follow, mesh, element in configs:
        if args.only and not any(word.lower() in name.lower() for word in args.only):
            if name in kept:
                lines.append(kept[name])
            continue
        basis = int(basis * scale)
        model = compile_model(spec_from_dict(spec_doc(radius, basis, follow, mesh, element)))
        start = time.perf_counter()
        with threadpool_limits(limits=1, user_api="blas"):
            offline = precompute(model)
        seconds = time.perf_counter() - start
        rms, worst, var_median, var_max, moves, per = against_kalman(model, offline, steps, seeds)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
        cells = [name, radius, basis, len(offline.weights), f"{seconds:.0f}", peak, f"{rms:.1e}",
                 f"{worst:.1e}", f"{var_median:.1%}", f"{var_max:.1%}", moves, f"{per * 1e6:.0f}"]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
        print(lines[-1], flush=True)
    write_fragment(FRAGMENT, lines)
    return 0


def _previous_rows() -> dict[str, str]:
    """The table rows of the fragment as it is, by their first cell (the ball's name)."""
    if not FRAGMENT.exists():
        return {}
    rows = {}
    for line in FRAGMENT.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and len(cells) == 12 and cells[1].replace(".", "").isdigit():
            rows[cells[0]] = line
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
