"""Models added at run time (service/models/jobs.py): POST /v1/models precomputes in the background.

The served model is the one ``yauyau.precompute`` makes of the same spec (the same content hash),
and a session on it matches the exact Kalman filter (the spec is linear).  The same spec twice is
one job; oversize and invalid specs are refused before any work; a job whose process died is
reported and can be started again.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from yauyau.service.http.app import create_app
from yauyau.service.models.jobs import Jobs
from yauyau.service.settings import Settings
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.storage.model_store import model_id

SPEC = {"name": "ou-runtime", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
        "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[0.5]]}, "domain": {"radius": 6.0},
        "discretization": {"dt": 0.01, "basis": 48}, "method": "yau-yau"}
PROBLEM = "application/problem+json"


@pytest.fixture
def api(tmp_path):
    settings = Settings(store=tmp_path / "store", session_db=tmp_path / "s.sqlite3", max_precompute_basis=500,
                        max_precompute_nodes=2000)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        yield client


def _wait(api, url, timeout=120.0):
    deadline, seen = time.monotonic() + timeout, []
    while time.monotonic() < deadline:
        job = api.get(url).json()
        seen.append(job["progress"])
        if job["status"] != "running":
            return job, seen
        time.sleep(0.2)
    raise AssertionError(f"job {url} still running after {timeout} s")


@pytest.mark.slow
def test_a_spec_posted_is_precomputed_in_the_background_and_served(api):
    expected = model_id(spec_from_dict(SPEC).canonical_json())
    first = api.post("/v1/models", json={"spec": SPEC})
    assert first.status_code == 202, first.text
    body = first.json()
    assert body["id"] == expected and body["status"] == "running" and first.headers["location"] == body["job"]
    again = api.post("/v1/models", json={"spec": SPEC})  # the same spec: the same job, not a second one
    assert again.status_code in (200, 202) and again.json()["id"] == expected
    assert expected not in [m["id"] for m in api.get("/v1/models").json()] or again.status_code == 200
    job, seen = _wait(api, body["job"])
    assert job["status"] == "done" and job["error"] is None and job["progress"] == 1.0
    assert all(0.0 <= p <= 1.0 for p in seen) and seen == sorted(seen)
    assert expected in [m["id"] for m in api.get("/v1/models").json()]
    assert api.post("/v1/models", json={"spec": SPEC}).status_code == 200  # stored: nothing to do
    # a session on the new model: the exact Kalman filter's answer (the model is linear)
    model = compile_model(spec_from_dict(SPEC))
    increments = simulate(model, 200, np.random.default_rng(5)).increments
    sid = api.post("/v1/sessions", json={"model": expected}).json()["id"]
    r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 0, "increments": increments.tolist()})
    assert r.status_code == 200, r.text
    kalman = DiscreteKalmanFilter(model)
    _, ref = kalman.run(kalman.initial_state(), increments)
    means = np.array([e["mean"][0] for e in r.json()["estimates"]])
    assert np.max(np.abs(means - np.array([e.mean[0] for e in ref]))) < 2e-3


@pytest.mark.parametrize("change, status, field", [
    ({"discretization": {"dt": 0.01, "basis": 800}}, 413, "spec.discretization.basis"),
    ({"discretization": {"dt": 0.01, "basis": 48, "mesh": 3000}}, 413, "spec.discretization.mesh"),
    ({"drift": ["sin(x)"], "domain": {"radius": 6.0, "follow": True, "region": [[0.0, 300.0]]}}, 413,
     "spec.domain.region"),
    ({"method": "yau-niu", "discretization": {"dt": 0.01, "basis": 48, "points": 10**13}}, 413,
     "spec.discretization.points"),
    ({"drift": ["__import__('os')"]}, 422, "spec.drift[0]"),
    ({"domain": {"radius": -1.0}}, 422, "spec.domain.radius"),
    # the steady-state Kalman-Bucy covariance of a model that is not linear: refused now, not a failed job
    ({"observation": ["atan(x/5)"], "domain": {"radius": 6.0, "shape": "posterior"}}, 422,
     "spec.domain.shape"),
])
def test_oversize_or_invalid_specs_are_refused_before_any_work(api, change, status, field, tmp_path):
    r = api.post("/v1/models", json={"spec": {**SPEC, **change}})
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    assert r.json()["field"].startswith(field), r.json()
    assert not (tmp_path / "store" / "jobs").exists() or not list((tmp_path / "store" / "jobs").iterdir())
    assert api.get("/v1/jobs/0123456789abcdef0123").status_code == 404


def test_a_point_budget_beyond_memory_is_413_naming_need_limit_and_fix(api):
    """yau-niu's arrays for 10^13 points would not fit (about 2 PB against this machine's memory):
    413 problem+json naming the field, both sizes and the largest budget that fits, before any job."""
    from yauyau.solver.qmc.budget import memory_limit, memory_needed

    spec = {**SPEC, "method": "yau-niu", "discretization": {"dt": 0.01, "basis": 48, "points": 10**13}}
    r = api.post("/v1/models", json={"spec": spec})
    assert r.status_code == 413 and r.headers["content-type"].startswith(PROBLEM), r.text
    body = r.json()
    detail = body["detail"]
    assert body["field"] == "spec.discretization.points" and body["status"] == 413
    assert f"{memory_needed(10**13, 1, 1) / 2**30:.1f} GiB" in detail
    assert f"{memory_limit() / 2**30:.1f} GiB this machine has" in detail
    assert "set discretization.points to at most" in detail
    fits = int(detail.split("at most ")[1].split()[0])
    ok = {**spec, "discretization": {**spec["discretization"], "points": fits}}
    from yauyau.service.models.jobs import _check_point_budget

    _check_point_budget(spec_from_dict(ok))  # the budget it names is accepted (no job started here)


def test_a_job_whose_process_died_is_reported_and_started_again(tmp_path, monkeypatch):
    import yauyau.service.models.jobs as jobs_module

    jobs = Jobs(tmp_path / "store", 500, 2000)
    mid = model_id(spec_from_dict(SPEC).canonical_json())
    (tmp_path / "store" / "jobs").mkdir(parents=True)
    dead = {"id": mid, "status": "running", "progress": 0.3, "updated": time.time() - 3600, "pid": 1}
    (tmp_path / "store" / "jobs" / f"{mid}.json").write_text(json.dumps(dead))
    assert jobs.status(mid)["status"] == "failed" and "died" in jobs.status(mid)["error"]
    started = []
    monkeypatch.setattr(jobs_module.subprocess, "Popen", lambda *a, **k: started.append(a) or _Fake())
    job, fresh = jobs.submit(SPEC)
    assert fresh and job["status"] == "running" and len(started) == 1
    job, fresh = jobs.submit(SPEC)  # running now: the same job
    assert not fresh and len(started) == 1


class _Fake:
    pid = 12345

    def wait(self):  # the dispatcher waits for its job processes to end (no process here)
        return 0


def test_a_silent_job_whose_process_holds_its_lock_is_alive(tmp_path, monkeypatch):
    """The eigensolve holds the GIL for minutes: no heartbeat, but the job's lock says it runs."""
    import subprocess
    import sys

    import yauyau.service.models.jobs as jobs_module

    jobs = Jobs(tmp_path / "store", 500, 2000)
    mid = model_id(spec_from_dict(SPEC).canonical_json())
    directory = tmp_path / "store" / "jobs"
    directory.mkdir(parents=True)
    silent = {"id": mid, "status": "running", "progress": 0.1, "updated": time.time() - 3600}
    (directory / f"{mid}.json").write_text(json.dumps(silent))
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'a'); "
                               "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
                               str(directory / f"{mid}.lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert jobs.status(mid)["status"] == "running"
        monkeypatch.setattr(jobs_module.subprocess, "Popen", lambda *a, **k: pytest.fail("started twice"))
        job, fresh = jobs.submit(SPEC)
        assert not fresh and job["status"] == "running"
    finally:
        holder.kill()
        holder.wait()
    assert jobs.status(mid)["status"] == "failed"  # the process is gone and the file silent: dead


def test_of_many_requests_taking_over_a_dead_job_one_wins(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    jobs = Jobs(tmp_path / "store", 500, 2000)
    directory = tmp_path / "store" / "jobs"
    directory.mkdir(parents=True)
    for attempt in range(5):
        mid = f"{attempt:020d}"
        (directory / f"{mid}.json").write_text(json.dumps({"id": mid, "status": "failed", "error": "x"}))
        job = {"id": mid, "status": "running", "updated": time.time()}
        with ThreadPoolExecutor(8) as pool:
            won = list(pool.map(lambda _, mid=mid, job=job: jobs._claim(mid, job), range(8)))
        assert sum(won) == 1, won
        assert json.loads((directory / f"{mid}.json").read_text())["status"] == "running"
    assert not list(directory.glob("*.tmp"))
