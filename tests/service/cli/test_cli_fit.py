"""`yauyau fit` (service/cli/fit.py, issue 39): the OU rate of a timed record as the library's fit
gives it, --json's exact keys, --out's fitted spec, exit 2 naming the field with nothing written, exit 1
when not converged (the console script), --profile's extra key and `yauyau plot FIT.json`."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.fit_specs import OU
from yauyau.service.cli import main

import yauyau


@pytest.fixture()
def record(tmp_path):
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.exponential(0.1, 200))
    x, prev, rows = rng.normal(), 0.0, []
    for tk in t:
        a = math.exp(-(tk - prev))
        x = a * x + rng.normal(0.0, math.sqrt((1 - a * a) / 2))
        rows.append(f"{float(tk)!r},{float(x + rng.normal(0.0, 0.3))!r}")
        prev = tk
    spec = tmp_path / "ou.toml"
    spec.write_text(OU)
    data = tmp_path / "obs.csv"
    data.write_text("t,z\n" + "\n".join(rows) + "\n")
    return spec, data, t, np.array([float(r.split(",")[1]) for r in rows])


def test_fit_json_and_fitted_spec(record, tmp_path, capsys):
    spec, data, t, z = record
    out = tmp_path / "fitted.toml"
    code = main(["fit", str(spec), "--observations", str(data), "--t0", "0", "--free", "theta=0.05:5",
                 "--free", "observation_noise[0][0]=0.01:1", "--json", "--out", str(out)])
    assert code == 0
    got = json.loads(capsys.readouterr().out)
    assert set(got) == {"estimates", "stderr", "loglik", "evaluations", "converged", "method"}
    assert got["converged"] and got["method"] == "kalman-bucy"
    lib = yauyau.fit(yauyau.load_spec(spec), z[:, None], t,
                     free={"theta": (0.05, 5), "observation_noise[0][0]": (0.01, 1)})
    for name in ("theta", "observation_noise[0][0]"):
        assert got["estimates"][name] == pytest.approx(lib.estimates[name], rel=1e-9)
    fitted = yauyau.load_spec(out)
    assert fitted.parameters["theta"] == pytest.approx(got["estimates"]["theta"])
    assert fitted.observation_noise[0][0] == pytest.approx(got["estimates"]["observation_noise[0][0]"])
    assert fitted.drift == ["-theta*x"] and fitted.measurement.kind == "discrete"


@pytest.mark.parametrize(("free", "field"), [
    ("nope=0.1:1", "free.nope"),
    ("theta=2:1", "free.theta"),
    ("theta=0.6:2", "free.theta"),
    ("observation_noise[0][0]=-1:1", "free.observation_noise[0][0]"),
    ("theta", "free"),
])
def test_bad_input_exits_2_naming_the_field(record, tmp_path, capsys, free, field):
    spec, data, _, _ = record
    out = tmp_path / "fitted.toml"
    code = main(["fit", str(spec), "--observations", str(data), "--free", free, "--out", str(out)])
    assert code == 2
    assert f"error: {field}" in capsys.readouterr().err
    assert not out.exists()


def test_observation_noise_from_continuous_increments_exits_2(tmp_path, capsys):
    """Continuous increments fix R by their quadratic variation (the likelihood grows without bound as
    R → 0): `fit --free observation_noise[0][0]=…` on examples/ou.toml exits 2 naming it, saying Σ dy² / T."""
    data = tmp_path / "dy.csv"
    dy = np.random.default_rng(3).normal(0.0, 0.1, 200)
    data.write_text("dy\n" + "\n".join(repr(float(v)) for v in dy) + "\n")
    out = tmp_path / "fitted.toml"
    code = main(["fit", str(EXAMPLES / "ou.toml"), "--increments", str(data), "--free",
                 "observation_noise[0][0]=0.0001:2", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "error: free.observation_noise[0][0]" in err and "Σ dy² / T" in err
    assert not out.exists()


FLAT = OU.replace('observation = ["x"]', 'observation = ["x + max(c, 0)"]').replace(
    "theta = 0.5 }", "theta = 0.5, c = -0.5 }")


def test_not_converged_exits_1_saying_why_through_the_console_script(record, tmp_path):
    """A likelihood flat in c where the fit starts (h = x + max(c, 0), c = -0.5): the real `yauyau`
    process exits 1, stderr says the fit did not converge and why (flat in c), --out is not written."""
    _, data, _, _ = record
    spec = tmp_path / "flat.toml"
    spec.write_text(FLAT)
    out = tmp_path / "fitted.toml"
    done = subprocess.run([str(Path(sys.executable).with_name("yauyau")), "fit", str(spec), "--observations",
                           str(data), "--t0", "0", "--free", "theta=0.05:5", "--free", "c=-1:1", "--json",
                           "--out", str(out)], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONWARNINGS="ignore"))
    assert done.returncode == 1, done.stderr
    assert "not converged" in done.stderr and "flat in c at c = -0.5" in done.stderr
    assert "Traceback" not in done.stderr
    got = json.loads(done.stdout, parse_constant=_not_json)  # strict JSON: no NaN / Infinity
    assert got["converged"] is False and got["estimates"]["c"] == -0.5
    assert got["stderr"]["c"] is None  # not finite there: JSON's null
    assert not out.exists()


def _not_json(constant: str):
    raise AssertionError(f"{constant} is not JSON")


def test_profile_key_and_its_plot(record, tmp_path, capsys):
    """--profile theta adds a seventh key, "profile" (its grid spans the box, its maximum at the grid
    point nearest the estimate); `yauyau plot FIT.json` writes the PNG; a FIT.json without a profile
    exits 2 naming the field, nothing written."""
    spec, data, _, _ = record
    args = ["fit", str(spec), "--observations", str(data), "--t0", "0", "--free", "theta=0.05:3", "--json"]
    assert main([*args, "--profile", "theta"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert set(got) == {"estimates", "stderr", "loglik", "evaluations", "converged", "method", "profile"}
    grid, ll = np.array(got["profile"]["grid"]), np.array(got["profile"]["loglik"])
    assert got["profile"]["name"] == "theta" and grid[0] == 0.05 and grid[-1] == 3.0
    assert abs(grid[np.argmax(ll)] - got["estimates"]["theta"]) <= grid[1] - grid[0]
    fit_json = tmp_path / "fit.json"
    fit_json.write_text(json.dumps(got))
    png = tmp_path / "profile.png"
    assert main(["plot", str(fit_json), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({k: v for k, v in got.items() if k != "profile"}))
    other = tmp_path / "other.png"
    assert main(["plot", str(bare), "--out", str(other)]) == 2
    assert "error: profile" in capsys.readouterr().err
    assert not other.exists()


def test_workers_must_be_positive(record, capsys):
    spec, data, _, _ = record
    code = main(["fit", str(spec), "--observations", str(data), "--free", "theta=0.05:5", "--workers", "0"])
    assert code == 2
    assert "error: workers" in capsys.readouterr().err
