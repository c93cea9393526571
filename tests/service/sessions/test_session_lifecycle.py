"""Sessions over HTTP: listed a page at a time, deleted after their idle expiry by the service's
sweeper (a real SQLite file; the store's own guarantees are in tests/storage/test_session_store.py)."""

from __future__ import annotations

import time

from fastapi.testclient import TestClient
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings


def _client(store, db, **settings):
    app = create_app(Settings(store=store, session_db=db, **settings))
    return TestClient(app, raise_server_exceptions=False)


def test_sessions_are_paged_and_filtered_by_model(example_store, tmp_path):
    store, ids = example_store
    with _client(store, tmp_path / "s.sqlite3") as api:
        made = {api.post("/v1/sessions", json={"model": ids["ou" if i % 2 else "cubic_sensor"]}).json()["id"]
                for i in range(7)}
        seen, after = [], None
        while True:
            page = api.get("/v1/sessions", params={"limit": 3, **({"after": after} if after else {})}).json()
            seen += [s["id"] for s in page["sessions"]]
            after = page["next"]
            if after is None:
                break
        assert seen == sorted(made) and page["idle_expiry"] == 7 * 86_400
        ou = api.get("/v1/sessions", params={"model": ids["ou"]}).json()["sessions"]
        assert len(ou) == 3 and {s["model"] for s in ou} == {ids["ou"]}
        assert set(ou[0]) == {"id", "model", "method", "step", "t", "next_seq", "created", "updated"}
        bad = api.get("/v1/sessions", params={"limit": 0})
        assert bad.status_code == 422 and bad.headers["content-type"].startswith("application/problem+json")


def test_idle_sessions_are_swept_and_active_ones_kept(example_store, tmp_path):
    store, ids = example_store
    with _client(store, tmp_path / "s.sqlite3", session_idle_expiry=1.0, session_sweep=0.1) as api:
        idle = api.post("/v1/sessions", json={"model": ids["ou"]}).json()["id"]
        active = api.post("/v1/sessions", json={"model": ids["ou"]}).json()["id"]
        deadline = time.monotonic() + 3.0
        seq = 0
        while time.monotonic() < deadline:  # one chunk every 0.2 s keeps it alive
            r = api.post(f"/v1/sessions/{active}/observations", json={"seq": seq, "increments": [[0.01]]})
            assert r.status_code == 200, r.text
            seq += 1
            time.sleep(0.2)
        assert api.get(f"/v1/sessions/{idle}").status_code == 404
        assert api.get(f"/v1/sessions/{active}").json()["next_seq"] == seq
        assert "yauyau_sessions_expired_total 1.0" in api.get("/metrics").text
