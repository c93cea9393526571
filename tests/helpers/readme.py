"""The sections and code blocks of the README and the docs/ pages, and running a Python block as a user
would (tests/docs/, and the tests that check a documented command's output)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

from helpers import ROOT


def readme_section(heading: str, page: str = "README.md") -> str:
    """The text under ``## heading`` of ``page`` (a path from the repository root: the README or a page
    of docs/), up to the next ``## `` heading."""
    text = (ROOT / page).read_text(encoding="utf-8")
    assert f"\n## {heading}\n" in text, f"no ## {heading} in {page}"
    return text.split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]


doc_section = readme_section


def readme_block(heading: str, language: str = "python", page: str = "README.md") -> str:
    """The first ```language block under ``## heading`` of the README (or of ``page``: docs/models.md)."""
    match = re.search(rf"```{language}\n(.*?)```", readme_section(heading, page), re.S)
    assert match, f"no {language} block under ## {heading} in {page}"
    return match.group(1)


def env() -> dict:
    """The environment of a README command: this checkout importable, one BLAS thread."""
    return dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")


def run_python_block(section: str, tmp_path, page: str = "README.md") -> str:
    """The Python block of ``page``'s section run in ``tmp_path`` (with examples/ linked there): its
    stdout."""
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    out = subprocess.run([sys.executable, "-c", readme_block(section, page=page)], cwd=tmp_path, env=env(),
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def json_objects(text: str) -> list[dict]:
    """The JSON documents printed one after another (curl's answers)."""
    decoder, objects, i = json.JSONDecoder(), [], 0
    while i < len(text):
        if text[i].isspace():
            i += 1
            continue
        obj, i = decoder.raw_decode(text, i)
        objects.append(obj)
    return objects
