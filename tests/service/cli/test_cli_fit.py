"""`yauyau fit` (service/cli/fit.py, issue 39): the OU rate of a timed record as the library's fit
gives it, --json's exact keys, --out's fitted spec, and exit 2 naming the field with nothing written."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
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
