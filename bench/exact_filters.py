"""µs per observation of the ODE filters (Kalman–Bucy, Yau–Hu) side by side with the engine.

    .venv/bin/python -m bench.exact_filters            # 2000 steps, engine included if it runs
    .venv/bin/python -m bench.exact_filters --quick    # 300 steps

Same simulated increments for every filter of a model, timed in one process (ratios, not
absolute numbers, are what a noisy machine can tell).  The issue asks that an ODE filter's
online step be >= 10x cheaper than the general engine on the same model.  Writes docs/bench-exact.md.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from solver.exact.kalman_bucy import KalmanBucyFilter
from solver.exact.yau_hu import YauHuFilter
from solver.model import compile_model
from solver.simulate import simulate
from solver.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "bench-exact.md"


def _time_run(filt, increments, repeats: int = 3) -> float:
    """Best-of-``repeats`` µs per observation of ``run`` over the whole chunk."""
    best = np.inf
    for _ in range(repeats):
        state = filt.initial_state()
        start = time.perf_counter()
        filt.run(state, increments)
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / len(increments)


def _engine(model):
    try:
        from solver.engine import YauYauFilter
        from solver.offline import precompute
    except ImportError:
        return None, "engine not importable"
    start = time.perf_counter()
    offline = precompute(model)
    return YauYauFilter(model, offline), f"precompute {time.perf_counter() - start:.1f} s"


def _case(name: str, path: str, steps: int, filters) -> list[str]:
    model = compile_model(load_spec(ROOT / path))
    increments = simulate(model, steps, np.random.default_rng(0)).increments
    rows = {label: _time_run(make(model), increments) for label, make in filters}
    engine, note = _engine(model)
    if engine is not None:
        rows["Yau–Yau engine (stable)"] = _time_run(engine, increments, repeats=1)
    base = rows.get("Yau–Yau engine (stable)")
    basis = model.spec.discretization.basis
    lines = [f"### {name} ({path}, {steps} steps, dt = {model.dt}, basis {basis}; {note})",
             "", "| filter | µs/obs (chunk) | engine time / this |", "|---|---:|---:|"]
    for label, us in rows.items():
        ratio = f"{base / us:.1f}x" if base else "n/a"
        lines.append(f"| {label} | {us:.1f} | {ratio} |")
    return lines + [""]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    steps = 300 if args.quick else 2000
    lines = ["## Exact ODE filters (bench/exact_filters.py)", "",
             f"Command: `.venv/bin/python -m bench.exact_filters{' --quick' if args.quick else ''}`", ""]
    lines += _case("Ornstein–Uhlenbeck", "examples/ou.toml", steps, [
        ("Kalman–Bucy (continuous)", KalmanBucyFilter),
        ("Kalman (discrete)", lambda m: KalmanBucyFilter(m, kind="discrete")),
        ("Yau–Hu", YauHuFilter)])
    lines += _case("Beneš", "examples/benes.toml", steps, [("Yau–Hu (4 components)",
                                                           lambda m: YauHuFilter(m, n_components=4))])
    OUT.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
