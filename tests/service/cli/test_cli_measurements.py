"""`yauyau filter --observations/--t0/--gate/--on-degenerate` and `yauyau simulate --mean-gap`: real
`yauyau` processes on real files.

Truth: the exact scalar Kalman recursion of the Ornstein–Uhlenbeck model, written here (θ = 0.5,
a = 1, prior N(1, 0.5)): over a gap τ the mean is multiplied by e^{−θτ} and the variance becomes
e^{−2θτ}P + (1 − e^{−2θτ})/(2θ); a discrete measurement z = x + v, v ~ N(0, R), updates with H = 1;
a continuous increment dy over the gap with x frozen at its end (the engine's model, the sampled-time
filter) with H = τ and noise Rτ; a missing component is left out of H and R; a gated row only
predicts.  The predictive log-likelihood is log N(row; H m⁻, H P⁻ Hᵀ + R).  The engine must be within
1e-3 (mean, predictive log-likelihood) and 1% (variance) of it; the Python API on the same rows must
give the numbers of the file to 1e-12.
"""

from __future__ import annotations

import csv
import math
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.irregular_refs import kalman_irregular

import yauyau

THETA, PRIOR_MEAN, PRIOR_VAR = 0.5, 1.0, 0.5
DISCRETE = '\n[measurement]\nkind = "discrete"\n'
R_TWO = [[1.0, 0.3], [0.3, 2.0]]


def _yauyau() -> list[str]:
    script = Path(sys.executable).parent / "yauyau"
    return [str(script)] if script.exists() else [sys.executable, "-m", "yauyau.service.cli"]


def _run(*argv, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(_yauyau() + [str(a) for a in argv], capture_output=True, text=True, timeout=600,
                          cwd=cwd)


def _read(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])


def _column(columns: list[str], table: np.ndarray, name: str) -> np.ndarray:
    return table[:, columns.index(name)]


