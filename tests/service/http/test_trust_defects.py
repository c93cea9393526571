"""Smaller defects of the "Trust" attack (issue 35, item 7), each against the real parts: the console
script as a subprocess, a real `yauyau serve`, a real Dask scheduler and workers.

* ``POST /v1/models`` answered 500 for every spec of more than 3 states (a mesh-free model plans no
  mesh nodes);
* precompute accepted specs whose offline stage could not be computed in floating point (a failed job
  or a model degenerate from its first step): refused now at the spec, naming the field;
* mixture weights [1e308, 1e308]: the Yau-Hu filter refused them at filter time, after precompute had
  stored the model;
* every Dask worker killed during ``precompute --scheduler``: a 74-line traceback.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib

import httpx
import numpy as np
import pytest
from helpers import EXAMPLES, ROOT
from helpers.cluster import SPEC, Cluster
from helpers.server import Server

PROBLEM = "application/problem+json"
OU = {"name": "ou", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
      "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]}, "domain": {"radius": 6.0},
      "discretization": {"dt": 0.01, "basis": 32}}


def cli(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "yauyau.service.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def wait_for_job(url: str, job: dict, timeout: float = 240.0) -> dict:
    deadline = time.monotonic() + timeout
    while job["status"] == "running" and time.monotonic() < deadline:
        time.sleep(0.3)
        job = httpx.get(url + job["job"], timeout=30).json()
    return job


# -- a model of more than three states over HTTP ----------------------------------------------------
@pytest.mark.service
@pytest.mark.slow
def test_the_4d_example_is_accepted_over_http_and_its_job_completes(tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    spec = tomllib.loads((EXAMPLES / "range_only_4d.toml").read_text())
    server = Server(store, tmp_path / "s.sqlite3")
    try:
        r = httpx.post(server.url + "/v1/models", json={"spec": spec}, timeout=60)
        assert r.status_code == 202, r.text  # was 500: KeyError in fem.default_resolution
        job = wait_for_job(server.url, r.json())
        assert job["status"] == "done" and job["error"] is None, job
        listed = {m["id"]: m for m in httpx.get(server.url + "/v1/models", timeout=30).json()}
        assert listed[job["id"]]["method"] == "yau-jia" and listed[job["id"]]["n"] == 4
        sid = httpx.post(server.url + "/v1/sessions", json={"model": job["id"]}, timeout=30)
        assert sid.status_code == 201, sid.text
    finally:
        server.kill()


def test_a_mesh_free_spec_plans_no_mesh_nodes():
    from yauyau.solver.offline.fem import planned_nodes
    from yauyau.solver.spec import load_spec, spec_from_dict

    assert planned_nodes(load_spec(EXAMPLES / "range_only_4d.toml")) == 0  # 4 states: no mesh
    assert planned_nodes(spec_from_dict({**OU, "method": "kalman-bucy"})) == 0  # no offline arrays
    assert planned_nodes(spec_from_dict(OU)) > 32  # the general engine's mesh


# -- specs whose offline stage cannot be computed: refused at the spec -----------------------------
UNCOMPUTABLE = [
    # h = exp(exp(x)) reaches 1.2e172 on radius 6: h^2 overflows (the solve: "Factor is exactly singular")
    pytest.param({"observation": ["exp(exp(x))"]}, "observation[0]", "overflows", id="exp-exp-observation"),
    # the same as a drift: the propagator made mass x-5e84 from the first step (stored, degenerate)
    pytest.param({"drift": ["exp(exp(x))"]}, "discretization", "unstable", id="exp-exp-drift"),
    # a/h^2 overflows (the propagators were NaN)
    pytest.param({"diffusion": [[1e308]]}, "diffusion", "precision", id="diffusion-1e308"),
    # the elements would be 3e-302 wide: 1/h^2 overflows (NaN propagators)
    pytest.param({"domain": {"radius": 1e-300}}, "domain.radius", "below what the mesh can resolve",
                 id="radius-1e-300"),
    # basis 48: mass x-6e30 from the first step, stored as a model degenerate from its first row
    pytest.param({"drift": ["-x**64"], "domain": {"radius": 7.0},
                  "discretization": {"dt": 0.01, "basis": 48}},
                 "discretization", "unstable", id="x64-basis-48"),
]


@pytest.mark.parametrize("change, field, words", UNCOMPUTABLE)
def test_an_uncomputable_spec_is_refused_by_precompute_naming_the_field(tmp_path, change, field, words):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({**OU, **change}))
    done = cli("precompute", spec, "--store", tmp_path / "store", "--workers", 1)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"error: {field}: " in lines[0] and words in lines[0], done.stderr
    assert not list((tmp_path / "store").glob("*.h5"))


@pytest.mark.service
@pytest.mark.slow
def test_uncomputable_specs_are_refused_over_http_before_any_job(tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    server = Server(store, tmp_path / "s.sqlite3")
    try:
        for param in UNCOMPUTABLE:
            change, field, words = param.values
            r = httpx.post(server.url + "/v1/models", json={"spec": {**OU, **change}}, timeout=60)
            assert r.status_code == 422, (param.id, r.text)
            assert r.headers["content-type"].startswith(PROBLEM)
            body = r.json()
            assert body["field"] == f"spec.{field}" and words in body["detail"], (param.id, body)
        assert httpx.get(server.url + "/v1/models", timeout=30).json() == []
    finally:
        server.kill()
    jobs = store / "jobs"
    assert not jobs.exists() or not list(jobs.iterdir())  # no job was started
    assert not list(store.glob("*.h5"))


def test_a_propagator_that_makes_negative_mass_is_refused_after_the_solve():
    """The backstop after the solve (solver.offline.check_stable): main took mass x-6.3e30 for no
    growth; the spec check above would refuse this one first, so the solver is called directly."""
    from yauyau.solver.errors import SpecError
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline.pipeline import precompute
    from yauyau.solver.spec import spec_from_dict

    doc = {**OU, "drift": ["-x**64"], "domain": {"radius": 7.0}, "discretization": {"dt": 0.01, "basis": 48}}
    with pytest.raises(SpecError) as err:
        precompute(compile_model(spec_from_dict(doc)))
    assert err.value.field == "discretization" and "multiplies the probability mass by -" in err.value.message


@pytest.mark.parametrize("example", sorted(p.name for p in EXAMPLES.glob("*.toml")))
def test_every_bundled_example_is_computable(example):
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline.computable import check_computable
    from yauyau.solver.spec import load_spec

    check_computable(compile_model(load_spec(EXAMPLES / example)))


def test_the_rules_leave_stiff_but_solvable_drifts_alone():
    """Far from the limits of a double: a stiff drift (dt|f|/h ~ 1e3 at the rim, measured stable) is
    the offline stage's to judge (check_stable), not the spec's."""
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline.computable import check_computable
    from yauyau.solver.spec import spec_from_dict

    stiff = {**OU, "drift": ["-x**5"], "discretization": {"dt": 0.01, "basis": 100}}  # mass stays 1 +- 2e-4
    check_computable(compile_model(spec_from_dict(stiff)))


# -- mixture weights that overflow their sum -----------------------------------------------------------
@pytest.mark.slow
def test_huge_mixture_weights_filter_like_unit_weights_with_yau_hu(tmp_path):
    """examples/ou.toml with a two-component mixture prior: ``auto`` chooses Yau-Hu (the prior is not
    Gaussian); weights [1e308, 1e308] are [0.5, 0.5], as the engine takes them."""
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    store = tmp_path / "store"
    assert cli("simulate", EXAMPLES / "ou.toml", "--steps", 300, "--seed", 4, "--out",
               tmp_path / "sim").returncode == 0
    outputs = {}
    for weights in ([1.0, 1.0], [1e308, 1e308]):
        spec = tmp_path / f"mixture-{weights[0]:g}.json"
        prior = {"kind": "mixture", "weights": weights, "means": [[0.0], [2.0]], "covs": [[[0.5]], [[0.3]]]}
        spec.write_text(json.dumps({**doc, "initial": prior}))
        done = cli("precompute", spec, "--store", store, "--workers", 1)
        assert done.returncode == 0, done.stderr
        assert "method yau-hu" in done.stderr, done.stderr
        out = tmp_path / f"out-{weights[0]:g}.csv"
        filtered = cli("filter", done.stdout.strip().splitlines()[-1], "--store", store, "--increments",
                       tmp_path / "sim" / "increments.csv", "--out", out)
        assert filtered.returncode == 0, filtered.stderr  # main: "weight: must be positive"
        outputs[weights[0]] = np.genfromtxt(out, delimiter=",", names=True)
    ones, huge = outputs[1.0], outputs[1e308]
    assert len(ones) == 300
    for column in ("mean_x", "cov_x_x"):
        assert np.max(np.abs(ones[column] - huge[column])) <= 1e-12, column
    # and the equal mixture is what it should be: the first mean is the prior's update, between 0 and 2
    assert 0.0 < ones["mean_x"][0] < 2.0


# -- every Dask worker killed during precompute --scheduler ---------------------------------------------
@pytest.mark.slow
def test_killing_every_dask_worker_ends_precompute_in_one_line(tmp_path):
    from distributed import Client

    cluster = Cluster(tmp_path, 2)
    try:
        spec = tmp_path / "spec.json"
        spec.write_text(json.dumps({**SPEC, "discretization": {"dt": 0.02, "basis": 600}}))
        command = ["precompute", str(spec), "--store", str(tmp_path / "store"), "--scheduler",
                   cluster.address]
        run = subprocess.Popen([sys.executable, "-m", "yauyau.service.cli", *command], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        with Client(cluster.address, timeout="60s") as watcher:
            deadline = time.monotonic() + 240
            while not any(watcher.processing().values()):  # the solves have started on the workers
                assert run.poll() is None and time.monotonic() < deadline, run.communicate()
                time.sleep(0.05)
        for worker in cluster.workers:
            os.kill(worker.pid, signal.SIGKILL)
        _, err = run.communicate(timeout=300)
    finally:
        cluster.close()
    assert run.returncode == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"the Dask cluster at {cluster.address}" in lines[0] and "start workers again" in lines[0], err
    assert not list((tmp_path / "store").glob("*.h5"))
