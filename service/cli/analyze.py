"""`yauyau analyze SPEC`: Wong matrix, η, conditions, estimation algebra, recommended method.

Prints the report of :func:`yauyau.solver.analysis.analyze` as text (``report.render()``) or as JSON
with ``--json`` (``report.to_dict()``, the same dict POST /v1/analyze returns).  Both name the papers
the conditions and the recommendation come from by author, year, title and theorem (solver.papers);
the JSON has them in ``references``.  Bounded by ``--time-limit`` seconds and ``--max-size``: the
analysis runs in a process of its own (solver/analysis/isolated.py) that is killed 2 s after the time
limit, and the report is then the bounded one (what was not decided by then is undecided; the general
engine, method yau-yau, is recommended unless the conditions decided say otherwise), exit status 0.
A bad spec raises SpecError, which the dispatcher prints as one line (exit status 2).
"""

from __future__ import annotations

import json


def add_arguments(parser) -> None:
    from yauyau.solver.analysis import (
        DEFAULT_MAX_DEPTH,
        DEFAULT_MAX_DIMENSION,
        DEFAULT_MAX_SIZE,
        DEFAULT_TIME_LIMIT,
    )
    from yauyau.solver.analysis.isolated import DEFAULT_GRACE

    parser.add_argument("spec", metavar="SPEC", help="model spec (.toml or .json)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH, metavar="K",
                        help=f"rounds of Lie brackets before giving up (default {DEFAULT_MAX_DEPTH})")
    parser.add_argument("--max-dimension", type=int, default=DEFAULT_MAX_DIMENSION, metavar="D",
                        help=f"largest algebra dimension explored (default {DEFAULT_MAX_DIMENSION})")
    parser.add_argument("--time-limit", type=float, default=DEFAULT_TIME_LIMIT, metavar="T",
                        help=f"seconds for the whole analysis (default {DEFAULT_TIME_LIMIT:g}); the report "
                             "then says which conditions or brackets were not decided within it (a "
                             f"wall-clock limit: its process is killed {DEFAULT_GRACE:g} s after it)")
    parser.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE, metavar="S",
                        help="largest coefficient of an algebra element, in expression-tree nodes "
                             f"(default {DEFAULT_MAX_SIZE})")


def run(args) -> int:
    from yauyau.solver.analysis.isolated import analyze_isolated
    from yauyau.solver.errors import SpecError
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import load_spec

    if not 1 <= args.max_depth <= 20:
        raise SpecError("--max-depth", "must be between 1 and 20")
    if not 1 <= args.max_dimension <= 64:
        raise SpecError("--max-dimension", "must be between 1 and 64")
    if not 0.1 <= args.time_limit <= 3600:  # also refuses nan and inf
        raise SpecError("--time-limit", "must be between 0.1 and 3600 seconds")
    if not 10 <= args.max_size <= 1_000_000:
        raise SpecError("--max-size", "must be between 10 and 1000000")
    model = compile_model(load_spec(args.spec))  # a bad spec is refused here, before any process starts
    done = analyze_isolated(model, args.time_limit, max_depth=args.max_depth,
                            max_dimension=args.max_dimension, max_size=args.max_size)
    print(json.dumps(done.report, indent=2) if args.json else done.text)
    return 0
