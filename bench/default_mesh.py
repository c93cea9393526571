"""The default discretisation, chosen by measurement: accuracy and cost against nodes per basis function.

    python -m bench.default_mesh [--quick]     # writes bench/results/default-mesh.md

The default mesh of a spec without ``mesh`` has about NODES_PER_MODE · N interior nodes
(solver/offline/fem.py).  For the bundled 1-D models it is varied over Q/N ≈ 1.25, 1.5 and 2 (the P2 cells
across the radius that give those) and each variant filters the same simulated paths; the largest
gap of the conditional mean to the truth over every step and path, and the engine's cost per row,
are reported.  Truth: the exact Kalman filter (Ornstein–Uhlenbeck), the exact Beneš filter, the
fine point-mass grid (4000 cells: the cubic sensor, the √(1+x²) sensor whose posterior has two
peaks).  The accuracy the default must keep: a gap ≤ 1e-3 on every one of them (the product's
promise is 4e-3 on models it has not seen; the margin is for those).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.reference.benes import BenesFilter
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.reference.pointmass import PointMassFilter
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "default-mesh.md"
TARGET = 1e-3
RATIOS = (1.25, 1.5, 2.0)
MODELS = [("cubic sensor", "cubic_sensor.toml", lambda m: PointMassFilter(m, cells=4000), 2000),
          ("√(1+x²) sensor (two peaks)", "yau_jia_1d.toml", lambda m: PointMassFilter(m, cells=4000), 400),
          ("Ornstein–Uhlenbeck", "ou.toml", DiscreteKalmanFilter, 2000),
          ("Beneš", "benes.toml", BenesFilter, 200)]  # its state drifts away: 200 steps stay in the ball


def _variant(name: str, ratio: float):
    """The example with the general engine and a mesh of about ratio · N nodes (2.0: the default)."""
    doc = load_spec(ROOT / "examples" / name).model_dump(mode="json")
    disc = {k: v for k, v in doc["discretization"].items() if k != "mesh"}
    if ratio != 2.0:  # 1-D P2: 4·cells − 1 interior nodes
        disc["mesh"] = int(round((ratio * disc["basis"] + 1) / 4))
    doc["discretization"], doc["method"] = disc, "yau-yau"
    return compile_model(spec_from_dict(doc))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.default_mesh", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer paths")
    args = parser.parse_args(argv)
    seeds = 3 if args.quick else 8
    rows = []
    with threadpool_limits(1, user_api="blas"):
        for label, name, reference, steps in MODELS:
            base = _variant(name, 2.0)
            truth = []
            for s in range(seeds):
                data = simulate(base, steps, np.random.default_rng(500 + s)).rows
                ref = reference(base)
                _, est = ref.run(ref.initial_state(), data)
                truth.append((data, np.array([e.mean[0] for e in est])))
            for ratio in RATIOS:
                model = _variant(name, ratio)
                engine = YauYauFilter(model, precompute(model))
                gap, seconds, degenerate = 0.0, 0.0, 0
                for data, mean in truth:
                    start = time.perf_counter()
                    _, result = engine.run_arrays(engine.initial_state(), data)
                    seconds += time.perf_counter() - start
                    gap = max(gap, float(np.max(np.abs(result.mean[:, 0] - mean))))
                    degenerate += int(result.degenerate.any())
                rows.append((label, engine.N, len(engine.nodes), gap, seconds / seeds / steps, degenerate))
                print(f"{label}: Q = {len(engine.nodes)} (Q/N {len(engine.nodes) / engine.N:.2f}) gap "
                      f"{gap:.2e}, {rows[-1][4] * 1e6:.1f} us/row, {degenerate} degenerate", flush=True)
    lines = ["## The default discretisation, by measurement", "",
             "`python -m bench.default_mesh" + (" --quick" if args.quick else "") + "`", "",
             f"Each bundled 1-D model with meshes of about 1.25, 1.5 and 2 nodes per basis function (2: the "
             f"default), {seeds} simulated paths each; the largest gap of the conditional mean to the truth "
             "(exact Kalman, exact Beneš, a 4000-cell point-mass grid) and the engine's cost per row (one "
             f"BLAS thread). The default must keep the gap ≤ {TARGET:g} on every model.", "",
             "| model | N | Q | Q/N | max mean gap | degenerate paths | µs/row | ≤ 1e-3 |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for label, N, Q, gap, cost, degenerate in rows:
        ok = gap <= TARGET and not degenerate
        lines.append(f"| {label} | {N} | {Q} | {Q / N:.2f} | {gap:.1e} | {degenerate} | {cost * 1e6:.1f} "
                     f"| {'yes' if ok else '**no**'} |")
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
