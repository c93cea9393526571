"""The service's fast path: stored JSON text sent as is, orjson encoding, SQLite durability setting.

Truth: floats must come back bit for bit (the identity, checked on awkward values: subnormals,
-0.0, the largest double, shortest-repr edge cases); a replay must return the very bytes of the
first answer; SQLite itself reports the synchronous level set; NaN and infinity never reach the
database or the wire.
"""

from __future__ import annotations

import json
import math
import sqlite3
import struct
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import EXAMPLES
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec
from yauyau.storage.errors import StoreError
from yauyau.storage.session_store import SqliteSessionStore

AWKWARD = [5e-324, -0.0, 1.7976931348623157e308, 0.1, 1 / 3, 2.0**-1074 * 3, 123456789.12345678, 1e-310,
           9007199254740993.0, -2.2250738585072014e-308]


def _bits(values):
    return [struct.pack("<d", v) for v in values]


def test_floats_round_trip_bit_for_bit(tmp_path: Path):
    rng = np.random.default_rng(0)
    values = AWKWARD + (rng.standard_normal(500) * 10.0 ** rng.integers(-300, 300, 500)).tolist()
    store = SqliteSessionStore(tmp_path / "s.sqlite")
    sid = store.create("m", "x", {"c": values, "nested": [[values[0]], [values[1]]]})
    back = store.get(sid).state
    assert _bits(back["c"]) == _bits(values)
    assert _bits([back["nested"][0][0], back["nested"][1][0]]) == _bits(values[:2])


@pytest.mark.parametrize("bad", [{"c": [1.0, math.nan]}, {"c": [[1.0], [math.inf]]}, {"c": {"d": -math.inf}},
                                 {"c": [np.float64("nan")]}, {"c": np.zeros(2)}])
def test_non_finite_or_foreign_states_are_refused(tmp_path: Path, bad):
    store = SqliteSessionStore(tmp_path / "s.sqlite")
    sid = store.create("m", "x", {"v": 0})
    with pytest.raises(StoreError) as err:
        store.apply_chunk(sid, 0, lambda s: (bad, {}))
    assert err.value.field == "state" and store.get(sid).next_seq == 0


def test_large_finite_values_whose_sum_overflows_are_kept(tmp_path: Path):
    store = SqliteSessionStore(tmp_path / "s.sqlite")
    sid = store.create("m", "x", {"c": [1.7e308, 1.7e308, -1.0]})
    assert store.get(sid).state["c"] == [1.7e308, 1.7e308, -1.0]


def test_encoded_apply_and_replay_return_the_same_bytes(tmp_path: Path):
    store = SqliteSessionStore(tmp_path / "s.sqlite")
    sid = store.create("m", "x", {"values": []})

    def compute(state):
        values = state["values"] + [len(state["values"])]
        return {"values": values, "step": len(values), "t": 0.1 * len(values)}, {"seq": 0, "mean": [1 / 3]}

    text, replayed = store.apply_chunk(sid, 0, compute, encoded=True)
    assert not replayed and json.loads(text) == {"seq": 0, "mean": [1 / 3]}
    again, replayed = store.apply_chunk(sid, 0, compute, encoded=True)
    assert replayed and again == text
    assert store.apply_chunk(sid, 0, compute) == ({"seq": 0, "mean": [1 / 3]}, True)
    rec = store.get(sid)
    assert (rec.next_seq, rec.step, rec.t) == (1, 1, 0.1)


def test_a_response_encoded_by_the_caller_is_stored_as_given(tmp_path: Path):
    store = SqliteSessionStore(tmp_path / "s.sqlite")
    sid = store.create("m", "x", {"step": 0})
    text = '{"seq":0,"note":"as given"}'
    assert store.apply_chunk(sid, 0, lambda s: ({"step": 4, "t": 0.4, "loglik": -1.5}, text)) == (
        {"seq": 0, "note": "as given"}, False)
    assert store.apply_chunk(sid, 0, lambda s: ({}, "{}"), encoded=True) == (text, True)
    rec = store.get(sid)
    assert (rec.step, rec.t, rec.loglik) == (4, 0.4, -1.5)  # progress columns from the state


@pytest.mark.parametrize("level, code", [("normal", 1), ("full", 2)])
def test_synchronous_level_is_what_sqlite_reports(tmp_path: Path, level, code):
    store = SqliteSessionStore(tmp_path / "s.sqlite", synchronous=level)
    assert store._connection().execute("PRAGMA synchronous").fetchone()[0] == code
    assert sqlite3.connect(store.path).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_unknown_synchronous_level_is_refused(tmp_path: Path, monkeypatch):
    with pytest.raises(StoreError) as err:
        SqliteSessionStore(tmp_path / "s.sqlite", synchronous="off")
    assert err.value.field == "synchronous"
    monkeypatch.setenv("YAUYAU_SESSION_SYNCHRONOUS", "full")
    assert Settings().session_synchronous == "full"
    monkeypatch.setenv("YAUYAU_SESSION_SYNCHRONOUS", "sometimes")
    with pytest.raises(ValueError, match="session_synchronous"):
        Settings()


@pytest.fixture(scope="module")
def api(example_store, tmp_path_factory):
    store, ids = example_store
    db = tmp_path_factory.mktemp("db") / "sessions.sqlite3"
    settings = Settings(store=store, session_db=db, session_synchronous="full")
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.ids = ids
        yield client


def test_chunk_answers_are_strict_json_and_replays_are_byte_identical(api):
    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    increments = simulate(model, 200, np.random.default_rng(1)).increments
    increments[30:40] = np.nan
    sid = api.post("/v1/sessions", json={"model": api.ids["cubic_sensor"]}).json()["id"]
    answers = []
    for seq in range(2):
        rows = [None if np.isnan(r[0]) else r.tolist() for r in increments[seq * 100:(seq + 1) * 100]]
        r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows})
        assert r.status_code == 200 and r.headers["content-type"] == "application/json"
        answers.append((rows, r.content))
    for seq, (rows, content) in enumerate(answers):
        again = api.post(f"/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows})
        assert again.content == content
    body = json.loads(answers[1][1], parse_constant=lambda c: pytest.fail(f"{c} in a response"))
    assert [e["step"] for e in body["estimates"]] == list(range(101, 201))
    assert body["estimates"][-1]["t"] == pytest.approx(2.0, abs=1e-12)
    # far outside the ball: the outlier gate (on by default) rejects the rows, no NaN token
    r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 2, "increments": [[1e6]] * 3})
    body = json.loads(r.content, parse_constant=lambda c: pytest.fail(f"{c} in a response"))
    assert r.status_code == 200 and body["degenerate"] is False and body["gated"] == [0, 1, 2]
    assert all(e["gated"] is True and "gated" in e["reason"] for e in body["estimates"])
    # the gate off: the same rows make the density degenerate, still no NaN token, and a replay of the
    # degenerate answer is the same bytes
    off = api.post("/v1/sessions", json={"model": api.ids["cubic_sensor"], "gate": 0}).json()["id"]
    assert api.get(f"/v1/sessions/{off}").json()["options"]["gate"] == 0.0
    chunk = {"seq": 0, "increments": [[1e6]] * 3}
    r = api.post(f"/v1/sessions/{off}/observations", json=chunk)
    body = json.loads(r.content, parse_constant=lambda c: pytest.fail(f"{c} in a response"))
    assert r.status_code == 200 and body["degenerate"] is True and body["gated"] == []
    assert body["reason"] and all(e["degenerate"] is True for e in body["estimates"])
    assert api.post(f"/v1/sessions/{off}/observations", json=chunk).content == r.content
