"""The README's sections and code blocks, and running a Python block as a user would (tests/docs/,
and the tests that check a README command's output)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

from helpers import ROOT


def readme_section(heading: str) -> str:
    """The text under the README's ``## heading`` (up to the next ``## ``)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return text.split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]


def readme_block(heading: str, language: str = "python") -> str:
    """The first ```language block under the README's ``## heading``."""
    match = re.search(rf"```{language}\n(.*?)```", readme_section(heading), re.S)
    assert match, f"no {language} block under ## {heading}"
    return match.group(1)


def env() -> dict:
    """The environment of a README command: this checkout importable, one BLAS thread."""
    return dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")


def run_python_block(section: str, tmp_path) -> str:
    """The README section's Python block run in ``tmp_path`` (with examples/ linked there): its stdout."""
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    out = subprocess.run([sys.executable, "-c", readme_block(section)], cwd=tmp_path, env=env(),
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
