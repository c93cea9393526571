"""The house's import drawing (issue "The house, second step", item 2; scripts/import_graph.py).

Every import counts, also those inside functions: no module of the project takes part in an import
circle, and none uses a name starting with ``_`` that another project module defines.

Sizes: no module of solver/, storage/, service/ or yauyau/ is over 600 lines.

The analysis itself is checked first on a hand-written package whose circle and private crossing
are known.
"""

from __future__ import annotations

import importlib.util

import pytest
from helpers import ROOT

MAX_LINES = 600


def load_import_graph():
    """scripts/import_graph.py as a module (it reads files with ``ast`` and imports nothing of ours)."""
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "scripts" / "import_graph.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_analysis_finds_a_known_circle_and_crossing(tmp_path):
    graph_tool = load_import_graph()
    files = {
        "yauyau.solver.a": "def f():\n    from . import b  # lazy: still an edge\n    return b\n",
        "yauyau.solver.b": "from .a import f\n_hidden = 1\n",
        "yauyau.solver.c": "from .b import _hidden\n",
    }
    known = {}
    for name, text in files.items():
        path = tmp_path / (name.rsplit(".", 1)[1] + ".py")
        path.write_text(text)
        known[name] = path
    graph, crossings = graph_tool.edges(known)
    assert graph == {"yauyau.solver.a": {"yauyau.solver.b"}, "yauyau.solver.b": {"yauyau.solver.a"},
                     "yauyau.solver.c": {"yauyau.solver.b"}}
    assert graph_tool.circles(graph) == [["yauyau.solver.a", "yauyau.solver.b", "yauyau.solver.a"]]
    assert crossings == [("yauyau.solver.c", "yauyau.solver.b", "_hidden", 1)]


@pytest.mark.slow
def test_no_circles_and_no_private_crossings():
    graph_tool = load_import_graph()
    known = graph_tool.modules()
    assert "yauyau.solver.spec" in known and "yauyau.solver.exact.yau_hu" in known  # the walk sees the rooms
    graph, crossings = graph_tool.edges(known)
    assert graph_tool.circles(graph) == []
    assert crossings == []


def test_no_module_over_600_lines():
    sizes = {}
    for folder in ("solver", "storage", "service", "yauyau"):
        for path in (ROOT / folder).rglob("*.py"):
            if "__pycache__" not in path.parts:
                sizes[path.relative_to(ROOT).as_posix()] = len(path.read_text().splitlines())
    assert len(sizes) > 90
    over = {name: lines for name, lines in sizes.items() if lines > MAX_LINES}
    assert over == {}


def test_every_package_folder_is_installed():
    """pyproject.toml lists the packages a non-editable install (``pip install .``, the Dockerfile,
    scripts/provision.py) copies: every folder of solver/, storage/ and service/ with an __init__.py
    must be there, or that install lacks it (solver/qmc, the yau-niu method, was missing: an editable
    install did not show it)."""
    import tomllib

    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setuptools["packages"])
    roots = {folder: name for name, folder in setuptools["package-dir"].items()}
    found = set()
    for folder, name in roots.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            relative = init.parent.relative_to(ROOT / folder)
            if "__pycache__" not in relative.parts:
                found.add(".".join([name, *relative.parts]))
    assert found - listed == set(), f"package folders not installed: {sorted(found - listed)}"
