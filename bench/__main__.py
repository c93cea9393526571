"""Run every benchmark side by side and assemble docs/benchmarks.md from their fragments.

    python -m bench            # everything (about 20-30 minutes on 2 cores)
    python -m bench --quick    # smaller runs, for a smoke test
    python -m bench --only filters,load

Each topic module bench/<topic>.py has ``main(argv)`` and writes docs/bench-<fragment>.md;
this driver then concatenates the fragments (in the order below) into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import platform
import sys
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parent.parent / "docs"
# (module, fragment) in reading order
TOPICS = [
    ("startup", "bench-startup.md"),
    ("precompute", "bench-precompute.md"),
    ("storage", "bench-storage.md"),
    ("engine_speed", "bench-engine.md"),
    ("blas_threads", "bench-blas.md"),
    ("engine_batch", "bench-engine-batch.md"),
    ("filters", "bench-filters.md"),
    ("exact_filters", "bench-exact.md"),
    ("measurements", "bench-measurements.md"),
    ("yau_jia", "bench-yau-jia.md"),
    ("engine_revision", "bench-engine-revision.md"),
    ("cli_speed", "bench-cli.md"),
    ("default_mesh", "bench-default-mesh.md"),
    ("default_3d", "bench-default-3d.md"),
    ("load", "bench-load.md"),
    ("load_2d", "bench-load-2d.md"),
    ("load_stores", "bench-load-stores.md"),
    ("load_windows", "bench-load-windows.md"),
    ("trust_cost", "bench-trust.md"),
    ("follow", "bench-follow.md"),
    ("psd", "bench-psd.md"),
    ("cv_basis", "bench-cv-basis.md"),
    ("three_d", "bench-3d.md"),
    ("follow_cost", "bench-follow-cost.md"),
]

HEADER = """# Benchmarks

All figures are measured on the project's reference machine (2 cores, 24 GiB, shared and noisy), so
speed is reported as ratios measured side by side in one run. Reproduce everything with

    python -m bench            # or: python -m bench --only filters

Each section below is written by its benchmark (`bench/<topic>.py`); this page is assembled by
`python -m bench` (or `python -m bench --assemble` to only re-assemble).
"""


def assemble() -> Path:
    parts = [HEADER, f"_Assembled {time.strftime('%Y-%m-%d')} on {platform.platform()}, Python "
             f"{platform.python_version()}._\n"]
    for _, fragment in TOPICS:
        path = DOCS / fragment
        if path.exists():
            parts.append(path.read_text().strip() + "\n")
    out = DOCS / "benchmarks.md"
    out.write_text("\n".join(parts))
    return out


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
    parser.add_argument("--quick", action="store_true", help="smaller runs")
    topics = ",".join(t for t, _ in TOPICS)
    parser.add_argument("--only", default="", help=f"comma-separated topics: {topics}")
    parser.add_argument("--assemble", action="store_true", help="only re-assemble docs/benchmarks.md")
    args = parser.parse_args(argv)
    if not args.assemble:
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
