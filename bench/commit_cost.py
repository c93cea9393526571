"""Session-store commit cost, this tree against an earlier revision, side by side in one run.

    python -m bench.commit_cost [--against REV] [--rounds 7]

Each round applies 500 chunks (a small response) to one session with each revision's
``storage/session_store.py`` (the earlier one from a temporary ``git worktree``), alternating the
revisions; the table gives the median µs per commit.  The fault checks added by the issue
"Hardening" (file identity, header, WAL checksum, generation, request digest, retention trim) are
what the difference measures.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ROUND = """
import sys, tempfile, time, os
sys.path.insert(0, {tree!r})
from storage.session_store import SqliteSessionStore
store = SqliteSessionStore(os.path.join(tempfile.mkdtemp(), "s.sqlite"))
response = '{{"estimates": [' + ",".join(['{{"step": 1, "mean": [0.1234]}}'] * 20) + "]}}"
sid = store.create("m", "x", {{"v": 0}})
start = time.perf_counter()
for seq in range(500):
    store.apply_chunk(sid, seq, lambda state: (state, response))
print((time.perf_counter() - start) / 500 * 1e6)
"""


def _round(tree: Path) -> float:
    out = subprocess.run([sys.executable, "-c", ROUND.format(tree=str(tree))], capture_output=True,
                         text=True, check=True)
    return float(out.stdout.strip())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="9c2939f",
                        help="the earlier revision (default: before hardening)")
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(old), args.against],
                       check=True)
        try:
            times = {"earlier": [], "this tree": []}
            for _ in range(args.rounds):
                times["earlier"].append(_round(old))
                times["this tree"].append(_round(ROOT))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    base = statistics.median(times["earlier"])
    print(f"| revision | µs per commit (median of {args.rounds} x 500) | ratio |\n|---|---|---|")
    for name, values in times.items():
        median = statistics.median(values)
        label = args.against if name == "earlier" else "this tree"
        print(f"| {label} | {median:.0f} | {median / base:.2f} |")


if __name__ == "__main__":
    main()
