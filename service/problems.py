"""RFC 9457 problem details: every error the service returns is ``application/problem+json``.

A problem names the field at fault (``field``, a dotted path such as ``increments[3][0]``) so that a
client can fix its request; client mistakes are 4xx, never 500.
"""

from __future__ import annotations

import json
import logging
import os
import re
import tempfile
from functools import cache
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response
from yauyau.solver.errors import InputError, SpecError, TooLarge
from yauyau.storage.errors import Conflict, NotFound, StoreError, Unavailable

PROBLEM_TYPE = "application/problem+json"
log = logging.getLogger("yauyau.service")

_TITLES = {400: "Bad request", 401: "Unauthorized", 403: "Forbidden", 404: "Not found",
           405: "Method not allowed", 409: "Conflict",
           413: "Request body too large", 415: "Unsupported media type", 422: "Invalid input",
           500: "Internal error", 503: "Service unavailable"}


_TAGS = ("gaussian", "mixture", "density")  # discriminator tags of the prior union


class Problem(Exception):
    """An HTTP error with a problem-details body."""

    def __init__(self, status: int, detail: str, field: str | None = None, title: str | None = None,
                 retry_after: int | None = None, headers: dict[str, str] | None = None):
        super().__init__(detail)
        self.headers = dict(headers or {})
        if retry_after is not None:
            self.headers["Retry-After"] = str(int(retry_after))
        self.status = status
        self.detail = detail
        self.field = field
        self.title = title or _TITLES.get(status, "Error")


# Server paths never leave in a 5xx detail (the log keeps them): the directories and files the
# service is configured with (hide_paths), the temporary and home directories, and any absolute path.
_PRIVATE: dict[str, str] = {}
_ABSOLUTE = re.compile(r"(?<![\w/:.~-])/(?!v1/)[^\s'\"()\[\]{},;:]+/[^\s'\"()\[\]{},;:]*")


def hide_paths(**paths: Any) -> None:
    """Name the server's own paths (``store=...``, ``session_database=...``) that a 5xx problem must
    not show; the temporary and home directories are always hidden."""
    for label, path in paths.items():
        if path is not None:
            _hide(str(path), label.replace("_", " "))
    _private_pattern.cache_clear()


def _hide(path: str, label: str) -> None:
    for text in {path, os.path.realpath(path), os.path.abspath(path)}:
        if len(Path(text).parts) > 1 or not Path(text).is_absolute():  # never "/" itself
            _PRIVATE.setdefault(text, f"<{label}>")


@cache
def _private_pattern() -> re.Pattern:
    """One pattern of every private path, the longest (the innermost) first, with what follows it."""
    alternatives = sorted(_PRIVATE, key=len, reverse=True)
    return re.compile("(" + "|".join(map(re.escape, alternatives)) + r")(?:/[^\s'\"(),;:]*)?(?![\w.-])")


def without_paths(detail: str) -> str:
    """``detail`` with every server path replaced by what it is (``<session database>``, ``<path>``)."""
    detail = _private_pattern().sub(lambda m: _PRIVATE[m.group(1)], detail)
    return _ABSOLUTE.sub("<path>", detail)


_hide(tempfile.gettempdir(), "temp")
_hide(os.path.expanduser("~"), "home")


def problem_response(status: int, detail: str, field: str | None = None, title: str | None = None,
                     instance: str | None = None, headers: dict[str, str] | None = None) -> Response:
    if status >= 500:
        detail = without_paths(detail)
    body: dict[str, Any] = {"type": "about:blank", "title": title or _TITLES.get(status, "Error"),
                            "status": status, "detail": detail}
    if field is not None:
        body["field"] = field
    if instance is not None:
        body["instance"] = instance
    return Response(json.dumps(body, allow_nan=False), status_code=status, media_type=PROBLEM_TYPE,
                    headers=headers)


