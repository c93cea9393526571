"""``WS /v1/sessions/{id}/stream``: a session's chunks in, its answers out, over one WebSocket.

For sensors that push continuously: no HTTP request per chunk.  Each message the client sends is a
chunk's JSON body exactly as ``POST /v1/sessions/{id}/observations`` takes it (``{"seq": n,
"increments": [...]}``, a text or a binary frame); each answer is a text frame: the chunk's response
(the same bytes as the POST's, with its ``seq``), or a problem (RFC 9457 fields: ``status``, ``title``,
``detail``, ``field``, plus the message's ``seq`` when it had one).  Answers come in the order the
messages came, one per message; a client may send ahead (up to ``MAX_IN_FLIGHT`` unanswered chunks,
then the server stops reading until it has answered).

The rules are the POST's (the chunks go through the same parser and the same batcher,
service/http/chunk_path.py): each seq is applied exactly once, a re-sent seq is answered with the
stored response, other data under a used seq or a gap is a 409 problem; a bad message is a 4xx
problem naming the field and leaves the session unchanged.  **A problem never closes the socket**:
the client fixes the message and sends again.  The socket closes with a code only for what the next
message cannot fix:

* at the handshake, as an HTTP answer (problem+json, no socket): 400 Host, 401 bearer token (a server
  with tenants; the ``Authorization`` header of the upgrade request), 404 unknown session or another
  tenant's, 429/503 at a cap (the same per-worker caps as ``/events`` listeners: at most
  ``YAUYAU_MAX_SESSION_LISTENERS`` streams per session, ``YAUYAU_MAX_LISTENERS`` in all);
* 1009 (message too big) for a message over ``YAUYAU_MAX_BODY_BYTES`` (uvicorn's ``ws_max_size``);
* 1012 (service restart; uvicorn's code) when the server shuts down.

A chunk sent before the socket dropped may have been applied: reconnect and send the same seq
again; its stored answer comes back (exactly once, as with POST).  Each chunk takes a token of the
client's request rate (``YAUYAU_RATE_REQUESTS``): beyond it, a 429 problem with ``retry_after``.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import orjson
from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketDisconnect

from ..problems import Problem, problem_of, problem_response, response_for
from .chunk_path import parse_chunk, submit
from .deps import sessions_of, tenant_of
from .limits import LIMITED

MAX_IN_FLIGHT = 64  # unanswered chunks a socket may have (then the server reads no further message)

stream = APIRouter(prefix="/v1/sessions", tags=["sessions"])


def _seq_of(data: bytes | str) -> int | None:
    """The ``seq`` of a message, when it is a JSON object with an integer one (for its problem)."""
    try:
        body = orjson.loads(data)
    except orjson.JSONDecodeError:
        return None
    seq = body.get("seq") if isinstance(body, dict) else None
    return seq if type(seq) is int else None


def problem_text(exc: BaseException, seq: int | None, path: str) -> str:
    """A problem as a text frame: the problem+json fields, ``retry_after`` (s) where the POST would send
    Retry-After, and the message's ``seq``."""
    status, detail, field, title, headers = problem_of(exc, path)
    body = orjson.loads(problem_response(status, detail, field, title, path).body)
    if headers and "Retry-After" in headers:
        body["retry_after"] = int(headers["Retry-After"])
    if seq is not None:
        body["seq"] = seq
    return orjson.dumps(body).decode()


def _rate_refusal(scope: Any) -> Problem | None:
    """429 when this chunk is over the client's request rate (the token the middleware left to us)."""
    buckets, key = (scope.get("state") or {}).get("rate_limit") or (None, None)
    if buckets is None:
        return None
    wait = buckets.take(key)
    if not wait:
        return None
    LIMITED.labels("requests").inc()
    retry = max(1, math.ceil(wait))
    return Problem(429, f"more than {buckets.rate:g} requests per second from this client on this worker "
                        f"(YAUYAU_RATE_REQUESTS; each chunk on a stream counts); retry in {retry} s", "seq",
                   title="Too many requests", retry_after=retry)


async def _deny(websocket: WebSocket, exc: BaseException) -> None:
    """Refuse the handshake with the problem+json an HTTP request would get (or close with 1008 where
    the server cannot answer a handshake with a response)."""
    response = response_for(exc, websocket.scope["path"])
    try:
        await websocket.send_denial_response(response)
    except RuntimeError:
        await websocket.close(code=1008, reason=orjson.loads(response.body)["detail"][:120])


@stream.websocket("/{session_id}/stream")
async def stream_chunks(websocket: WebSocket, session_id: str) -> None:
    scope, path = websocket.scope, websocket.scope["path"]
    slots = scope["app"].state.stream_slots
    try:
        sessions = sessions_of(scope)
        tenant = tenant_of(scope)
        if len(session_id) > 100:
            raise Problem(404, f"no session {session_id[:100]!r}... (ids are at most 100 characters)",
                          "session_id")
        await asyncio.to_thread(sessions.version, session_id, tenant)  # 404 unless the tenant's session
        slots.take((session_id, tenant))
    except Exception as exc:  # noqa: BLE001 - the handshake's answer
        return await _deny(websocket, exc)
    try:
        await websocket.accept()
        await _serve(websocket, sessions, session_id, tenant, path)
    finally:
        slots.give_back((session_id, tenant))


async def _serve(websocket: WebSocket, sessions: Any, session_id: str, tenant: str | None, path: str) -> None:
    answers: asyncio.Queue = asyncio.Queue(MAX_IN_FLIGHT)
    sender = asyncio.create_task(_answer(websocket, answers, path))
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            data = message.get("text")
            if data is None:
                data = message.get("bytes") or b""
            try:
                refused = _rate_refusal(websocket.scope)
                if refused is not None:
                    raise refused
                answer: Any = submit(sessions, parse_chunk(data, session_id, tenant))
            except Exception as exc:  # noqa: BLE001 - that message's answer
                answer = exc
            await answers.put((answer, data))
    except WebSocketDisconnect:
        pass
    finally:
        await answers.put(None)  # the sender drains what is queued (it never stops before None)
        await sender


async def _answer(websocket: WebSocket, answers: asyncio.Queue, path: str) -> None:
    """Send the answers in the order of the messages (each awaited: the chunks go through the batcher).
    Once the client is gone the answers are still awaited (their chunks are applied) but not sent."""
    gone = False
    while True:
        item = await answers.get()
        if item is None:
            return
        answer, data = item
        try:
            text = answer if isinstance(answer, BaseException) else await answer
            if isinstance(text, BaseException):
                raise text
        except Exception as exc:  # noqa: BLE001 - that chunk's problem
            text = problem_text(exc, _seq_of(data), path)
        if not gone:
            try:
                await websocket.send_text(text if isinstance(text, str) else text.decode())
            except (WebSocketDisconnect, RuntimeError, OSError):  # the client went away
                gone = True
