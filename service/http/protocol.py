"""The HTTP/1.1 protocol of `yauyau serve`: uvicorn's h11 protocol with three changes.

* TCP_NODELAY on every accepted connection.  With several workers uvicorn hands each worker the
  listening socket through a file descriptor (socket.fromfd), whose ``proto`` is 0, so asyncio does
  not set TCP_NODELAY (it only does for IPPROTO_TCP sockets); a response written in two parts
  (head, then body) then waits for the client's delayed ACK: +40 ms per keep-alive request
  (upstream Kludex/uvicorn#3149).
* Errors that h11 finds before the application sees the request (a request head over the limit,
  an invalid Content-Length, bad framing) are answered with problem+json like every other error,
  not uvicorn's plain-text 400.
* What a client can make a worker hold in connections is bounded (service/http/connections.py): a request
  head must be complete within ``header_timeout`` seconds, and at most ``max_connections`` are open
  (a newcomer at the cap closes the one waiting longest for its head, or is answered 503).
"""

from __future__ import annotations

import asyncio
import json
import socket

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from ..problems import problem_response
from .connections import QuietLogger, connection_guard

MAX_HEAD_BYTES = 512 * 1024  # request line + headers: the documented 100 000-character points, encoded


def set_nodelay(transport) -> None:
    sock = transport.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:  # pragma: no cover - a socket closed under us
            pass


def _head_size(request: h11.Request) -> int:
    """Bytes of the request line and headers (as sent, up to whitespace)."""
    size = len(request.method) + len(request.target) + 12
    return size + sum(len(name) + len(value) + 4 for name, value in request.headers)


async def at_capacity(scope, receive, send) -> None:
    """The answer to a connection that found every other one busy with a request (the cap reached)."""
    response = problem_response(503, "this worker has as many connections as it serves at once, all busy; "
                                "retry (max_connections)", "connections", instance=scope.get("path"),
                                headers={"Retry-After": "1", "Connection": "close"})
    await response(scope, receive, send)


class ServiceProtocol(H11Protocol):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._protocol_error: h11.RemoteProtocolError | None = None
        self._guard = connection_guard(self.loop)
        self.logger = QuietLogger(self.logger, self._guard)
        self._head_deadline: asyncio.TimerHandle | None = None
        self._awaiting_head = False
        next_event = self.conn.next_event

        def remember_error():
            try:
                event = next_event()
                if isinstance(event, h11.Request):
                    self._head_arrived()
                    if _head_size(event) > MAX_HEAD_BYTES:
                        # h11 bounds only a head still incomplete in its buffer; one that arrives whole
                        # in a single read would pass, so the size is checked here as well
                        raise h11.RemoteProtocolError("request head buffer too long", error_status_hint=431)
                return event
            except h11.RemoteProtocolError as exc:
                self._protocol_error = exc
                raise

        self.conn.next_event = remember_error

    def connection_made(self, transport) -> None:  # type: ignore[override]
        set_nodelay(transport)
        super().connection_made(transport)
        self._awaiting_head = True
        self._arm_head_deadline()
        if not self._guard.opened(self):
            self.app = at_capacity  # answered 503 when its head arrives (unless evicted first)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._awaiting_head and self._head_deadline is None and not self.transport.is_closing():
            self._arm_head_deadline()  # a kept-alive connection's next head began and is incomplete

    def on_response_complete(self) -> None:
        if not self.transport.is_closing():  # kept alive: waiting for the next head (uvicorn's
            self._awaiting_head = True       # keep-alive timer closes it if none starts)
            self._guard.wait_for_head(self)
        super().on_response_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._guard.closed(self)
        self._awaiting_head = False
        self._cancel_head_deadline()
        super().connection_lost(exc)

    def handle_websocket_upgrade(self, event: h11.Request) -> None:
        self._guard.closed(self)  # the connection is the WebSocket protocol's now (the app has no such route)
        super().handle_websocket_upgrade(event)

    def evict(self) -> None:
        """Close this connection, which waited longest for its request head, to make room for a newcomer."""
        self._awaiting_head = False
        self._cancel_head_deadline()
        if not self.transport.is_closing():
            self.transport.close()

    def _head_arrived(self) -> None:
        self._awaiting_head = False
        self._cancel_head_deadline()
        self._guard.head_received(self)

    def _arm_head_deadline(self) -> None:
        self._head_deadline = self.loop.call_later(self._guard.header_timeout, self._head_overdue)

    def _cancel_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None

    def _head_overdue(self) -> None:
        self._head_deadline = None
        if self._awaiting_head and not self.transport.is_closing():
            self._guard.closed(self)
            self._guard.note("header_timeout")
            self._awaiting_head = False
            self.transport.close()

    def send_400_response(self, msg: str) -> None:
        error = self._protocol_error
        status = getattr(error, "error_status_hint", 400) or 400
        text = str(error) if error is not None else msg
        if status == 431 or "buffer too long" in text.lower():
            status = 431
            field = "head"
            detail = (f"request line and headers larger than {MAX_HEAD_BYTES} bytes; send long point lists "
                      "in several requests")
            title = "Request header fields too large"
        elif "content-length" in text.lower():
            field, detail, title = "Content-Length", f"invalid Content-Length header ({text})", "Bad request"
        else:
            field, detail, title = "request", f"malformed HTTP request ({text})", "Bad request"
        body = json.dumps({"type": "about:blank", "title": title, "status": status, "detail": detail,
                           "field": field}).encode()
        headers = [(b"content-type", b"application/problem+json"), (b"connection", b"close"),
                   (b"content-length", str(len(body)).encode())]
        try:
            self.transport.write(self.conn.send(h11.Response(status_code=status, headers=headers)))
            self.transport.write(self.conn.send(h11.Data(data=body)))
            self.transport.write(self.conn.send(h11.EndOfMessage()))
        except h11.LocalProtocolError:  # the connection is past the point of answering
            pass
        self.transport.close()
