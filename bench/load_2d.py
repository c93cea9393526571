"""HTTP load on the 2-D example, micro-batching on and off side by side (bench/load.py --example 2d).

    python -m bench.load_2d [--quick]     # writes bench/results/load-2d.md
"""

from __future__ import annotations

from . import load


def main(argv: list[str] | None = None) -> int:
    argv = list(argv or [])
    return load.main(["--example", "2d", "--unbatched", "--clients", "lean", "--streams-list", "1,64", *argv])


if __name__ == "__main__":
    raise SystemExit(main())
