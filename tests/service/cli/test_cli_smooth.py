"""`yauyau smooth` (service/cli/smooth.py): the smoothed columns against an RTS smoother written in
tests/helpers/smoothing_refs.py on the sampled OU model, and the error contract (exit 2 naming the field,
nothing written)."""

from __future__ import annotations

import csv
import tomllib

import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.smoothing_refs import point_mass_smoother, rts_sampled, sample_ou, simulate_bimodal
from yauyau.service.cli import main
from yauyau.solver import spec_from_dict

import yauyau


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())  # θ = 0.5, a = 1, R = 1, dt = 0.01, N(1, 0.5)
    doc["discretization"]["basis"] = 48
    doc["domain"]["radius"] = 6.0
    directory = tmp_path_factory.mktemp("store")
    model_id = yauyau.precompute(spec_from_dict(doc), directory)
    data = tmp_path_factory.mktemp("data")
    _, dy = sample_ou(300, seed=8)  # the helper's OU differs (a, R): only the rows are taken from it
    path = data / "dy.csv"
    path.write_text("dy\n" + "\n".join(repr(float(v)) for v in dy) + "\n")
    return directory, model_id, path, dy


def _read(out):
    with out.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])


def _smooth(stored, tmp_path, *extra):
    directory, model_id, path, _ = stored
    out = tmp_path / "out.csv"
    code = main(["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out", str(out),
                 *extra])
    return code, out


