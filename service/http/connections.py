"""What a client can make one worker hold in connections: a deadline for the request head and a cap.

uvicorn bounds neither: it arms its keep-alive timer only after a response, so a connection that
never completes a request head is kept forever, and its ``limit_concurrency`` is checked only when a
head is complete (the half-open connections then count against it, so it answers the real requests
503 instead).  Five thousand sockets that each send half a head exhausted a 4 096-descriptor worker:
asyncio's accept failed with EMFILE (logged with its traceback, again and again) and ``/livez``
timed out.  Here, per worker process:

* a connection that has not delivered a complete request head ``header_timeout`` seconds after it
  opened (or, on a kept-alive connection, after the first byte of its next head) is closed;
* at most ``max_connections`` are open: a newcomer at the cap closes the connection that has been
  waiting longest for its request head (a slowloris victim, or an idle kept-alive one); when every
  other connection is busy with a request, the newcomer is answered 503 problem+json with
  Retry-After once its head arrives (it is itself the first to go for the next newcomer);
* none of this is logged per connection: one warning at most every ``WARN_EVERY`` seconds says how
  many were closed, evicted or refused (asyncio's accept errors are counted there too).

The cap's default comes from the process's descriptor limit (RLIMIT_NOFILE): the limit less a
reserve for the session store, models, logs and child processes (``FD_RESERVE``; a worker that has
served sessions of two models holds 16 descriptors, measured) and less the listen backlog, because
asyncio accepts up to a backlog's worth of connections in one go before any of them can be looked at.
A half-open connection costs about 5.5 kB of memory (measured with 2 000 and 8 000), hence the ceiling.
"""

from __future__ import annotations

import logging
import resource
import time
from collections import Counter
from typing import Any

from prometheus_client import Counter as PromCounter

log = logging.getLogger("yauyau.service")

FD_RESERVE = 256  # descriptors kept for the store, the models, logs, pipes to analysis and job processes
UVICORN_BACKLOG = 2048  # uvicorn's default listen backlog, lowered when the descriptor limit is small
MAX_CONNECTIONS_CEILING = 4096  # the default cap however high the limit (about 22 MB of connections)
WARN_EVERY = 10.0  # seconds between two warnings about closed or refused connections

CLOSED = PromCounter("yauyau_connections_closed_total", "connections the server closed or refused to "
                     "bound what clients hold", ["reason"])

_REASONS = {"header_timeout": "sent no complete request head within {timeout:g} s (header_timeout)",
            "evicted": "waited longest for a request head when a newcomer found {cap} connections open "
                       "(max_connections)",
            "refused": "found {cap} connections busy with requests and were answered 503",
            "invalid": "sent an invalid request (answered 400)",
            "accept_failed": "could not be accepted: the process is out of file descriptors"}


def descriptor_limit() -> int:
    """The soft RLIMIT_NOFILE of this process (what it may have open)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return soft if soft != resource.RLIM_INFINITY else 1 << 20


def plan(max_connections: int | None, limit: int | None = None) -> tuple[int, int]:
    """(connections per worker, listen backlog) for a process that may open ``limit`` descriptors:
    ``max_connections`` when set, else what fits beside the reserve and a backlog's worth of
    connections accepted at once."""
    limit = descriptor_limit() if limit is None else limit
    budget = max(limit - FD_RESERVE, 128)
    backlog = min(UVICORN_BACKLOG, budget // 2)
    return (max_connections or min(MAX_CONNECTIONS_CEILING, budget - backlog)), backlog


class ConnectionGuard:
    """The connections of one worker: which are open, which wait for a request head (oldest first),
    and the counts of those closed since the last warning."""

    def __init__(self, loop, max_connections: int, header_timeout: float):
        self.loop, self.cap, self.header_timeout = loop, max_connections, header_timeout
        self.open: set[Any] = set()
        self.waiting: dict[Any, None] = {}  # insertion order: the longest waiting first
        self._counts: Counter[str] = Counter()
        self._flush = None
        self._last_warning = -WARN_EVERY
        previous = loop.get_exception_handler()
        loop.set_exception_handler(lambda loop, context: self._loop_error(previous, loop, context))

    def opened(self, conn) -> bool:
        """Register ``conn`` (just accepted, waiting for its head): True when it may be served, after
        closing the longest-waiting other connection if the cap is reached; False when every other
        connection is busy with a request (``conn`` is then to be answered 503)."""
        self.open.add(conn)
        self.wait_for_head(conn)
        if len(self.open) <= self.cap:
            return True
        victim = next(iter(self.waiting))
        if victim is conn:
            self.note("refused")
            return False
        self.closed(victim)
        victim.evict()
        self.note("evicted")
        return True

    def wait_for_head(self, conn) -> None:
        self.waiting.pop(conn, None)
        self.waiting[conn] = None

    def head_received(self, conn) -> None:
        self.waiting.pop(conn, None)

    def closed(self, conn) -> None:
        self.open.discard(conn)
        self.waiting.pop(conn, None)

    def note(self, reason: str) -> None:
        """Count one connection closed for ``reason``; the warning follows, at most every WARN_EVERY s."""
        self._counts[reason] += 1
        CLOSED.labels(reason).inc()
        if self._flush is None:
            delay = max(0.0, self._last_warning + WARN_EVERY - time.monotonic())
            self._flush = self.loop.call_later(delay, self._warn)

    def _warn(self) -> None:
        self._flush, self._last_warning = None, time.monotonic()
        counts, self._counts = self._counts, Counter()
        parts = [f"{n} {_REASONS[reason].format(timeout=self.header_timeout, cap=self.cap)}"
                 for reason, n in sorted(counts.items())]
        if parts:
            log.warning("connections closed or refused to bound what clients hold (at most one such line "
                        "every %g s): %s", WARN_EVERY, "; ".join(parts))

    def _loop_error(self, previous, loop, context) -> None:
        if context.get("message") == "socket.accept() out of system resource":
            self.note("accept_failed")  # asyncio retries the accept a second later by itself
            return
        if previous is not None:
            previous(loop, context)
        else:
            loop.default_exception_handler(context)


_guard: ConnectionGuard | None = None


def connection_guard(loop) -> ConnectionGuard:
    """This worker's guard (made on the first connection, from the ``YAUYAU_*`` settings)."""
    global _guard
    if _guard is None or _guard.loop is not loop:
        from ..settings import Settings

        settings = Settings()
        cap, _ = plan(settings.max_connections)
        _guard = ConnectionGuard(loop, cap, settings.header_timeout)
        log.info("connections: at most %d per worker (descriptor limit %d), request heads within %g s",
                 cap, descriptor_limit(), settings.header_timeout)
    return _guard


class QuietLogger:
    """uvicorn's logger for one connection, except that a request the parser finds invalid is counted for the
    periodic warning instead of a line each (a client decides how many it sends)."""

    INVALID = "Invalid HTTP request received."

    def __init__(self, logger: logging.Logger, guard: ConnectionGuard):
        self._logger, self._guard = logger, guard

    def warning(self, msg, *args, **kwargs) -> None:
        if msg == self.INVALID:
            self._guard.note("invalid")
        else:
            self._logger.warning(msg, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._logger, name)
