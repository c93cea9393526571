"""The 3-D defaults, chosen by measurement: what a spec leaves out, against the exact Kalman filter.

    python -m bench.default_3d [--quick] [--only WORD ...]     # writes bench/results/default-3d.md

Issue 36's 3-D linear model f = (−x1 + 0.5x2, −x2, −0.5x3), h = (x1, x3), a = R = I, dt = 0.02, prior
N(0, ½I), ``method = "yau-yau"``: its spec with dt, basis 500 and a fixed ball of radius 4 and nothing
else, and the documented following ball (radius 3.5, basis 600, ``follow = true``).  What they leave out
is filled by the old default (P1 on about 2N nodes), by P2 + bubbles on another mesh, and by today's
default (solver/defaults.py).  Each against the exact Kalman filter of the sampled model over 500 steps,
seeds 5 and 6 (bench/three_d.py's measure), and whether ``yauyau precompute`` warns that the mesh is
coarser than the measured default (solver/check.py ``coarser_than_measured``).

``--only WORD ...`` runs the rows whose name contains one of the WORDs (``--only old``); the others are
kept from the fragment as it was.  Precompute seconds in one process with one BLAS thread; µs per
observation with one BLAS thread (one run each: the runs take minutes, the ball refined three times
about five).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.check import coarser_than_measured
from yauyau.solver.offline.pipeline import precompute

from .fragments import write_fragment
from .three_d import against_kalman, spec_doc

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "default-3d.md"
# (row, radius, basis, follow, mesh, element); mesh and element None: left out (the defaults)
ROWS = [("fixed ball: P1 on about 2N nodes (the old default)", 4.0, 500, False, None, "lagrange"),
        ("fixed ball: P2 + bubbles, the ball refined three times", 4.0, 500, False, 3, "bubble"),
        ("fixed ball: the default (P2 + bubbles on about 2N nodes)", 4.0, 500, False, None, None),
        ("following ball: P2 + bubbles, the ball refined twice", 3.5, 600, True, 2, "bubble"),
        ("following ball: the default (P2 + bubbles, the ball refined three times)", 3.5, 600, True, None,
         None)]
COLUMNS = 13


def row(name: str, radius: float, basis: int, follow: bool, mesh: int | None, element: str | None, steps: int,
        seeds) -> str:
    spec = spec_from_dict(spec_doc(radius, basis, follow, mesh, element))
    model = compile_model(spec)
    start = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        offline = precompute(model)
    seconds = time.perf_counter() - start
    rms, worst, var_median, var_max, moves, per = against_kalman(model, offline, steps, seeds)
    warned = coarser_than_measured(spec)
    cells = [name, radius, basis, f'"{spec.element()}"', len(offline.weights), f"{seconds:.0f}", f"{rms:.1e}",
             f"{worst:.1e}", f"{var_median:.1%}", f"{var_max:.1%}", moves, f"{per * 1e6:.0f}",
             "no" if warned is None else f"yes ({warned[0]})"]
    return "| " + " | ".join(map(str, cells)) + " |"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.default_3d", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller basis, fewer steps")
    parser.add_argument("--only", nargs="+", metavar="WORD", help="run only the rows whose name has a WORD")
    args = parser.parse_args(argv)
    steps, seeds, scale = (100, (5,), 0.4) if args.quick else (500, (5, 6), 1.0)
    kept = previous_rows() if args.only else {}
    lines = ["## The 3-D defaults, by measurement", "",
             "`python -m bench.default_3d" + (" --quick" if args.quick else "") + "`", "",
             "f = (−x1 + 0.5x2, −x2, −0.5x3), h = (x1, x3), a = R = I, dt = 0.02, prior N(0, ½I), "
             "`method = \"yau-yau\"`: issue 36's spec with dt, basis and radius only (the fixed ball) and "
             "the documented following ball, each with what the spec leaves out filled by the old default, "
             "by P2 + bubbles on another mesh, and by today's default; against the exact Kalman filter of "
             f"the sampled model, {steps} steps, seeds {', '.join(map(str, seeds))}. Precompute in one "
             "process; µs per observation with one BLAS thread, one run each. The last column: whether "
             "`yauyau precompute` warns that the mesh is coarser than the measured default.", "",
             "| ball and discretisation | radius | N | element | Q | precompute s | rms mean gap "
             "| max mean gap | variance error median | variance error max | moves | µs/obs "
             "| precompute warns |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for name, radius, basis, follow, mesh, element in ROWS:
        if args.only and not any(word.lower() in name.lower() for word in args.only):
            if name in kept:
                lines.append(kept[name])
            continue
        lines.append(row(name, radius, int(basis * scale), follow, mesh, element, steps, seeds))
        print(lines[-1], flush=True)
    write_fragment(FRAGMENT, lines)
    return 0


def previous_rows() -> dict[str, str]:
    """The table rows of the fragment as it is, by their first cell."""
    if not FRAGMENT.exists():
        return {}
    rows = {}
    for line in FRAGMENT.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and len(cells) == COLUMNS and cells[2].isdigit():
            rows[cells[0]] = line
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
