"""Prometheus metrics of one app instance (its own registry, so apps never collide)."""

from __future__ import annotations

from typing import Any, Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client import CONTENT_TYPE_LATEST

from .workers import PoolStats

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
                   120.0)


class Metrics:
    """The service's metrics.

    ``planner_http_requests_total{route,method,status}``,
    ``planner_http_request_duration_seconds{route,method,status}``,
    ``planner_solve_duration_seconds{job,method,outcome}`` (wall time of a job on a worker;
    ``outcome`` is ``success`` or the problem code), ``planner_worker_restarts_total{reason}``
    gauges of the pool (``planner_workers{state}``: ``idle``, ``busy``;
    ``planner_workers_live``, ``planner_workers_configured``, ``planner_queue_waiting``) and
    ``planner_requests_cancelled_total{reason}`` (``client_gone``, ``shutdown``),
    ``planner_connections_closed_total{reason}``.
    """

    content_type = CONTENT_TYPE_LATEST

    def __init__(self, pool_stats: Callable[[], PoolStats] | None = None) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("planner_http_requests", "HTTP requests by route and status.",
                                ["route", "method", "status"], registry=self.registry)
        self.latency = Histogram("planner_http_request_duration_seconds",
                                 "HTTP request latency by route and status.",
                                 ["route", "method", "status"], buckets=LATENCY_BUCKETS,
                                 registry=self.registry)
        self.solve = Histogram("planner_solve_duration_seconds",
                               "Time of a job on a worker, by job, method and outcome.",
                               ["job", "method", "outcome"], buckets=LATENCY_BUCKETS,
                               registry=self.registry)
        self.restarts = Counter("planner_worker_restarts", "Worker processes replaced.",
                                ["reason"], registry=self.registry)
        self.workers = Gauge("planner_workers", "Worker processes by state.", ["state"],
                             registry=self.registry)
        self.live = Gauge("planner_workers_live", "Worker processes started, warmed up and "
                          "answering pings.", registry=self.registry)
        self.configured = Gauge("planner_workers_configured", "Configured worker processes.",
                                registry=self.registry)
        self.waiting = Gauge("planner_queue_waiting", "Requests waiting for a worker.",
                             registry=self.registry)
        self.connections_closed = Counter(
            "planner_connections_closed", "Client connections refused or closed by the server, "
            "by reason (limit, header_timeout, bad_request, body_timeout, unread_body, "
            "send_timeout).",
            ["reason"], registry=self.registry)
        self.cancelled = Counter("planner_requests_cancelled", "Requests given up before "
                                 "their answer, by reason.", ["reason"], registry=self.registry)
        self._pool_stats = pool_stats
        # the labelled children, looked up once (``labels()`` costs more than the update)
        self._request_children: dict[tuple[str, str, int], tuple[Any, Any]] = {}
        self._solve_children: dict[tuple[str, str, str], Any] = {}

    def bind_pool(self, pool_stats: Callable[[], PoolStats]) -> None:
        """Read the pool gauges from ``pool_stats`` at each scrape."""
        self._pool_stats = pool_stats

    def observe_request(self, route: str, method: str, status: int, seconds: float) -> None:
        """Count one HTTP request and its latency."""
        key = (route, method, status)
        children = self._request_children.get(key)
        if children is None:  # (labels are bounded: route templates, methods, statuses)
            labels = (route, method, str(status))
            children = (self.requests.labels(*labels), self.latency.labels(*labels))
            self._request_children[key] = children
        children[0].inc()
        children[1].observe(seconds)

    def observe_solve(self, job: str, method: str, outcome: str, seconds: float) -> None:
        """Record one job's time on a worker."""
        key = (job, method, outcome)
        child = self._solve_children.get(key)
        if child is None:
            child = self._solve_children[key] = self.solve.labels(job, method, outcome)
        child.observe(seconds)

    def render(self) -> bytes:
        """The text exposition format."""
        if self._pool_stats is not None:
            st = self._pool_stats()
            self.workers.labels("idle").set(st.idle)
            self.workers.labels("busy").set(st.busy)
            self.live.set(st.live)
            self.configured.set(st.size)
            self.waiting.set(st.waiting)
        return generate_latest(self.registry)