def _write(path: Path, header: str, times, rows) -> Path:
    lines = [header] + [",".join([repr(float(t))] + ["" if math.isnan(v) else repr(float(v)) for v in row])
                        for t, row in zip(times, rows, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


def kalman(times, rows, *, t0: float, R, kind: str = "discrete", skip=()):
    """The exact OU Kalman recursion (module docstring): means, variances, predictive log-likelihoods
    (NaN where nothing is observed or the row is skipped, i.e. gated) and the predictive scores."""
    R = np.atleast_2d(np.asarray(R, dtype=float))
    m, P, t = PRIOR_MEAN, PRIOR_VAR, t0
    means, variances, pll, score = [], [], [], []
    for k, (tk, row) in enumerate(zip(times, np.atleast_2d(rows), strict=True)):
        tau = tk - t
        decay = math.exp(-THETA * tau)
        m, P = decay * m, decay ** 2 * P + (1 - math.exp(-2 * THETA * tau)) / (2 * THETA)
        seen = ~np.isnan(row)
        value, s = math.nan, math.nan
        if seen.any():
            y = row[seen]
            scale = tau if kind == "continuous" else 1.0
            H = np.full(len(y), scale)
            S = P * np.outer(H, H) + R[np.ix_(seen, seen)] * scale
            innovation = y - H * m
            quad = float(innovation @ np.linalg.solve(S, innovation))
            s = math.sqrt(quad)
            if k not in skip:
                value = -0.5 * (len(y) * math.log(2 * math.pi) + np.linalg.slogdet(S)[1] + quad)
                gain = P * np.linalg.solve(S, H)
                m, P = m + float(gain @ innovation), P * (1 - float(gain @ H))
        means.append(m)
        variances.append(P)
        pll.append(value)
        score.append(s)
        t = tk
    return np.array(means), np.array(variances), np.array(pll), np.array(score)


def _precompute(spec: Path, store: Path) -> str:
    done = _run("precompute", spec, "--store", store, "--quiet")
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def specs(tmp_path_factory):
    """Temporary specs: OU with discrete measurements (one sensor, and two correlated sensors of x)."""
    directory = tmp_path_factory.mktemp("specs")
    ou = (EXAMPLES / "ou.toml").read_text()
    one = directory / "ou_discrete.toml"
    one.write_text(ou + DISCRETE)
    two = directory / "ou_two_sensors.toml"
    two.write_text(ou.replace('observation = ["x"]', 'observation = ["x", "x"]\nobservation_noise = '
                              f"{R_TWO}") + DISCRETE)
    assert two.read_text() != ou + DISCRETE
    return {"ou_discrete": one, "ou_two": two, "ou": EXAMPLES / "ou.toml",
            "cubic_sensor": EXAMPLES / "cubic_sensor.toml"}


@pytest.fixture(scope="module")
def store(tmp_path_factory, specs):
    directory = tmp_path_factory.mktemp("measurements-store")
    return directory, {name: _precompute(path, directory) for name, path in specs.items()}


def _filter(store, name: str, out: Path, *argv) -> subprocess.CompletedProcess:
    directory, ids = store
    return _run("filter", ids[name], "--store", directory, "--out", out, *argv)


def _printed_command(stderr: str, store, name: str, out: Path, command: str = "filter") -> list[str]:
    """The `yauyau filter ...` (or `yauyau precompute ...`) line simulate prints, on this test's store and
    ``out``; the filter line names the model by the id precompute gave the spec (no placeholder)."""
    directory, ids = store
    line = next(x for x in stderr.splitlines() if x.strip().startswith(f"yauyau {command} "))
    words = shlex.split(line, comments=True)
    if command == "filter":
        assert words[2] == ids[name], line
    words[words.index("--store") + 1] = str(directory)
    return [str(out) if w == "OUT.csv" else w for w in words[1:]]


@pytest.mark.slow
def test_discrete_measurements_at_random_times_match_the_exact_kalman_recursion(store, specs, tmp_path):
    sim = tmp_path / "sim"
    done = _run("simulate", specs["ou_discrete"], "--steps", 400, "--seed", 3, "--mean-gap", 0.05,
                "--out", sim)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(sim / "truth.csv"), str(sim / "observations.csv")]
    again = _run("simulate", specs["ou_discrete"], "--steps", 400, "--seed", 3, "--mean-gap", 0.05,
                 "--out", tmp_path / "again")
    assert again.returncode == 0 and not (sim / "increments.csv").exists()
    for name in ("truth.csv", "observations.csv"):  # the same seed, the same files
        assert (sim / name).read_bytes() == (tmp_path / "again" / name).read_bytes()
    columns, data = _read(sim / "observations.csv")
    assert columns == ["t", "z_1"]
    times, z = data[:, 0], data[:, 1:]
    gaps = np.diff(times, prepend=0.0)
    assert (gaps > 0).all() and 0.04 < gaps.mean() < 0.06 and gaps.std() > 0.5 * gaps.mean()  # exponential
    _, truth = _read(sim / "truth.csv")
    np.testing.assert_array_equal(truth[1:, 1], times)  # the truth at the observation times
    assert truth[0, 1] == 0.0

    out = tmp_path / "out.csv"
    precompute = _run(*_printed_command(done.stderr, store, "ou_discrete", out, "precompute"))
    assert precompute.returncode == 0 and precompute.stdout.split() == [store[1]["ou_discrete"]]
    command = _printed_command(done.stderr, store, "ou_discrete", out)
    assert "--observations" in command and command[command.index("--t0") + 1] == "0"
    run = _run(*command, "--method", "yau-yau")
    assert run.returncode == 0, run.stderr
    columns, table = _read(out)
    assert columns == ["step", "t", "mean_x", "cov_x_x", "loglik", "degenerate", "gated", "predictive_loglik",
                       "reinitialised"]
    np.testing.assert_array_equal(table[:, 0], np.arange(1, 401))
    np.testing.assert_array_equal(table[:, 1], times)
    mean, var, pll, _ = kalman(times, z, t0=0.0, R=1.0)
    gap_mean = np.abs(table[:, 2] - mean).max()
    gap_var = np.abs(table[:, 3] / var - 1).max()
    gap_pll = np.abs(_column(columns, table, "predictive_loglik") - pll).max()
    gap_ll = np.abs(table[:, 4] - np.cumsum(pll)).max()  # discrete: the loglik is the sum of the predictive
    print(f"discrete OU, 400 random times: mean {gap_mean:.2e}, variance {gap_var:.2e}, "
          f"predictive loglik {gap_pll:.2e}, loglik {gap_ll:.2e}")
    assert gap_mean < 1e-3 and gap_var < 0.01 and gap_pll < 1e-3 and gap_ll < 1e-2
    assert not table[:, 5:7].any() and not table[:, 8].any()

    # the Python API on the same rows: the numbers of the file
    directory, ids = store
    flt = yauyau.open_filter(directory, ids["ou_discrete"], method="yau-yau", t0=0.0)
    result = flt.run(z, times)
    for got, expected in ((result.t, table[:, 1]), (result.mean[:, 0], table[:, 2]),
                          (result.cov[:, 0, 0], table[:, 3]), (result.loglik, table[:, 4]),
                          (result.predictive_loglik, table[:, 7])):
        # the CLI runs one BLAS thread, a test worker may run more: the products' sums in another order
        # (seen once under a loaded parallel run: 1.4e-12 on a predictive log-likelihood of 0.15)
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(result.gated, table[:, 6].astype(bool))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kalman-bucy", "yau-hu", "wei-norman"])
def test_exact_methods_take_timed_measurements_exactly_or_refuse_in_one_line(store, specs, tmp_path, method):
    """An exact filter either takes discrete measurements at random times (then it must be the exact
    recursion) or refuses before anything runs: one line naming what it cannot take and the fix."""
    sim = tmp_path / "sim"
    assert _run("simulate", specs["ou_discrete"], "--steps", 100, "--seed", 9, "--mean-gap", 0.05,
                "--out", sim).returncode == 0
    _, data = _read(sim / "observations.csv")
    out = tmp_path / "out.csv"
    run = _filter(store, "ou_discrete", out, "--observations", sim / "observations.csv", "--t0", 0,
                  "--method", method)
    if run.returncode == 2:  # one line naming the field and the fix: the general engine
        assert run.stderr.count("\n") == 1 and "yau-yau" in run.stderr.split("error: ", 1)[1], run.stderr
        assert not out.exists()
        return
    assert run.returncode == 0, run.stderr
    columns, table = _read(out)
    mean, var, _, _ = kalman(data[:, 0], data[:, 1:], t0=0.0, R=1.0)
    assert np.abs(table[:, 2] - mean).max() < 1e-3 and np.abs(table[:, 3] / var - 1).max() < 0.01


@pytest.mark.slow
def test_default_t0_is_the_first_observation_and_an_earlier_one_propagates(store, tmp_path):
    rng = np.random.default_rng(8)
    times = 2.0 + np.concatenate([[0.0], np.cumsum(rng.exponential(0.1, 59))])
    z = rng.normal(1.0, 1.2, (60, 1))
    z[[7, 30]] = np.nan  # times with nothing observed ("t," rows): the filter only predicts
    source = _write(tmp_path / "z.csv", "t,speed", times, z)  # any column names
    first = {}
    for t0 in (None, 1.5):
        out = tmp_path / f"out-{t0}.csv"
        run = _filter(store, "ou_discrete", out, "--observations", source, "--method", "yau-yau",
                      *([] if t0 is None else ["--t0", t0]))
        assert run.returncode == 0, run.stderr
        columns, table = _read(out)
        mean, var, pll, _ = kalman(times, z, t0=times[0] if t0 is None else t0, R=1.0)
        gaps = (np.abs(table[:, 2] - mean).max(), np.abs(table[:, 3] / var - 1).max(),
                np.nanmax(np.abs(_column(columns, table, "predictive_loglik") - pll)))
        print(f"t0 {t0 or 'default (2.0)'}: mean {gaps[0]:.2e}, variance {gaps[1]:.2e}, "
              f"predictive loglik {gaps[2]:.2e}")
        assert gaps[0] < 1e-3 and gaps[1] < 0.01 and gaps[2] < 1e-3
        assert np.isnan(_column(columns, table, "predictive_loglik")[[7, 30]]).all()
        first[t0] = table[0, 2:4]
        if t0 is None:  # the prior at the first observation: an update with no propagation
            assert table[0, 2] == pytest.approx(1.0 + 0.5 / 1.5 * (z[0, 0] - 1.0), abs=1e-3)
            assert table[0, 3] == pytest.approx(0.5 / 1.5, rel=0.01)
    assert np.abs(first[None] - first[1.5]).min() > 0.02  # the two priors' times do make a difference


@pytest.mark.slow
def test_partly_missing_components_are_marginalised(store, specs, tmp_path):
    sim = tmp_path / "sim"
    done = _run("simulate", specs["ou_two"], "--steps", 300, "--seed", 11, "--out", sim)
    assert done.returncode == 0, done.stderr
    columns, data = _read(sim / "observations.csv")
    assert columns == ["t", "z_1", "z_2"]
    np.testing.assert_allclose(data[:, 0], 0.01 * np.arange(1, 301), rtol=1e-12)  # every dt: regular times
    rng = np.random.default_rng(12)
    z = data[:, 1:].copy()
    z[rng.uniform(size=z.shape) < 0.3] = np.nan
    z[[50, 51]] = np.nan
    partial = np.isnan(z).any(axis=1) & ~np.isnan(z).all(axis=1)
    assert partial.sum() > 100
    source = _write(tmp_path / "partial.csv", "t,z_1,z_2", data[:, 0], z)
    out = tmp_path / "out.csv"
    run = _filter(store, "ou_two", out, "--observations", source, "--t0", 0, "--method", "yau-yau")
    assert run.returncode == 0, run.stderr
    columns, table = _read(out)
    mean, var, pll, _ = kalman(data[:, 0], z, t0=0.0, R=R_TWO)
    got = _column(columns, table, "predictive_loglik")
    gaps = (np.abs(table[:, 2] - mean).max(), np.abs(table[:, 3] / var - 1).max(),
            np.nanmax(np.abs(got - pll)))
    print(f"two sensors, {partial.sum()} partly missing rows: mean {gaps[0]:.2e}, variance {gaps[1]:.2e}, "
          f"predictive loglik {gaps[2]:.2e}")
    assert gaps[0] < 1e-3 and gaps[1] < 0.01 and gaps[2] < 1e-3
    assert np.array_equal(np.isnan(got), np.isnan(z).all(axis=1))  # empty only where nothing is observed


@pytest.mark.slow
def test_a_1000_sigma_outlier_is_gated_and_later_rows_are_healthy(store, specs, tmp_path):
    sim = tmp_path / "sim"
    assert _run("simulate", specs["ou_discrete"], "--steps", 300, "--seed", 5, "--mean-gap", 0.05,
                "--out", sim).returncode == 0
    _, data = _read(sim / "observations.csv")
    times, z = data[:, 0], data[:, 1:].copy()
    bad = 120
    mean, var, _, _ = kalman(times[:bad], z[:bad], t0=0.0, R=1.0)
    decay = math.exp(-THETA * (times[bad] - times[bad - 1]))
    predicted, spread = decay * mean[-1], math.sqrt(decay ** 2 * var[-1] + (1 - decay ** 2) / (2 * THETA) + 1)
    z[bad] = predicted + 1000 * spread
    source = _write(tmp_path / "outlier.csv", "t,z_1", times, z)
    out = tmp_path / "out.csv"
    run = _filter(store, "ou_discrete", out, "--observations", source, "--t0", 0, "--method", "yau-yau")
    assert run.returncode == 0, run.stderr
    assert "1 gated" in run.stderr and f"step {bad + 1}" in run.stderr and "gated" in run.stderr
    columns, table = _read(out)
    gated = _column(columns, table, "gated")
    assert gated[bad] == 1 and gated.sum() == 1
    assert not _column(columns, table, "degenerate").any()
    assert table[bad, 4] == pytest.approx(table[bad - 1, 4], abs=1e-9)  # a gated row adds no likelihood
    assert _column(columns, table, "predictive_loglik")[bad] < -1e4  # log N(1000 sd) ~ -5e5, or -inf
    mean, var, pll, score = kalman(times, z, t0=0.0, R=1.0, skip={bad})
    assert score[bad] == pytest.approx(1000, rel=1e-6)
    healthy = np.arange(len(z)) != bad
    gaps = (np.abs(table[:, 2] - mean).max(), np.abs(table[:, 3] / var - 1).max(),
            np.abs(_column(columns, table, "predictive_loglik")[healthy] - pll[healthy]).max())
    print(f"1000-sd outlier gated at row {bad}, vs the Kalman recursion that skips it: mean {gaps[0]:.2e}, "
          f"variance {gaps[1]:.2e}, predictive loglik {gaps[2]:.2e}")
    assert gaps[0] < 1e-3 and gaps[1] < 0.01 and gaps[2] < 1e-3


@pytest.mark.slow
def test_reinitialise_continues_where_stop_exits_3_and_the_gate_only_predicts(store, tmp_path):
    """cubic_sensor, one increment of 1e5 at step 13 (row 12)."""
    sim = tmp_path / "sim"
    assert _run("simulate", EXAMPLES / "cubic_sensor.toml", "--steps", 300, "--seed", 6,
                "--out", sim).returncode == 0
    lines = (sim / "increments.csv").read_text().splitlines()  # a header line, then the rows
    clean = tmp_path / "clean.csv"
    clean.write_text("\n".join(lines) + "\n")
    lines[13] = "100000.0"
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    lines[13] = ""
    skipped = tmp_path / "skipped.csv"  # that row missing: what a gated row amounts to
    skipped.write_text("\n".join(lines) + "\n")
    outs = {name: tmp_path / f"{name}.csv" for name in ("stop", "again", "gated", "clean", "skipped")}
    runs = {"stop": _filter(store, "cubic_sensor", outs["stop"], "--increments", bad, "--gate", 0),
            "again": _filter(store, "cubic_sensor", outs["again"], "--increments", bad, "--gate", 0,
                             "--on-degenerate", "reinitialise"),
            "gated": _filter(store, "cubic_sensor", outs["gated"], "--increments", bad),
            "clean": _filter(store, "cubic_sensor", outs["clean"], "--increments", clean),
            "skipped": _filter(store, "cubic_sensor", outs["skipped"], "--increments", skipped)}
    assert {k: r.returncode for k, r in runs.items()} == {"stop": 3, "again": 0, "gated": 0, "clean": 0,
                                                          "skipped": 0}, runs["again"].stderr
    assert "degenerate from step 13 (t = 0.13)" in runs["stop"].stderr
    assert "1 re-initialised" in runs["again"].stderr and "step 13" in runs["again"].stderr
    assert "1 gated" in runs["gated"].stderr
    tables = {k: _read(p) for k, p in outs.items()}
    columns, stop = tables["stop"]
    flagged = _column(columns, stop, "degenerate")
    assert flagged[12:].all() and not flagged[:12].any()
    columns, again = tables["again"]
    flagged = _column(columns, again, "reinitialised")
    assert flagged[12] == 1 and flagged.sum() == 1
    assert not _column(columns, again, "degenerate").any() and np.isfinite(again[:, :5]).all()
    assert np.isnan(_column(columns, again, "predictive_loglik")[12])  # that row's observation was not used
    assert again[12, 3] > 3.9 * again[11, 3]  # started again from the last estimate, its sd doubled
    _, clean_table = tables["clean"]
    drift = np.abs(again[:, 2] - clean_table[:, 2])
    print(f"re-initialised at step 13: |mean - mean of the clean run| {drift[20]:.2e} at step 21, "
          f"{drift[100]:.2e} at step 101, {drift[-1]:.2e} at step 300")
    assert drift[-50:].max() < 1e-3  # a stable filter forgets its start: the restarted run rejoins
    columns, gated = tables["gated"]
    assert _column(columns, gated, "gated")[12] == 1 and _column(columns, gated, "gated").sum() == 1
    _, skipped_table = tables["skipped"]
    estimates = [columns.index(c) for c in ("mean_x", "cov_x_x", "loglik")]
    np.testing.assert_allclose(gated[:, estimates], skipped_table[:, estimates], rtol=1e-12, atol=1e-12)

    # yauyau plot marks the gated row (orange x) and the re-initialisation (purple dotted line)
    colours = {"orange": (1.0, 0.498, 0.055), "purple": (0.580, 0.404, 0.741)}
    seen = {}
    for name in ("gated", "again", "clean"):
        figure = tmp_path / f"{name}.png"
        run = _run("plot", outs[name], "--truth", sim / "truth.csv", "--out", figure)
        assert run.returncode == 0, run.stderr
        import matplotlib.image

        rgb = matplotlib.image.imread(figure)[..., :3]
        seen[name] = {c: int((np.abs(rgb - v) < 0.06).all(axis=-1).sum()) for c, v in colours.items()}
    print(f"plot pixels of the gate's x markers / the re-initialisation lines: {seen}")
    assert seen["clean"] == {"orange": 0, "purple": 0}, seen
    assert seen["gated"]["orange"] > 10 and seen["gated"]["purple"] == 0, seen
    assert seen["again"]["purple"] > 10 and seen["again"]["orange"] == 0, seen


@pytest.mark.slow
def test_reinitialise_gives_the_same_rows_in_any_chunking(store, tmp_path):
    """--on-degenerate reinitialise over chunks of 5 rows, and row by row (--quantiles), gives the rows
    of one chunk: the state goes on from chunk to chunk (steps 1..K, no restart at a chunk's end)."""
    sim = tmp_path / "sim"
    assert _run("simulate", EXAMPLES / "cubic_sensor.toml", "--steps", 60, "--seed", 6,
                "--out", sim).returncode == 0
    lines = (sim / "increments.csv").read_text().splitlines()
    lines[13] = "100000.0"
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    tables = {}
    chunkings = {"one": [], "five": ["--chunk", "5"], "rows": ["--chunk", "5", "--quantiles", "0.5"]}
    for name, extra in chunkings.items():
        out = tmp_path / f"{name}.csv"
        run = _filter(store, "cubic_sensor", out, "--increments", bad, "--gate", 0, "--on-degenerate",
                      "reinitialise", *extra)
        assert run.returncode == 0, run.stderr
        columns, table = _read(out)
        tables[name] = table[:, [i for i, c in enumerate(columns) if not c.startswith("q")]]
    np.testing.assert_array_equal(tables["one"][:, 0], np.arange(1, 61))
    assert tables["one"][:, -1].sum() == 1
    for name in ("five", "rows"):
        np.testing.assert_array_equal(tables[name][:, 0], np.arange(1, 61), err_msg=name)
        np.testing.assert_allclose(tables[name], tables["one"], rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.slow
def test_continuous_increments_at_random_times(store, tmp_path):
    sim = tmp_path / "sim"
    done = _run("simulate", EXAMPLES / "ou.toml", "--steps", 300, "--seed", 5, "--mean-gap", 0.02,
                "--out", sim)
    assert done.returncode == 0, done.stderr
    assert not (sim / "increments.csv").exists()
    columns, data = _read(sim / "observations.csv")
    assert columns == ["t", "dy_1"]
    out = tmp_path / "out.csv"
    run = _run(*_printed_command(done.stderr, store, "ou", out), "--method", "yau-yau")
    assert run.returncode == 0, run.stderr
    columns, table = _read(out)
    # increments over gaps longer than 2.25 dt come in pieces of about 2 dt (y linear over the gap)
    exact = kalman_irregular([[-THETA]], [0.0], [[1.0]], [[1.0]], [0.0], [[1.0]], [PRIOR_MEAN], [[PRIOR_VAR]],
                             data[:, 1:], data[:, 0], "continuous", max_piece=0.02)
    mean, var, pll = exact.mean[:, 0], exact.cov[:, 0, 0], exact.predictive_loglik
    gaps = (np.abs(table[:, 2] - mean).max(), np.abs(table[:, 3] / var - 1).max(),
            np.abs(_column(columns, table, "predictive_loglik") - pll).max())
    print(f"continuous OU, increments over 300 random gaps: mean {gaps[0]:.2e}, variance {gaps[1]:.2e}, "
          f"predictive loglik {gaps[2]:.2e}")
    assert gaps[0] < 1e-3 and gaps[1] < 0.01 and gaps[2] < 1e-3


BAD_INPUT = {
    "times not increasing": ("ou_discrete", "t,z\n0.1,1\n0.2,1\n0.3,1\n0.25,1\n", [], "times[3]: ", "line 5"),
    "equal times": ("ou_discrete", "t,z\n0.1,1\n0.1,1\n", [], "times[1]: ", "increase strictly"),
    "NaN time": ("ou_discrete", "t,z\n0.1,1\nnan,1\n", [], "times[1]: ", "line 3"),
    "empty time": ("ou_discrete", "t,z\n0.1,1\n,1\n", [], "times[1]: ", "needs its time"),
    "no t column": ("ou_discrete", "z\n1.0\n2.0\n", [], "observations: ", "must start with the time column"),
    "no header": ("ou_discrete", "0.1,1.0\n0.2,2.0\n", [], "observations: ", "the time column t"),
    "wrong width": ("ou_discrete", "t,z_1,z_2\n0.1,1,2\n", [], "observations: ", "expected t and 1 column"),
    "short row": ("ou_two", "t,a,b\n0.1,1,2\n0.2,1\n", [], "observations[1]: ", "line 3: expected 3 fields"),
    "bad value": ("ou_discrete", "t,z\n0.1,1\n0.2,abc\n", [], "observations[1][0]: ", "line 3"),
    "t0 after the first row": ("ou_discrete", "t,z\n0.1,1\n", ["--t0", "5"], "times[0]: ", "--t0"),
    "increments for a discrete model": ("ou_discrete", "1.0\n2.0\n", ["INCREMENTS"], "increments: ",
                                        "--observations"),
    "continuous row at t0": ("ou", "t,dy\n0.1,0.01\n0.2,0.02\n", [], "observations[0]: ", "--t0"),
    "literal form at random times": ("ou", "t,dy\n0.1,0.01\n0.2,0.02\n",
                                     ["--t0", "0", "--method", "yau-yau", "--form", "literal"], "times: ",
                                     "stable form"),
    "negative gate": ("ou_discrete", "t,z\n0.1,1\n", ["--gate=-1"], "gate: ", "0 turns the gate off"),
    "infinite t0": ("ou_discrete", "t,z\n0.1,1\n", ["--t0", "inf"], "t0: ", "finite"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BAD_INPUT))
def test_bad_input_exits_2_in_one_line_naming_the_row_and_writes_nothing(store, tmp_path, case):
    name, content, extra, field, words = BAD_INPUT[case]
    source = tmp_path / "in.csv"
    source.write_text(content)
    out = tmp_path / "out.csv"
    option = ["--increments", source] if extra[:1] == ["INCREMENTS"] else ["--observations", source, *extra]
    run = _filter(store, name, out, *option, "--density", tmp_path / "d.h5")
    assert run.returncode == 2, (case, run.stderr)
    assert run.stderr.count("\n") == 1 and "Traceback" not in run.stderr, run.stderr
    assert f"error: {field}" in run.stderr and words in run.stderr, run.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv"]  # nothing written


def test_help_documents_formats_options_columns_and_exit_statuses():
    run = _run("filter", "-h")
    assert run.returncode == 0
    for text in ("--observations", "--increments", "header whose first column is t", "--t0", "--gate",
                 "--on-degenerate", "reinitialise", "an empty field is a missing component", "mean_<var>",
                 "cov_<var>_<var>", "loglik", "degenerate", "gated", "predictive_loglik", "reinitialised",
                 "exit status: 0", "2 bad input", "3 the filter degenerated"):
        assert text in run.stdout, text
    simulate = _run("simulate", "-h")
    assert simulate.returncode == 0
    assert "--mean-gap" in simulate.stdout and "observations.csv" in simulate.stdout
