"""The HTTP/1.1 protocol of `yauyau serve`: uvicorn's httptools protocol (its C parser; h11's where
httptools is not installed) with three changes.

* TCP_NODELAY on every accepted connection.  With several workers uvicorn hands each worker the
  listening socket through a file descriptor (socket.fromfd), whose ``proto`` is 0, so asyncio does
  not set TCP_NODELAY (it only does for IPPROTO_TCP sockets); a response written in two parts
  (head, then body) then waits for the client's delayed ACK: +40 ms per keep-alive request
  (upstream Kludex/uvicorn#3149).
* Errors that the parser finds before the application sees the request (a request head over the limit,
  an invalid Content-Length, bad framing) are answered with problem+json like every other error,
  not uvicorn's plain-text 400.
* What a client can make a worker hold in connections is bounded (service/http/connections.py): a request
  head must be complete within ``header_timeout`` seconds and hold at most MAX_HEAD_BYTES, and at most
  ``max_connections`` are open (a newcomer at the cap closes the one waiting longest for its head, or is
  answered 503).

httptools against h11, the server's CPU per 100-row chunk (bench/load.py, 64 streams, one worker, with
uvloop, which uvicorn takes where it is installed): 1.60 against 1.95 ms; h11 on asyncio's loop 2.29 ms.
"""

from __future__ import annotations

import asyncio
import json
import socket

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from ..problems import problem_response
from .connections import QuietLogger, connection_guard

try:
    import httptools
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:  # pragma: no cover - httptools is a dependency; h11 is uvicorn's fallback
    httptools = None
    HttpToolsProtocol = None

MAX_HEAD_BYTES = 512 * 1024  # request line + headers: the documented 100 000-character points, encoded
URL_PARSER_LIMIT = 65_535  # httptools.parse_url's largest URL


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


def parser_problem(text: str, status: int = 400) -> tuple[int, bytes]:
    """The status and problem+json body for what the parser refused (``text``: its message)."""
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
    return status, json.dumps({"type": "about:blank", "title": title, "status": status, "detail": detail,
                               "field": field}).encode()


class _Guarded:
    """What both parsers' protocols add (module docstring): TCP_NODELAY, the head's deadline and the
    connection cap.  ``_awaiting_head``: no complete request head since the last response."""

    def _guard_connections(self) -> None:
        self._guard = connection_guard(self.loop)
        self.logger = QuietLogger(self.logger, self._guard)
        self._head_deadline: asyncio.TimerHandle | None = None
        self._awaiting_head = False

    def connection_made(self, transport) -> None:  # type: ignore[override]
        set_nodelay(transport)
        super().connection_made(transport)
        self._awaiting_head = True
        self._arm_head_deadline()
        if not self._guard.opened(self):
            self.app = at_capacity  # answered 503 when its head arrives (unless evicted first)

    def _head_began(self) -> None:
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

    def handle_websocket_upgrade(self, *event) -> None:
        self._guard.closed(self)  # the connection is the WebSocket protocol's now (the app has no such route)
        super().handle_websocket_upgrade(*event)

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


class ServiceProtocol(_Guarded, H11Protocol):
    """The module's protocol on h11 (uvicorn's pure-Python parser)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._protocol_error: h11.RemoteProtocolError | None = None
        self._guard_connections()
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

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._head_began()

    def send_400_response(self, msg: str) -> None:
        error = self._protocol_error
        text = str(error) if error is not None else msg
        status, body = parser_problem(text, getattr(error, "error_status_hint", 400) or 400)
        headers = [(b"content-type", b"application/problem+json"), (b"connection", b"close"),
                   (b"content-length", str(len(body)).encode())]
        try:
            self.transport.write(self.conn.send(h11.Response(status_code=status, headers=headers)))
            self.transport.write(self.conn.send(h11.Data(data=body)))
            self.transport.write(self.conn.send(h11.EndOfMessage()))
        except h11.LocalProtocolError:  # the connection is past the point of answering
            pass
        self.transport.close()


class _HeadTooLarge(Exception):
    """Raised from the parser's callback: the request head is over MAX_HEAD_BYTES."""


if HttpToolsProtocol is not None:
    class ServiceToolsProtocol(_Guarded, HttpToolsProtocol):
        """The module's protocol on httptools (llhttp, in C).  The head's size is bounded twice: bytes of
        a head not yet complete after each read (llhttp keeps a partial head in memory without limit),
        and a complete head's request line and headers as parsed (one that arrives whole in a read)."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self._guard_connections()
            self._partial_head = 0

        def data_received(self, data: bytes) -> None:
            # uvicorn's, with the parser's own message kept for the problem and the partial head bounded
            self._unset_keepalive_if_required()
            try:
                self.parser.feed_data(data)
            except httptools.HttpParserUpgrade:
                if self._should_upgrade():
                    self.handle_websocket_upgrade()
                else:
                    self._unsupported_upgrade_warning()
                return
            except httptools.HttpParserError as exc:
                too_large = isinstance(exc.__context__, _HeadTooLarge)
                self.logger.warning("Invalid HTTP request received.")
                self._answer_problem(*parser_problem(str(exc), 431 if too_large else 400))
                return
            if self._awaiting_head:  # every byte of this read belongs to a head not yet complete
                self._partial_head += len(data)
                if self._partial_head > MAX_HEAD_BYTES:
                    self._answer_problem(*parser_problem("", 431))
                    return
            self._head_began()

        def on_headers_complete(self) -> None:
            self._head_arrived()
            self._partial_head = 0
            size = len(self.parser.get_method()) + len(self.url) + 12
            size += sum(len(name) + len(value) + 4 for name, value in self.headers)
            if size > MAX_HEAD_BYTES:
                raise _HeadTooLarge
            url = self.url
            if len(url) <= URL_PARSER_LIMIT or b"?" not in url:
                super().on_headers_complete()
                return
            # httptools.parse_url stops at 64 KiB; the documented 100 000-character points of
            # GET .../density are a longer query: uvicorn parses the path, the query is set here (the
            # request's task has not started yet)
            path, _, query = url.partition(b"?")
            self.url = path
            try:
                super().on_headers_complete()
            finally:
                self.url = url
            self.scope["query_string"] = query

        def send_400_response(self, msg: str) -> None:  # pragma: no cover - data_received answers instead
            self._answer_problem(*parser_problem(msg))

        def _answer_problem(self, status: int, body: bytes) -> None:
            reason = "Request Header Fields Too Large" if status == 431 else "Bad Request"
            self.transport.write(b"".join([
                f"HTTP/1.1 {status} {reason}\r\n".encode(), b"content-type: application/problem+json\r\n",
                b"content-length: " + str(len(body)).encode() + b"\r\n", b"connection: close\r\n\r\n", body]))
            self.transport.close()
else:  # pragma: no cover
    ServiceToolsProtocol = None


def protocol_class() -> type:
    """The protocol `yauyau serve` runs: httptools' where it is installed, else h11's."""
    return ServiceProtocol if ServiceToolsProtocol is None else ServiceToolsProtocol
