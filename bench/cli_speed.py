"""`yauyau filter` over a file against the engine's `run_arrays` and the `particles` library.

    python -m bench.cli_speed [--quick]     # writes bench/results/cli.md

The 1-D cubic sensor with its tuned mesh (examples/cubic_sensor.toml: mesh = 40, Q = 159) and the
same spec without ``mesh`` (the default discretisation, Q ≈ 2N = 259), also in single precision (what
the products' halved memory traffic buys towards 100×): a CSV of K increments, filtered
by the CLI in a subprocess (its cost per row: the run on K rows minus the run on one row, which holds
the start-up and the model load) and by ``run_arrays`` in chunks of 1000 in this process (as the
CLI chunks), one BLAS thread, interleaved, medians.  The `particles` library's bootstrap filter with
10 000 particles (bench/peer_particles.py in bench/out/peers-venv; ``python -m bench.measurements
--setup-peers`` makes it) filters the first rows of the same data as readings z = dy/dt with noise
variance R/dt, the exact Ornstein–Uhlenbeck transition; its cost per observation is beside ours.
Targets (issue "Many streams at once"): CLI ≤ 1.3× ``run_arrays`` per row; the CLI ≥ 100× faster
per observation than the 10k-particle filter.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "cli.md"
SPEC = ROOT / "examples" / "cubic_sensor.toml"
TARGET_CLI, TARGET_PF = 1.3, 100.0


def _cli(model_id: str, store: Path, rows: Path, out: Path, kernel: str) -> float:
    """CPU seconds (user + system) of `yauyau filter` with ``kernel`` forced (YAUYAU_KERNEL)."""
    yauyau = Path(sys.executable).with_name("yauyau")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", YAUYAU_KERNEL=kernel)
    command = [str(yauyau), "filter", model_id, "--store", str(store), "--increments", str(rows),
               "--out", str(out)]
    before = os.times()
    subprocess.run(command, check=True, capture_output=True, env=env)
    after = os.times()
    return (after.children_user - before.children_user) + (after.children_system - before.children_system)


def _engine(flt, increments: np.ndarray) -> float:
    state = flt.initial_state()
    start = time.process_time()
    for k in range(0, len(increments), 1000):
        state, _ = flt.run_arrays(state, increments[k:k + 1000])
    return time.process_time() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.cli_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rows and repeats")
    args = parser.parse_args(argv)
    K, repeats, pf_rows = (200_000, 3, 2000) if not args.quick else (20_000, 2, 500)
    from threadpoolctl import threadpool_limits
    from yauyau.solver.methods import make_filter
    from yauyau.solver.spec import spec_from_dict

    import yauyau

    from .measurements import ParticlesPeer

    spec = yauyau.load_spec(SPEC)
    doc = spec.model_dump(mode="json")
    doc["discretization"] = {k: v for k, v in doc["discretization"].items() if k != "mesh"}
    single = {**doc, "discretization": {**doc["discretization"], "precision": "single"}}
    specs = {"tuned mesh (mesh = 40)": spec, "default discretisation": spec_from_dict(doc),
             "default discretisation, single precision": spec_from_dict(single)}
    rows = []
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1, user_api="blas"):
        tmp = Path(tmp)
        model = yauyau.compile_model(spec)
        increments = yauyau.simulate(spec, steps=K, seed=11).increments
        data, one = tmp / "rows.csv", tmp / "one.csv"
        data.write_text("dy\n" + "\n".join(repr(v) for v in increments[:, 0].tolist()) + "\n")
        one.write_text("dy\n" + repr(float(increments[0, 0])) + "\n")
        sets = [(0, increments[:pf_rows], model.dt * np.arange(1, pf_rows + 1))]
        peer, why = ParticlesPeer.start(model, sets, increments_dt=model.dt)
        for label, s in specs.items():
            mid = yauyau.precompute(s, tmp / "store")
            loaded = yauyau.api.load_model(tmp / "store", mid)
            flt = make_filter(loaded.model, loaded.offline, loaded.method)
            cli, base, slow, slow_base, engine, pf = [], [], [], [], [], []
            for _ in range(repeats):
                cli.append(_cli(mid, tmp / "store", data, tmp / "out.csv", "compiled"))
                base.append(_cli(mid, tmp / "store", one, tmp / "out1.csv", "compiled"))
                slow.append(_cli(mid, tmp / "store", data, tmp / "out.csv", "numpy"))
                slow_base.append(_cli(mid, tmp / "store", one, tmp / "out1.csv", "numpy"))
                engine.append(_engine(flt, increments))
                if peer is not None:
                    pf.append(peer.run(0) / pf_rows)
            per_row = (statistics.median(cli) - statistics.median(base)) / (K - 1)
            numpy_row = (statistics.median(slow) - statistics.median(slow_base)) / (K - 1)
            eng = statistics.median(engine) / K
            peer_row = statistics.median(pf) if pf else None
            rows.append((label, len(flt.nodes), per_row, numpy_row, eng, peer_row))
            pf_text = f", particles 10k {rows[-1][-1] * 1e6:.0f} us/obs" if pf else ""
            print(f"{label}: Q = {len(flt.nodes)}, CLI {per_row * 1e6:.1f} us/row (numpy kernel "
                  f"{numpy_row * 1e6:.1f}), run_arrays {eng * 1e6:.1f} us/row "
                  f"({per_row / eng:.2f}x){pf_text}")
        if peer is not None:
            peer.close()
    command = "python -m bench.cli_speed" + (" --quick" if args.quick else "")
    peer_note = "" if peer is not None else f": {why}"
    lines = ["## `yauyau filter` over a file", "", f"`{command}`", "",
             f"1-D cubic sensor (N = 128), {K} increments in a CSV file; the CLI's cost per row is the run "
             "on the file minus the run on one row (start-up, model load), CPU time of the process, with "
             "the compiled kernel forced (what `filter` takes from `COMPILED_MIN_ROWS` = 100 000 rows on: "
             "below, numba's start-up costs more than it saves, bench/results/startup.md) and with the "
             "numpy kernel (what it takes below); `run_arrays` in chunks of 1000 "
             f"as the CLI chunks, compiled, CPU time; one BLAS thread, interleaved, medians of {repeats}. "
             "The `particles` "
             f"library's 10k-particle bootstrap filter on the first {pf_rows} rows (bench/peer_particles.py, "
             f"exact OU transition){peer_note}.", "",
             "| discretisation | Q | CLI µs/row | CLI µs/row, numpy kernel | `run_arrays` µs/row "
             "| CLI / run_arrays | particles 10k µs/obs | particles / CLI |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, Q, cli, numpy_row, eng, pf in rows:
        lines.append(f"| {label} | {Q} | {cli * 1e6:.1f} | {numpy_row * 1e6:.1f} | {eng * 1e6:.1f} | "
                     f"{cli / eng:.2f}× | " + (f"{pf * 1e6:.0f} | {pf / cli:.0f}× |" if pf else "— | — |"))
    lines += ["", f"Targets: CLI ≤ {TARGET_CLI:g}× `run_arrays` per row; ≥ {TARGET_PF:g}× faster than the "
              "10k-particle filter (default discretisation)."]
    write_fragment(FRAGMENT, lines)
    print(f"wrote {FRAGMENT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
