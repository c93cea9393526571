"""The README's Python example runs verbatim (so it cannot rot), and its numbers hold against truth.

The optimal filter is calibrated: over a long path E[(x_t − E[x_t|Y_t])²] = E[Var(x_t|Y_t)], so the
printed RMSE must match the printed posterior standard deviation (an independent property of the
conditional density, not of this code), and the density it prints must integrate to 1.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT
from helpers.readme import readme_block

pytestmark = pytest.mark.slow  # every test here takes seconds of CPU: the full run only


def test_python_example_runs_verbatim(tmp_path):
    """From a directory that holds no examples/: the spec comes from the package (yauyau.examples)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", readme_block("Python")], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    check_python_example(out, tmp_path)


def check_python_example(out: subprocess.CompletedProcess, cwd: Path) -> None:
    """The README's Python example ran in ``cwd`` and printed calibrated numbers."""
    assert out.returncode == 0, out.stderr[-3000:]
    assert (cwd / "var" / "store").is_dir()
    assert re.search(r"^method: yau-yau$", out.stdout, re.M), out.stdout
    rmse, spread = map(float, re.search(r"RMSE ([\d.]+) \(posterior sd ([\d.]+)\)", out.stdout).groups())
    assert 0.6 < rmse / spread < 1.6, out.stdout  # calibration of the conditional density
    mass = float(re.search(r"mass on \[-3, 3\]: ([\d.]+)", out.stdout).group(1))
    assert abs(mass - 1.0) < 5e-3, out.stdout
    assert "nan" not in out.stdout.lower()


SOURCES = ("pyproject.toml", "README.md", "yauyau", "solver", "storage", "service", "examples")


@pytest.mark.slow
def test_python_example_runs_after_a_wheel_install_from_any_directory(tmp_path):
    """A NON-editable install: the wheel pip builds from this checkout, installed into a fresh virtual
    environment (its dependencies: this interpreter's site-packages, by a .pth line), runs the README's
    Python example from a directory outside the checkout; yauyau comes from the wheel, not the tree."""
    source = tmp_path / "src"  # a copy: pip's in-tree build writes build/ and *.egg-info beside the sources
    source.mkdir()
    for name in SOURCES:
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        kwargs = {"ignore": shutil.ignore_patterns("__pycache__", "*.pyc")} if (ROOT / name).is_dir() else {}
        copy(ROOT / name, source / name, **kwargs)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "-w", str(tmp_path / "dist"), str(source)], check=True,
                   capture_output=True, timeout=600)
    wheel = next((tmp_path / "dist").glob("yauyau-*.whl"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True, timeout=300)
    python = venv / "bin" / "python"
    purelib = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                             check=True, capture_output=True, text=True).stdout.strip()
    deps = [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages") and Path(p).is_dir()]
    (Path(purelib) / "zz_test_deps.pth").write_text("".join(f"{p}\n" for p in deps))
    subprocess.run([python, "-m", "pip", "--disable-pip-version-check", "-q", "install", "--no-deps",
                    str(wheel)], check=True, capture_output=True, timeout=300)
    run = tmp_path / "elsewhere"
    run.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["OPENBLAS_NUM_THREADS"] = "1"
    found = subprocess.run([python, "-c", "import yauyau, yauyau.examples as e; print(yauyau.__file__); "
                                          "print(e.path('cubic_sensor'))"],
                           cwd=run, env=env, capture_output=True, text=True, timeout=300)
    assert found.returncode == 0, found.stderr[-3000:]
    where = found.stdout.split()
    assert all(Path(p).is_relative_to(purelib) for p in where), where  # the wheel's files, not the tree's
    assert not (Path(purelib) / "examples").exists()  # inside yauyau/, nothing new at the top
    out = subprocess.run([python, "-c", readme_block("Python")], cwd=run, env=env, capture_output=True,
                         text=True, timeout=300)
    check_python_example(out, run)