def test_smooth_writes_the_smoothed_columns(stored, tmp_path):
    """Measured against RTS on the sampled model: mean 4.7e-6, variance 9.7e-6 relative (bound 0.01, 3%)."""
    code, out = _smooth(stored, tmp_path, "--method", "yau-yau")
    assert code == 0
    header, values = _read(out)
    assert header[:4] == ["step", "t", "mean_x", "cov_x_x"] and "loglik" in header and "gated" in header
    _, _, ms, Ps = rts_sampled(stored[3], 1.0, 0.5, theta=0.5, a=1.0, r=1.0)
    mean_gap = np.abs(values[:, 2] - ms).max()
    var_gap = np.abs(values[:, 3] / Ps - 1).max()
    print(f"cli: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03
    code, out = _smooth(stored, tmp_path, "--method", "yau-yau", "--lag", "4")
    assert code == 0 and len(_read(out)[1]) == 300


@pytest.mark.parametrize("extra, field", [
    (["--method", "yau-yau", "--lag", "-1"], "lag"),
    (["--method", "yau-yau", "--lag", "1.5"], "lag"),
    (["--method", "yau-jia"], "method"),
    (["--method", "yau-yau", "--memory", "1e-6"], "increments"),
])
def test_bad_input_exits_2_naming_the_field(stored, tmp_path, capsys, extra, field):
    code, out = _smooth(stored, tmp_path, *extra)
    err = capsys.readouterr().err
    assert code == 2 and field in err and not out.exists()
    if field == "increments":
        assert "rows fit" in err and "--memory" in err


def test_a_file_over_the_memory_budget_says_the_budget_and_the_rows_that_fit(stored, tmp_path, capsys):
    """--memory 0.0008 (GB) for 300 rows: exit 2 naming increments, the budget and the count that fits,
    nothing written; that many rows then smooth under the same budget, with or without --lag."""
    import re

    code, out = _smooth(stored, tmp_path, "--method", "yau-yau", "--memory", "0.0008")
    err = capsys.readouterr().err
    assert code == 2 and not out.exists()
    assert "error: increments: 300 rows need about" in err
    assert "over the budget of 0.0008 GB (--memory)" in err
    fits = int(re.search(r"at most (\d+) rows fit", err).group(1))
    assert 0 < fits < 300
    directory, model_id, _, dy = stored
    path = tmp_path / "head.csv"
    path.write_text("dy\n" + "".join(f"{float(v)!r}\n" for v in dy[:fits]))
    for extra in ([], ["--lag", "3"]):
        out = tmp_path / "head_out.csv"
        assert main(["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out",
                     str(out), "--method", "yau-yau", "--memory", "0.0008", *extra]) == 0
        assert len(_read(out)[1]) == fits


def test_smooth_on_a_ball_that_follows_the_state(tmp_path):
    """`yauyau smooth` on [domain] follow: 800 rows of the random walk with a trend (travelling ~8 units, a
    ball of radius 6), the smoothed columns (and the ball's centre_x, recentred, as filter writes them)
    against RTS of the sampled model (measured mean 2.3e-5, variance 1.0e-4; bounds 0.02, 5%); --lag 5 on
    the first 200 rows against the fixed-lag RTS (measured 1.2e-5)."""
    from helpers.linear_rts import TREND, rts_trend
    from yauyau.solver import compile_model
    from yauyau.solver.simulate import simulate

    spec = spec_from_dict(TREND)
    model_id = yauyau.precompute(spec, tmp_path / "store")
    dy = simulate(compile_model(spec), 800, np.random.default_rng(5)).increments[:, 0]
    path = tmp_path / "dy.csv"
    path.write_text("dy\n" + "".join(f"{float(v)!r}\n" for v in dy))
    out = tmp_path / "out.csv"
    store = str(tmp_path / "store")
    base = ["smooth", model_id, "--store", store, "--increments", str(path), "--out", str(out)]
    assert main(base) == 0
    names, values = _read(out)
    _, _, ms, Ps = rts_trend(dy, np.full(800, 0.01))
    mean_gap, var_gap = np.abs(values[:, 2] - ms).max(), np.abs(values[:, 3] / Ps - 1).max()
    print(f"cli follow: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert names[:4] == ["step", "t", "mean_x", "cov_x_x"] and names[-2:] == ["center_x", "recentred"]
    assert values.shape[1] == len(names) and values[:, -1].sum() >= 1  # the ball moved
    assert mean_gap < 0.02 and var_gap < 0.05 and ms[-1] - ms[0] > 6.0
    head = dy[:200]
    path.write_text("dy\n" + "".join(f"{float(v)!r}\n" for v in head))
    assert main([*base, "--lag", "5"]) == 0
    lagged = _read(out)[1]
    ms_lag = np.array([rts_trend(head[:k + 6], np.full(len(head[:k + 6]), 0.01))[2][k] for k in range(200)])
    lag_gap = np.abs(lagged[:, 2] - ms_lag).max()
    print(f"cli follow --lag 5: mean {lag_gap:.2e}")
    assert lag_gap < 0.02


BIMODAL = {"name": "bimodal", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x**2/2"],
           "diffusion": [[1.0]], "observation_noise": [[0.1]], "measurement": {"kind": "discrete"},
           "initial": {"kind": "gaussian", "mean": [0.3], "cov": [[1.0]]},
           "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 128}}


def test_smooth_discrete_readings_with_times(tmp_path):
    """--observations (t, z) of the bimodal sensor, irregular times, 5% missing, --t0 0: against the
    point-mass forward–backward smoother (measured: mean 9.1e-5, variance 0.36%)."""
    directory = tmp_path / "store"
    model_id = yauyau.precompute(spec_from_dict(BIMODAL), directory)
    rng = np.random.default_rng(12)
    taus = rng.exponential(0.05, 150) + 1e-3
    z = simulate_bimodal(taus, seed=13, missing=0.05)
    path = tmp_path / "obs.csv"
    path.write_text("t,z\n" + "".join(f"{t!r},{'' if v != v else repr(float(v))}\n"
                                        for t, v in zip(np.cumsum(taus).tolist(), z.tolist(), strict=True)))
    out = tmp_path / "out.csv"
    code = main(["smooth", model_id, "--store", str(directory), "--observations", str(path), "--t0", "0",
                 "--out", str(out), "--method", "yau-yau"])
    assert code == 0
    _, values = _read(out)
    _, mean, var = point_mass_smoother(z, taus)
    mean_gap, var_gap = np.abs(values[:, 2] - mean).max(), np.abs(values[:, 3] / var - 1).max()
    print(f"cli discrete: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03


def test_smooth_quantiles_and_mode_columns(tmp_path):
    """--quantiles 0.1,0.5,0.9 --mode on the bimodal sensor's readings at irregular times: filter's column
    names (mode_x, q0.1_x, …), each row's quantiles within 0.02 of the point-mass forward–backward
    smoother's (its smoothed masses' distribution function inverted, 1200 cells); --density: snapshots
    whose mean by quadrature is the smoothed mean; --lag 5 with the quantiles: its last 5 rows are the
    fixed-interval smoother's."""
    directory = tmp_path / "store"
    model_id = yauyau.precompute(spec_from_dict(BIMODAL), directory)
    rng = np.random.default_rng(14)
    taus = rng.exponential(0.05, 100) + 1e-3
    z = simulate_bimodal(taus, seed=15, missing=0.05)
    path = tmp_path / "obs.csv"
    path.write_text("t,z\n" + "".join(f"{t!r},{'' if v != v else repr(float(v))}\n"
                                        for t, v in zip(np.cumsum(taus).tolist(), z.tolist(), strict=True)))
    out = tmp_path / "out.csv"
    base = ["smooth", model_id, "--store", str(directory), "--observations", str(path), "--t0", "0",
            "--out", str(out), "--method", "yau-yau", "--quantiles", "0.1,0.5,0.9"]
    assert main([*base, "--mode"]) == 0
    names, values = _read(out)
    assert names[3:8] == ["cov_x_x", "mode_x", "q0.1_x", "q0.5_x", "q0.9_x"]
    _, mean, _, x, smoothed = point_mass_smoother(z, taus, cells=1200, full=True)
    cdf = np.cumsum(smoothed, axis=1) - 0.5 * smoothed
    reference = np.array([np.interp([0.1, 0.5, 0.9], c / c[-1], x) for c in cdf])
    gap = np.abs(values[:, 5:8] - reference).max()
    print(f"cli smoothed quantiles: {gap:.2e}")
    assert gap < 0.02 and np.abs(values[:, 2] - mean).max() < 0.01
    # --density: the smoothed density every 20 steps, its mean by quadrature the smoothed mean column
    from yauyau.storage.density_file import read_density

    density = tmp_path / "d.h5"
    assert main([*base[:-2], "--density", str(density), "--density-every", "20"]) == 0
    series = read_density(density)
    assert series.step.tolist() == [20, 40, 60, 80, 100]
    grid, marginal = series.axes[0], series.marginals[0]
    assert np.abs(np.trapezoid(marginal, grid, axis=1) - 1).max() < 1e-3
    found = np.trapezoid(marginal * grid, grid, axis=1)
    assert np.abs(found - values[series.step - 1, 2]).max() < 1e-3
    assert np.abs(found - mean[series.step - 1]).max() < 0.01
    # --lag 5 with the quantiles: its last 5 rows are given every row, the fixed-interval smoother's
    lagged = tmp_path / "lag.csv"
    assert main([*base[:base.index("--out")], "--out", str(lagged), *base[base.index("--out") + 2:], "--mode",
                 "--lag", "5"]) == 0
    names_lag, values_lag = _read(lagged)
    assert names_lag == names and np.abs(values_lag[-5:, 2:8] - values[-5:, 2:8]).max() < 1e-8


def fixed_lag_rts(dy, lag, **model):
    """Row k's RTS-smoothed mean and variance given rows 0 … k + lag (helpers' RTS over that window)."""
    K = len(dy)
    ms, Ps = np.empty(K), np.empty(K)
    for k in range(K):
        _, _, m, P = rts_sampled(dy[:min(k + lag + 1, K)], 1.0, 0.5, **model)
        ms[k], Ps[k] = m[k], P[k]
    return ms, Ps


def test_fixed_lag_quantiles_and_mode(stored, tmp_path):
    """--lag 4 --quantiles 0.05,0.5,0.95 --mode: each row's quantiles of its density given the 4 rows after
    it, against the fixed-lag RTS's Gaussian m + √P Φ⁻¹(p): measured 0.010 (bound 0.02, the bimodal
    test's), where the means are within 1e-5: the smoothed density handed to the quantile code is the
    projection of σ_k ⊙ β_k onto the 48 basis functions (fixed-interval on the same rows: 0.006; the filter's
    own quantiles: 2.7e-4).  The mode, the nodal one as without --lag, within the node spacing of the
    Gaussian's (its mean)."""
    from scipy.special import ndtri

    code, out = _smooth(stored, tmp_path, "--method", "yau-yau", "--lag", "4", "--quantiles", "0.05,0.5,0.95",
                        "--mode")
    assert code == 0
    names, values = _read(out)
    assert names[2:8] == ["mean_x", "cov_x_x", "mode_x", "q0.05_x", "q0.5_x", "q0.95_x"]
    ms, Ps = fixed_lag_rts(stored[3], 4, theta=0.5, a=1.0, r=1.0)
    exact = ms[:, None] + np.sqrt(Ps)[:, None] * ndtri([0.05, 0.5, 0.95])[None, :]
    gap = np.abs(values[:, 5:8] - exact).max()
    print(f"cli fixed-lag quantiles: {gap:.2e}, mode {np.abs(values[:, 4] - ms).max():.2e}")
    assert gap < 0.02 and np.abs(values[:, 2] - ms).max() < 0.01
    assert np.abs(values[:, 4] - ms).max() < 0.15


def _png(path):
    import matplotlib.image

    return matplotlib.image.imread(path)[..., :3]


def test_plot_draws_the_smoothed_band_beside_the_filtered_one(stored, tmp_path, capsys):
    """`yauyau plot F.csv --smoothed S.csv`: one PNG with both means and both 95% bands, labelled; the
    lines and bands are drawn from the two files' columns (read back from the figure's artists); the
    smoothed band is narrower (it uses more data). Bad --smoothed (missing file, other rows, other t,
    other variables, not a run's output) exits 2 naming smoothed, nothing written."""
    import matplotlib

    matplotlib.use("Agg")
    from yauyau.service.cli import plot

    directory, model_id, path, _ = stored
    filtered, smoothed = tmp_path / "f.csv", tmp_path / "s.csv"
    assert main(["filter", model_id, "--store", str(directory), "--increments", str(path), "--out",
                 str(filtered), "--method", "yau-yau"]) == 0
    assert main(["smooth", model_id, "--store", str(directory), "--increments", str(path), "--out",
                 str(smoothed), "--method", "yau-yau"]) == 0
    fig_path, plain = tmp_path / "both.png", tmp_path / "plain.png"
    assert main(["plot", str(filtered), "--smoothed", str(smoothed), "--out", str(fig_path)]) == 0
    assert main(["plot", str(filtered), "--out", str(plain)]) == 0
    image = _png(fig_path)
    assert image.std() > 0.05
    def red(img):  # the tab:red smoothed mean line
        return (np.abs(img - np.array([0.84, 0.15, 0.16])) < 0.08).all(axis=-1).mean()

    assert red(image) > 0.001 and red(_png(plain)) < 1e-4
    # the data the figure is drawn from
    f_cols, s_cols = plot.read_table(str(filtered), "estimates"), plot.read_table(str(smoothed), "smoothed")
    names = plot.variables(f_cols, str(filtered))
    plot.check_smoothed(f_cols, names, s_cols, str(smoothed))
    fig = plot.draw(f_cols, names, None, None, "t", s_cols)
    ax = fig.axes[0]
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    assert np.array_equal(lines["filtered conditional mean"].get_ydata(), np.array(f_cols["mean_x"]))
    assert np.array_equal(lines["smoothed mean"].get_ydata(), np.array(s_cols["mean_x"]))
    bands = {c.get_label(): c for c in ax.collections}
    assert set(bands) == {"filtered mean ± 1.96 sd", "smoothed mean ± 1.96 sd"}
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"filtered conditional mean", "smoothed mean", *bands} <= set(legend)

    def width(label):  # the band's height along t, from the polygon fill_between drew
        verts = bands[label].get_paths()[0].vertices
        k = len(f_cols["t"])
        return verts[k + 2:2 * k + 2, 1][::-1] - verts[1:k + 1, 1]

    s_sd = np.sqrt(np.array(s_cols["cov_x_x"]))
    assert np.allclose(width("smoothed mean ± 1.96 sd"), 2 * 1.96 * s_sd, atol=1e-9)
    assert (width("smoothed mean ± 1.96 sd") <= width("filtered mean ± 1.96 sd") + 1e-9).all()
    # bad --smoothed: exit 2 naming it, nothing written
    text = smoothed.read_text().splitlines()
    cases = {"missing.csv": None, "short.csv": "\n".join(text[:-1]),
             "shifted.csv": "\n".join([text[0], text[1].replace(",0.01,", ",0.015,", 1), *text[2:]]),
             "renamed.csv": "\n".join([text[0].replace("mean_x", "mean_y").replace("cov_x_x", "cov_y_y"),
                                        *text[1:]]),
             "nomean.csv": "a,b\n1,2"}
    for name, body in cases.items():
        if body is not None:
            (tmp_path / name).write_text(body + "\n")
        out = tmp_path / f"bad-{name}.png"
        capsys.readouterr()
        assert main(["plot", str(filtered), "--smoothed", str(tmp_path / name), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err
        assert "error: smoothed" in err and "Traceback" not in err and not out.exists(), (name, err)
