"""The HTTP/1.1 protocol of `yauyau serve`: uvicorn's h11 protocol with two changes.

* TCP_NODELAY on every accepted connection.  With several workers uvicorn hands each worker the
  listening socket through a file descriptor (socket.fromfd), whose ``proto`` is 0, so asyncio does
  not set TCP_NODELAY (it only does for IPPROTO_TCP sockets); a response written in two parts
  (head, then body) then waits for the client's delayed ACK: +40 ms per keep-alive request
  (upstream Kludex/uvicorn#3149).
* Errors that h11 finds before the application sees the request (a request head over the limit,
  an invalid Content-Length, bad framing) are answered with problem+json like every other error,
  not uvicorn's plain-text 400.
"""

from __future__ import annotations

import json
import socket

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

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


class ServiceProtocol(H11Protocol):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._protocol_error: h11.RemoteProtocolError | None = None
        next_event = self.conn.next_event

        def remember_error():
            try:
                event = next_event()
                if isinstance(event, h11.Request) and _head_size(event) > MAX_HEAD_BYTES:
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
