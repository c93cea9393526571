"""`yauyau check SPEC`: does the discretisation resolve the posterior this model will have?

Simulates ``--paths`` paths of ``--steps`` steps from the model, filters them with the spec's
discretisation (the general engine) and compares the conditional means with the truth — the exact
Kalman filter for a linear model, else the engine at twice the basis (yauyau.solver.check) — then
says the mean and largest gap, the share of degenerate steps and, when the mean gap is over
``--target`` or a step degenerated, the smallest basis (1.5, 2 or 3 times the spec's) that passes.  It
also says which fraction of the paths leave the domain (a fixed ball, or a following ball's region)
and fails when any does, naming the fix (domain.follow = true, a larger domain.radius).
Exit status: 0 resolved, 1 not resolved or a path left the domain, 2 bad input.
"""

from __future__ import annotations

import json

from yauyau.solver.check import DEFAULT_TARGET


def add_arguments(parser) -> None:
    parser.add_argument("spec", metavar="SPEC", help="model spec (.toml or .json)")
    parser.add_argument("--paths", type=int, default=4, help="simulated paths (default 4)")
    parser.add_argument("--steps", type=int, default=300, help="steps per path (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated paths (default 0)")
    parser.add_argument("--target", type=float, default=DEFAULT_TARGET,
                        help=f"largest mean gap to the truth that passes (default {DEFAULT_TARGET:g})")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args) -> int:
    from yauyau.solver.check import resolution_check
    from yauyau.solver.spec import load_spec

    report = resolution_check(load_spec(args.spec), paths=args.paths, steps=args.steps, seed=args.seed,
                              target=args.target)
    print(json.dumps(report.to_dict(), indent=2) if args.json else report.render())
    return 0 if report.ok else 1
