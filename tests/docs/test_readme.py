"""The README's Python example runs verbatim (so it cannot rot), and its numbers hold against truth.

The optimal filter is calibrated: over a long path E[(x_t − E[x_t|Y_t])²] = E[Var(x_t|Y_t)], so the
printed RMSE must match the printed posterior standard deviation (an independent property of the
conditional density, not of this code), and the density it prints must integrate to 1.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from helpers import ROOT
from helpers.readme import readme_block


def test_python_example_runs_verbatim(tmp_path):
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", readme_block("Python")], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "var" / "store").is_dir()
    assert re.search(r"^method: yau-yau$", out.stdout, re.M), out.stdout
    rmse, spread = map(float, re.search(r"RMSE ([\d.]+) \(posterior sd ([\d.]+)\)", out.stdout).groups())
    assert 0.6 < rmse / spread < 1.6, out.stdout  # calibration of the conditional density
    mass = float(re.search(r"mass on \[-3, 3\]: ([\d.]+)", out.stdout).group(1))
    assert abs(mass - 1.0) < 5e-3, out.stdout
    assert "nan" not in out.stdout.lower()
