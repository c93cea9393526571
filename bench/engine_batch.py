"""Many streams of one model stepped together (solver/engine/batch.py) against one ``run_arrays`` each.

    python -m bench.engine_batch [--quick]     # writes bench/results/engine-batch.md

S states of a model, each with its own 100-row chunk (simulated), advanced by ``run_batch`` and by
a loop of ``run_arrays``, interleaved, one BLAS thread, medians of the repeats.  Models: the 1-D
cubic sensor (examples/cubic_sensor.toml: Q = 159 nodes, N = 128, the fused P Π operator) and the
2-D rotation (examples/range_2d.toml: Q = 1801, N = 850, single precision as its spec says, and
double).  The largest gap between the two answers' means is reported beside the times.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, load_spec
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "engine-batch.md"
CHUNK = 100
MODELS = [("1-D cubic sensor", "cubic_sensor.toml", None), ("2-D rotation", "range_2d.toml", None),
          ("2-D rotation", "range_2d.toml", "double")]


def _measure(engine, chunks, repeats: int) -> tuple[float, float, float]:
    """(ms alone, ms together, largest |mean gap|) for the states' chunks, interleaved."""
    states = [engine.initial_state() for _ in chunks]
    alone_t, together_t = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        alone = [engine.run_arrays(s, c) for s, c in zip(states, chunks, strict=True)]
        alone_t.append(time.perf_counter() - start)
        start = time.perf_counter()
        together = engine.run_batch(states, chunks)
        together_t.append(time.perf_counter() - start)
    gap = max(float(np.max(np.abs(a[1].mean - b[1].mean))) for a, b in zip(alone, together, strict=True))
    return statistics.median(alone_t) * 1e3, statistics.median(together_t) * 1e3, gap


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.engine_batch", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and streams")
    args = parser.parse_args(argv)
    streams = (1, 8, 64) if not args.quick else (1, 8)
    repeats = 5 if not args.quick else 2
    rows = []
    with threadpool_limits(1, user_api="blas"):
        for label, name, precision in MODELS:
            spec = load_spec(ROOT / "examples" / name)
            model = compile_model(spec)
            offline = precompute(model)
            engine = YauYauFilter(model, offline, precision=precision or spec.discretization.precision)
            for S in streams:
                chunks = [simulate(model, CHUNK, np.random.default_rng(100 + i)).increments for i in range(S)]
                alone, together, gap = _measure(engine, chunks, repeats if S < 64 else max(2, repeats - 2))
                rows.append((label, engine.precision, len(engine.nodes), engine.N, S, alone, together, gap))
                print(f"{label} {engine.precision} S={S}: alone {alone:.1f} ms, together {together:.1f} ms "
                      f"({alone / together:.2f}x), mean gap {gap:.1e}")
    lines = ["## Many streams stepped together (`run_batch`)", "",
             "`python -m bench.engine_batch" + (" --quick" if args.quick else "") + "`", "",
             f"S states of one model, each with its own {CHUNK}-row chunk: one `run_arrays` per state "
             "against one `run_batch` for all (solver/engine/batch.py: a matrix–matrix product per step), "
             "interleaved, one BLAS thread, medians. *gap*: the largest difference between the two "
             "answers' means (rounding; the documented tolerance is `BATCH_RTOL`).", "",
             "| model | precision | Q | N | streams | alone ms | together ms | speed-up | per stream µs/row "
             "| mean gap |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for label, precision, Q, N, S, alone, together, gap in rows:
        lines.append(f"| {label} | {precision} | {Q} | {N} | {S} | {alone:.1f} | {together:.1f} "
                     f"| {alone / together:.2f}× | {together / S / CHUNK * 1e3:.1f} | {gap:.1e} |")
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
