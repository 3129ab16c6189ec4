"""``/metrics`` in the Prometheus text format.

Queue figures are read from Redis at scrape time (so any API replica reports the same): jobs
by state (queued, running), workers, completed jobs by outcome (counters the workers keep in
Redis) and the job-duration histogram; plus this process's HTTP request counter.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
)

from pbrsr_jobs.store import JobIndex

log = logging.getLogger("pbrsr.service")
router = APIRouter(tags=["metrics"])


class QueueCollector:
    """Collects queue state from Redis on every scrape."""

    def __init__(self, app: Any):
        self.app = app

    def describe(self) -> list:
        return []

    def collect(self):  # noqa: ANN201 - prometheus protocol
        from rq import Queue, Worker
        from rq.registry import ScheduledJobRegistry, StartedJobRegistry

        settings = self.app.state.settings
        up = GaugeMetricFamily("pbrsr_redis_up", "1 when Redis answered this scrape.")
        try:
            redis = self.app.state.metrics_redis()
            queues = [Queue(q, connection=redis) for q in settings.listen_queues("all")]
            depths = {q.name: q.count for q in queues}
            queued = sum(depths.values()) + sum(ScheduledJobRegistry(queue=q).count for q in queues)
            running = sum(StartedJobRegistry(queue=q).count for q in queues)
            workers = len({w.name for q in queues for w in Worker.all(queue=q)})
            index = JobIndex(redis, settings.key_prefix)
            outcomes = index.outcomes()
            buckets, _count, total = index.duration_histogram()
        except Exception as exc:  # noqa: BLE001 - a scrape must not fail
            log.warning("metrics: redis unavailable: %s", exc)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        jobs = GaugeMetricFamily("pbrsr_jobs", "Jobs by state (queued, running).", labels=["state"])
        jobs.add_metric(["queued"], queued)
        jobs.add_metric(["running"], running)
        yield jobs
        depth = GaugeMetricFamily("pbrsr_queue_depth", "Jobs waiting, per queue.", labels=["queue"])
        for name, n in depths.items():
            depth.add_metric([name], n)
        yield depth
        w = GaugeMetricFamily("pbrsr_workers", "Workers listening on the queues.")
        w.add_metric([], workers)
        yield w
        done = CounterMetricFamily(
            "pbrsr_jobs_completed", "Jobs that ended, by outcome.", labels=["state"]
        )
        for state in ("finished", "failed", "canceled"):
            done.add_metric([state], outcomes.get(state, 0))
        yield done
        hist = HistogramMetricFamily(
            "pbrsr_job_duration_seconds", "Run time of finished jobs (seconds)."
        )
        hist.add_metric([], buckets=buckets, sum_value=total)
        yield hist


def install_metrics(app: Any) -> None:
    """Give ``app`` its own registry (so several apps in one process don't clash)."""
    registry = CollectorRegistry()
    registry.register(QueueCollector(app))
    app.state.metrics_registry = registry
    counter = Counter(
        "pbrsr_http_requests",
        "HTTP requests answered, by method and status class.",
        ["method", "status"],
        registry=registry,
    )
    app.add_middleware(RequestCounter, counter=counter)


class RequestCounter:
    """Pure ASGI middleware counting responses (does not touch streamed request bodies)."""

    def __init__(self, app: Any, counter: Counter):
        self.app = app
        self.counter = counter

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = {"code": 500}

        async def _send(message: dict) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, _send)
        finally:
            self.counter.labels(scope.get("method", "?"), f"{status['code'] // 100}xx").inc()


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}},
    summary="Prometheus metrics",
)
def metrics(request: Request) -> Response:
    data = generate_latest(request.app.state.metrics_registry)
    return Response(data, media_type=CONTENT_TYPE_LATEST)
