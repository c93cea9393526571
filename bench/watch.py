"""The numbers behind the watch (solver/watch.py): how healthy runs gate, restart and alarm, and how fast
the innovation monitor sees a biased sensor.

    python -m bench.watch                      # every bundled model, 50 000 rows each, and the bias cases
    python -m bench.watch --rows 5000 --models ou,cubic_sensor --no-bias
    python -m bench.watch --jobs 8             # models in parallel processes

1. Healthy runs: each ``examples/*.toml`` is precomputed (var/bench-watch-store), a path of ``--rows`` rows
   is simulated from the model itself (``yauyau.simulate``, seed 1) and filtered in chunks of 1000 with
   the method stored at precompute, ``on_degenerate = "reinitialise"``, the lost-track rule off (to count
   what it would see: gated rows, the longest run of them, restarts, the most restarts within 100 rows)
   and the monitor at its default (alarms, the largest |statistic|).  The innovation scores z are
   reported too (mean and standard deviation: 0 and 1 for an exact predictive).  The monitor's cost is
   the time of its two steps (scores, charts) against the chunk's filter time.
2. Bias cases (``--bias``, default on): a sensor that reads off by a constant, the first alarm row over
   ``--seeds`` seeds: the power meter (examples/power_meter.toml) reading 0.33 low ("the 0.33 bias case":
   its innovations mostly on one side, since x² cannot follow a reading below 0); the OU dynamics with a
   discrete sensor z = x + v, sd 0.1, every 0.05, reading 0.33 high (a bias the filter takes for the
   state: its mean ends 0.33 off); the OU example's increments with h = x + 0.33.  And a pure shift δ of
   N(0, 1) scores (the monitor alone).

Prints a Markdown table per part (pasted into docs/reliability.md) and writes var/bench-watch.json.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
STORE = ROOT / "var" / "bench-watch-store"
CHUNK = 1000
WINDOW = 100
OU_DISCRETE = """
name = "ou-discrete-sensor"
state = ["x"]
drift = ["-0.5*x"]
observation = ["x"]
observation_noise = [[0.01]]
[measurement]
kind = "discrete"
[initial]
kind = "gaussian"
mean = [0.0]
cov = [[1.0]]
[domain]
radius = 7.0
[discretization]
dt = 0.05
basis = 96
"""


def healthy(path: str, rows: int, seed: int = 1) -> dict:
    """Part 1 for one spec file."""
    from threadpoolctl import threadpool_limits
    from yauyau.solver.watch import innovation_scores, run_charts

    import yauyau

    spec = yauyau.load_spec(path)
    started = time.perf_counter()
    mid = yauyau.precompute(spec, STORE)
    precompute_s = time.perf_counter() - started
    flt = yauyau.open_filter(STORE, mid, on_degenerate="reinitialise", lost_track={"gated": 0, "restarts": 0},
                             monitor=1e9)  # on for every method (yau-jia too: its default is off)
    sim = yauyau.simulate(spec, rows, seed=seed)
    data = sim.rows
    gated, restarts, alarms, run, longest, worst = 0, [], 0, 0, 0, 0.0
    scores, filter_s, monitor_s = [], 0.0, 0.0
    with threadpool_limits(limits=1, user_api="blas"):
        for start in range(0, rows, CHUNK):
            chunk = data[start:start + CHUNK]
            before = flt.state
            tick = time.perf_counter()
            result = flt.run(chunk)
            filter_s += time.perf_counter() - tick
            tick = time.perf_counter()
            z = innovation_scores(flt.filter, before, result, chunk)
            run_charts((), z, 1e9)
            monitor_s += time.perf_counter() - tick
            scores.append(z[:, 0])
            gated += int(result.gated.sum())
            for flag in result.gated.tolist():
                run = run + 1 if flag else 0
                longest = max(longest, run)
            restarts += (start + np.flatnonzero(result.reinitialised)).tolist()
            alarms += int(result.alarm.sum())
            worst = max(worst, float(np.nanmax(np.abs(result.monitor))) if len(result) else 0.0)
    z = np.concatenate(scores)
    z = z[np.isfinite(z)]
    in_window = max((sum(1 for s in restarts if r <= s < r + WINDOW) for r in restarts), default=0)
    return {"model": Path(path).stem, "method": flt.method, "rows": rows, "gated": gated,
            "longest_gated": longest,
            "restarts": len(restarts), "restarts_in_window": in_window, "degenerate_end": flt.degenerate,
            "alarms": alarms, "max_statistic": worst, "z_mean": float(z.mean()), "z_sd": float(z.std()),
            "scored": len(z) / rows, "filter_us": 1e6 * filter_s / rows, "monitor_us": 1e6 * monitor_s / rows,
            "precompute_s": precompute_s}


def bias_case(name: str, seeds: int, rows: int) -> dict:
    """Part 2: the first alarm row of a biased sensor, per seed."""
    from yauyau.solver.spec import parse_spec_text

    import yauyau

    if name == "ou-discrete +0.33":
        spec, offset, method = parse_spec_text(OU_DISCRETE, "toml"), 0.33, None
    elif name == "power-meter -0.33":
        spec, offset, method = yauyau.load_spec(ROOT / "examples" / "power_meter.toml"), -0.33, None
    else:
        spec, offset, method = yauyau.load_spec(ROOT / "examples" / "ou.toml"), 0.33, None
    mid = yauyau.precompute(spec, STORE)
    discrete = spec.measurement.kind == "discrete"
    delays, errors = [], []
    for seed in range(seeds):
        sim = yauyau.simulate(spec, rows, seed=100 + seed)
        data = sim.rows + offset * (1.0 if discrete else spec.discretization.dt)
        flt = yauyau.open_filter(STORE, mid, method=method, monitor=1e9)
        found = None
        for start in range(0, rows, CHUNK):
            result = flt.run(data[start:start + CHUNK])
            if found is None and result.alarm.any():
                found = start + int(np.argmax(result.alarm)) + 1
                truth = sim.states[start + 1:start + 1 + len(result), 0]
                errors.append(float(np.mean(result.mean[:, 0] - truth)))
                break
        delays.append(found)
    seen = [d for d in delays if d is not None]
    return {"case": name, "method": flt.method, "rows": rows, "seeds": seeds, "detected": len(seen),
            "median": float(np.median(seen)) if seen else None, "max": max(seen) if seen else None,
            "mean_error_at_alarm": float(np.mean(errors)) if errors else None}


def shift(delta: float, seeds: int, rows: int) -> dict:
    """Part 2, the monitor alone: N(δ, 1) scores."""
    from yauyau.solver.watch import run_charts

    rng = np.random.default_rng(7)
    delays = []
    for _ in range(seeds):
        z = rng.normal(delta, 1.0, (rows, 1))
        _, _, alarm = run_charts((), z, 1e9)
        delays.append(int(np.argmax(alarm)) + 1 if alarm.any() else None)
    seen = [d for d in delays if d is not None]
    return {"case": f"scores N({delta:g}, 1)", "method": "-", "rows": rows, "seeds": seeds,
            "detected": len(seen),
            "median": float(np.median(seen)) if seen else None, "max": max(seen) if seen else None,
            "mean_error_at_alarm": None}


def false_alarms(arl: float, rows: int, seeds: int) -> dict:
    """The monitor on N(0, 1) scores at a small ``arl`` (where alarms are frequent enough to count):
    rows per alarm measured against the Siegmund target."""
    from yauyau.solver.watch import run_charts

    rng = np.random.default_rng(11)
    count = 0
    for _ in range(seeds):
        _, _, alarm = run_charts((), rng.normal(0.0, 1.0, (rows, 1)), arl)
        count += int(alarm.sum())
    return {"target": arl, "rows": rows * seeds, "alarms": count,
            "rows_per_alarm": rows * seeds / count if count else math.inf}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=50_000)
    parser.add_argument("--models", default=None,
                        help="comma-separated stems of examples/*.toml (default: all)")
    parser.add_argument("--no-bias", action="store_true")
    parser.add_argument("--no-healthy", action="store_true")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--cases", default="ou-discrete +0.33,power-meter -0.33,ou +0.33",
                        help="comma-separated bias cases (default: all three)")
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args(argv)
    paths = sorted(str(p) for p in (ROOT / "examples").glob("*.toml"))
    if args.models:
        wanted = set(args.models.split(","))
        paths = [p for p in paths if Path(p).stem in wanted]
    out: dict = {"healthy": [], "bias": [], "calibration": []}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        jobs = [] if args.no_healthy else [pool.submit(healthy, p, args.rows) for p in paths]
        cases = [] if args.no_bias else [pool.submit(bias_case, c, args.seeds, 40_000)
                                         for c in args.cases.split(",") if c]
        for job in jobs:
            row = job.result()
            out["healthy"].append(row)
            print(json.dumps(row), flush=True)
        for case in cases:
            row = case.result()
            out["bias"].append(row)
            print(json.dumps(row), flush=True)
    if not args.no_bias:
        for delta in (1.0, 0.33, 0.1):
            out["bias"].append(shift(delta, args.seeds, 200_000))
        for arl in (1e3, 1e4):
            out["calibration"].append(false_alarms(arl, 200_000, 10))
    (ROOT / "var").mkdir(exist_ok=True)
    (ROOT / "var" / "bench-watch.json").write_text(json.dumps(out, indent=1))
    print(render(out))
    return 0


def render(out: dict) -> str:
    lines = []
    if out["healthy"]:
        lines += ["| model | method | rows | gated | longest gated run | restarts | most in 100 rows | "
                  "alarms | largest \\|statistic\\| | z mean | z sd | filter µs/row | monitor µs/row |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in out["healthy"]:
            lines.append(f"| {r['model']} | {r['method']} | {r['rows']} | {r['gated']} | "
                         f"{r['longest_gated']} | {r['restarts']} | {r['restarts_in_window']} | "
                         f"{r['alarms']} | {r['max_statistic']:.2f} | {r['z_mean']:+.3f} | {r['z_sd']:.3f} | "
                         f"{r['filter_us']:.1f} | {r['monitor_us']:.2f} |")
    if out["bias"]:
        lines += ["", "| case | method | seeds | detected | median delay (rows) | longest | "
                      "mean error at alarm |",
                  "|---|---|---|---|---|---|---|"]
        for r in out["bias"]:
            err = "" if r["mean_error_at_alarm"] is None else f"{r['mean_error_at_alarm']:+.2f}"
            lines.append(f"| {r['case']} | {r['method']} | {r['seeds']} | {r['detected']}/{r['seeds']} | "
                         f"{r['median']} | {r['max']} | {err} |")
    if out["calibration"]:
        lines += ["", "| monitor target (rows per false alarm) | rows of N(0, 1) scores | alarms | "
                      "rows per alarm |",
                  "|---|---|---|---|"]
        for r in out["calibration"]:
            lines.append(f"| {r['target']:g} | {r['rows']} | {r['alarms']} | {r['rows_per_alarm']:.0f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
