"""The live page of a session (GET /v1/sessions/{id}/view): one HTML file with one small script, no
build step and nothing fetched from elsewhere (it works offline).  It listens to the session's
Server-Sent Events (/events) and draws each frame on a canvas.  SSE rather than a WebSocket: the
page only listens, EventSource reconnects by itself (resuming from Last-Event-ID), and it is plain
HTTP through any proxy.
"""

from __future__ import annotations

from functools import cache
from importlib.resources import files


@cache
def live_page() -> str:
    return files("yauyau.service").joinpath("static", "view.html").read_text(encoding="utf-8")
