"""The benchmarks' results: each benchmark writes its fragment into bench/results/ (keeping the
hand-written analysis under it), and docs/benchmarks.md is assembled from those fragments.

    python -m bench assemble     # docs/benchmarks.md from bench/results/, no benchmark run

The page is the hand-written head (bench/results/head.md), a list of contents, then the fragments in
the order of FRAGMENTS.  A fragment's relative links are written from bench/results/ and rebased to
docs/ on the page, so both resolve.  The page is a pure function of the fragments: edit a fragment or
the head, never docs/benchmarks.md.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
HEAD = RESULTS / "head.md"
PAGE = ROOT / "docs" / "benchmarks.md"
ANALYSIS = "<!-- analysis: kept when the figures above are rewritten -->"

# (benchmark module bench/<topic>.py, the fragment it writes in bench/results/), in reading order
FRAGMENTS = [
    ("startup", "startup.md"),
    ("precompute", "precompute.md"),
    ("storage", "storage.md"),
    ("engine_speed", "engine.md"),
    ("compiled_kernels", "compiled.md"),
    ("irregular_cost", "irregular.md"),
    ("blas_threads", "blas.md"),
    ("engine_batch", "engine-batch.md"),
    ("filters", "filters.md"),
    ("peer_gap", "peer-gap.md"),
    ("range_2d", "range-2d.md"),
    ("exact_filters", "exact.md"),
    ("measurements", "measurements.md"),
    ("yau_jia", "yau-jia.md"),
    ("yau_jia_speed", "yau-jia-speed.md"),
    ("yau_niu", "yau-niu.md"),
    ("yau_niu_speed", "yau-niu-speed.md"),
    ("yau_niu_state", "yau-niu-state.md"),
    ("engine_revision", "engine-revision.md"),
    ("cli_speed", "cli.md"),
    ("default_mesh", "default-mesh.md"),
    ("default_3d", "default-3d.md"),
    ("load", "load.md"),
    ("load_2d", "load-2d.md"),
    ("load_stores", "load-stores.md"),
    ("load_windows", "load-windows.md"),
    ("trust_cost", "trust.md"),
    ("follow", "follow.md"),
    ("psd", "psd.md"),
    ("cv_basis", "cv-basis.md"),
    ("three_d", "3d.md"),
    ("follow_cost", "follow-cost.md"),
    ("smoother", "smoother.md"),
    ("fit", "fit.md"),
]

_LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def write_fragment(path: Path, lines: list[str]) -> Path:
    """Write ``lines`` (the generated figures) to ``path``; what followed the ANALYSIS marker stays."""
    kept = path.read_text().split(ANALYSIS, 1) if path.exists() else []
    tail = "\n" + ANALYSIS + kept[1] if len(kept) == 2 else ""
    path.write_text("\n".join(lines) + "\n" + tail)
    return path


def anchor(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _rebase(text: str, source: Path, target: Path) -> str:
    """``text``'s relative links, written from the directory ``source``, rewritten from ``target``."""
    def move(match: re.Match) -> str:
        link = match.group(2)
        if link.startswith(("#", "/")) or re.match(r"[a-z][a-z0-9+.-]*:", link):
            return match.group(0)
        path, sep, fragment = link.partition("#")
        moved = Path(os.path.relpath(os.path.normpath(source / path), target)).as_posix()
        return match.group(1) + moved + sep + fragment + match.group(3)

    return _LINK.sub(move, text)


def assembled() -> str:
    """The text of docs/benchmarks.md: the head, the contents, the fragments that exist, in order."""
    bodies = [(RESULTS / name).read_text(encoding="utf-8").strip() for _, name in FRAGMENTS
              if (RESULTS / name).exists()]
    titles = [body.splitlines()[0].removeprefix("## ") for body in bodies]
    contents = "\n".join(f"- [{title}](#{anchor(title)})" for title in titles)
    parts = [HEAD.read_text(encoding="utf-8").strip(), "## Contents\n\n" + contents, *bodies]
    return _rebase("\n\n".join(parts) + "\n", RESULTS, PAGE.parent)


def assemble(page: Path = PAGE) -> Path:
    """Write docs/benchmarks.md (or ``page``) from the head and the fragments."""
    page.write_text(assembled(), encoding="utf-8")
    return page
