"""The documentation holds together.

Every relative link (and image) in README.md, docs/*.md and bench/results/*.md resolves to a file of
the repository (anchors are not checked); docs/benchmarks.md is exactly what ``python -m bench
assemble`` makes of bench/results/ (so a fragment edited without re-assembling, or the page edited by
hand, fails here); and its headings name no issue and no revision hash.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from urllib.parse import unquote

import pytest
from helpers import ROOT

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
         *sorted((ROOT / "bench" / "results").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def relative_links(page: Path) -> list[str]:
    """The link targets of ``page`` that point into the repository (no scheme, not a bare #anchor),
    outside code blocks and code spans."""
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.S | re.M)
    text = re.sub(r"`[^`\n]*`", "", text)
    return [link for link in LINK.findall(text)
            if not link.startswith("#") and not re.match(r"[a-zA-Z][a-zA-Z0-9+.-]*:", link)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = [link for link in relative_links(page)
              if not (page.parent / unquote(link.split("#", 1)[0])).resolve().exists()]
    assert not broken, f"{page.relative_to(ROOT)} links to missing files: {broken}"


def test_the_checker_sees_links():
    """The README has links (to docs/ and pictures), so an empty result would mean a broken pattern."""
    links = relative_links(ROOT / "README.md")
    assert "docs/README.md" in links and any(link.endswith(".png") for link in links)


def _fragments():
    spec = importlib.util.spec_from_file_location("bench_fragments", ROOT / "bench" / "fragments.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_benchmarks_page_is_assembled_from_the_results():
    fragments = _fragments()
    listed = {name for _, name in fragments.FRAGMENTS}
    on_disk = {p.name for p in (ROOT / "bench" / "results").glob("*.md")} - {"head.md"}
    assert on_disk == listed, f"fragments not in FRAGMENTS: {on_disk - listed}; missing: {listed - on_disk}"
    page = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert page == fragments.assembled(), "docs/benchmarks.md differs: run python -m bench assemble"


def test_benchmark_headings_name_no_issue_or_revision():
    hexes = r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"
    headings = re.findall(r"^#+ .*$", (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8"), re.M)
    bad = [h for h in headings if re.search(rf"\bissue\b|#\d|{hexes}", h, re.I)]
    assert not bad, bad
