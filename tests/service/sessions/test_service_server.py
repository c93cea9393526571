"""A real `yauyau serve` process: SIGKILL mid-stream loses nothing and applies nothing twice.

Two sessions get the same prior and the same chunks: one uninterrupted, one whose server is
killed (SIGKILL, no clean shutdown) while a chunk is in flight and restarted with two workers
sharing the SQLite session store.  The client re-sends the chunk whose answer it lost (and later
one it did get an answer for); the interrupted session's estimates must be identical (==) to
the uninterrupted one's.
"""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.server import Server, session_db
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

pytestmark = pytest.mark.service  # a real `yauyau serve` process

CHUNK = 50
CHUNKS = 8


def _rows(block):
    return [None if np.isnan(r[0]) else r.tolist() for r in block]


def _post_chunk(client, url, sid, seq, rows):
    r = client.post(f"{url}/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows},
                    timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def _create(client, url: str, body: dict) -> str:
    """A new session's id (a refusal fails with the server's answer: one run on a loaded CI machine got
    no id here and said nothing more)."""
    answer = client.post(url + "/v1/sessions", json=body)
    assert answer.status_code == 201, (answer.status_code, answer.text)
    return answer.json()["id"]


@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_sigkill_mid_stream_then_restart_gives_identical_estimates(example_store, tmp_path, request, kind):
    """SQLite: the restarted server has two workers sharing the file.  PostgreSQL: two servers on
    different ports (two hosts) share the database, and the client alternates between them."""
    store, ids = example_store
    db = session_db(kind, request, tmp_path)
    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    increments = simulate(model, CHUNK * CHUNKS, np.random.default_rng(3)).increments
    increments[120:130] = np.nan
    chunks = [_rows(increments[i * CHUNK:(i + 1) * CHUNK]) for i in range(CHUNKS)]
    body = {"model": ids["cubic_sensor"], "prior": {"kind": "gaussian", "mean": [0.3], "cov": [[0.8]]}}

    server = Server(store, db)
    servers = [server]
    try:
        with httpx.Client() as client:
            reference = _create(client, server.url, body)
            expected = [_post_chunk(client, server.url, reference, k, c) for k, c in enumerate(chunks)]
            sid = _create(client, server.url, body)
            got = [_post_chunk(client, server.url, sid, k, chunks[k]) for k in range(3)]

        # kill 1: while chunk 3 is in flight (it may or may not have been applied)
        def send_lost_chunk():
            try:
                httpx.post(f"{server.url}/v1/sessions/{sid}/observations",
                           json={"seq": 3, "increments": chunks[3]}, timeout=30)
            except httpx.TransportError:
                pass
        sender = threading.Thread(target=send_lost_chunk)
        sender.start()
        time.sleep(0.005)
        server.kill()
        sender.join()

        servers[:] = [Server(store, db, workers=2)] if kind == "sqlite" else [Server(store, db) for _ in "ab"]

        def url(k):
            return servers[k % len(servers)].url

        with httpx.Client() as client:
            got += [_post_chunk(client, url(k), sid, k, chunks[k]) for k in (3, 4)]
            _post_chunk(client, url(5), sid, 5, chunks[5])  # answered, but say the answer was lost
            got += [_post_chunk(client, url(k + 1), sid, k, chunks[k]) for k in (5, 6, 7)]  # the other host
            assert _post_chunk(client, url(0), sid, 7, chunks[7]) == got[7]  # a replay changes nothing
            gap = client.post(f"{url(1)}/v1/sessions/{sid}/observations",
                              json={"seq": 9, "increments": chunks[0]})
            assert gap.status_code == 409
            assert gap.headers["content-type"].startswith("application/problem+json")
            info = client.get(f"{url(1)}/v1/sessions/{sid}").json()
    finally:
        for one in servers:
            one.kill()

    assert got == expected  # identical floats, not approximately equal
    assert (info["step"], info["next_seq"]) == (CHUNK * CHUNKS, CHUNKS)
    assert info["estimate"]["mean"] == expected[-1]["estimates"][-1]["mean"]
