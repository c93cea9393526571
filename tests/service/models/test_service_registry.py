"""`yauyau serve` starts without loading models: they are listed from the files' attributes, loaded
on first use and kept in a bounded cache; the online products run with one BLAS thread per worker.

Truth: the prior N(1, 0.5) of the Ornstein–Uhlenbeck example (its first estimate) and the method the
estimation-algebra analysis chose at precompute (linear model, Gaussian prior: Kalman–Bucy).
"""

from __future__ import annotations

import shutil

import pytest
from fastapi.testclient import TestClient
from helpers import EXAMPLES, ROOT
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings

import yauyau


@pytest.fixture()
def store(example_store, tmp_path):
    source, ids = example_store
    target = tmp_path / "store"
    target.mkdir()
    for mid in ids.values():
        shutil.copy(source / f"{mid}.h5", target / f"{mid}.h5")
    return target, ids


def _client(store, tmp_path, **settings):
    return TestClient(create_app(Settings(store=store, session_db=tmp_path / "s.sqlite3", **settings)),
                      raise_server_exceptions=False)


def test_start_up_loads_no_model_and_lists_them_from_attributes(store, tmp_path):
    directory, ids = store
    with _client(directory, tmp_path) as api:
        registry = api.app.state.registry
        assert api.get("/readyz").json() == {"status": "ready", "models": 2}
        listed = {m["id"]: m for m in api.get("/v1/models").json()}
        assert registry.loads == 0 and registry.loaded_ids() == []  # listing reads attributes only
        assert listed[ids["ou"]]["method"] == "kalman-bucy" and listed[ids["ou"]]["state"] == ["x"]
        assert listed[ids["cubic_sensor"]]["method"] == "yau-yau"
        created = api.post("/v1/sessions", json={"model": ids["ou"]})
        assert created.status_code == 201 and created.json()["method"] == "kalman-bucy"
        assert created.json()["estimate"]["mean"][0] == pytest.approx(1.0)
        assert created.json()["estimate"]["cov"][0][0] == pytest.approx(0.5)
        assert registry.loaded_ids() == [ids["ou"]] and registry.loads == 1


def test_the_listing_and_the_detail_show_the_summary_stored_at_precompute(tmp_path, monkeypatch):
    """GET /v1/models and GET /v1/models/{id} show the summary the file holds (computed once, when it
    was written: storage/model_store.py), not one computed again from the model: a file whose stored
    summary names the model otherwise is shown with that name by both."""
    from yauyau.storage import model_store

    computed = model_store.spec_summary
    monkeypatch.setattr(model_store, "spec_summary", lambda *args: {**computed(*args), "name": "as stored"})
    mid = yauyau.precompute(EXAMPLES / "ou.toml", tmp_path / "store")
    monkeypatch.undo()
    with _client(tmp_path / "store", tmp_path) as api:
        [listed] = api.get("/v1/models").json()
        detail = api.get(f"/v1/models/{mid}").json()
    assert listed["name"] == detail["name"] == "as stored" and detail["spec"]["name"] == "ornstein-uhlenbeck"
    assert [listed[key] for key in ("n", "m", "dt", "radius", "basis")] == [1, 1, 0.01, 8.0, 96]
    assert {key: value for key, value in detail.items() if key != "spec"} == listed


def test_the_cache_is_bounded_and_an_evicted_model_comes_back(store, tmp_path):
    directory, ids = store
    with _client(directory, tmp_path, model_cache=1) as api:
        registry = api.app.state.registry
        first = api.post("/v1/sessions", json={"model": ids["ou"]}).json()["id"]
        api.post("/v1/sessions", json={"model": ids["cubic_sensor"]})
        assert registry.loaded_ids() == [ids["cubic_sensor"]]  # the least recently used was dropped
        chunk = api.post(f"/v1/sessions/{first}/observations", json={"seq": 0, "increments": [[0.01]]})
        assert chunk.status_code == 200 and registry.loaded_ids() == [ids["ou"]] and registry.loads == 3


def test_an_unreadable_model_is_listed_with_its_error_and_refused_on_use(store, tmp_path):
    directory, ids = store
    (directory / f"{ids['ou']}.h5").write_bytes(b"not an HDF5 file")
    with _client(directory, tmp_path) as api:
        listed = {m["id"]: m for m in api.get("/v1/models").json()}
        assert listed[ids["ou"]]["error"] and "method" not in listed[ids["ou"]]
        r = api.post("/v1/sessions", json={"model": ids["ou"]})
        assert r.status_code == 503 and r.headers["content-type"].startswith("application/problem+json")
        assert "corrupt or unreadable" in r.json()["detail"]
        assert api.post("/v1/sessions", json={"model": ids["cubic_sensor"]}).status_code == 201


_WORKER = """
import json, sys
from fastapi.testclient import TestClient
from threadpoolctl import threadpool_info
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings
settings = Settings(store=sys.argv[1], session_db=sys.argv[2], blas_threads=int(sys.argv[3]),
                    allowed_hosts="testserver")
with TestClient(create_app(settings)) as api:
    assert api.get("/readyz").status_code == 200
    # after a chunk too: the engine's products run in scipy's own BLAS, loaded with the first model
    listing = api.get("/v1/models")
    assert listing.status_code == 200, listing.text
    model = listing.json()[0]["id"]
    sid = api.post("/v1/sessions", json={"model": model}).json()["id"]
    chunk = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 0, "increments": [[0.01]] * 20})
    assert chunk.status_code == 200, chunk.text
    loaded = [p for p in threadpool_info() if p["user_api"] == "blas"]
    assert any("scipy_openblas-" in p["filepath"] or "scipy" in p["filepath"] for p in loaded), loaded
    print(json.dumps(sorted({p["num_threads"] for p in loaded})))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_the_worker_runs_its_blas_with_the_configured_threads(store, tmp_path, threads):
    """In a process of its own: BLAS thread counts are process-wide, and other tests change them."""
    import json
    import os
    import subprocess
    import sys

    directory, _ = store
    root = str(ROOT)
    env = {k: v for k, v in os.environ.items()
           if not k.endswith("_NUM_THREADS") and not k.startswith("YAUYAU_")}
    args = [str(directory), str(tmp_path / "s.sqlite3"), str(threads)]
    out = subprocess.run([sys.executable, "-c", _WORKER, *args], capture_output=True, text=True,
                         env=dict(env, PYTHONPATH=root), timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [threads]


def test_precompute_records_why_it_chose(store):
    directory, ids = store
    summaries = {s.id: s for s in yauyau.ModelStore(directory).list()}
    assert "affine" in summaries[ids["ou"]].extra["method_reason"]
