"""What a following ball saves: the basis and cost for a 0.01 gap on the 2-D range example.

    python -m bench.follow_cost [--quick]     # writes docs/bench-follow-cost.md

examples/range_2d.toml: a damped rotation f = (−0.5x1 + x2, −x1 − 0.5x2) observed through h = x1³,
dt = 0.01, 1000 steps (t = 0..10), seeds 1 and 2.  Truth: the point-mass filter on 256² cells of the
box around the radius-4.5 ball (solver/reference/pointmass.py).  The fixed ball must hold the whole
stationary law (radius 4.5); the drift is affine, so a following ball rides the frame of ċ = Ac
(solver/frame.py) and only has to hold the posterior.  For each ball the basis grows until the worst
mean gap over both runs is ≤ 0.01; the cheapest of each is compared: µs per observation (chunks of
1000, one BLAS thread, median of interleaved runs) and precompute seconds.
"""

from __future__ import annotations

import argparse
import statistics
import time
import tomllib
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine import build
from yauyau.solver.offline import precompute
from yauyau.solver.reference.pointmass import PointMassFilter
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "docs" / "bench-follow-cost.md"
TARGET = 0.01


def _spec(radius: float, basis: int, follow: bool):
    with open(ROOT / "examples" / "range_2d.toml", "rb") as fh:
        doc = tomllib.load(fh)
    doc["domain"] = {"radius": radius, **({"follow": True} if follow else {})}
    doc["discretization"].update(basis=basis, precision="double")
    return spec_from_dict(doc)


def _gap(flt, runs) -> tuple[float, float]:
    """The worst and the median mean gap over the runs' steps (inf: a degenerate step)."""
    gaps = []
    for rows, reference in runs:
        _, result = flt.run_arrays(flt.initial_state(), rows)
        if result.degenerate.any():
            return float("inf"), float("inf")
        gaps.append(np.abs(result.mean - reference).max(axis=1))
    gaps = np.concatenate(gaps)
    return float(gaps.max()), float(np.median(gaps))


def _per_obs(flt, rows) -> float:
    start = time.perf_counter()
    flt.run_arrays(flt.initial_state(), rows)
    return (time.perf_counter() - start) / len(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.follow_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one seed, 300 steps, a coarse reference")
    args = parser.parse_args(argv)
    steps, seeds, cells = (300, (1,), 128) if args.quick else (1000, (1, 2), 256)
    fixed_model = compile_model(_spec(4.5, 300, False))
    runs = []
    for seed in seeds:
        rows = simulate(fixed_model, steps, np.random.default_rng(seed)).increments
        grid = PointMassFilter(fixed_model, cells=cells)
        _, estimates = grid.run(grid.initial_state(), rows)
        runs.append((rows, np.array([e.mean for e in estimates])))
    # a following ball of radius 3.5 degenerates at the first step: the prior N((0.5, 0), I), and the
    # posterior wherever x1 ≈ 0 (h' = 3x1² ≈ 0), is as wide as the stationary law (measured)
    sizes = (850, 1200, 1600, 2000, 2400) if not args.quick else (300, 600)
    balls = [("fixed", 4.5, False, sizes), ("following", 4.0, True, sizes)]
    lines = ["## What a following ball saves (2-D range example)", "",
             "`python -m bench.follow_cost" + (" --quick" if args.quick else "") + "`", "",
             f"examples/range_2d.toml (damped rotation, h = x1³), {steps} steps, seeds "
             f"{', '.join(map(str, seeds))}, against the point-mass filter on {cells}² cells. Each ball's "
             f"basis grows until the worst mean gap is ≤ {TARGET}; the following balls ride the frame of "
             "ċ = Ac (solver/frame.py). µs per observation: one BLAS thread, chunks of the whole run, median "
             "of 5 interleaved runs.", "",
             "| ball | radius | N | Q | worst mean gap | median mean gap | precompute s |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    chosen = {}
    for name, radius, follow, sizes in balls:
        for basis in sizes:
            model = compile_model(_spec(radius, basis, follow))
            start = time.perf_counter()
            with threadpool_limits(limits=1, user_api="blas"):
                offline = precompute(model)
            seconds = time.perf_counter() - start
            flt = build(model, offline)
            gap, median = _gap(flt, runs)
            q = len(offline.weights)
            lines.append(f"| {name} | {radius} | {basis} | {q} | {gap:.1e} | {median:.1e} | {seconds:.1f} |")
            print(lines[-1], flush=True)
            if gap <= TARGET:
                chosen[(name, radius)] = (basis, len(offline.weights), flt, seconds)
                break
    times = {key: [] for key in chosen}
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(5):
            for key, (_, _, flt, _) in chosen.items():
                times[key].append(_per_obs(flt, runs[0][0]))
    lines += ["", "The cheapest ball of each kind that meets the gap:", "",
              "| ball | radius | N | Q | µs/obs | precompute s | vs fixed (time per observation) |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    base = statistics.median(times[("fixed", 4.5)]) if ("fixed", 4.5) in times else float("nan")
    for (name, radius), (basis, q, _, seconds) in chosen.items():
        per = statistics.median(times[(name, radius)])
        lines.append(f"| {name} | {radius} | {basis} | {q} | {per * 1e6:.0f} | {seconds:.1f} | "
                     f"{base / per:.2f}× cheaper |")
        print(lines[-1], flush=True)
    write_fragment(FRAGMENT, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
