"""What the protections of the issue "Trust" cost one stream, side by side with the revision before them.

    python -m bench.trust_cost [--rounds 5] [--seconds 5] [--against 6118770]

One stream posts chunks of 100 increments of the 1-D cubic sensor over one keep-alive connection
(bench/load.py's lean client) to three servers started in the same run and driven in turn, round after
round: the revision before the issue, this tree, and this tree with a tenants file (every request
authenticated, every session's owner checked).  What the rows measure together: the session store's
file checks through kept descriptors and the rows' checksums, the PostgreSQL-free SQLite path, the
connection bookkeeping and header timeout, the rate limiter, the Host check, the lost-track watch
and the time checks (the innovation monitor is off by default).  bench.chunk_accounting splits the part
below HTTP function by function.  The issue's bound: at most 5% of one-stream throughput.  Medians
over rounds of the chunks' latency; the server's CPU per chunk (from /proc, what varies least on a
shared machine).

Writes bench/results/trust.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import load
from .fragments import write_fragment

DOC = Path(__file__).resolve().parent.parent / "bench" / "results" / "trust.md"
BEFORE = "6118770"  # main before the issue "Trust"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.trust_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--against", default=BEFORE)
    parser.add_argument("--quick", action="store_true", help="2 rounds of 1 s")
    args = parser.parse_args(argv)
    if args.quick:
        args.rounds, args.seconds = 2, 1.0
    load_args = load._parse(["--baseline", args.against, "--tenants", "--streams-list", "1", "--clients",
                             "lean", "--rounds", str(args.rounds), "--seconds", str(args.seconds)])
    rows, engine_ms, _, _, average = load.measure(load_args)
    base = next(r for r in rows if r["server"].startswith("baseline"))
    command = "python -m bench.trust_cost" + (" --quick" if args.quick else
                                              f" --rounds {args.rounds} --seconds {args.seconds:g}")
    lines = ["## The cost of the protections (one stream)", "",
             f"`{command}`, load average {average:.2f} before the run; one stream of 100-increment chunks "
             f"of the 1-D cubic sensor, SQLite sessions, {args.rounds} rounds of {args.seconds:g} s per "
             f"server, interleaved. The filter alone takes {engine_ms:.2f} ms per chunk.", "",
             "| server | observations/s | ratio | p50 ms | p99 ms | server CPU ms/chunk | ratio |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        name = r["server"].replace(f"baseline {args.against}", f"before ({args.against})")
        lines.append(f"| {name} | {r['rate']:,.0f} | {r['rate'] / base['rate']:.3f} | {r['p50']:.2f} | "
                     f"{r['p99']:.2f} | {r['server_ms']:.3f} | {r['server_ms'] / base['server_ms']:.3f} |")
    print("\n".join(lines))
    write_fragment(DOC, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
