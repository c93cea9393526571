"""Micro-batching in the service (service/sessions/batching.py, Sessions.observe_many).

* The executor: chunks that queue while one batch computes form the next batch, one chunk per
  session (a pipelined next chunk waits for the next batch), a reset keeps its place in the order,
  each answer goes to its own caller.
* ``observe_many``: chunks of several sessions in one call give the answers that observing each
  alone gives (the engine's batch tolerance, solver/engine/batch.py), exactly once, and one bad chunk
  (wrong seq, wrong width, a degenerate one re-initialised by its policy) changes nothing of the others.
* A real uvicorn process with concurrent streams: every stream matches the exact Kalman filter,
  and the server did step chunks together (its batch-size histogram).
"""

from __future__ import annotations

import re
import threading
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from helpers import EXAMPLES
from helpers.server import Server, session_db
from yauyau.service.http.app import create_app
from yauyau.service.sessions.batching import ChunkBatcher
from yauyau.service.sessions.manager import ChunkRequest
from yauyau.service.settings import Settings
from yauyau.solver.engine.batch import BATCH_RTOL
from yauyau.solver.errors import InputError
from yauyau.solver.model import compile_model
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec
from yauyau.storage.errors import Conflict


class _Chunk:
    def __init__(self, session_id, name):
        self.session_id, self.name = session_id, name


def test_the_executor_batches_what_queued_one_chunk_per_session_in_order():
    gate, batches, calls = threading.Event(), [], []

    def apply_many(requests):
        if not batches:
            gate.wait(10)
        batches.append([r.name for r in requests])
        return [ValueError(r.name) if r.name == "B1" else r.name.lower() for r in requests]

    batcher = ChunkBatcher(apply_many)
    first = batcher.submit_chunk(_Chunk("x", "X"))
    while batcher._queue.qsize():  # until the thread took X (it then waits for the gate)
        pass
    futures = {name: batcher.submit_chunk(_Chunk(name[0], name)) for name in ("A1", "B1", "A2")}
    call = batcher.submit(lambda: calls.append(list(batches)) or "reset")
    futures["C1"] = batcher.submit_chunk(_Chunk("C", "C1"))
    gate.set()
    assert first.result(10) == "x"
    assert call.result(10) == "reset"
    assert futures["A1"].result(10) == "a1" and futures["A2"].result(10) == "a2"
    assert futures["C1"].result(10) == "c1"
    with pytest.raises(ValueError, match="B1"):
        futures["B1"].result(10)
    batcher.shutdown()
    assert batches == [["X"], ["A1", "B1"], ["A2"], ["C1"]]
    assert calls == [[["X"], ["A1", "B1"], ["A2"]]]  # the reset ran after A2, before C1


@pytest.fixture(scope="module")
def api(example_store, tmp_path_factory):
    store, ids = example_store
    db = tmp_path_factory.mktemp("db") / "sessions.sqlite3"
    app = create_app(Settings(store=store, session_db=db))
    with TestClient(app, raise_server_exceptions=False) as client:
        client.ids = ids
        yield client


def _rows(block):
    return [None if np.isnan(r[0]) else r.tolist() for r in block]


