"""HTTP load with the session store in SQLite and in PostgreSQL, one and two server processes side by
side (bench/load.py --stores).

    python -m bench.load_stores [--quick]     # writes bench/results/load-stores.md
"""

from __future__ import annotations

from . import load


def main(argv: list[str] | None = None) -> int:
    return load.main(["--stores", "--clients", "lean", "--streams-list", "1,64", *(argv or [])])


if __name__ == "__main__":
    raise SystemExit(main())
