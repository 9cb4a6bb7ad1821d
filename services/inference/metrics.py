"""Prometheus metrics of one inference server (its own registry, so several can share a process)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64)


class Metrics:
    """requests, request latency, batch sizes, queue wait, model time, queue depth, reloads."""

    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("n3dmap_requests", "Requests answered, by transport, route and status",
                                ["transport", "route", "status"], registry=r)
        self.latency = Histogram("n3dmap_request_seconds", "End-to-end request latency in the server",
                                 ["transport", "route"], buckets=LATENCY_BUCKETS, registry=r)
        self.batch_size = Histogram("n3dmap_batch_size", "Requests per model call", ["route"],
                                    buckets=BATCH_BUCKETS, registry=r)
        self.queue_wait = Histogram("n3dmap_queue_wait_seconds", "Time a request waited for its batch",
                                    ["route"], buckets=LATENCY_BUCKETS, registry=r)
        self.model_time = Histogram("n3dmap_model_seconds", "Duration of one batched model call",
                                    ["route"], buckets=LATENCY_BUCKETS, registry=r)
        self.queue_depth = Gauge("n3dmap_queue_depth", "Requests waiting for a batch", registry=r)
        self.in_flight = Gauge("n3dmap_in_flight", "Requests waiting for or inside a model call", registry=r)
        self.reloads = Counter("n3dmap_reloads", "Bundle reloads by result", ["result"], registry=r)
        self.stream_dropped = Counter("n3dmap_stream_frames_dropped",
                                      "StreamMovingObjects frames dropped unanswered, by reason", ["reason"], registry=r)

    def observe_batch(self, route: str, batch_size: int, waits_s: list[float], model_s: float) -> None:
        self.batch_size.labels(route).observe(batch_size)
        self.model_time.labels(route).observe(model_s)
        for w in waits_s:
            self.queue_wait.labels(route).observe(w)

    def observe_request(self, transport: str, route: str, status: str, seconds: float) -> None:
        self.requests.labels(transport, route, status).inc()
        self.latency.labels(transport, route).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)
