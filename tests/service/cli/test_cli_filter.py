"""`yauyau filter` through a real HDF5 model store, and the method choice of solver/methods.py.

Truth: the exact sampled-time Kalman filter (solver.reference) on the same increments; the
input/output layout and the error contract (one line naming the row/field, exit 2, no file).
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers import EXAMPLES, ROOT
from scipy.stats import norm
from yauyau.service.cli import main
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.errors import SpecError
from yauyau.solver.methods import make_filter, resolve_method
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate

import yauyau

TWO_D = {"name": "ou-2d-small", "state": ["p", "q"], "drift": ["-p", "-0.5*q"], "observation": ["p", "q"],
         "initial": {"kind": "gaussian", "mean": [0.2, -0.2], "cov": [[0.5, 0.0], [0.0, 0.5]]},
         "domain": {"radius": 5.0}, "discretization": {"dt": 0.02, "basis": 30}}


def _store(directory: Path, spec) -> str:
    return yauyau.precompute(spec, directory)  # the method is chosen here, once


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    directory = tmp_path_factory.mktemp("store")
    ou = load_spec(EXAMPLES / "ou.toml")
    ids = {"ou": _store(directory, ou), "2d": _store(directory, spec_from_dict(TWO_D))}
    return directory, ids, compile_model(ou)


def _filter(store, key, tmp_path, increments_file, *extra) -> tuple[int, Path]:
    directory, ids, _ = store
    out = tmp_path / "out.csv"
    code = main(["filter", ids[key], "--store", str(directory), "--increments", str(increments_file),
                 "--out", str(out), *extra])
    return code, out


def _read(out: Path) -> tuple[list[str], np.ndarray]:
    with out.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) if v else np.nan for v in r] for r in rows[1:]])


@pytest.mark.slow
def test_filter_csv_round_trip_matches_kalman(store, tmp_path):
    _, _, model = store
    dy = simulate(model, 120, np.random.default_rng(21)).increments
    dy[[10, 11]] = np.nan
    lines = ["dy"] + ["" if np.isnan(v) else repr(float(v)) for v in dy[:, 0]]
    source = tmp_path / "in.csv"
    source.write_text("\n".join(lines) + "\n\n")  # header, blank lines = missing, trailing blank ignored
    code, out = _filter(store, "ou", tmp_path, source, "--method", "yau-yau")  # the spec says auto
    assert code == 0
    columns, table = _read(out)
    assert columns == ["step", "t", "mean_x", "cov_x_x", "loglik", "degenerate", "gated", "predictive_loglik",
                       "reinitialised"]
    assert np.array_equal(table[:, 0], np.arange(1, 121)) and np.allclose(table[:, 1], 0.01 * table[:, 0])
    kalman = DiscreteKalmanFilter(model)
    _, ref = kalman.run(kalman.initial_state(), dy)
    assert np.max(np.abs(table[:, 2] - [e.mean[0] for e in ref])) < 1e-3
    assert np.max(np.abs(table[:, 3] / [e.cov[0, 0] for e in ref] - 1)) < 0.01
    assert np.max(np.abs(table[:, 4] - [e.loglik for e in ref])) < 1e-3
    assert abs(table[10, 4] - table[9, 4]) < 1e-6  # a missing row adds no likelihood
    assert not table[:, 5].any() and not table[:, 6].any() and not table[:, 8].any()
    # predictive log-likelihood log p(dy_k | dy_1..k-1): the Kalman loglik's increment (relative to the
    # Wiener measure) plus log N(dy_k; 0, R dt); empty (NaN here) on the missing rows
    seen = ~np.isnan(dy[:, 0])
    expected = np.diff([e.loglik for e in ref], prepend=0.0) + norm.logpdf(dy[:, 0], 0.0,
                                                                           np.sqrt(model.R[0, 0] * model.dt))
    assert np.isnan(table[~seen, 7]).all()
    assert np.max(np.abs(table[seen, 7] - expected[seen])) < 1e-3
    # the same data as .npy, in chunks of 7: the identical file
    npy = tmp_path / "in.npy"
    np.save(npy, dy)
    first = out.read_bytes()
    code, out = _filter(store, "ou", tmp_path, npy, "--chunk", "7", "--method", "yau-yau")
    assert code == 0 and out.read_bytes() == first
    code, out = _filter(store, "ou", tmp_path, npy, "--method", "yau-yau", "--precision", "single")
    _, single = _read(out)
    assert code == 0 and np.max(np.abs(single[:, 2] - [e.mean[0] for e in ref])) < 1e-3


def test_filter_two_dimensional_layout(store, tmp_path):
    model = compile_model(spec_from_dict(TWO_D))
    dy = simulate(model, 30, np.random.default_rng(2)).increments
    source = tmp_path / "in.csv"
    source.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in dy) + "\n ,\n")
    code, out = _filter(store, "2d", tmp_path, source, "--method", "yau-yau")
    assert code in (0, 3)  # basis 30 is coarse: it may degenerate (exit 3), the layout is the point
    columns, table = _read(out)
    assert columns == ["step", "t", "mean_p", "mean_q", "cov_p_p", "cov_p_q", "cov_q_q", "loglik",
                       "degenerate", "gated", "predictive_loglik", "reinitialised"]
    assert table.shape == (31, 12) and np.all(np.isfinite(table[:, :10]))
    assert np.isnan(table[-1, 10]) and np.isfinite(table[:30, 10][table[:30, 8] == 0]).all()
    assert table[-1, 7] == pytest.approx(table[-2, 7], abs=1e-3)  # last row missing (coarse basis)


@pytest.mark.parametrize("content, field", [
    ("dy\n0.1\n0.2,0.3\n", "increments[1]: line 3"),
    ("0.1\nabc\n", "increments[1][0]: line 2"),
    ("0.1\n0.2\ninf\n", "increments[2][0]: line 3"),
    ("0.1\nnan\n", "increments[1][0]: line 2"),
])
def test_bad_input_one_line_exit_2_no_output(store, tmp_path, capsys, content, field):
    source = tmp_path / "bad.csv"
    source.write_text(content)
    code, out = _filter(store, "ou", tmp_path, source)
    err = capsys.readouterr().err
    assert code == 2 and not out.exists()
    assert err.count("\n") == 1 and field in err  # input is checked before anything else is said


@pytest.mark.parametrize("content, field", [
    ("0.1,abc\n0.2,0.3\n", "increments[0][1]: line 1"),  # used to be taken for a header: every step shifted
    ("abc,0.1\n0.2,0.3\n", "increments[0][0]: line 1"),
])
def test_malformed_first_row_is_an_error_not_a_header(store, tmp_path, capsys, content, field):
    source = tmp_path / "bad.csv"
    source.write_text(content)
    code, out = _filter(store, "2d", tmp_path, source)
    err = capsys.readouterr().err
    assert code == 2 and not out.exists() and field in err


def test_header_of_text_is_skipped_and_rows_keep_their_steps(store, tmp_path):
    source = tmp_path / "in.csv"
    source.write_text("dy_p,dy_q\n0.01,0.02\n0.03,-0.01\n")
    code, out = _filter(store, "2d", tmp_path, source, "--method", "yau-yau")
    columns, table = _read(out)
    assert code == 0 and table.shape[0] == 2 and list(table[:, 0]) == [1.0, 2.0]


@pytest.mark.slow
def test_filter_uses_the_stored_method_says_so_and_never_analyses(store, tmp_path):
    """The method is chosen at precompute: `yauyau filter` prints it and does not load the analysis."""
    import json
    import os
    import subprocess
    import sys

    directory, ids, model = store
    source = tmp_path / "in.npy"
    np.save(source, simulate(model, 5, np.random.default_rng(1)).increments)
    code = ("import sys, json; from yauyau.service.cli import main; code = main(sys.argv[1:]); "
            "print(json.dumps({'code': code, 'analysis': 'yauyau.solver.analysis' in sys.modules}))")
    root = str(ROOT)
    out = subprocess.run([sys.executable, "-c", code, "filter", ids["ou"], "--store", str(directory),
                          "--increments", str(source), "--out", str(tmp_path / "o.csv")],
                         capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=root), timeout=120)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["code"] == 0 and not result["analysis"], out.stderr
    assert "yauyau filter: method kalman-bucy (stored at precompute: f and h are affine" in out.stderr


# the hot path's BLAS threads, read by a spy around filter_rows, in a fresh process: under pytest-xdist a
# worker's earlier tests can leave OpenBLAS capped (a fresh CI run once read 1 thread for --blas-threads 2)
_SPY = """
import json, sys
from threadpoolctl import threadpool_info
from yauyau.service.cli import filter as command
real, seen = command.filter_rows, []
def spy(*args, **kwargs):
    seen.extend(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")
    return real(*args, **kwargs)
command.filter_rows = spy
from yauyau.service.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "seen": seen}))
"""


@pytest.mark.parametrize("flag, threads", [([], 1), (["--blas-threads", "2"], 2)])
def test_blas_threads_of_the_hot_path(store, tmp_path, flag, threads):
    import json
    import os
    import subprocess
    import sys

    directory, ids, _ = store
    source = tmp_path / "in.csv"
    source.write_text("0.1\n")
    root = str(ROOT)
    out = subprocess.run([sys.executable, "-c", _SPY, "filter", ids["ou"], "--store", str(directory),
                          "--increments", str(source), "--out", str(tmp_path / "o.csv"),
                          "--method", "yau-yau", *flag], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=root), timeout=120)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["code"] == 0 and result["seen"] and set(result["seen"]) == {threads}, out.stderr


def test_blas_threads_refused_when_not_positive(store, tmp_path, capsys, monkeypatch):
    source = tmp_path / "in.csv"
    source.write_text("0.1\n")
    code, _ = _filter(store, "ou", tmp_path, source, "--blas-threads", "0")
    assert code == 2 and "blas_threads" in capsys.readouterr().err
    monkeypatch.setenv("YAUYAU_BLAS_THREADS", "many")
    code, _ = _filter(store, "ou", tmp_path, source)
    assert code == 2 and "YAUYAU_BLAS_THREADS" in capsys.readouterr().err


def test_partly_missing_2d_rows_and_missing_model(store, tmp_path, capsys):
    """A partly missing row (empty field): the general engine marginalises it; a form that cannot take
    it (the literal form of (5.35): the potential inside the stored propagator) refuses it up front, in
    one line naming the row, its line and the fix, before anything else is said or written."""
    source = tmp_path / "partial.csv"
    source.write_text("0.1,0.2\n0.1,\n")
    code, out = _filter(store, "2d", tmp_path, source, "--method", "yau-yau", "--form", "literal")
    err = capsys.readouterr().err
    assert code == 2 and not out.exists() and err.count("\n") == 1
    assert "error: increments[1] (line 2): " in err and "stable form" in err
    code, out = _filter(store, "2d", tmp_path, source, "--method", "yau-yau")
    assert code == 0, capsys.readouterr().err
    _, table = _read(out)
    assert table.shape == (2, 12) and np.isfinite(table[1, 10])  # the observed component counts
    out.unlink()
    directory, _, _ = store
    code = main(["filter", "0" * 20, "--store", str(directory), "--increments", str(source),
                 "--out", str(tmp_path / "x.csv")])
    assert code == 2 and "model" in capsys.readouterr().err
    npy = tmp_path / "bad.npy"
    np.save(npy, np.array([[0.1], [np.inf]]))
    code, out = _filter(store, "ou", tmp_path, npy)
    assert code == 2 and not out.exists() and "increments[1]" in capsys.readouterr().err


def test_exact_method_through_the_cli(store, tmp_path):
    _, _, model = store
    dy = simulate(model, 40, np.random.default_rng(4)).increments
    source = tmp_path / "in.npy"
    np.save(source, dy)
    code, out = _filter(store, "ou", tmp_path, source, "--method", "kalman-bucy")
    assert code == 0
    _, exact = _read(out)
    code, out = _filter(store, "ou", tmp_path, source, "--method", "yau-yau")
    _, engine = _read(out)
    # continuous Kalman–Bucy vs the sampled-time engine: both O(dt) from each other
    assert np.max(np.abs(exact[:, 2] - engine[:, 2])) < 5 * model.dt


# -- method choice ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cubic():
    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    return model, precompute(model)


@pytest.mark.slow
def test_make_filter_methods(store, cubic):
    _, _, ou = store
    model, offline = cubic
    assert resolve_method(ou, "auto") == "kalman-bucy"  # linear model, Gaussian prior
    assert make_filter(ou, None, "auto").method == "kalman-bucy"
    assert resolve_method(model) == "yau-yau"  # examples/cubic_sensor.toml: method auto
    flt = make_filter(model, offline)
    assert isinstance(flt, YauYauFilter) and flt.form == "stable"
    assert make_filter(model, offline, "yau-yau", form="literal").form == "literal"
    for method, offline_arg in (("kalman-bucy", offline), ("yau-yau", None), ("magic", offline)):
        with pytest.raises(SpecError) as err:
            make_filter(model, offline_arg, method)
        assert err.value.field == "method"


@pytest.mark.slow
def test_auto_picks_the_exact_yau_hu_filter_for_benes():
    """Beneš (f = tanh x, h = x, a = 1) is a Yau filtering system (seed 000): exact filter, no offline."""
    model = compile_model(load_spec(EXAMPLES / "benes.toml"))
    assert make_filter(model, None, "auto").method == "yau-hu"


def test_spec_method_is_honoured(cubic):
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["method"] = "yau-yau"
    model = compile_model(spec_from_dict(doc))
    assert resolve_method(model) == "yau-yau"
    with pytest.raises(SpecError):
        make_filter(model)  # yau-yau without the offline arrays


def test_the_fast_csv_paths_read_and_write_the_same_numbers():
    """numpy's parse of a plain file and orjson's formatting of a chunk give exactly the numbers the
    line-by-line paths give (floats round-trip bit for bit); anything unusual takes the slow path."""
    import numpy as np
    from yauyau.service.cli import csv_io as cli
    from yauyau.solver.filtering import ChunkResult

    rng = np.random.default_rng(0)
    values = rng.normal(size=(50, 2)) * 10.0 ** rng.integers(-8, 8, size=(50, 2))
    text = "dy1,dy2\n" + "\n".join(f"{a!r},{b!r}" for a, b in values.tolist()) + "\n"
    numbers: list[int] = []
    fast = cli.parse_plain(text, 2, numbers)
    assert fast is not None and np.array_equal(fast, values) and numbers == list(range(2, 52))
    for unusual in ("1,2\n\n3,4\n", "1,\n3,4\n", "1,2\n3,nan\n", "1,2,3\n4,5\n", "1,2\n3\n"):
        assert cli.parse_plain(unusual, 2, None) is None  # blank line, empty field, nan, widths
    K = 7
    result = ChunkResult(step=np.arange(1, K + 1), t=0.01 * np.arange(1, K + 1), mean=rng.normal(size=(K, 2)),
                         cov=rng.normal(size=(K, 2, 2)) * 1e-7, mode=None,
                         loglik=np.cumsum(rng.normal(size=K)), loglik_increment=np.zeros(K),
                         degenerate=np.arange(K) >= 5,
                         predictive_loglik=np.where(np.arange(K) == 2, np.nan, rng.normal(size=K)))
    i, j = np.triu_indices(2)
    fast_lines = cli.fast_lines(result, i, j)
    slow_lines = cli.csv_lines(result, [[] for _ in range(K)])  # with (empty) extras: the line-by-line path
    for a, b in zip(fast_lines, slow_lines, strict=True):
        fa, fb = a.split(","), b.split(",")
        assert [float(x) if x else None for x in fa] == [float(x) if x else None for x in fb]
    inf = ChunkResult(**{**result.__dict__, "predictive_loglik": np.full(K, -np.inf)})
    assert cli.csv_lines(inf)[0].split(",")[-2] == "-inf"  # an impossible row keeps its -inf


@pytest.mark.parametrize("key", ["ou", "2d"])
def test_a_timed_file_given_to_increments_suggests_observations(store, tmp_path, capsys, key):
    """simulate --mean-gap writes observations.csv (t, dy_1..dy_m): given to --increments its times would be
    read as increments; exit 2, nothing written, and the option the message names reads the file."""
    directory, ids, _ = store
    spec = EXAMPLES / "ou.toml" if key == "ou" else tmp_path / "2d.json"
    if key == "2d":
        spec.write_text(json.dumps(TWO_D))
    assert main(["simulate", str(spec), "--steps", "20", "--mean-gap", "0.05", "--out", str(tmp_path)]) == 0
    timed = tmp_path / "observations.csv"
    capsys.readouterr()
    code, out = _filter(store, key, tmp_path, timed)
    err = capsys.readouterr().err
    assert code == 2 and not out.exists() and err.count("\n") == 1, err
    assert "error: increments:" in err and f"--observations {timed}" in err and "--t0 0" in err, err
    assert main(["filter", ids[key], "--store", str(directory), "--observations", str(timed), "--t0", "0",
                 "--out", str(out)]) == 0
    assert len(_read(out)[1]) == 20


def _imports_numba(store, model_id: str, rows: Path, kernel: str | None) -> bool:
    env = {k: v for k, v in os.environ.items() if k != "YAUYAU_KERNEL"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    if kernel:
        env["YAUYAU_KERNEL"] = kernel
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "yauyau.service.cli", "filter", model_id,
                           "--store", str(store), "--increments", str(rows), "--out",
                           str(rows.with_suffix(".out.csv"))], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    written = rows.with_suffix(".out.csv").read_text().splitlines()
    assert len(written) == 1 + len(rows.read_text().splitlines())
    names = [line.split("|")[-1].strip() for line in done.stderr.splitlines()
             if line.startswith("import time:")]
    return any(name == "numba" or name.startswith("numba.") for name in names)


def test_a_short_input_takes_the_numpy_kernel_and_never_imports_numba(example_store, tmp_path):
    """Below jit.COMPILED_MIN_ROWS rows numba's start-up costs more than its loops save
    (bench/results/startup.md): `filter` takes the numpy path unless YAUYAU_KERNEL says otherwise."""
    from yauyau.solver import jit

    store, ids = example_store
    rows = tmp_path / "in.csv"
    rows.write_text("0.01\n-0.02\n0.03\n")
    assert not _imports_numba(store, ids["cubic_sensor"], rows, None)
    assert _imports_numba(store, ids["cubic_sensor"], rows, "compiled")
    assert jit.COMPILED_MIN_ROWS > 3


def test_the_kernel_choice_for_a_one_shot_run(monkeypatch):
    from yauyau.solver import jit

    monkeypatch.delenv("YAUYAU_KERNEL", raising=False)
    monkeypatch.setattr(jit, "_chosen", {})
    assert jit.choose_for_rows(10) == "numpy" and not jit.enabled()
    assert jit.choose_for_rows(jit.COMPILED_MIN_ROWS) == "compiled" and jit.enabled()
    assert jit.choose_for_rows(400, min_rows=300) == "compiled"  # a filter whose rows save more
    monkeypatch.setenv("YAUYAU_KERNEL", "compiled")  # the user's choice wins
    assert jit.choose_for_rows(10) == "compiled"
    monkeypatch.setenv("YAUYAU_KERNEL", "numpy")
    assert jit.choose_for_rows(10**9) == "numpy"
    monkeypatch.delenv("YAUYAU_KERNEL")
    with jit.one_shot():
        assert jit.choose_for_rows(10) == "numpy" and not jit.enabled()
    assert jit.enabled()  # the choice ended with the command


def test_an_in_process_filter_leaves_the_kernel_as_it_found_it(example_store, tmp_path, monkeypatch):
    from yauyau.solver import jit

    monkeypatch.delenv("YAUYAU_KERNEL", raising=False)
    store, ids = example_store
    rows = tmp_path / "in.csv"
    rows.write_text("0.01\n")
    assert main(["filter", ids["cubic_sensor"], "--store", str(store), "--increments", str(rows),
                 "--out", str(tmp_path / "out.csv")]) == 0
    assert jit.enabled() and not jit._chosen
