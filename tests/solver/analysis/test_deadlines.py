"""Time limits that hold everywhere the analysis runs (issue 35, item 5), and spec files read within
their size limit.

The attack spec (nested trigonometric functions in 3-D) sends SymPy's ``simplify`` into minutes when
the analysis has time left to tidy its report: ``yauyau analyze --time-limit 5`` ran past 60 s and a
``POST /v1/models`` job 6.5 min against a 60 s limit.  Now the analysis runs in a child process killed
2 s after its limit (solver/analysis/isolated.py), and the caller gets the bounded report.  The tests
assert that report (the limit named in it, the general engine chosen); how long past the limit a run
ends depends on the machine's load and is measured by bench/deadlines.py.  The subprocesses' timeouts
are hang guards only (the limit, the grace and a minute or more of slack; before the fix, minutes).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from helpers import ROOT
from helpers.server import Server

GRACE = 2.0
STARTUP = 30.0  # seconds of slack for starting the CLI and the analysis process on a loaded machine

ATTACK = {
    "name": "attack", "state": ["x", "y", "z"],
    "drift": ["-tanh(x+y)**9*cos(z)**9", "-exp(sin(y*z))", "-atan(x*y*z)**7"],
    "observation": ["sin(x*y*z)**64"],
    "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0],
                "cov": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
    "domain": {"radius": 3.0}, "discretization": {"dt": 0.01, "basis": 8}}
# SymPy's term order follows the hash seed; with this one, today's main hangs in simplify every time
# (the fixed code does not care)
SEEDED = {"PYTHONHASHSEED": "0"}


def cli(*args: str, timeout: float, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "yauyau.service.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})})


def attack_file(tmp_path: Path, **changes) -> Path:
    path = tmp_path / "attack.json"
    path.write_text(json.dumps({**ATTACK, **changes}))
    return path


def assert_bounded(report: dict, limit: float) -> None:
    """The report of an analysis stopped by one of its bounds: the general engine, and the bound named
    — the time limit (the conditions not decided within it, the process stopped at it, or the algebra
    stopped by it), or the algebra's expression-size guard, which an idle fast machine reaches first
    (the final CI run of stop 46, an unloaded AVX-512 machine: "expression size 4000" within 2 s; under
    load the 2 s come first).  That the run ends near the limit is the subprocess timeout's business."""
    assert report["recommendation"]["method"] == "yau-yau", report["recommendation"]
    named = (f"within time {limit:g} s", f"time limit of {limit:g} s")
    stopped_by = report["estimation_algebra"]["stopped_by"] or ""
    assert (any(any(words in note for words in named) for note in report["notes"])
            or stopped_by == f"time {limit:g} s" or stopped_by.startswith("expression size")), report


@pytest.mark.slow
@pytest.mark.parametrize("limit, extra", [
    (2.0, []),
    # depth 1: the conditions and the algebra end early, so the report is tidied with time left: on
    # main sp.simplify of the Wong matrix then ran for minutes
    (20.0, ["--max-depth", "1"]),
])
def test_analyze_keeps_its_time_limit_on_the_attack_spec(tmp_path, limit, extra):
    done = cli("analyze", attack_file(tmp_path), "--time-limit", limit, *extra, "--json",
               timeout=limit + GRACE + STARTUP + 60, env=SEEDED)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert_bounded(report, limit)
    assert report["estimation_algebra"]["closed"] is False


@pytest.mark.slow
def test_precompute_auto_stores_the_general_engine_within_the_time_limit(tmp_path):
    limit = 20.0
    store = tmp_path / "store"
    done = cli("precompute", attack_file(tmp_path), "--store", store, "--workers", 1,
               "--time-limit", limit, timeout=limit + GRACE + STARTUP + 120, env=SEEDED)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    import yauyau

    assert yauyau.load_model(store, done.stdout.strip().splitlines()[-1]).method == "yau-yau"


@pytest.mark.service
@pytest.mark.slow
def test_a_posted_model_job_keeps_the_analysis_time_limit(tmp_path):
    """POST /v1/models on a real server: the job's analysis is stopped at its setting
    (YAUYAU_PRECOMPUTE_TIME_LIMIT) + YAUYAU_ANALYZE_GRACE and the job ends done with the general
    engine, not after minutes."""
    limit = 20.0
    store = tmp_path / "store"
    store.mkdir()
    env = {"YAUYAU_PRECOMPUTE_TIME_LIMIT": str(limit), **SEEDED}
    server = Server(store, tmp_path / "s.sqlite3", env=env)
    try:
        posted = time.monotonic()
        r = httpx.post(server.url + "/v1/models", json={"spec": ATTACK}, timeout=60)
        assert r.status_code == 202, r.text
        job = r.json()
        deadline = posted + limit + GRACE + STARTUP + 60
        while job["status"] == "running" and time.monotonic() < deadline:
            time.sleep(0.5)
            job = httpx.get(server.url + job["job"], timeout=30).json()
        assert job["status"] == "done", job
        detail = httpx.get(f"{server.url}/v1/models/{job['id']}", timeout=30).json()
        assert detail["method"] == "yau-yau", detail
    finally:
        server.kill()


@pytest.mark.slow
def test_the_library_precompute_keeps_its_time_limit_in_a_script_without_a_main_guard(tmp_path):
    """yauyau.precompute from a plain script (no ``if __name__ == "__main__"``): the analysis process
    (a fork of the script, or a fresh Python) does not run the script again, as a spawned one would."""
    script = tmp_path / "plain.py"
    marker = tmp_path / "runs.txt"
    script.write_text(
        "import yauyau\n"
        f"open({str(marker)!r}, 'a').write('run\\n')\n"
        f"print(yauyau.precompute({str(ROOT / 'examples' / 'ou.toml')!r}, {str(tmp_path / 'store')!r}, "
        "time_limit=30))\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert marker.read_text() == "run\n"
    import yauyau

    assert yauyau.load_model(tmp_path / "store", done.stdout.strip()).method == "kalman-bucy"


# -- spec files are read within their size limit ---------------------------------------------------------
@pytest.mark.parametrize("command", [
    ["analyze"], ["precompute", "--store", "{tmp}/store"], ["simulate", "--steps", "2", "--out", "{tmp}/sim"],
    ["check"]])
def test_an_endless_spec_stream_is_refused_at_the_size_limit(tmp_path, command):
    """/dev/zero never ends: main read it whole (memory and time without bound)."""
    args = [a.replace("{tmp}", str(tmp_path)) for a in command]
    done = cli(args[0], "/dev/zero", *args[1:], timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "/dev/zero" in lines[0] and "65536 bytes" in lines[0], done.stderr


def test_a_huge_spec_file_is_read_only_to_the_limit(tmp_path):
    from yauyau.solver.errors import SpecError
    from yauyau.solver.spec import MAX_SPEC_BYTES, load_spec

    big = tmp_path / "big.toml"
    with open(big, "wb") as handle:
        handle.truncate(1 << 34)  # 16 GiB, sparse: reading it whole would take the machine's memory
    with pytest.raises(SpecError) as err:
        load_spec(big)
    assert err.value.field == "spec" and str(big) in err.value.message
    assert f"{MAX_SPEC_BYTES} bytes" in err.value.message
    exact = tmp_path / "exact.toml"
    exact.write_text("#" * (MAX_SPEC_BYTES - 1) + "\n")  # at the limit: read, then refused as a spec
    with pytest.raises(SpecError) as err:
        load_spec(exact)
    assert "larger than" not in err.value.message
