"""The live page of a session (GET /v1/sessions/{id}/view): one HTML file with one small script, no
build step and nothing fetched from elsewhere (it works offline).  It reads the session's
Server-Sent Events (/events) with ``fetch()`` and a streamed parser, so that it can send the
tenant's token in an ``Authorization`` header (EventSource sends no headers; the token never goes
into a URL).  With tenants, a browser opening the page gets it with status 401 (service/http/tenants.py),
and the page asks for the token once and keeps it in ``sessionStorage``.

The page is sent with a strict Content-Security-Policy: nothing but its own inline script and style
(allowed by their SHA-256, computed here from the file) and requests to its own origin.
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import cache
from importlib.resources import files

from starlette.responses import HTMLResponse


@cache
def live_page() -> str:
    return files("yauyau.service.http").joinpath("static", "view.html").read_text(encoding="utf-8")


def _hashes(tag: str, page: str) -> str:
    """The CSP source list of every inline ``<tag>`` element of the page: 'sha256-…' of its text."""
    bodies = re.findall(rf"<{tag}>(.*?)</{tag}>", page, flags=re.S)
    return " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(b.encode()).digest()).decode()}'"
                    for b in bodies)


@cache
def security_headers() -> dict[str, str]:
    """The live page's headers: a CSP allowing its own inline script and style only, no sniffing, no
    referrer."""
    page = live_page()
    policy = (f"default-src 'none'; script-src {_hashes('script', page)}; "
              f"style-src {_hashes('style', page)}; img-src data:; connect-src 'self'; "
              "frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
    return {"Content-Security-Policy": policy, "X-Content-Type-Options": "nosniff",
            "Referrer-Policy": "no-referrer", "Cache-Control": "no-store"}


def live_response(status: int = 200, headers: dict[str, str] | None = None) -> HTMLResponse:
    """The live page with its security headers (and ``headers``)."""
    return HTMLResponse(live_page(), status_code=status, headers={**security_headers(), **(headers or {})})
