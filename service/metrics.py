"""Prometheus metrics of the service (GET /metrics).

With several uvicorn workers ``yauyau serve`` sets ``PROMETHEUS_MULTIPROC_DIR`` before the workers
start; each worker then writes its samples there and /metrics aggregates all workers.  With one
worker the default in-process registry is used.
"""

from __future__ import annotations

import os
import time

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
    multiprocess,
)

REQUESTS = Counter("yauyau_http_requests_total", "HTTP requests", ["method", "route", "status"])
LATENCY = Histogram("yauyau_http_request_seconds", "HTTP request latency", ["route"],
                    buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0, 5.0))
OBSERVATIONS = Counter("yauyau_observations_total", "observation increments applied")
CHUNKS = Counter("yauyau_chunks_total", "observation chunks", ["outcome"])  # applied | replayed
SESSIONS = Counter("yauyau_sessions_created_total", "sessions created", ["method"])
DEGENERATE = Counter("yauyau_degenerate_chunks_total", "chunks whose answer was degenerate")
GATED = Counter("yauyau_gated_observations_total",
                "rows rejected by the outlier gate (the step only predicted)")
REINITIALISED = Counter("yauyau_reinitialised_total",
                        "rows where a degenerate filter started again by itself "
                        "(on_degenerate = reinitialise)")
BATCH_SIZE = Histogram("yauyau_chunk_batch_size", "chunks applied together in one batch (micro-batching)",
                       buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256))
EXPIRED = Counter("yauyau_sessions_expired_total", "sessions deleted after their idle expiry")
RESETS = Counter("yauyau_resets_total", "sessions reset over HTTP (POST /v1/sessions/{id}/reset)")
ALARMS = Counter("yauyau_monitor_alarms_total",
                 "rows where the innovation monitor raised its alarm (a sustained bias of the observations "
                 "against their predictions: solver/watch.py)")
LOST = Counter("yauyau_lost_track_chunks_total",
               "chunks answered degenerate because the filter lost track (it kept gating or restarting: "
               "solver/watch.py)")


def render() -> tuple[bytes, str]:
    """The exposition text (all workers when in multiprocess mode)."""
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry), CONTENT_TYPE_LATEST
    return generate_latest(), CONTENT_TYPE_LATEST


class RequestMetrics:
    """ASGI middleware counting requests by route template (not raw path: bounded label set)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start = time.perf_counter()
        status = {"code": 500}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            REQUESTS.labels(scope.get("method", ""), route, str(status["code"])).inc()
            LATENCY.labels(route).observe(time.perf_counter() - start)
