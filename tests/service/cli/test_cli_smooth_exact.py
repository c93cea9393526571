"""`yauyau smooth` through the exact filters' smoothers (solver/smoothing.py): kalman-bucy
(solver/exact/kalman_bucy_backward.py) and yau-hu (solver/exact/yau_hu_smoother.py) on continuous increments
against RTS on the exact discrete model of each gap written in tests/helpers/smoothing_refs.py; yau-jia, which
has no exact smoother, exits 2 naming the method."""

from __future__ import annotations

import csv
import tomllib

import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.smoothing_refs import rts_exact_gaps, sample_ou
from yauyau.service.cli import main
from yauyau.solver import spec_from_dict

import yauyau


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())  # θ = 0.5, a = 1, R = 1, dt = 0.01, N(1, 0.5)
    doc["discretization"]["basis"] = 16
    directory = tmp_path_factory.mktemp("store")
    model_id = yauyau.precompute(spec_from_dict(doc), directory)
    _, dy = sample_ou(400, seed=18)
    dy[np.random.default_rng(19).random(400) < 0.05] = np.nan
    path = tmp_path_factory.mktemp("data") / "dy.csv"
    path.write_text("dy\n" + "\n".join("" if v != v else repr(float(v)) for v in dy) + "\n")
    return directory, model_id, path, dy


def _read(out):
    with out.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])


@pytest.mark.parametrize("method", ["kalman-bucy", "yau-hu"])
def test_exact_methods_smooth_continuous_increments(stored, tmp_path, method):
    """400 rows, 5% missing: the smoothed columns equal RTS on the exact gaps (asserted 1e-8); --lag 5
    writes every row, its last 6 equal to the fixed-interval ones."""
    directory, model_id, path, dy = stored
    out = tmp_path / "out.csv"
    base = ["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out", str(out),
            "--method", method, "--gate", "0"]
    assert main(base) == 0
    header, values = _read(out)
    assert header[:4] == ["step", "t", "mean_x", "cov_x_x"]
    one = np.ones((1, 1))
    _, _, ms, Ps = rts_exact_gaps(-0.5 * one, np.zeros(1), one, one, np.zeros(1), one, np.array([1.0]),
                                  0.5 * one, dy[:, None], np.full(400, 0.01), np.zeros(400, bool))
    gaps = np.abs(values[:, 2] - ms[:, 0]).max(), np.abs(values[:, 3] - Ps[:, 0, 0]).max()
    print("cli", method, gaps)
    assert max(gaps) < 1e-8
    assert main([*base, "--lag", "5"]) == 0
    _, lagged = _read(out)
    assert len(lagged) == 400 and np.abs(lagged[-6:, 2] - values[-6:, 2]).max() < 1e-10


def test_yau_jia_has_no_smoother_and_exits_2(stored, tmp_path, capsys):
    method = "yau-jia"
    directory, model_id, path, _ = stored
    out = tmp_path / "out.csv"
    code = main(["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out", str(out),
                 "--method", method])
    err = capsys.readouterr().err
    assert code == 2 and "method" in err and method in err and "yau-yau" in err and not out.exists()


@pytest.mark.parametrize("option", [["--mode"], ["--quantiles", "0.5"], ["--density", "D.h5"]])
def test_yau_hu_smooths_moments_only_and_refuses_the_density_options_by_name(stored, tmp_path, capsys,
                                                                             option):
    """yau-hu's smoother gives the smoothed mean and covariance: --mode (its mixture's mode is not its
    mean), --quantiles and --density exit 2 naming the option, nothing written."""
    directory, model_id, path, _ = stored
    out = tmp_path / "out.csv"
    if option[0] == "--density":
        option = ["--density", str(tmp_path / "d.h5")]
    code = main(["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out", str(out),
                 "--method", "yau-hu", *option])
    err = capsys.readouterr().err
    field = option[0].lstrip("-")
    assert code == 2 and field in err and "yau-yau" in err and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "d.h5").exists()
