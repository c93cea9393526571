"""The `particles` library's bootstrap filter against the engine on the bundled 1-D examples: gap and cost.

    .venv/bin/python -m bench.peer_gap            # 10 seeds x 1000 steps per model
    .venv/bin/python -m bench.peer_gap --quick    # 3 seeds x 300 steps

The peer ratios the README and docs/benchmarks.md quote (how much faster, how much closer to the optimal
filter) against the real peer, not a filter of our own: on the same simulated paths as bench/filters.py
(its cases and references: the point-mass grid for the cubic sensor, the exact sampled Kalman filter for
the OU model), the engine (`run_arrays` over the whole path, compiled rows) and
`particles`' bootstrap filter with N = 10 000 (bench/peer_particles.py in bench/out/peers-venv, the
increments read as z = dy/dt with noise R/dt, the exact transition where the drift is linear, else
Euler–Maruyama with 4 substeps; warmed up before the first timed run).  Gap: |E[x] − E_ref[x]| averaged
over steps and seeds.  Cost: CPU seconds per observation, one BLAS thread, medians over seeds; the two
filters run one after the other on each seed, so the ratio is side by side.
Writes bench/results/peer-gap.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver.methods import make_filter
from yauyau.solver.model import compile_model
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

from .filters import CASES, _reference, _run
from .fragments import write_fragment
from .measurements import ParticlesPeer

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "peer-gap.md"
KEYS = ("cubic", "ou")  # the 1-D polynomial cases (the peer script takes no other; Beneš's tanh drift is not)


def run_case(case, seeds: int, steps: int) -> dict:
    model = compile_model(load_spec(ROOT / case.spec))
    offline = precompute(model)
    flt = make_filter(model, offline, "yau-yau", precision=model.spec.discretization.precision)
    steps = min(steps, case.max_steps or steps)
    paths = [simulate(model, steps, np.random.default_rng(seed)) for seed in range(seeds)]
    times = model.dt * np.arange(1, steps + 1)
    peer, why = ParticlesPeer.start(model, [(s, p.increments, times) for s, p in enumerate(paths)],
                                    increments_dt=model.dt)
    if peer is None:
        raise SystemExit(f"{case.key}: {why}")
    engine_gap, engine_us, peer_us, references = [], [], [], []
    for s, path in enumerate(paths):
        ref_means, *_ = _run(_reference(model, case), path.increments)
        references.append(ref_means[:, 0])
        flt.run_arrays(flt.initial_state(), path.increments[:10])  # compiled and cached before timing
        start = time.process_time()
        _, res = flt.run_arrays(flt.initial_state(), path.increments)
        engine_us.append(1e6 * (time.process_time() - start) / steps)
        engine_gap.append(np.abs(res.mean[:, 0] - ref_means[:, 0]))
        peer_us.append(1e6 * peer.run(s) / steps)
    out = peer.close()
    if out is None:
        raise SystemExit(f"{case.key}: the particles peer failed")
    peer_gap = [np.abs(out["means"][s] - references[s]) for s in range(seeds)]
    return {"case": case, "Q": len(flt.nodes), "engine_gap": float(np.mean(engine_gap)),
            "peer_gap": float(np.mean(peer_gap)), "engine_us": statistics.median(engine_us),
            "peer_us": statistics.median(peer_us), "transition": out.get("transition"),
            "version": out.get("version"), "seeds": seeds, "steps": steps}


def write(results: list[dict], command: str, load: float) -> None:
    version = next((r["version"] for r in results if r["version"]), "?")
    lines = ["## The `particles` library's bootstrap filter against the engine (1-D examples)", "",
             f"`{command}`", "",
             f"Same simulated paths for both; reference as bench/results/filters.md (point-mass grid, exact "
             f"Kalman); `particles` {version}, N = 10 000, increments read as z = dy/dt with "
             "noise R/dt, warmed up; the engine's `run_arrays` over each whole path (compiled rows). CPU "
             "time per observation, one BLAS thread, medians over seeds; gap = |E[x] − E_ref[x]| averaged "
             f"over steps and seeds. Load average at the start: {load:.1f} on 2 cores.", "",
             "| model | seeds × steps | Q | engine µs/obs | particles µs/obs | particles / engine (cost) "
             "| engine gap | particles gap | particles / engine (gap) | peer transition |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in results:
        lines.append(f"| {r['case'].title} | {r['seeds']} × {r['steps']} | {r['Q']} | {r['engine_us']:.1f} "
                     f"| {r['peer_us']:.0f} | {r['peer_us'] / r['engine_us']:.0f}× | {r['engine_gap']:.1e} "
                     f"| {r['peer_gap']:.1e} | {r['peer_gap'] / r['engine_gap']:.0f}× | {r['transition']} |")
    write_fragment(OUT, lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.peer_gap", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 seeds x 300 steps")
    parser.add_argument("--seeds", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    args = parser.parse_args(argv)
    seeds = args.seeds or (3 if args.quick else 10)
    steps = args.steps or (300 if args.quick else 1000)
    load = os.getloadavg()[0]
    results = []
    with threadpool_limits(1, user_api="blas"):
        for case in CASES:
            if case.key in KEYS:
                results.append(run_case(case, seeds, steps))
                r = results[-1]
                print(f"{case.key}: engine {r['engine_us']:.1f} us/obs gap {r['engine_gap']:.2e}; particles "
                      f"{r['peer_us']:.0f} us/obs gap {r['peer_gap']:.2e}", flush=True)
    command = "python -m bench.peer_gap" + (" --quick" if args.quick else "")
    write(results, command, load)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
