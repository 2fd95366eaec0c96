"""``GET /metrics``: Prometheus text for the HTTP side and the placement loop.

HTTP request counts and latencies are recorded by a middleware; the placement loop's and the
link's counters are read when Prometheus scrapes (a custom collector), so the service itself
knows nothing of Prometheus.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LINK_STATES = ("connecting", "up", "link_lost")


class ServiceCollector(Collector):
    """Reads the placement service's counters and the link's state at scrape time."""

    def __init__(self, get_service: Callable[[], Any]) -> None:
        self._get_service = get_service

    def collect(self) -> Iterator[Any]:
        service = self._get_service()
        if service is None:
            return
        counters = service.snapshot_counters()
        decisions = CounterMetricFamily(
            "tupa_decisions", "Placement decisions, by outcome", labels=["outcome"]
        )
        decisions.add_metric(["decided"], counters.get("decisions", 0))
        for outcome in ("held_stale", "waiting_link", "rejected"):
            decisions.add_metric([outcome], counters.get(f"decisions_{outcome}", 0))
        decisions.add_metric(["error"], counters.get("decision_errors", 0))
        yield decisions
        reports = CounterMetricFamily("tupa_reports", "User reports, by result", labels=["result"])
        reports.add_metric(["accepted"], counters.get("reports_accepted", 0))
        reports.add_metric(["out_of_order"], counters.get("reports_out_of_order", 0))
        reports.add_metric(["from_the_future"], counters.get("reports_from_the_future", 0))
        yield reports
        yield CounterMetricFamily(
            "tupa_policy_swaps", "Policies swapped in", value=counters.get("policy_swaps", 0)
        )
        yield from _vehicle_families(service.vehicles())
        hub = service.live.hub
        yield GaugeMetricFamily(
            "tupa_live_streams", "Operator-view streams open", value=float(len(hub))
        )
        yield CounterMetricFamily(
            "tupa_live_frames_dropped",
            "Operator-view frames a slow client lost (its queue was full)",
            value=hub.dropped,
        )
        if service.is_fleet:
            yield CounterMetricFamily(
                "tupa_fleet_decisions_degraded",
                "Fleet decisions taken without every vehicle (degraded mode)",
                value=counters.get("decisions_degraded", 0),
            )
            return
        state = service.vehicle()
        link_counters = state.counters
        yield CounterMetricFamily(
            "tupa_setpoints_sent",
            "MAVLink position setpoints sent",
            value=link_counters.get("setpoints_sent", 0),
        )
        yield CounterMetricFamily(
            "tupa_geofence_clamps",
            "Targets clamped to the geofence",
            value=link_counters.get("geofence_clamps", 0),
        )
        yield CounterMetricFamily(
            "tupa_link_reconnects",
            "MAVLink reconnections",
            value=link_counters.get("reconnects", 0),
        )
        link = GaugeMetricFamily(
            "tupa_link_state", "MAVLink link state (1 = current)", labels=["state"]
        )
        for name in LINK_STATES:
            link.add_metric([name], 1.0 if state.link == name else 0.0)
        yield link
        yield GaugeMetricFamily(
            "tupa_vehicle_armed", "Vehicle armed (1) or not (0)", value=float(state.armed)
        )
        yield GaugeMetricFamily(
            "tupa_streaming",
            "Setpoints being streamed (1) or not (0)",
            value=float(state.streaming),
        )


def _vehicle_families(views: list[Any]) -> Iterator[Any]:
    """Per-vehicle families, labelled ``vehicle`` (one vehicle: ``uav1``): link state,
    commanded, armed, setpoints sent, reconnects."""
    link = GaugeMetricFamily(
        "tupa_vehicle_link_state",
        "Each vehicle's MAVLink link state (1 = current)",
        labels=["vehicle", "state"],
    )
    commanded = GaugeMetricFamily(
        "tupa_vehicle_commanded",
        "Whether the vehicle is streamed a target now (1) or not (0)",
        labels=["vehicle"],
    )
    armed = GaugeMetricFamily("tupa_vehicle_is_armed", "Vehicle armed (1)", labels=["vehicle"])
    setpoints = CounterMetricFamily(
        "tupa_vehicle_setpoints_sent", "Setpoints sent to each vehicle", labels=["vehicle"]
    )
    reconnects = CounterMetricFamily(
        "tupa_vehicle_link_reconnects", "MAVLink reconnections, by vehicle", labels=["vehicle"]
    )
    for view in views:
        state = view.state
        for name in LINK_STATES:
            link.add_metric([view.id, name], 1.0 if state.link == name else 0.0)
        commanded.add_metric([view.id], float(view.problem is None and view.decision is not None))
        armed.add_metric([view.id], float(state.armed))
        setpoints.add_metric([view.id], state.counters.get("setpoints_sent", 0))
        reconnects.add_metric([view.id], state.counters.get("reconnects", 0))
    yield from (link, commanded, armed, setpoints, reconnects)


class HttpMetrics:
    """Request counter and latency histogram, labelled by route template (bounded cardinality)."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.requests = Counter(
            "tupa_http_requests",
            "HTTP requests, by route, method and status",
            ["route", "method", "status"],
            registry=registry,
        )
        self.latency = Histogram(
            "tupa_http_request_duration_seconds",
            "HTTP request latency, by route",
            ["route", "method"],
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5),
            registry=registry,
        )
        self.rate_limited = Counter(
            "tupa_http_rate_limited",
            "HTTP requests turned away with 429 (over a client's rate)",
            registry=registry,
        )


class HttpMetricsMiddleware:
    """Pure ASGI middleware recording :class:`HttpMetrics` for every HTTP request (cheaper than
    Starlette's ``BaseHTTPMiddleware``, which copies each response through a stream)."""

    def __init__(self, app: ASGIApp, metrics: HttpMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def recording_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, recording_send)
        finally:
            template = getattr(scope.get("route"), "path", "unmatched")
            method = scope["method"]
            self.metrics.requests.labels(template, method, str(status)).inc()
            self.metrics.latency.labels(template, method).observe(time.perf_counter() - started)