def field_path(loc: tuple[Any, ...] | list[Any]) -> str:
    """('body', 'increments', 3, 0) -> 'increments[3][0]'."""
    path = ""
    for part in loc:
        if part in ("body", "query", "path", "header") and not path:
            continue
        if isinstance(part, int):
            path += f"[{part}]"
        elif str(part).startswith(("function-", "list[", "nullable[", "union[")) or part in _TAGS:
            continue  # pydantic inserts the validator kind or the union tag into locations
        else:
            path += f".{part}" if path else str(part)
    return path or "body"


def _validation_problem(exc: RequestValidationError) -> tuple[int, str, str]:
    errors = exc.errors()
    err = errors[0] if errors else {"loc": ("body",), "msg": "invalid request", "type": ""}
    if err.get("type") == "json_invalid":
        return 400, "body", "malformed JSON: " + str((err.get("ctx") or {}).get("error", "cannot parse"))
    if err.get("type") == "missing" and tuple(err.get("loc", ())) == ("body",):
        return 400, "body", "a JSON request body is required"
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    return 422, field_path(tuple(err.get("loc", ()))), msg


def problem_of(exc: BaseException, instance: str | None = None) -> tuple[int, str, str | None, str | None,
                                                                       dict[str, str] | None]:
    """(status, detail, field, title, headers) of an exception raised while serving a request: the one
    mapping the exception handlers, the chunk route's fast path and the WebSocket stream share.  A 5xx is
    logged (with ``instance``, the path)."""
    if isinstance(exc, Problem):
        return exc.status, exc.detail, exc.field, exc.title, exc.headers
    if isinstance(exc, RequestValidationError):
        status, field, detail = _validation_problem(exc)
        return status, detail, field, None, None
    if isinstance(exc, TooLarge):  # arrays that would not fit in memory
        return 413, exc.message, exc.field, None, None
    if isinstance(exc, (SpecError, InputError)):
        return 422, exc.message, exc.field, None, None
    if isinstance(exc, NotFound):
        return 404, exc.message, exc.field, None, None
    if isinstance(exc, Conflict):
        return 409, exc.message, exc.field, None, None
    if isinstance(exc, Unavailable):
        log.error("session store unavailable on %s: %s", instance, exc.message)
        headers = {"Retry-After": str(exc.retry_after)} if exc.retry_after is not None else None
        return 503, exc.message, exc.field, None, headers
    if isinstance(exc, StoreError):
        log.error("store error on %s: %s", instance, exc)
        return 503, exc.message, exc.field, None, None
    log.error("internal error on %s", instance, exc_info=exc)
    return 500, "internal error (logged)", None, None, None


def response_for(exc: BaseException, instance: str | None = None) -> Response:
    """The problem+json response of an exception (:func:`problem_of`)."""
    status, detail, field, title, headers = problem_of(exc, instance)
    return problem_response(status, detail, field, title, instance, headers)


def _allowed_methods(request: Request) -> list[str]:
    """Every method some route takes at this path (the Allow header of a 405)."""
    from starlette.routing import Match

    allowed = []
    for method in ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE"):
        scope = {**request.scope, "method": method}
        if any(route.matches(scope)[0] == Match.FULL for route in request.app.routes):
            allowed.append(method)
    return allowed


def install_handlers(app: FastAPI) -> None:
    """Map every error to a problem+json response."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> Response:
        return problem_response(exc.status, exc.detail, exc.field, exc.title, request.url.path, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> Response:
        status, field, detail = _validation_problem(exc)
        return problem_response(status, detail, field, instance=request.url.path)

    @app.exception_handler(SpecError)
    @app.exception_handler(InputError)
    @app.exception_handler(NotFound)
    @app.exception_handler(Conflict)
    @app.exception_handler(StoreError)  # Unavailable too
    async def _mapped(request: Request, exc: Exception) -> Response:
        return response_for(exc, request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        detail = exc.detail if isinstance(exc.detail, str) else _TITLES.get(exc.status_code, "error")
        headers = dict(exc.headers or {})
        if exc.status_code == 405:  # Starlette names the first matching route's methods only
            headers["Allow"] = ", ".join(_allowed_methods(request))
        return problem_response(exc.status_code, detail, instance=request.url.path, headers=headers)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> Response:
        return response_for(exc, request.url.path)
