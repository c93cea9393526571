"""ASGI middleware: cap the request body before anything parses it (413 problem+json) and refuse
bodies that are not JSON (415 problem+json)."""

from __future__ import annotations

from ..problems import problem_response


class BodyLimit:
    """Reject bodies over ``max_bytes``: by Content-Length at once, else while reading the stream."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or ()).get(b"content-length")
        if declared is not None:
            try:
                too_big = int(declared) > self.max_bytes
            except ValueError:
                return await self._reject(scope, receive, send, 400, "invalid Content-Length header")
            if too_big:
                return await self._reject(scope, receive, send, 413, self._detail())
            return await self.app(scope, receive, send)
        # No length given (chunked): buffer up to the cap, then replay to the app.
        messages, size = [], 0
        while True:
            message = await receive()
            messages.append(message)
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                return await self._reject(scope, receive, send, 413, self._detail())
            if message["type"] != "http.request" or not message.get("more_body", False):
                break

        async def replay():
            return messages.pop(0) if messages else await receive()

        return await self.app(scope, replay, send)

    def _detail(self) -> str:
        return f"request body larger than {self.max_bytes} bytes"

    async def _reject(self, scope, receive, send, status, detail):
        response = problem_response(status, detail, "body", instance=scope.get("path"))
        await response(scope, receive, send)


_BODY_METHODS = {"POST", "PUT", "PATCH"}


class JsonBodies:
    """A request body must be JSON: Content-Type application/json (or a +json type), else 415."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["method"] in _BODY_METHODS:
            headers = dict(scope.get("headers") or ())
            declared = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
            has_body = headers.get(b"content-length", b"0") != b"0" or b"transfer-encoding" in headers
            json_type = declared == b"application/json" or declared.endswith(b"+json")
            if (declared and not json_type) or (has_body and not declared):
                shown = declared.decode("latin-1") or "none"
                detail = f"the body must be JSON: send Content-Type: application/json (got {shown})"
                response = problem_response(415, detail, "Content-Type", instance=scope.get("path"))
                return await response(scope, receive, send)
        return await self.app(scope, receive, send)
