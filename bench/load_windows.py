"""HTTP load with micro-batching windows of 0, 1 and 3 ms side by side (bench/load.py --windows): how
the default window (0) was chosen.

    python -m bench.load_windows [--quick]     # writes bench/results/load-windows.md
"""

from __future__ import annotations

from . import load


def main(argv: list[str] | None = None) -> int:
    return load.main(["--windows", "0,1,3", "--clients", "lean", "--rounds", "2", *(argv or [])])


if __name__ == "__main__":
    raise SystemExit(main())
