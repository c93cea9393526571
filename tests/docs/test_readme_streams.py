"""docs/measurements.md's "Readings at irregular times" section runs as printed: its Python block
verbatim (its output is the text block under it), its three commands, and its curl walk-through
against a real `yauyau serve`.

Truth: the power meter (examples/power_meter.toml, z = x² + v) is symmetric under x -> -x once the
prior's mean has decayed (e^(-0.5 t), t ≈ 20), so the density must have two equal peaks at ±|x| and a
mean of 0; the log-likelihood and the estimates are those of the independent fine-grid filter of
tests/helpers/irregular_refs.py on the same readings (the gated glitch left out).
"""

from __future__ import annotations

import csv
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT
from helpers.irregular_refs import GridReference
from helpers.readme import env, json_objects, readme_block, readme_section, run_python_block
from helpers.server import Server

pytestmark = pytest.mark.slow  # every test here takes seconds of CPU: the full run only

PAGE = "docs/measurements.md"
SECTION = "Readings at irregular times, missing values, outliers"


def test_python_block_prints_what_the_page_shows(tmp_path):
    stdout = run_python_block(SECTION, tmp_path, PAGE)
    assert stdout.strip() == readme_block(SECTION, "text", PAGE).strip()
    # the numbers against truth: the fine grid on the same readings, the glitch left out (it was gated)
    import yauyau

    spec = yauyau.load_spec(ROOT / "examples" / "power_meter.toml")
    times = np.cumsum(np.random.default_rng(2).exponential(0.05, 400))
    z = yauyau.simulate(spec, steps=400, seed=2, times=times).observations.copy()
    z[100] = np.nan
    z[200:210] = np.nan
    model = yauyau.compile_model(spec)
    truth = GridReference(model, cells=2048).run(z, times, "discrete")
    loglik = float(re.search(r"log p\(z\) = (-?[\d.]+)", stdout).group(1))
    assert abs(loglik - truth.loglik[-1]) < 0.1
    low, high = map(float, re.search(r"density ([\d.]+) at -[\d.]+, ([\d.]+) at", stdout).groups())
    assert low == high and abs(truth.mean[-1, 0]) < 0.005  # two equal peaks, a mean of 0


def test_three_commands_filter_the_readings(tmp_path):
    shell = readme_block(SECTION, "sh", PAGE)
    commands = [line for line in shell.splitlines() if line.startswith("yauyau ")][:3]
    assert [c.split()[1] for c in commands] == ["precompute", "simulate", "filter"]
    yauyau = str(Path(sys.executable).with_name("yauyau"))
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    printed = []
    for command in commands:
        out = subprocess.run([yauyau, *command.split()[1:]], cwd=tmp_path, env=env(), capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, (command, out.stderr[-2000:])
        printed.append(out.stdout.strip())
    assert printed[0] in commands[2], "the page's filter command names the id precompute prints"
    with open(tmp_path / "var" / "meter" / "observations.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t", "z_1"] and len(rows) == 401
    times = np.array([float(r[0]) for r in rows[1:]])
    z = np.array([[float(r[1])] for r in rows[1:]])
    with open(tmp_path / "var" / "meter" / "out.csv") as f:
        out = list(csv.DictReader(f))
    assert len(out) == 400 and not any(int(r["degenerate"]) or int(r["gated"]) for r in out)
    import yauyau as api

    model = api.compile_model(api.load_spec(ROOT / "examples" / "power_meter.toml"))
    truth = GridReference(model, cells=2048).run(z, times, "discrete")
    means = np.array([float(r["mean_x"]) for r in out])
    assert np.max(np.abs(means - truth.mean[:, 0])) < 0.01


@pytest.mark.service
def test_curl_walk_through_against_a_real_server(tmp_path):
    assert shutil.which("curl"), "curl is needed (python3 dev.py test installs it)"
    store = tmp_path / "store"
    import yauyau

    model_id = yauyau.precompute(ROOT / "examples" / "power_meter.toml", store)
    walk = [b for b in re.findall(r"```sh\n(.*?)```", readme_section(SECTION, PAGE), re.S) if "curl" in b][0]
    assert f"MODEL={model_id}" in walk
    server = Server(store, tmp_path / "sessions.sqlite3")
    try:
        script = walk.replace("localhost:8000", f"127.0.0.1:{server.port}")
        out = subprocess.run(["bash", "-c", "set -euo pipefail\n" + script], capture_output=True, text=True,
                             timeout=120, env=env())
    finally:
        server.kill()
    assert out.returncode == 0, out.stderr
    chunk, forecast, reset = json_objects(out.stdout)
    assert chunk["gated"] == [2] and chunk["degenerate"] is False
    gated = chunk["estimates"][2]
    assert gated["gated"] is True and "predictive standard deviations" in gated["reason"]
    assert chunk["estimates"][1]["predictive_loglik"] is None  # null: no reading, a prediction
    assert forecast["t"] == 1.0 and forecast["step"] == chunk["step"]
    # OU from 0.16 to 1.0: the forecast mean decays by e^(-0.5 Δt) (the drift is linear)
    decay = np.exp(-0.5 * (1.0 - 0.16))
    assert abs(forecast["estimate"]["mean"][0] - decay * chunk["estimates"][-1]["mean"][0]) < 1e-3
    assert reset["seq"] == 1 and reset["t"] == 0.16 and "last good estimate" in reset["note"]
    assert reset["estimate"]["cov"][0][0] > 3.9 * chunk["estimates"][-1]["cov"][0][0]



