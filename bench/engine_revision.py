"""The engine's regular step, this tree against an earlier revision, side by side in one run.

    python -m bench.engine_revision [--against REV] [--rounds 9]

What the issue "Real sensor streams" costs the rows that use none of it: regular continuous
increments of the bundled 1-D cubic sensor and 2-D example, through ``YauYauFilter.run_arrays`` on
chunks of 1000 rows, one BLAS thread.  Each round runs each revision in a fresh process (the earlier
one from a temporary ``git worktree``), alternating; the table gives medians of µs per observation.
The difference is the outlier gate (on by default: one comparison per observed row) and the row
bookkeeping of the new observation kinds.  Wall times on this shared machine move by ±30% between
processes of the same code (memory layout), so the instructions per observation are counted too
(valgrind's callgrind: the same count whatever else the machine does), from the difference of runs
of one and six chunks in the same process.

Writes bench/results/engine-revision.md.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
EXAMPLES = {"cubic_sensor": 30, "range_2d": 3}  # example -> repeats of a 1000-row chunk per round
COUNTED = ("cubic_sensor",)  # instructions counted (under valgrind the 2-D products take half an hour)
ROUND = """
import os, sys, time
os.chdir({tree!r}); sys.path.insert(0, {tree!r})
import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver.spec import load_spec
from yauyau.solver.model import compile_model
from yauyau.solver.offline.pipeline import OfflineModel
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.simulate import simulate
import yauyau.solver.engine.filter as engine
assert engine.__file__.startswith({tree!r}), engine.__file__
spec = load_spec("examples/{example}.toml")
model = compile_model(spec)
arrays = dict(np.load({arrays!r}))
flt = YauYauFilter(model, OfflineModel.from_arrays(model, arrays), precision=spec.discretization.precision)
dy = simulate(model, 1000, np.random.default_rng(3)).increments
times = []
with threadpool_limits(1):
    flt.run_arrays(flt.initial_state(), dy)
    for _ in range({repeats}):
        state = flt.initial_state()
        start = time.perf_counter()
        flt.run_arrays(state, dy)
        times.append(time.perf_counter() - start)
print(sorted(times)[len(times) // 2] / 1000 * 1e6)
"""


def _arrays(example: str, folder: Path) -> Path:
    """The offline arrays of an example, computed once by this tree (both revisions read the same)."""
    sys.path.insert(0, str(ROOT))
    import numpy as np
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline.pipeline import ARRAY_NAMES, precompute
    from yauyau.solver.spec import load_spec

    path = folder / f"{example}.npz"
    offline = precompute(compile_model(load_spec(ROOT / "examples" / f"{example}.toml")))
    np.savez(path, **{name: getattr(offline, name) for name in ARRAY_NAMES})
    return path


def _round(tree: Path, example: str, arrays: Path) -> float:
    code = ROUND.format(tree=str(tree), example=example, arrays=str(arrays), repeats=EXAMPLES[example])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    return float(out.stdout.strip())


COUNT = """
import os, sys
os.chdir({tree!r}); sys.path.insert(0, {tree!r})
import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver.spec import load_spec
from yauyau.solver.model import compile_model
from yauyau.solver.offline.pipeline import OfflineModel
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.simulate import simulate
spec = load_spec("examples/{example}.toml")
model = compile_model(spec)
flt = YauYauFilter(model, OfflineModel.from_arrays(model, dict(np.load({arrays!r}))),
                   precision=spec.discretization.precision)
dy = simulate(model, 1000, np.random.default_rng(3)).increments
with threadpool_limits(1):
    state = flt.initial_state()
    for _ in range({chunks}):
        flt.run_arrays(state, dy)
"""


def _instructions(tree: Path, example: str, arrays: Path) -> float | None:
    """Instructions per observation (callgrind: six chunks minus one, over 5000 rows), or None."""
    import re
    import shutil

    if shutil.which("valgrind") is None:
        return None
    counts = []
    for chunks in (1, 6):
        code = COUNT.format(tree=str(tree), example=example, arrays=str(arrays), chunks=chunks)
        command = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, "-c",
                   code]
        out = subprocess.run(command, capture_output=True, text=True,
                             env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
        found = re.search(r"Collected : (\d+)", out.stderr)
        if out.returncode != 0 or found is None:
            return None
        counts.append(int(found.group(1)))
    return (counts[1] - counts[0]) / 5000.0


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.engine_revision",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="56e0dee",
                        help="the earlier revision (default: before the issue)")
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--quick", action="store_true", help="3 rounds")
    args = parser.parse_args(argv)
    rounds = 3 if args.quick else args.rounds
    started = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(old), args.against],
                       check=True)
        try:
            for example in EXAMPLES:
                arrays = _arrays(example, Path(tmp))
                earlier, this = [], []
                for _ in range(rounds):
                    earlier.append(_round(old, example, arrays))
                    this.append(_round(ROOT, example, arrays))
                ratios = [b / a for a, b in zip(earlier, this, strict=True)]
                counted = ((_instructions(old, example, arrays), _instructions(ROOT, example, arrays))
                           if example in COUNTED else (None, None))
                rows.append((example, statistics.median(earlier), statistics.median(this),
                             statistics.median(ratios), min(ratios), max(ratios), counted))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    about = __doc__.split("\n\n")[2].replace("\n", " ")
    lines = ["## The engine's regular step against the previous revision", "",
             f"Command: `.venv/bin/python -m bench.engine_revision --against {args.against}` (wall time "
             f"{time.perf_counter() - started:.0f} s, {rounds} rounds). {about}", "",
             f"| example | {args.against} µs/obs | this tree µs/obs | ratio (median of rounds) | "
             "ratio min – max | instructions/obs, earlier → this tree (ratio) |",
             "|---|---:|---:|---:|---|---|"]
    for example, a, b, ratio, low, high, (before, after) in rows:
        count = ("not counted" if example not in COUNTED else "valgrind not found") \
            if before is None or after is None else f"{before:,.0f} → {after:,.0f} ({after / before:.3f})"
        lines.append(f"| `examples/{example}.toml` | {a:.2f} | {b:.2f} | {ratio:.3f} | "
                     f"{low:.3f} – {high:.3f} | {count} |")
    text = "\n".join(lines) + "\n"
    (RESULTS / "engine-revision.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
