"""docs/service.md's "Many streams" section runs as printed: its Python block (16 streams stepped together)
and its curl walk-through against a real `yauyau serve`.

Truth: the block's streams are Ornstein–Uhlenbeck (linear), so the printed mean and variance are the
exact Kalman filter's on the same increments; the model the curl block adds is the one
``yauyau.precompute`` makes of the same spec (the same content hash).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time

import httpx
import pytest
from helpers import ROOT
from helpers.readme import doc_section, env, json_objects, run_python_block
from helpers.server import Server

pytestmark = pytest.mark.slow  # every test here takes seconds of CPU: the full run only

PAGE = "docs/service.md"
SECTION = "Many streams, several hosts, models at run time"


def test_python_block_matches_the_kalman_filter(tmp_path):
    from yauyau.solver.reference.kalman import DiscreteKalmanFilter

    import yauyau

    stdout = run_python_block(SECTION, tmp_path, PAGE)
    found = re.search(r"t = ([\d.]+): mean (-?[\d.]+), variance ([\d.]+)", stdout)
    t, mean, var = map(float, found.groups())
    spec = yauyau.load_spec(ROOT / "examples" / "ou.toml")
    kalman = DiscreteKalmanFilter(yauyau.compile_model(spec))
    _, ref = kalman.run(kalman.initial_state(), yauyau.simulate(spec, steps=200, seed=3).increments)
    assert t == 2.0 and abs(mean - ref[-1].mean[0]) < 1e-3 and abs(var / ref[-1].cov[0, 0] - 1) < 0.01


@pytest.mark.service
def test_curl_block_adds_a_model_to_a_running_server(tmp_path):
    assert shutil.which("curl"), "curl is needed (python3 dev.py test installs it)"
    from yauyau.solver.spec import spec_from_dict
    from yauyau.storage.model_store import model_id

    block = [b for b in re.findall(r"```sh\n(.*?)```", _section(), re.S) if "curl" in b][0]
    spec = json.loads(re.search(r"-d '(.*?)'", block, re.S).group(1))["spec"]
    mid = model_id(spec_from_dict(spec).canonical_json())
    store = tmp_path / "store"
    store.mkdir()
    server = Server(store, tmp_path / "sessions.sqlite3")
    try:
        script = block.replace("localhost:8000", f"127.0.0.1:{server.port}").replace("MID", mid)
        out = subprocess.run(["bash", "-c", "set -euo pipefail\n" + script], capture_output=True, text=True,
                             timeout=120, env=env())
        assert out.returncode == 0, out.stderr
        started, job, page = json_objects(out.stdout)
        assert started["id"] == mid and started["status"] in ("running", "done")
        assert job["id"] == mid and job["status"] in ("running", "done")
        assert page["sessions"] == [] and page["next"] is None and page["idle_expiry"] == 604800
        deadline = time.monotonic() + 120
        while httpx.get(f"{server.url}/v1/jobs/{mid}").json()["status"] == "running":
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert mid in [m["id"] for m in httpx.get(f"{server.url}/v1/models").json()]
    finally:
        server.kill()


def _section() -> str:
    return doc_section(SECTION, PAGE)
