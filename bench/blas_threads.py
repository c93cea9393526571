"""BLAS threads in the online hot path: one thread (yauyau's default) vs OpenBLAS's default.

    python -m bench.blas_threads [--quick]     # writes bench/results/blas.md

The engine's step is two small matrix-vector products (seed 002 (5.35)–(5.38)); OpenBLAS splits each
over all cores, which pays a hand-off per product and collapses when another process holds a core.
Measured on the 2-D example (``examples/range_2d.toml``: Q ≈ 1700 nodes, N = 850, single precision)
through ``run_arrays`` in chunks of 1000, the two settings interleaved, on an idle machine and with
one CPU-bound process beside it (a busy service host); medians of the repeats.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits
from yauyau.solver import compile_model, load_spec
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.offline.pipeline import precompute

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "blas.md"
CHUNK = 1000


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        x += 1


def _default_threads() -> int:
    counts = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
    return max(counts) if counts else 1


def measure(flt: YauYauFilter, repeats: int) -> dict[tuple[str, str], float]:
    dy = np.zeros((CHUNK, flt.model.m))
    start = flt.initial_state()
    default = _default_threads()
    settings = {"1 thread (yauyau default)": 1, f"{default} threads (OpenBLAS default)": None}
    out: dict[tuple[str, str], float] = {}
    ctx = multiprocessing.get_context("spawn")
    for load in ("idle", "one busy process beside it"):
        stop = ctx.Event()
        spinner = ctx.Process(target=_spin, args=(stop,), daemon=True) if load != "idle" else None
        if spinner:
            spinner.start()
            time.sleep(0.5)
        times: dict[str, list[float]] = {name: [] for name in settings}
        try:
            for _ in range(repeats):  # interleaved: the noise hits both settings alike
                for name, limit in settings.items():
                    with threadpool_limits(limits=limit, user_api="blas"):
                        began = time.perf_counter()
                        flt.run_arrays(start, dy)
                        times[name].append((time.perf_counter() - began) / CHUNK * 1e6)
        finally:
            if spinner:
                stop.set()
                spinner.join(5)
        for name, values in times.items():
            out[(load, name)] = float(np.median(values))
    return out


def render(rows: dict, shape: tuple[int, int], repeats: int) -> str:
    lines = ["## BLAS threads in the online engine", "",
             "`python -m bench.blas_threads`", "",
             f"2-D example (`examples/range_2d.toml`, Q = {shape[0]}, N = {shape[1]}, single precision), "
             f"`run_arrays` in chunks of {CHUNK}: µs per observation, medians of {repeats} interleaved "
             f"repeats on {os.cpu_count()} cores.", "",
             "| machine | BLAS threads | µs / observation | × one thread |", "|---|---|---:|---:|"]
    for load in dict.fromkeys(load for load, _ in rows):
        one = next(v for (lo, name), v in rows.items() if lo == load and name.startswith("1 thread"))
        for (lo, name), value in rows.items():
            if lo == load:
                lines.append(f"| {load} | {name} | {value:.0f} | {value / one:.2f} |")
    ratio = {load: value / next(v for (lo, n), v in rows.items() if lo == load and n.startswith("1 thread"))
             for (load, name), value in rows.items() if not name.startswith("1 thread")}
    idle, busy = ratio.get("idle", float("nan")), ratio.get("one busy process beside it", float("nan"))
    lines += ["", f"On an idle machine the default threads take {idle:.2f}× the time of one thread; with one "
              f"busy process beside it {busy:.2f}×.  Each step is two matrix-vector products of a few MB: "
              "split over threads they pay a hand-off per product, and when another process holds a core "
              "the split waits for it — the normal state of a service host or of several filters side by "
              "side.  `yauyau filter`, `yauyau serve` and `yauyau.open_filter` therefore run the hot path "
              "with one BLAS thread per process by default (threadpoolctl; `--blas-threads N`, "
              "`open_filter(..., blas_threads=N)` (0: leave BLAS as it is) or `YAUYAU_BLAS_THREADS`): "
              "scale with processes (`--workers`), and raise the threads only on a machine kept idle.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.blas_threads", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    args = parser.parse_args(argv)
    pinned = [k for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS") if k in os.environ]
    if pinned:  # the library's own default is the point here: measure in a process without the pin
        import subprocess
        import sys

        env = {k: v for k, v in os.environ.items() if k not in pinned}
        subprocess.run([sys.executable, "-m", "bench.blas_threads", *(argv or [])], env=env, check=True,
                       cwd=ROOT)
        return
    repeats = 3 if args.quick else 9
    spec = load_spec(ROOT / "examples" / "range_2d.toml")
    model = compile_model(spec)
    offline = precompute(model)
    flt = YauYauFilter(model, offline, precision=spec.discretization.precision)
    rows = measure(flt, repeats)
    text = render(rows, offline.basis.shape, repeats)
    FRAGMENT.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
