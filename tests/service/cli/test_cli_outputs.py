"""`yauyau simulate`, `yauyau filter --quantiles/--mode/--density`, `yauyau plot`, exit statuses.

Truth: docs/cli.md's three commands reproduce the output the page prints (real processes, real
files); quantile columns against the normal quantiles of the exact Kalman–Bucy posterior (OU); the
density file integrates to 1 and its mean is the filter's mean; the plot is checked as an image.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import EXAMPLES, ROOT
from helpers.readme import doc_section, readme_block
from scipy.stats import norm
from yauyau.service.cli import main
from yauyau.solver import compile_model, load_spec
from yauyau.solver.simulate import simulate

import yauyau

PAGE = "docs/cli.md"
HEADING = "From a spec to a filtered path in three commands"


def _yauyau() -> list[str]:
    script = Path(sys.executable).parent / "yauyau"
    return [str(script)] if script.exists() else [sys.executable, "-m", "yauyau.service.cli"]


def _read(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])


def _png(path: Path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)


@pytest.mark.slow
def test_three_commands_reproduce_the_printed_output(tmp_path):
    (tmp_path / "examples").symlink_to(EXAMPLES)
    commands = [line for line in readme_block(HEADING, "sh", PAGE).splitlines() if line.strip()]
    plot = [line for line in readme_block_all(HEADING, "sh")[1].splitlines() if line.strip()]
    assert [c.split()[1] for c in commands] == ["precompute", "simulate", "filter"]
    outputs = []
    for line in commands + plot:
        argv = shlex.split(line)
        assert argv[0] == "yauyau"
        run = subprocess.run(_yauyau() + argv[1:], cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, (line, run.stderr[-2000:])
        outputs.append(run.stdout)
    model_id = outputs[0].strip()
    assert model_id in commands[2], "the page's filter command names the id precompute prints"
    printed = readme_block(HEADING, "text", PAGE).strip().splitlines()
    produced = (tmp_path / "var" / "run" / "out.csv").read_text().splitlines()[:3]
    assert produced[0] == printed[0]
    # the same numbers (to 1e-9 relative: the last digit of a float may differ with the BLAS build)
    np.testing.assert_allclose(np.array([r.split(",") for r in produced[1:]], float),
                               np.array([r.split(",") for r in printed[1:]], float), rtol=1e-9, atol=1e-12)
    image = _png(tmp_path / "var" / "run" / "cubic.png")
    assert image.shape[0] > 200 and image.shape[1] > 600
    assert (ROOT / "docs" / "img" / "cubic-sensor-run.png").exists()


def readme_block_all(heading: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", doc_section(heading, PAGE), re.S)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    directory = tmp_path_factory.mktemp("outputs-store")
    ids = {name: yauyau.precompute(load_spec(EXAMPLES / f"{name}.toml"), directory)
           for name in ("ou", "cubic_sensor", "range_2d")}
    return directory, ids


def _simulate(tmp_path: Path, name: str, steps: int, seed: int = 1) -> Path:
    out = tmp_path / f"sim-{name}-{seed}"
    assert main(["simulate", str(EXAMPLES / f"{name}.toml"), "--steps", str(steps), "--seed", str(seed),
                 "--out", str(out)]) == 0
    return out


def test_simulate_writes_what_filter_reads_and_is_reproducible(tmp_path):
    first = _simulate(tmp_path, "range_2d", 50, seed=4)
    again = tmp_path / "again"
    assert main(["simulate", str(EXAMPLES / "range_2d.toml"), "--steps", "50", "--seed", "4",
                 "--out", str(again)]) == 0
    for name in ("truth.csv", "increments.csv"):
        assert (first / name).read_bytes() == (again / name).read_bytes()
    columns, truth = _read(first / "truth.csv")
    spec = load_spec(EXAMPLES / "range_2d.toml")
    assert columns == ["step", "t", *spec.state] and truth.shape == (51, 2 + len(spec.state))
    model = compile_model(spec)
    sim = simulate(model, 50, np.random.default_rng(4))  # the library's simulator, same seed
    np.testing.assert_array_equal(truth[:, 2:], sim.states)
    columns, inc = _read(first / "increments.csv")
    assert columns == [f"dy_{j + 1}" for j in range(model.m)]
    np.testing.assert_array_equal(inc, sim.increments)


def _beside_kalman_bucy(store, tmp_path, rows, method, extra):
    """Kalman–Bucy's table, and ``method``'s columns and table with quantiles 0.05, 0.5, 0.95, on one
    simulated OU run."""
    directory, ids = store
    run = _simulate(tmp_path, "ou", rows, seed=2)
    exact, out = tmp_path / "kb.csv", tmp_path / "other.csv"
    common = ["--store", str(directory), "--increments", str(run / "increments.csv")]
    assert main(["filter", ids["ou"], *common, "--out", str(exact), "--method", "kalman-bucy"]) == 0
    assert main(["filter", ids["ou"], *common, "--out", str(out), "--method", method,
                 "--quantiles", "0.05,0.5,0.95", *extra]) == 0
    _, kb = _read(exact)
    return (kb, *_read(out))


@pytest.mark.slow
def test_quantile_and_mode_columns_against_the_normal_posterior(store, tmp_path):
    kb, columns, table = _beside_kalman_bucy(store, tmp_path, 300, "yau-hu", ["--mode"])
    assert columns == ["step", "t", "mean_x", "cov_x_x", "mode_x", "q0.05_x", "q0.5_x", "q0.95_x",
                       "loglik", "degenerate", "gated", "predictive_loglik", "reinitialised"]
    truth = norm.ppf([0.05, 0.5, 0.95], loc=kb[:, 2:3], scale=np.sqrt(kb[:, 3:4]))
    assert np.abs(table[:, 5:8] - truth).max() < 1e-3
    assert np.abs(table[:, 4] - kb[:, 2]).max() < 1e-3  # the mode of a normal is its mean


@pytest.mark.slow
def test_density_file_is_cf_style_and_integrates_to_one(store, tmp_path):
    directory, ids = store
    run = _simulate(tmp_path, "range_2d", 40, seed=3)
    out, dens = tmp_path / "out.csv", tmp_path / "d.h5"
    code = main(["filter", ids["range_2d"], "--store", str(directory), "--increments",
                 str(run / "increments.csv"), "--out", str(out), "--density", str(dens),
                 "--density-every", "20", "--density-points", "81"])
    assert code == 0
    columns, table = _read(out)
    with h5py.File(dens) as f:
        assert f.attrs["Conventions"] == "CF-1.10" and f.attrs["model_id"] == ids["range_2d"]
        names = list(f.attrs["state"])
        np.testing.assert_array_equal(f["step"][()], [0, 20, 40])
        np.testing.assert_allclose(f["time"][()], [0.0, *table[[19, 39], 1]])
        assert f["time"].attrs["axis"] == "T"
        axes = [f[v][()] for v in names]
        joint = f["density"][()]
        assert joint.shape == (3, 81, 81)
        assert [d.label for d in f["density"].dims] == ["time", *names]
        assert [d[0].name for d in f["density"].dims] == ["/time", *[f"/{v}" for v in names]]
        for k in range(3):
            mass = np.trapezoid(np.trapezoid(joint[k], axes[1], axis=1), axes[0])
            assert mass == pytest.approx(1.0, abs=0.02)
        for i, v in enumerate(names):
            marginal = f[f"marginal_{v}"][()]
            mean = np.trapezoid(marginal[2] * axes[i], axes[i]) / np.trapezoid(marginal[2], axes[i])
            assert mean == pytest.approx(table[39, 2 + i], abs=0.02)


@pytest.mark.slow
def test_plot_draws_band_truth_and_heat_map(store, tmp_path):
    directory, ids = store
    run = _simulate(tmp_path, "cubic_sensor", 200, seed=5)
    out, dens, fig, svg = tmp_path / "out.csv", tmp_path / "d.h5", tmp_path / "fig.png", tmp_path / "fig.svg"
    assert main(["filter", ids["cubic_sensor"], "--store", str(directory), "--increments",
                 str(run / "increments.csv"), "--out", str(out), "--density", str(dens)]) == 0
    assert main(["plot", str(out), "--out", str(tmp_path / "plain.png")]) == 0
    assert main(["plot", str(out), "--truth", str(run / "truth.csv"), "--density", str(dens),
                 "--out", str(fig)]) == 0
    assert main(["plot", str(out), "--truth", str(run / "truth.csv"), "--out", str(svg)]) == 0
    plain, image = _png(tmp_path / "plain.png"), _png(fig)
    assert image.shape[1] > 1.6 * plain.shape[1]  # the heat map panel beside the series
    rgb = plain[..., :3]
    assert rgb.std() > 0.05  # not blank
    band = (np.abs(rgb - np.array([0.80, 0.87, 0.94])) < 0.05).all(axis=-1)  # tab:blue at alpha 0.25
    assert band.mean() > 0.02, "the 95% band is drawn"
    dark = (rgb.sum(axis=-1) < 0.3).mean()
    assert dark > 0.001  # the black truth line... in the heat-map figure too:
    assert (image[..., :3].sum(axis=-1) < 0.3).mean() > 0.05  # the magma heat map
    assert svg.read_text().lstrip().startswith("<?xml")


@pytest.mark.slow
def test_degenerate_run_exits_3_and_says_from_where(store, tmp_path, capsys):
    """An increment of 1e5 with the outlier gate off (--gate 0; the default gate would reject it:
    tests/service/cli/test_cli_measurements.py) pushes the density out of the ball: exit 3, flagged from
    there."""
    directory, ids = store
    run = _simulate(tmp_path, "cubic_sensor", 30, seed=6)
    rows = (run / "increments.csv").read_text().splitlines()
    rows[12] = "100000.0"
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(rows) + "\n")
    out = tmp_path / "out.csv"
    code = main(["filter", ids["cubic_sensor"], "--store", str(directory), "--increments", str(bad),
                 "--out", str(out), "--quantiles", "0.5", "--mode", "--gate", "0"])
    assert code == 3
    err = capsys.readouterr().err
    assert re.search(r"degenerate from step 12 \(t = 0\.12\)", err), err
    columns, table = _read(out)
    flagged = table[:, columns.index("degenerate")]
    assert flagged[:11].sum() == 0 and flagged[11:].all()
    assert np.isnan(table[11:, columns.index("q0.5_x")]).all()  # no quantile of a lost density
    assert not table[:, columns.index("gated")].any() and not table[:, columns.index("reinitialised")].any()


@pytest.mark.slow
def test_cumulative_observations_are_recognised(store, tmp_path, capsys):
    directory, ids = store
    for name in ("cubic_sensor", "ou", "range_2d"):
        run = _simulate(tmp_path, name, 400, seed=7)
        assert main(["filter", ids[name], "--store", str(directory), "--increments",
                     str(run / "increments.csv"), "--out", str(tmp_path / "a.csv")]) in (0, 3)
        assert "looks like the cumulative" not in capsys.readouterr().err, name
        _, inc = _read(run / "increments.csv")
        path = tmp_path / "y.csv"
        cumulative = np.cumsum(inc, axis=0)
        path.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in cumulative) + "\n")
        main(["filter", ids[name], "--store", str(directory), "--increments", str(path),
              "--out", str(tmp_path / "b.csv")])
        err = capsys.readouterr().err
        assert "looks like the cumulative observation" in err and "numpy.diff" in err, (name, err)


@pytest.mark.slow
@pytest.mark.parametrize("extra, field", [
    (["--quantiles", "0.5,1.5"], "quantiles"), (["--quantiles", "a"], "quantiles"),
    (["--quantiles", "0.5,0.5"], "quantiles"), (["--density", "d.csv"], "density"),
    (["--density-every", "0", "--density", "d.h5"], "density_every"),
    (["--density-points", "1", "--density", "d.h5"], "density_points")])
def test_bad_output_options_exit_2_and_write_nothing(store, tmp_path, capsys, extra, field):
    directory, ids = store
    run = _simulate(tmp_path, "ou", 5)
    out = tmp_path / "out.csv"
    extra = [str(tmp_path / e) if e.startswith("d.") else e for e in extra]
    code = main(["filter", ids["ou"], "--store", str(directory), "--increments", str(run / "increments.csv"),
                 "--out", str(out), *extra])
    assert code == 2
    err = capsys.readouterr().err
    assert f"error: {field}" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob("d.*"))


@pytest.mark.parametrize("argv, field", [
    (["simulate", "SPEC", "--steps", "0", "--out", "o"], "steps"),
    (["simulate", "missing.toml", "--steps", "3", "--out", "o"], "spec"),
    (["plot", "missing.csv", "--out", "f.png"], "estimates"),
    (["plot", "OUT", "--out", "f.jpg"], "out"),
    (["plot", "TRUTHASOUT", "--out", "f.png"], "estimates")])
def test_simulate_and_plot_errors_exit_2(tmp_path, capsys, argv, field):
    truth = _simulate(tmp_path, "ou", 5) / "truth.csv"
    argv = [str(EXAMPLES / "ou.toml") if a == "SPEC" else str(truth) if a == "TRUTHASOUT"
            else str(truth) if a == "OUT" else str(tmp_path / a) if "." in a else a for a in argv]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"error: {field}" in err and "Traceback" not in err


@pytest.mark.slow
def test_progress_bar_on_request(store, tmp_path, capsys):
    directory, ids = store
    run = _simulate(tmp_path, "ou", 50)
    capsys.readouterr()
    for flag, shown in (("on", True), ("auto", False)):  # auto: stderr is not a terminal here
        main(["filter", ids["ou"], "--store", str(directory), "--increments", str(run / "increments.csv"),
              "--out", str(tmp_path / "o.csv"), "--progress", flag])
        assert ("50/50" in capsys.readouterr().err) is shown


def test_every_help_page_prints(capsys):
    """`yauyau -h` and each command's -h exit 0 (argparse %-formats help text: a bare % breaks it)."""
    from yauyau.service.cli.main import COMMANDS

    for argv in (["-h"], *[[name, "-h"] for name in COMMANDS]):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 0, argv
        out = capsys.readouterr().out
        assert out.startswith("usage: yauyau"), argv


