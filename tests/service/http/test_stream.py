"""The WebSocket stream ``/v1/sessions/{id}/stream`` (issue 37, item 4) against a real `yauyau serve`
process, with a real WebSocket client (websocket-client), and the chunk route's fast path
(service/http/chunk_path.py) beside it.

Truth: the POST route's rules.  A chunk sent over the socket is applied exactly once (its answer is
the very bytes POST returns for that seq, and a re-sent seq over either gets them again); a gap or
other data under a used seq is a 409 problem, a bad message a 4xx problem naming the field, and the
session is unchanged by either; the socket stays usable after a problem; answers come in the order
of the messages; the handshake is refused with the problem+json an HTTP request gets (401 without a
tenant's token, 404 for another tenant's session); a message over the body cap closes the socket
with 1009; no frame holds a NaN token.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import struct

import httpx
import pytest
import websocket
from helpers.server import Server

ROWS = [[0.01 * ((i * 7) % 5 - 2)] for i in range(20)]


def strict(text: str) -> dict:
    """JSON without NaN/Infinity tokens."""
    def refuse(token):
        raise AssertionError(f"{token} in a frame")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture
def served(example_store, tmp_path):
    """A server with tenants alice and bob: (server, {name: token}, model id)."""
    store, ids = example_store
    tokens = {name: secrets.token_urlsafe(24) for name in ("alice", "bob")}
    path = tmp_path / "tenants.toml"
    path.write_text("".join(f'[[tenant]]\nname = "{name}"\ntoken_sha256 = '
                            f'"{hashlib.sha256(token.encode()).hexdigest()}"\n\n'
                            for name, token in tokens.items()))
    server = Server(store, tmp_path / "sessions.sqlite3",
                    env={"YAUYAU_TENANTS_FILE": str(path), "YAUYAU_MAX_BODY_BYTES": "4096"})
    try:
        yield server, tokens, ids["cubic_sensor"]
    finally:
        server.kill()


def _auth(token):
    return {"Authorization": f"Bearer {token}"} if token else {}


def _session(server, token, model):
    r = httpx.post(server.url + "/v1/sessions", json={"model": model}, headers=_auth(token), timeout=120)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _connect(server, sid, token):
    return websocket.create_connection(f"ws://127.0.0.1:{server.port}/v1/sessions/{sid}/stream",
                                       header=[f"Authorization: Bearer {token}"], timeout=60)


def _step(server, sid, token):
    return httpx.get(f"{server.url}/v1/sessions/{sid}", headers=_auth(token), timeout=30).json()["step"]


def test_stream_applies_chunks_exactly_once_with_the_post_rules(served):
    server, tokens, model = served
    alice = tokens["alice"]
    sid = _session(server, alice, model)
    ws = _connect(server, sid, alice)
    try:
        ws.send(json.dumps({"seq": 0, "increments": ROWS}))
        first = ws.recv()
        answer = strict(first)
        assert answer["seq"] == 0 and len(answer["estimates"]) == len(ROWS)
        # the same seq again, over the socket and over POST: the stored answer, byte for byte
        ws.send(json.dumps({"seq": 0, "increments": ROWS}))
        assert ws.recv() == first
        posted = httpx.post(f"{server.url}/v1/sessions/{sid}/observations", headers=_auth(alice),
                            json={"seq": 0, "increments": ROWS}, timeout=30)
        assert posted.status_code == 200 and posted.text == first
        step = _step(server, sid, alice)
        assert step == len(ROWS)
        # problems: each names the field, carries the seq, leaves the session and the socket as they were
        bad = [({"seq": 3, "increments": ROWS}, 409, "seq"),
               ({"seq": 0, "increments": ROWS[:5]}, 409, None),
               ({"seq": 1, "increments": [[0.1], ["x"]]}, 422, "increments[1][0]"),
               ({"seq": 1, "increments": [[0.1, 0.2]]}, 422, "increments[0]"),
               ({"seq": 1, "increments": ROWS, "extra": 1}, 422, "extra"),
               ({"seq": -1, "increments": ROWS}, 422, "seq")]
        for message, status, field in bad:
            ws.send(json.dumps(message))
            problem = strict(ws.recv())
            assert problem["status"] == status, problem
            assert problem["seq"] == message["seq"] and problem["detail"]
            if field is not None:
                assert problem["field"] == field, problem
        ws.send("[1.0, NaN")  # not JSON
        problem = strict(ws.recv())
        assert problem["status"] == 400 and problem["field"] == "body" and "seq" not in problem
        ws.send(b'{"seq": 1, "increments": [[NaN]]}', opcode=websocket.ABNF.OPCODE_BINARY)
        assert strict(ws.recv())["status"] in (400, 422)
        assert _step(server, sid, alice) == step
        # sent ahead: five chunks, then their answers, in order
        for seq in range(1, 6):
            ws.send(json.dumps({"seq": seq, "increments": ROWS}))
        assert [strict(ws.recv())["seq"] for _ in range(5)] == [1, 2, 3, 4, 5]
        assert _step(server, sid, alice) == 6 * len(ROWS)
    finally:
        ws.close()
    # a new socket goes on where the last one stopped (and replays what it sent)
    ws = _connect(server, sid, alice)
    try:
        ws.send(json.dumps({"seq": 5, "increments": ROWS}))
        assert strict(ws.recv())["seq"] == 5
        assert _step(server, sid, alice) == 6 * len(ROWS)
    finally:
        ws.close()


def test_handshake_is_guarded_like_the_other_session_routes(served):
    server, tokens, model = served
    sid = _session(server, tokens["alice"], model)
    url = f"ws://127.0.0.1:{server.port}/v1/sessions/{sid}/stream"
    with pytest.raises(websocket.WebSocketBadStatusException) as err:
        websocket.create_connection(url, timeout=30)
    assert err.value.status_code == 401
    assert json.loads(err.value.resp_body)["field"] == "Authorization"
    with pytest.raises(websocket.WebSocketBadStatusException) as err:  # bob: alice's session does not exist
        _connect(server, sid, tokens["bob"])
    assert err.value.status_code == 404
    with pytest.raises(websocket.WebSocketBadStatusException) as err:
        _connect(server, "no-such-session", tokens["alice"])
    assert err.value.status_code == 404 and json.loads(err.value.resp_body)["detail"]
    assert _step(server, sid, tokens["alice"]) == 0


def test_a_message_over_the_body_cap_closes_with_1009(served):
    server, tokens, model = served
    sid = _session(server, tokens["alice"], model)
    ws = _connect(server, sid, tokens["alice"])
    try:
        ws.send(json.dumps({"seq": 0, "increments": [[0.001]] * 2000}))  # ~16 KB over a 4 KB cap
        frame = ws.recv_data_frame(control_frame=True)[1]
        assert frame.opcode == websocket.ABNF.OPCODE_CLOSE
        assert struct.unpack("!H", frame.data[:2])[0] == 1009
    finally:
        ws.close()
    assert _step(server, sid, tokens["alice"]) == 0


def test_post_fast_path_answers_problems_as_the_route_did(served):
    """The fast path (no FastAPI routing) gives the problems the FastAPI route gave."""
    server, tokens, model = served
    sid = _session(server, tokens["alice"], model)
    url = f"{server.url}/v1/sessions/{sid}/observations"
    r = httpx.post(url, json={"seq": 0, "increments": ROWS}, timeout=30)  # no token
    assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
    r = httpx.post(url, json={"seq": 0, "increments": ROWS}, headers=_auth(tokens["bob"]), timeout=30)
    assert r.status_code == 404
    r = httpx.post(url, content=b"", headers={**_auth(tokens["alice"]), "Content-Type": "application/json"},
                   timeout=30)
    assert r.status_code == 400 and r.json()["field"] == "body"
    r = httpx.post(url, json={"seq": 0, "increments": [[0.1], [True]]}, headers=_auth(tokens["alice"]),
                   timeout=30)
    assert r.status_code == 422 and r.json()["field"] == "increments[1][0]"
    assert r.headers["content-type"].startswith("application/problem+json")
    r = httpx.post(url, json={"seq": 0, "increments": ROWS}, headers=_auth(tokens["alice"]), timeout=30)
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"


def test_the_documented_python_block_runs(example_store, tmp_path):
    """docs/service.md's WebSocket block, against a real server (its placeholders filled in)."""
    import subprocess
    import sys

    from helpers.readme import env, readme_block

    store, ids = example_store
    server = Server(store, tmp_path / "sessions.sqlite3")
    try:
        sid = _session(server, "", ids["cubic_sensor"])
        block = readme_block("A WebSocket stream per session", page="docs/service.md")
        block = block.replace("localhost:8000", f"127.0.0.1:{server.port}").replace("SID", sid)
        out = subprocess.run([sys.executable, "-c", block], env=env(), capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        lines = out.stdout.split("\n")
        assert lines[0].startswith("0 2 [") and lines[1].startswith("1 4 [")
    finally:
        server.kill()


def test_streams_are_capped_per_session(example_store, tmp_path):
    """A second socket on a session at YAUYAU_MAX_SESSION_LISTENERS = 1 is refused with 429 at the
    handshake; the first goes on."""
    store, ids = example_store
    server = Server(store, tmp_path / "sessions.sqlite3", env={"YAUYAU_MAX_SESSION_LISTENERS": "1"})
    try:
        sid = _session(server, "", ids["cubic_sensor"])
        url = f"ws://127.0.0.1:{server.port}/v1/sessions/{sid}/stream"
        first = websocket.create_connection(url, timeout=60)
        try:
            with pytest.raises(websocket.WebSocketBadStatusException) as err:
                websocket.create_connection(url, timeout=60)
            assert err.value.status_code == 429
            assert "WebSocket streams" in json.loads(err.value.resp_body)["detail"]
            first.send(json.dumps({"seq": 0, "increments": ROWS}))
            assert strict(first.recv())["seq"] == 0
        finally:
            first.close()
    finally:
        server.kill()


def test_the_service_declares_a_websocket_implementation_for_uvicorn():
    """A plain install (no test extras, whose selenium happens to bring wsproto) must still serve the
    stream: uvicorn takes websockets or wsproto, whichever is installed."""
    from importlib.metadata import requires

    runtime = [r.split(";")[0].strip().lower() for r in requires("yauyau") or [] if "extra ==" not in r]
    assert any(r.startswith(("wsproto", "websockets")) for r in runtime), runtime
