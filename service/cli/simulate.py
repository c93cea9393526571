"""`yauyau simulate SPEC --steps K --seed S --out DIR [--mean-gap G]`: a sample path and its observations.

Writes DIR/truth.csv (step, t, one column per state variable: x(t_k), k = 0..K, t_0 = 0) and the rows
that `yauyau filter` reads, by the spec's ``[measurement] kind``:

* continuous, every dt: DIR/increments.csv (header dy_1..dy_m, one row per step: the observation
  increments dy_k = ∫ h(x) dt + dw over (t_(k−1), t_k]), for ``filter --increments``;
* continuous with --mean-gap G (irregular times, exponential gaps of mean G): DIR/observations.csv
  (header t,dy_1..dy_m: each row the increment over the gap that ends at its t);
* discrete: DIR/observations.csv (header t,z_1..z_m: the measurements z_k = h(x(t_k)) + v_k), every dt
  or with --mean-gap at random times;

the last two for ``filter --observations ... --t0 0`` (the path starts from the prior at t = 0).
Euler–Maruyama with --substeps steps per dt (yauyau.simulate); the same seed gives the same files (the
random times come from a child of the seed, solver.simulate.random_times).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from pathlib import Path

from .csv_io import write_csv
from .precompute import default_store

EPILOG = """\
files (in DIR):
  truth.csv         step, t, one column per state variable: x(t_k), k = 0..K, from the prior at t = 0
  increments.csv    continuous model, every dt: header dy_1..dy_m, one row per step, the increments
                    dy_k of y over (t_(k-1), t_k]: yauyau filter --increments reads it
  observations.csv  discrete model, or --mean-gap: header t,z_1..z_m (measurements z = h(x(t)) + v)
                    or t,dy_1..dy_m (increments over the gap ending at t): yauyau filter
                    --observations reads it, with --t0 0 (the path starts at t = 0)
stderr ends with the commands that filter the files: yauyau precompute SPEC (once) and yauyau filter
with the model id it prints, computed here from the spec.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="model spec (.toml or .json)")
    parser.add_argument("--steps", type=int, required=True, metavar="K", help="number of observations")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default %(default)s)")
    parser.add_argument("--substeps", type=int, default=10, metavar="J",
                        help="Euler-Maruyama steps per dt (default %(default)s)")
    parser.add_argument("--mean-gap", type=float, default=None, metavar="G",
                        help="observe at random times (exponential gaps of mean G) instead of every dt; "
                             "writes observations.csv with a t column")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="directory for truth.csv and increments.csv or observations.csv")
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from yauyau.solver.errors import InputError
    from yauyau.solver.spec import load_spec

    from yauyau.api import simulate

    if args.steps < 1 or args.steps > 10_000_000:
        raise InputError("steps", "must be a positive integer (at most 10 000 000)")
    if not 1 <= args.substeps <= 10_000:
        raise InputError("substeps", "must be an integer in 1..10000")
    if args.seed < 0:
        raise InputError("seed", "must be a non-negative integer")
    if args.mean_gap is not None and not (math.isfinite(args.mean_gap) and args.mean_gap > 0):
        raise InputError("mean_gap", "must be a positive number (the mean time between observations)")
    spec = load_spec(args.spec)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("out", f"{out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError("out", f"cannot create {out}: {exc}") from None
    times = None
    if args.mean_gap is not None:
        from yauyau.solver.simulate import random_times

        times = random_times(args.steps, args.mean_gap, np.random.default_rng(times_seed(args.seed)))
    sim = simulate(spec, steps=args.steps, seed=args.seed, substeps=args.substeps, times=times)
    names = list(spec.state)
    truth = [[k, float(t), *map(float, x)]
             for k, (t, x) in enumerate(zip(sim.times, sim.states, strict=True))]
    write_csv(str(out / "truth.csv"), ["step", "t", *names], truth)
    discrete = spec.measurement.kind == "discrete"
    m = sim.rows.shape[1]
    columns = [f"{'z' if discrete else 'dy'}_{j + 1}" for j in range(m)]
    if discrete or times is not None:
        path = out / "observations.csv"
        write_csv(str(path), ["t", *columns], [[float(t), *map(float, row)]
                                              for t, row in zip(sim.times[1:], sim.rows, strict=True)])
        option = ["--observations", str(path), "--t0", "0"]
    else:
        path = out / "increments.csv"
        write_csv(str(path), columns, [[float(v) for v in row] for row in sim.rows])
        option = ["--increments", str(path)]
    print(f"{out / 'truth.csv'}\n{path}")
    when = "every dt" if times is None else f"at random times (mean gap {args.mean_gap:g})"
    print(f"yauyau simulate: {args.steps} {'measurements' if discrete else 'increments'} of {spec.name!r} "
          f"{when} (seed {args.seed}); filter them with", file=sys.stderr)
    print(follow_up(args.spec, spec, option), file=sys.stderr)
    return 0


def follow_up(spec_path: str, spec, option: list[str]) -> str:
    """The two commands that filter the files: precompute the spec (once; it prints the model id) and
    filter with that id, the content hash of the spec (storage.model_store.model_id), in the store a
    command given no --store uses."""
    from yauyau.storage.model_store import model_id  # h5py: not at start-up (yauyau -h imports this module)

    store = default_store()
    mid = model_id(spec.canonical_json())
    precompute = shlex.join(["yauyau", "precompute", spec_path, "--store", store])
    run = shlex.join(["yauyau", "filter", mid, "--store", store, *option, "--out", "OUT.csv"])
    return f"  {precompute}    # once: it prints {mid}\n  {run}"


def times_seed(seed: int):
    """The seed of the random observation times: a child of ``seed`` (independent of the path's noise)."""
    import numpy as np

    return np.random.SeedSequence(seed).spawn(1)[0]
