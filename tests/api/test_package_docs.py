"""What ``help(yauyau)`` shows: the package docstring names every public name (``yauyau.__all__``) in
its API table, names nothing else there, and its example runs as printed.

The package is imported in a child process with PYTHONPATH at this checkout, so the docstring read is
this checkout's ``yauyau/__init__.py``, as ``help`` would show it.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from helpers import ROOT


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")


def _package() -> dict:
    code = ("import json, yauyau; "
            "print(json.dumps({'doc': yauyau.__doc__, 'all': yauyau.__all__, 'file': yauyau.__file__}))")
    out = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    package = json.loads(out.stdout)
    assert Path(package["file"]).resolve() == ROOT / "yauyau" / "__init__.py"
    return package


def _table(doc: str) -> list[str]:
    """The names of the docstring's API table: the ``name -- what it does`` lines."""
    return re.findall(r"^ {3}(\w+) +-- ", doc, re.M)


def test_docstring_table_names_every_public_name():
    package = _package()
    doc, names = package["doc"], package["all"]
    table = _table(doc)
    assert len(table) == len(set(table)), "a name listed twice"
    missing = [name for name in names if name not in table and name != "__version__"]
    assert not missing, f"public names the docstring's table leaves out: {missing}"
    extra = set(table) - set(names)
    assert not extra, f"names in the table that yauyau does not export: {extra}"
    assert "``__version__``" in doc
    for group in ("Specs and models", "Filtering", "Simulation and checks", "Analysis"):
        assert re.search(rf"^{group}\n-+$", doc, re.M), group


@pytest.mark.slow
def test_docstring_example_runs(tmp_path):
    doc = _package()["doc"]
    block = re.search(r"^Example[^\n]*::\n\n((?: {4}[^\n]*\n)+)", doc, re.M)
    assert block, "no indented example after 'Example ...::'"
    example = textwrap.dedent(block.group(1))
    assert len(example.strip().splitlines()) == 6
    out = subprocess.run([sys.executable, "-c", example], cwd=tmp_path, env=_env(), capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.startswith("yau-yau ") and "nan" not in out.stdout.lower(), out.stdout
