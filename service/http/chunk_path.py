"""``POST /v1/sessions/{id}/observations`` without FastAPI's routing and dependencies: the chunk's fast path.

A 100-row chunk cost the ASGI application ~410 µs before it reached the session (routing over every
route, solving the dependencies, the stdlib ``json.loads`` of the body, then pydantic on the parsed
objects, Starlette's request and response objects); the filter and the store take about as much
again.  This pure ASGI middleware, innermost in the stack (after the Host and tenant guard, the rate
limits, the body cap and the JSON check), answers that one route itself: the body is parsed and
validated in one pass by pydantic's JSON parser (``Observations.model_validate_json``: the same model,
so a bad body gets the same 422 naming ``increments[i][j]``), the chunk goes to the worker's batcher,
and the stored JSON text is sent as is.  Every error is the problem+json the exception handlers give
(service/problems.py ``response_for``).  The FastAPI route stays for the OpenAPI document (and takes
what this one leaves, e.g. a session id over 100 characters, answered 422 there).

The WebSocket stream (service/http/stream.py) applies its chunks through :func:`parse_chunk` and
:func:`submit` too: one set of rules for both.
"""

from __future__ import annotations

import asyncio
import re
from typing import Any

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from ..problems import Problem, response_for
from ..sessions.chunks import ChunkRequest
from ..sessions.responses import Extras
from .deps import sessions_of, tenant_of
from .schemas import Observations

CHUNK_PATH = re.compile(r"/v1/sessions/([^/]{1,100})/observations")
_HEADERS = [(b"content-type", b"application/json")]


def parse_chunk(data: bytes | str, session_id: str, tenant: str | None) -> ChunkRequest:
    """A chunk's body (JSON) -> the request the batcher applies; 400 (malformed JSON) or 422 naming the
    field, as the FastAPI route would answer."""
    if not data or not data.strip():
        raise Problem(400, "a JSON request body is required", "body")
    try:
        body = Observations.model_validate_json(data)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors(include_url=False)) from None
    return ChunkRequest(session_id, body.seq, body.increments, Extras(body.quantiles, body.mode),
                        observations=body.observations, times=body.times, tenant=tenant)


def submit(sessions: Any, request: ChunkRequest) -> asyncio.Future:
    """The chunk applied in the worker's next batch (service/sessions/batching.py): its response text."""
    return asyncio.wrap_future(sessions.chunk_executor.submit_chunk(request))


async def _body(receive) -> bytes | None:
    """The request body, or None when the client went away."""
    parts = []
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return None
        parts.append(message.get("body", b""))
        if not message.get("more_body", False):
            return b"".join(parts)


class ChunkFastPath:
    """Answers ``POST /v1/sessions/{id}/observations``; everything else goes on to the application."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        match = CHUNK_PATH.fullmatch(scope["path"]) if scope["type"] == "http" and \
            scope["method"] == "POST" else None
        if match is None:
            return await self.app(scope, receive, send)
        data = await _body(receive)
        if data is None:
            return
        try:
            sessions = sessions_of(scope)
            request = parse_chunk(data, match.group(1), tenant_of(scope))
            text = await submit(sessions, request)
        except Exception as exc:  # noqa: BLE001 - every error is the client's problem+json (5xx logged)
            return await response_for(exc, scope["path"])(scope, receive, send)
        body = text if isinstance(text, bytes) else text.encode()
        await send({"type": "http.response.start", "status": 200,
                    "headers": [*_HEADERS, (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})
