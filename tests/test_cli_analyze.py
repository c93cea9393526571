"""`yauyau analyze` run as the real console script (subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def yauyau(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", "analyze", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


SEED004 = """
name = "seed004-example"
state = ["x1", "x2", "x3"]
drift = ["x1 + x2 - x3", "x1 + x2**2 + x3**2 + x3 - x2 + 1", "-x1 + x2**2 + x3**2"]
observation = ["x1"]
[initial]
kind = "gaussian"
mean = [0.0, 0.0, 0.0]
cov = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
[domain]
radius = 3.0
[discretization]
dt = 0.01
basis = 20
"""


def test_text_report_of_the_seed004_example(tmp_path):
    spec = tmp_path / "seed004.toml"
    spec.write_text(SEED004)
    done = yauyau(str(spec))
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "2*x2 - 2*x3 - 1" in out  # ω23 of seed 004
    assert "dimension 4, linear rank 1, non-maximal rank" in out
    assert "recommended method: wei-norman" in out


def test_json_report_of_the_ou_example():
    done = yauyau(str(ROOT / "examples" / "ou.toml"), "--json")
    assert done.returncode == 0, done.stderr
    data = json.loads(done.stdout)
    assert data["estimation_algebra"]["dimension"] == 4  # n = 1 linear, observed: 2n + 2
    assert data["recommendation"]["method"] == "kalman-bucy"
    assert data["conditions"]["linear"]["holds"] is True


def test_cubic_sensor_with_small_bound_does_not_close():
    done = yauyau(str(ROOT / "examples" / "cubic_sensor.toml"), "--max-depth", "2", "--json")
    assert done.returncode == 0, done.stderr
    data = json.loads(done.stdout)["estimation_algebra"]
    assert data["closed"] is False and data["dimension"] is None


def test_bad_spec_is_one_line_naming_the_field(tmp_path):
    spec = tmp_path / "bad.toml"
    spec.write_text(SEED004.replace('"x1 + x2 - x3"', '"x1 + __import__(1)"'))
    done = yauyau(str(spec))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "drift[0]" in lines[0] and "Traceback" not in done.stderr


def test_bad_bound_is_rejected():
    done = yauyau(str(ROOT / "examples" / "ou.toml"), "--max-depth", "0")
    assert done.returncode == 2 and "--max-depth" in done.stderr