def test_observe_many_answers_as_each_chunk_alone(api):
    sessions = api.app.state.sessions
    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    data = [simulate(model, 80, np.random.default_rng(40 + i)).increments for i in range(6)]
    data[2][10] = np.nan
    data[4][30] = 1e6  # impossible: degenerates (the gate is off for this session), then re-initialises

    def create(i):
        options = {"on_degenerate": "reinitialise", "gate": 0} if i == 4 else {}
        return sessions.create(api.ids["cubic_sensor"], None, "yau-yau", **options)["id"]

    twins = [create(i) for i in range(6)]
    batched = [create(i) for i in range(6)]
    first = None
    for seq, block in enumerate((slice(0, 50), slice(50, 80))):
        alone = [orjson.loads(sessions.observe(s, seq, _rows(d[block]), True))
                 for s, d in zip(twins, data, strict=True)]
        first = first or alone
        requests = [ChunkRequest(s, seq, _rows(d[block])) for s, d in zip(batched, data, strict=True)]
        answers = sessions.observe_many(requests + [ChunkRequest("no-such-session", 0, _rows(data[0][:3]))])
        assert isinstance(answers[6], Exception)
        for a, b in zip(alone, answers[:6], strict=True):
            b = orjson.loads(b)
            assert [r["step"] for r in a["estimates"]] == [r["step"] for r in b["estimates"]]
            assert [r.get("reason") for r in a["estimates"]] == [r.get("reason") for r in b["estimates"]]
            mean_a = np.array([r["mean"] if r["mean"] else [np.nan] for r in a["estimates"]], dtype=float)
            mean_b = np.array([r["mean"] if r["mean"] else [np.nan] for r in b["estimates"]], dtype=float)
            np.testing.assert_allclose(mean_b, mean_a, rtol=BATCH_RTOL["double"], atol=1e-12, equal_nan=True)
            assert a["reinitialised"] == b["reinitialised"] and a["degenerate"] == b["degenerate"]
        gap = sessions.observe_many([ChunkRequest(batched[0], seq + 2, _rows(data[0][:3]))])[0]
        assert isinstance(gap, Conflict)  # a gap: 409, nothing applied
    assert first[4]["reinitialised"] == [30]  # the policy ran (alone) in both
    # a replay of the batched chunk is the stored bytes; a wrong width names its row
    replay = sessions.observe_many([ChunkRequest(batched[1], 1, _rows(data[1][50:80]))])[0]
    assert replay == sessions.store._stored_text(batched[1], 1)
    bad = sessions.observe_many([ChunkRequest(batched[0], 2, [[1.0, 2.0]]),
                                 ChunkRequest(batched[1], 2, _rows(data[1][:5]))])
    assert isinstance(bad[0], InputError) and bad[0].field == "increments[0]"
    assert orjson.loads(bad[1])["step"] == 85


@pytest.mark.service
@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_concurrent_streams_on_real_servers_match_kalman_and_are_batched(example_store, tmp_path, request,
                                                                         kind):
    """SQLite: one server.  PostgreSQL: two servers on different ports (two hosts) sharing the
    database, each stream alternating between them chunk by chunk."""
    store, ids = example_store
    model = compile_model(load_spec(EXAMPLES / "ou.toml"))
    kalman = DiscreteKalmanFilter(model)
    streams, chunk, chunks = 24, 25, 8
    data = [simulate(model, chunk * chunks, np.random.default_rng(70 + i)).increments for i in range(streams)]
    db = session_db(kind, request, tmp_path)
    servers = [Server(store, db) for _ in range(1 if kind == "sqlite" else 2)]
    server = servers[0]
    try:
        with httpx.Client(timeout=60) as client:
            sids = [client.post(server.url + "/v1/sessions", json={"model": ids["ou"], "method": "yau-yau"}
                                ).json()["id"] for _ in range(streams)]

            def run(i):
                means = []
                with httpx.Client(timeout=60) as own:
                    for seq in range(chunks):
                        rows = _rows(data[i][seq * chunk:(seq + 1) * chunk])
                        host = servers[(i + seq) % len(servers)]
                        url = f"{host.url}/v1/sessions/{sids[i]}/observations"
                        r = own.post(url, json={"seq": seq, "increments": rows})
                        assert r.status_code == 200, r.text
                        means += [e["mean"][0] for e in r.json()["estimates"]]
                        if i == 0 and seq == 3:  # a gap from one client: its own 409, nobody else's
                            assert own.post(url, json={"seq": 9, "increments": rows}).status_code == 409
                return np.array(means)

            with ThreadPoolExecutor(streams) as pool:
                results = list(pool.map(run, range(streams)))
            texts = [client.get(one.url + "/metrics").text for one in servers]
    finally:
        for one in servers:
            one.kill()
    for i, means in enumerate(results):
        _, ref = kalman.run(kalman.initial_state(), data[i])
        assert np.max(np.abs(means - np.array([e.mean[0] for e in ref]))) < 1e-3
    count = sum(float(re.search(r"yauyau_chunk_batch_size_count (\S+)", text).group(1)) for text in texts)
    total = sum(float(re.search(r"yauyau_chunk_batch_size_sum (\S+)", text).group(1)) for text in texts)
    assert total == streams * chunks + 1  # every chunk (and the refused gap) went through one batch
    assert count < total  # and some batches held several chunks
