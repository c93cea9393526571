"""Run every benchmark side by side and assemble docs/benchmarks.md from their fragments.

    python -m bench            # everything (about 20-30 minutes on 2 cores)
    python -m bench --quick    # smaller runs, for a smoke test
    python -m bench --only filters,load
    python -m bench assemble   # only re-assemble docs/benchmarks.md (also: --assemble)

Each topic module bench/<topic>.py has ``main(argv)`` and writes its fragment, bench/results/<name>.md;
this driver then assembles the fragments (in the order of bench.fragments.FRAGMENTS) into
docs/benchmarks.md (bench.fragments.assemble).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import sys

from .fragments import FRAGMENTS, assemble

TOPICS = FRAGMENTS  # (module, fragment) in reading order


def _call_main(module, argv: list[str]) -> None:
    """Call ``module.main`` with argv whether it takes an argument list or reads sys.argv."""
    if inspect.signature(module.main).parameters:
        module.main(argv)
        return
    saved, sys.argv = sys.argv, [module.__name__, *argv]
    try:
        module.main()
    finally:
        sys.argv = saved


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("command", nargs="?", choices=["assemble"],
                        help="assemble: only re-assemble docs/benchmarks.md from bench/results/")
    parser.add_argument("--quick", action="store_true", help="smaller runs")
    topics = ",".join(t for t, _ in TOPICS)
    parser.add_argument("--only", default="", help=f"comma-separated topics: {topics}")
    parser.add_argument("--assemble", action="store_true", help="only re-assemble docs/benchmarks.md")
    args = parser.parse_args(argv)
    if not (args.assemble or args.command == "assemble"):
        wanted = [t for t in args.only.split(",") if t] or [t for t, _ in TOPICS]
        for topic, _ in TOPICS:
            if topic in wanted:
                print(f"== bench.{topic}", flush=True)
                module = importlib.import_module(f"bench.{topic}")
                _call_main(module, ["--quick"] if args.quick else [])
    print(f"wrote {assemble()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
