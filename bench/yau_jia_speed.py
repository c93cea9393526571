"""The Yau–Jia filter's compiled kernels against its numpy path, in-process and through `yauyau filter`.

    python -m bench.yau_jia_speed [--quick]     # writes bench/results/yau-jia-speed.md

examples/range_only_4d.toml (4 states, 16 components by default): K simulated increments.  In-process:
``run_arrays`` over rows 100..K (the mixture has grown to its cap by row ~50: the steady state the CLI
sees on a long file), after the first 100 rows, ``YAUYAU_KERNEL`` = numpy and compiled interleaved,
process CPU time, medians.  Through the CLI: ``yauyau filter`` on the K rows minus on one row (start-up,
model load, numba's cache), user + system CPU of the subprocess, both kernels interleaved, medians.
One BLAS thread.  The largest relative difference of the CLI's columns between the kernels is shown.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .fragments import write_fragment
from .yau_jia import peers

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "yau-jia-speed.md"
SPEC = ROOT / "examples" / "range_only_4d.toml"
KERNELS = ("numpy", "compiled")


def _child_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _cli(kernel: str, model_id: str, store: Path, rows: Path, out: Path) -> float:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", YAUYAU_KERNEL=kernel)
    command = [str(Path(sys.executable).with_name("yauyau")), "filter", model_id, "--store", str(store),
               "--increments", str(rows), "--out", str(out), "--progress", "off"]
    before = _child_cpu()
    subprocess.run(command, check=True, capture_output=True, env=env)
    return _child_cpu() - before


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_jia_speed",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rows and repeats")
    args = parser.parse_args(argv)
    K, repeats = (1000, 3) if not args.quick else (400, 2)
    from threadpoolctl import threadpool_limits
    from yauyau.solver.exact.yau_jia import YauJiaFilter

    import yauyau

    spec = yauyau.load_spec(SPEC)
    model = yauyau.compile_model(spec)
    increments = yauyau.simulate(spec, steps=K, seed=11).increments
    flt = YauJiaFilter(model)
    inproc = {k: [] for k in KERNELS}
    cli = {k: [] for k in KERNELS}
    base = {k: [] for k in KERNELS}
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1, user_api="blas"):
        tmp = Path(tmp)
        for kernel in KERNELS:  # compile (or load the kernels) before timing
            os.environ["YAUYAU_KERNEL"] = kernel
            start, _ = flt.run_arrays(flt.initial_state(), increments[:100])
        for _ in range(repeats):
            for kernel in KERNELS:
                os.environ["YAUYAU_KERNEL"] = kernel
                t0 = time.process_time()
                flt.run_arrays(start, increments[100:])
                inproc[kernel].append((time.process_time() - t0) / (K - 100))
        os.environ.pop("YAUYAU_KERNEL", None)
        model_id = yauyau.precompute(spec, tmp / "store")
        data, one = tmp / "rows.csv", tmp / "one.csv"
        data.write_text("dy\n" + "\n".join(repr(v) for v in increments[:, 0].tolist()) + "\n")
        one.write_text("dy\n" + repr(float(increments[0, 0])) + "\n")
        for _ in range(repeats):
            for kernel in KERNELS:
                cli[kernel].append(_cli(kernel, model_id, tmp / "store", data, tmp / f"{kernel}.csv"))
                base[kernel].append(_cli(kernel, model_id, tmp / "store", one, tmp / "one-out.csv"))
        outs = [np.genfromtxt(tmp / f"{k}.csv", delimiter=",", names=True) for k in KERNELS]
        diff = max(float(np.nanmax(np.abs(outs[0][c] - outs[1][c]) / (1 + np.abs(outs[0][c]))))
                   for c in outs[0].dtype.names)
        pf, ukf = [], []
        for _ in range(repeats):  # the peers on the same increments (their own venv), after ours
            got = peers(model, increments, seed=11)
            if got is None:
                break
            pf.append(float(got["pf_seconds"][0]) / K)
            ukf.append(float(got["ukf_seconds"][0]) / K)
    per = {k: statistics.median(inproc[k]) for k in KERNELS}
    per_cli = {k: (statistics.median(cli[k]) - statistics.median(base[k])) / (K - 1) for k in KERNELS}
    start_cli = {k: statistics.median(base[k]) for k in KERNELS}
    load = os.getloadavg()[0]
    for k in KERNELS:
        print(f"{k}: in-process {per[k] * 1e3:.3f} ms/row, CLI {per_cli[k] * 1e3:.3f} ms/row "
              f"(one-row run {start_cli[k]:.2f} s CPU)")
    command = "python -m bench.yau_jia_speed" + (" --quick" if args.quick else "")
    lines = ["## Yau-Jia filter: compiled kernels", "", f"`{command}`", "",
             f"examples/range_only_4d.toml, {K} simulated increments, {flt.max_components} components (the "
             "default cap, reached by row ~50); the sensor compiled into the kernels "
             "(solver/exact/sensor_tape.py). In-process: `run_arrays` over rows 100 to "
             f"{K}, process CPU time per row. CLI: `yauyau filter` on the {K} rows minus on one row, user + "
             f"system CPU of the subprocess per row. `YAUYAU_KERNEL` = numpy (the reference path) and "
             f"compiled (solver/exact/yau_jia_fast.py) interleaved, medians of {repeats}, one BLAS thread, "
             f"load average {load:.1f} on 2 cores.", "",
             "| kernel | in-process ms/row | CLI ms/row | CLI one-row run, s CPU |", "|---|---:|---:|---:|"]
    for k in KERNELS:
        lines.append(f"| {k} | {per[k] * 1e3:.3f} | {per_cli[k] * 1e3:.3f} | {start_cli[k]:.2f} |")
    lines += ["", f"Compiled vs numpy: {per['numpy'] / per['compiled']:.1f}× in-process, "
              f"{per_cli['numpy'] / per_cli['compiled']:.1f}× through the CLI. Largest relative difference "
              f"of the CLI's output columns between the kernels over the {K} rows: {diff:.1e}."]
    if pf:
        pf_row, ukf_row = statistics.median(pf), statistics.median(ukf)
        ours_cli, ours = per_cli["compiled"], per["compiled"]
        print(f"particles 10k {pf_row * 1e3:.3f} ms/row, UKF {ukf_row * 1e3:.3f} ms/row")
        lines += ["", "The peers on the same increments (bench/peer_range_only.py in bench/out/peers-venv: "
                  "`particles`' bootstrap filter with 10 000 particles and the exact constant-velocity "
                  "transition, FilterPy's UKF; CPU time of the filtering loop, in the same run, medians of "
                  f"{len(pf)}):", "",
                  "| filter | ms/row | yau-jia (compiled) through the CLI is | in-process is |",
                  "|---|---:|---|---|",
                  f"| particles bootstrap, 10k | {pf_row * 1e3:.3f} | {pf_row / ours_cli:.1f}× faster "
                  f"| {pf_row / ours:.1f}× faster |",
                  f"| FilterPy UKF | {ukf_row * 1e3:.3f} | {ours_cli / ukf_row:.1f}× its cost "
                  f"| {ours / ukf_row:.1f}× its cost |", "",
                  "Targets (issue 37): ≥ 10× faster than the particle filter and ≤ 2× the UKF's cost, "
                  "through the CLI."]
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
