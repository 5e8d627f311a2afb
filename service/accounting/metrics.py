"""Prometheus metrics of one app, in the app's own registry (several apps can live in one process).

Label sets are bounded: ``route`` is the matched route template (``unmatched`` otherwise), ``model``
and ``tenant`` come from the settings (never from what a client sends), ``status`` is an HTTP code.
"""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
HTTP_METHODS = frozenset({"GET", "POST", "PUT", "PATCH", "DELETE", "HEAD", "OPTIONS"})
STAGE_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class ServiceMetrics:
    """The service's metrics: request counts and latency, inference stages, MACs, errors, queue depth."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter("radarseg_http_requests", "HTTP requests by route, method and status code",
                                ["route", "method", "status"], registry=r)
        self.request_seconds = Histogram("radarseg_http_request_duration_seconds", "HTTP request latency (s)",
                                         ["route", "method"], buckets=LATENCY_BUCKETS, registry=r)
        self.errors = Counter("radarseg_http_errors", "HTTP error answers by status code", ["status"], registry=r)
        self.stage_seconds = Histogram("radarseg_stage_duration_seconds", "Latency of a segmentation stage (s)",
                                       ["model", "stage"], buckets=STAGE_BUCKETS, registry=r)
        self.segmentations = Counter("radarseg_segment_requests", "Segmentation requests billed, by model and tenant",
                                     ["model", "tenant"], registry=r)
        self.macs = Counter("radarseg_macs", "MACs spent by model and tenant", ["model", "tenant"], registry=r)
        self.roi_voxels = Counter("radarseg_roi_voxels", "ROI voxels segmented by model", ["model"], registry=r)
        self.rejected = Counter("radarseg_rejected_requests", "Segmentation requests refused before inference",
                                ["model", "reason"], registry=r)
        self.queue = Gauge("radarseg_model_slots_held", "Requests running or queued per model", ["model"], registry=r)
        self.ready = Gauge("radarseg_model_ready", "1 when the model is loaded", ["model"], registry=r)
        self.server_refusals = Counter(
            "radarseg_server_refusals", "Connections and requests the HTTP server layer refused or closed before "
            "the app saw them (header_timeout, head_too_large, target_too_long, malformed_http, connection_cap, "
            "connection_evicted)", ["reason"], registry=r)


class MetricsMiddleware:
    """Pure ASGI middleware: counts every HTTP request by route template, method and status, and times it."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500  # unless a response starts

        async def send_with_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_with_status)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            method = scope.get("method", "GET")
            method = method if method in HTTP_METHODS and template != "unmatched" else "other"
            self.metrics.requests.labels(template, method, str(status)).inc()
            self.metrics.request_seconds.labels(template, method).observe(time.perf_counter() - start)
            if status >= 400:
                self.metrics.errors.labels(str(status)).inc()
