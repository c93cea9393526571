"""Writing a benchmark's fragment of docs/benchmarks.md, keeping its hand-written analysis."""

from __future__ import annotations

from pathlib import Path

ANALYSIS = "<!-- analysis: kept when the figures above are rewritten -->"


def write_fragment(path: Path, lines: list[str]) -> Path:
    """Write ``lines`` (the generated figures) to ``path``; what followed the ANALYSIS marker stays."""
    kept = path.read_text().split(ANALYSIS, 1) if path.exists() else []
    tail = "\n" + ANALYSIS + kept[1] if len(kept) == 2 else ""
    path.write_text("\n".join(lines) + "\n" + tail)
    return path