def test_version_is_the_distribution_version():
    """`yauyau --version` (the console script) prints the version pyproject.toml gives the distribution."""
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    done = subprocess.run(_yauyau() + ["--version"], capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (0, f"yauyau {version}\n", "")


@pytest.mark.slow
def test_output_files_get_the_users_umask(store, tmp_path):
    """Under umask 022 every file the commands write for the user is 0644, as open() would make it (the
    temporary files they were renamed from were mkstemp's 0600): simulate --out, filter --out and
    --density, plot --out, precompute's model file."""
    directory, ids = store
    spec = tmp_path / "ou.json"  # a mesh-free method: precompute writes its file at once
    spec.write_text(json.dumps({"name": "ou-umask", "state": ["x"], "drift": ["-x"], "observation": ["x"],
                                "method": "kalman-bucy", "domain": {"radius": 6.0},
                                "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
                                "discretization": {"dt": 0.01, "basis": 16}}))
    old = os.umask(0o022)
    try:
        run = _simulate(tmp_path, "cubic_sensor", 20, seed=8)
        out, dens, fig = tmp_path / "out.csv", tmp_path / "d.h5", tmp_path / "fig.png"
        assert main(["filter", ids["cubic_sensor"], "--store", str(directory), "--increments",
                     str(run / "increments.csv"), "--out", str(out), "--density", str(dens)]) == 0
        assert main(["plot", str(out), "--out", str(fig)]) == 0
        assert main(["precompute", str(spec), "--store", str(tmp_path / "store"), "--quiet"]) == 0
    finally:
        os.umask(old)
    written = [run / "truth.csv", run / "increments.csv", out, dens, fig, *(tmp_path / "store").glob("*.h5")]
    assert len(written) == 6
    assert {p.name: oct(p.stat().st_mode & 0o777) for p in written} == {p.name: "0o644" for p in written}


@pytest.mark.slow
def test_yau_niu_quantile_columns_against_the_normal_posterior(store, tmp_path):
    """yau-niu's quantiles (a weighted KDE of its points) finish and sit within 0.08 of the exact
    Kalman–Bucy posterior's normal quantiles (posterior sd ≥ 0.7, so 0.11 sd; measured 0.052 on this
    path, 0.031 when each row built its own Sobol set; over 12 runs of 300 rows, 3 paths × 4 seeds,
    the worst mean was up to 0.021 and the worst sd up to 2.8% off, which move a 5% quantile by up
    to ~0.05)."""
    kb, columns, table = _beside_kalman_bucy(store, tmp_path, 100, "yau-niu", [])
    assert columns[4:7] == ["q0.05_x", "q0.5_x", "q0.95_x"]
    truth = norm.ppf([0.05, 0.5, 0.95], loc=kb[:, 2:3], scale=np.sqrt(kb[:, 3:4]))
    assert np.abs(table[:, 4:7] - truth).max() < 0.08
