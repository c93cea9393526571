"""`yauyau simulate SPEC --steps K --seed S --out DIR`: a sample path and its observations.

Writes DIR/truth.csv (step, t, one column per state variable: x(t_k), k = 0..K) and
DIR/increments.csv (header dy_1..dy_m, one row per step: the observation increments
dy_k = ∫ h(x) dt + dw over (t_(k−1), t_k], exactly what `yauyau filter --increments` reads).
Euler–Maruyama with --substeps steps per dt (yauyau.simulate); the same seed gives the same files.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .filter import write_csv


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="model spec (.toml or .json)")
    parser.add_argument("--steps", type=int, required=True, metavar="K", help="number of observation steps")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default %(default)s)")
    parser.add_argument("--substeps", type=int, default=10, metavar="J",
                        help="Euler-Maruyama steps per dt (default %(default)s)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="directory for truth.csv and increments.csv")


def run(args: argparse.Namespace) -> int:
    from yauyau.solver.errors import InputError
    from yauyau.solver.spec import load_spec

    from yauyau.api import simulate

    if args.steps < 1 or args.steps > 10_000_000:
        raise InputError("steps", "must be a positive integer (at most 10 000 000)")
    if not 1 <= args.substeps <= 10_000:
        raise InputError("substeps", "must be an integer in 1..10000")
    if args.seed < 0:
        raise InputError("seed", "must be a non-negative integer")
    spec = load_spec(args.spec)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("out", f"{out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError("out", f"cannot create {out}: {exc}") from None
    sim = simulate(spec, steps=args.steps, seed=args.seed, substeps=args.substeps)
    names = list(spec.state)
    truth = [[k, float(t), *map(float, x)]
             for k, (t, x) in enumerate(zip(sim.times, sim.states, strict=True))]
    write_csv(str(out / "truth.csv"), ["step", "t", *names], truth)
    m = sim.increments.shape[1]
    write_csv(str(out / "increments.csv"), [f"dy_{j + 1}" for j in range(m)],
              [[float(v) for v in row] for row in sim.increments])
    print(f"{out / 'truth.csv'}\n{out / 'increments.csv'}")
    print(f"yauyau simulate: {args.steps} steps of {spec.name!r} (seed {args.seed}); filter them with\n"
          f"  yauyau filter MODEL_ID --store STORE --increments {out / 'increments.csv'} --out OUT.csv",
          file=sys.stderr)
    return 0
