"""Request rates per client: token buckets, and the ASGI middleware that applies them to ``/v1``.

A client is its tenant when the request was authenticated (the tenants' middleware, which runs before
this one, puts the tenant's name in ``scope["state"]["tenant"]``), else its IP address.  Two buckets a
client: every ``/v1`` request takes a token of ``rate_requests`` per second (``rate_requests_burst``
at once), and creating a session (``POST /v1/sessions``) one of ``rate_sessions`` per second
(``rate_sessions_burst``), given back when no session was created (a refused body costs only a
request token).  An empty bucket is answered 429 problem+json with Retry-After, the seconds until a
token is back (rounded up).  ``/livez``, ``/readyz`` and ``/metrics`` are never limited (nor /docs).

Each worker process keeps its own buckets and allows its share, ``rate / workers`` and
``burst / workers`` (at least 1): connections are spread over the workers by the kernel, so a client
gets about the whole rate in all.  The buckets of idle clients are dropped (a full bucket is the same
as none), and at most ``MAX_CLIENTS`` are kept: memory stays bounded whoever connects.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable

from prometheus_client import Counter as PromCounter

from ..problems import problem_response

MAX_CLIENTS = 100_000  # buckets kept per limit and worker (the least recently used beyond are dropped)
LIMITED = PromCounter("yauyau_rate_limited_total", "requests answered 429 by a rate limit", ["limit"])


class TokenBuckets:
    """A token bucket per key: ``rate`` tokens a second, at most ``burst`` kept."""

    def __init__(self, rate: float, burst: float, max_keys: int = MAX_CLIENTS,
                 clock: Callable[[], float] = time.monotonic):
        self.rate, self.burst, self.max_keys, self.clock = rate, burst, max_keys, clock
        self._buckets: OrderedDict[Hashable, list[float]] = OrderedDict()  # key: [tokens, when]; oldest first

    def take(self, key: Hashable) -> float:
        """Take a token of ``key``'s: 0.0, or (none left) the seconds until one is back."""
        now = self.clock()
        bucket = self._buckets.pop(key, None)
        tokens = self.burst if bucket is None else min(self.burst, bucket[0] + (now - bucket[1]) * self.rate)
        wait = 0.0
        if tokens >= 1.0:
            tokens -= 1.0
        else:
            wait = (1.0 - tokens) / self.rate
        self._buckets[key] = [tokens, now]
        self._forget_idle(now)
        return wait

    def give_back(self, key: Hashable) -> None:
        bucket = self._buckets.get(key)
        if bucket is not None:
            bucket[0] = min(self.burst, bucket[0] + 1.0)

    def __len__(self) -> int:
        return len(self._buckets)

    def _forget_idle(self, now: float) -> None:
        """Drop the least recently used buckets that have filled up again, and any beyond max_keys."""
        while self._buckets:
            key, (tokens, when) = next(iter(self._buckets.items()))
            if len(self._buckets) <= self.max_keys and tokens + (now - when) * self.rate < self.burst:
                return
            del self._buckets[key]


def per_worker(rate: float, burst: int, workers: int) -> TokenBuckets | None:
    """This worker's buckets for a limit of ``rate`` a second (0: none) over ``workers`` workers."""
    if rate <= 0:
        return None
    return TokenBuckets(rate / workers, max(1.0, math.ceil(burst / workers)))


def rate_limits(settings) -> dict[str, TokenBuckets | None]:
    """The RateLimits middleware's buckets for these settings (this worker's share)."""
    return {"requests": per_worker(settings.rate_requests, settings.rate_requests_burst, settings.workers),
            "sessions": per_worker(settings.rate_sessions, settings.rate_sessions_burst, settings.workers)}


def client_key(scope) -> tuple[str, str]:
    """Who is asking: the authenticated tenant, else the client's IP address."""
    tenant = (scope.get("state") or {}).get("tenant")
    if tenant:
        return ("tenant", str(tenant))
    client = scope.get("client")
    return ("address", client[0] if client else "")


def _creates_session(scope) -> bool:
    return scope["method"] == "POST" and scope["path"].rstrip("/") == "/v1/sessions"


class RateLimits:
    """ASGI middleware: the request and session-creation rates of each client on ``/v1``."""

    def __init__(self, app, requests: TokenBuckets | None, sessions: TokenBuckets | None):
        self.app, self.requests, self.sessions = app, requests, sessions

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket") or not scope["path"].startswith("/v1/"):
            return await self.app(scope, receive, send)
        key = client_key(scope)
        if self.requests is not None:
            wait = self.requests.take(key)
            if wait:
                return await self._refuse("requests", wait, scope, receive, send)
        if scope["type"] == "websocket":  # each chunk on the socket takes a request's token (stream.py)
            scope.setdefault("state", {})["rate_limit"] = (self.requests, key)
            return await self.app(scope, receive, send)
        if self.sessions is None or not _creates_session(scope):
            return await self.app(scope, receive, send)
        wait = self.sessions.take(key)
        if wait:
            return await self._refuse("sessions", wait, scope, receive, send)
        status = {}

        async def watch(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, watch)
        finally:
            if status.get("code") != 201:  # no session made: its token is given back
                self.sessions.give_back(key)

    async def _refuse(self, limit: str, wait: float, scope, receive, send) -> None:
        LIMITED.labels(limit).inc()
        buckets = self.requests if limit == "requests" else self.sessions
        what = "requests" if limit == "requests" else "sessions created"
        setting = f"YAUYAU_RATE_{limit.upper()}"
        retry = max(1, math.ceil(wait))
        detail = (f"more than {buckets.rate:g} {what} per second from this client on this worker ({setting}, "
                  f"burst {setting}_BURST); retry in {retry} s")
        response = problem_response(429, detail, title="Too many requests", instance=scope.get("path"),
                                    headers={"Retry-After": str(retry)})
        await response(scope, receive, send)
