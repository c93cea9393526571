"""The engine's rows compiled (numba) against the numpy path, and the floor of their two BLAS products.

    python -m bench.compiled_kernels [--quick]     # writes bench/results/compiled.md

µs per row of ``run_arrays`` (chunks of 1000 rows of zero increments; regular rows one dt apart and irregular
rows 0.5–1.5 dt apart, modal flow) on the 1-D cubic sensor and the 2-D example as the bundled specs
give them, ``YAUYAU_KERNEL=numpy`` against ``compiled`` (solver/engine/compiled.py), next to the two
BLAS products of a row alone (the same gemv called from a compiled loop: no Python at all).  CPU time
(time.process_time), one BLAS thread (threadpoolctl), the configurations interleaved, medians.  The
compiled chunks run fused (solver/engine/fused.py: the update factor and the moments' sums inside the
row); the table gives both paths' largest difference per column, relative to the column's largest value.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, load_spec
from yauyau.solver.methods import make_filter
from yauyau.solver.offline.pipeline import precompute

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "compiled.md"
CASES = {"1-D cubic sensor": "cubic_sensor.toml", "2-D rotation, cubic sensor": "range_2d.toml"}
CHUNK = 1000
KERNELS = ("numpy", "compiled")


def _run(flt, state, rows, times, kernel: str):
    os.environ["YAUYAU_KERNEL"] = kernel
    return flt.run_arrays(state, rows, times)


def _difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a − b| per column over the column's max |a|, the largest over the columns."""
    a2, b2 = a.reshape(len(a), -1), b.reshape(len(b), -1)
    scale = np.maximum(np.abs(a2).max(axis=0), 1e-300)
    return float((np.abs(a2 - b2) / scale).max())


def _floor(flt):
    """The two products of a row alone, CHUNK times, from a compiled loop."""
    from yauyau.solver.engine.compiled import products

    carried = np.append(flt.initial_state().coefficients, 1.0).astype(flt.arith.dtype)
    following, row = np.empty_like(carried), np.empty(flt.nodes.shape[0], dtype=flt.arith.dtype)
    return lambda: products(CHUNK, flt.observation_propagator, flt.projection, carried, following, row)


def _loop(flt, state, rows):
    """The fused compiled loop alone (compiled.run_fused on a chunk's arguments, regular rows)."""
    from yauyau.solver.engine import compiled

    calls, original = [], compiled.run_fused
    compiled.run_fused = lambda *args: calls.append(args) or original(*args)
    try:
        _run(flt, state, rows, None, "compiled")
    finally:
        compiled.run_fused = original
    args = list(calls[0])

    def run():
        args[4], args[5] = calls[0][4].copy(), calls[0][5].copy()  # the two buffers it overwrites
        return original(*args)

    return run


def measure(example: str, repeats: int) -> dict:
    model = compile_model(load_spec(ROOT / "examples" / example))
    offline = precompute(model)
    flt = make_filter(model, offline, "yau-yau")
    # zero increments (as bench/engine_speed.py): every row a full step on both kinds of times
    rows = np.zeros((CHUNK, model.m))
    times = np.cumsum(np.random.default_rng(3).uniform(0.5, 1.5, CHUNK) * model.dt)
    start = flt.initial_state()
    jobs = {(label, kernel): (lambda g=given, k=kernel: _run(flt, start, rows, g, k))
            for label, given in (("regular", None), ("irregular", times)) for kernel in KERNELS}
    identical, first_call = {}, {}
    for (label, kernel), job in jobs.items():  # warm: the flow's eigenbasis, numba's import and cache
        began = time.process_time()
        state, result = job()
        first_call[(label, kernel)] = time.process_time() - began
        assert not result.degenerate.any(), (example, label, kernel)
        identical.setdefault(label, []).append((result.mean, result.cov, result.loglik, state.coefficients))
    same = {label: max(_difference(a, b) for a, b in zip(*pair, strict=True))
            for label, pair in identical.items()}
    jobs[("loop", "fused")] = _loop(flt, start, rows)
    jobs[("floor", "BLAS")] = _floor(flt)
    for key in (("loop", "fused"), ("floor", "BLAS")):
        jobs[key]()
    times_us: dict = {key: [] for key in jobs}
    for _ in range(repeats):  # interleaved: the machine's noise hits every configuration alike
        for key, job in jobs.items():
            began = time.process_time()
            job()
            times_us[key].append((time.process_time() - began) / CHUNK * 1e6)
    medians = {key: float(np.median(v)) for key, v in times_us.items()}
    return {"shape": offline.basis.shape, "precision": flt.arith.dtype.__name__, "us": medians,
            "same": same, "first": first_call[("regular", "compiled")]}


def render(results: dict, load: float) -> list[str]:
    lines = ["## Compiled row loops (numba) against the numpy path", "",
             "`python -m bench.compiled_kernels`", "",
             f"µs per row of `run_arrays` (the initial state made once, outside the timing), chunks of "
             f"{CHUNK} rows of zero increments (irregular: "
             "gaps 0.5–1.5 dt, modal flow), `YAUYAU_KERNEL=numpy` against `compiled` (fused chunks); "
             "*max rel. difference*: the largest over mean, cov, loglik and the state's coefficients of "
             "max |numpy − compiled| per column over the column's max |numpy|; *floor*: the "
             "row's two BLAS products alone (the same gemv from a compiled loop).  CPU time, one BLAS "
             f"thread, configurations interleaved, medians; load average {load:.1f} on "
             f"{os.cpu_count()} cores at the start.", "",
             "| model | precision | Q | N | rows | numpy µs | compiled µs | speed-up | floor µs "
             "| compiled / floor | max rel. difference |",
             "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    loops = ["", "The fused compiled loop alone (`compiled.run_fused` on a chunk's arguments: the factor, "
             "the row's two products, the moments' sums; regular rows), the rest of `run_arrays` being its "
             "Python before and after (the row terms, the gate's floors, the moments and checks from the "
             "sums, the result):", "", "| model | fused loop µs | fused loop / floor |", "|---|---:|---:|"]
    for title, r in results.items():
        floor = r["us"][("floor", "BLAS")]
        for label in ("regular", "irregular"):
            numpy_us, compiled_us = r["us"][(label, "numpy")], r["us"][(label, "compiled")]
            lines.append(f"| {title} | {r['precision']} | {r['shape'][0]} | {r['shape'][1]} | {label} | "
                         f"{numpy_us:.2f} | {compiled_us:.2f} | {numpy_us / compiled_us:.2f}× | "
                         f"{floor:.2f} | {compiled_us / floor:.2f} | {r['same'][label]:.1e} |")
        loop = r["us"][("loop", "fused")]
        loops.append(f"| {title} | {loop:.2f} | {loop / floor:.2f} |")
    lines += loops
    firsts = ", ".join(f"{title}: {r['first']:.2f} s" for title, r in results.items())
    lines += ["", f"First compiled chunk of the process (numba's import and its on-disk cache, or the "
              f"compilation where the cache is cold): {firsts}.", ""]
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.compiled_kernels",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    args = parser.parse_args(argv)
    repeats = 3 if args.quick else 9
    load = os.getloadavg()[0]
    saved = os.environ.get("YAUYAU_KERNEL")
    try:
        with threadpool_limits(1):
            results = {title: measure(example, repeats) for title, example in CASES.items()}
    finally:
        if saved is None:
            os.environ.pop("YAUYAU_KERNEL", None)
        else:
            os.environ["YAUYAU_KERNEL"] = saved
    lines = render(results, load)
    write_fragment(FRAGMENT, lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
