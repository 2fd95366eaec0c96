"""``GET /metrics``: Prometheus text for the HTTP side and the placement loop.

HTTP request counts and latencies are recorded by a middleware; the placement loop's and the
link's counters are read when Prometheus scrapes (a custom collector), so the service itself
knows nothing of Prometheus.

Every label value comes from a closed set, whatever a client sends (any client may send
anything, and the middleware runs before the token check): the method is one the route takes
(one of :data:`HTTP_METHODS` where no route matched) or ``other``, the route is a route's
template (``/v1/reports``) or ``other``, never the raw path; the status is the one the app
answered. So the text a scrape renders has a bounded size however many odd requests came
before it (:func:`render_metrics` renders it off the event loop).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LINK_STATES = ("connecting", "up", "link_lost")
CONTROL_HOLDERS = ("service", "pilot", "autopilot", "operator")
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
"""The methods a request is counted under by name; any other: ``other``."""
OTHER = "other"
CONNECTION_CLOSE_REASONS = (
    "client_cap",
    "evicted",
    "full",
    "read_timeout",
    "write_timeout",
)
"""Why the server closed a connection itself (:class:`api.server.ConnectionTable`)."""


def method_label(scope: Scope) -> str:
    """The request's method if the route that matched takes it (no route matched: if it is a
    standard one), else ``other``: a 405 is counted under ``other``, so that a route has
    label sets for its own methods only."""
    method = scope.get("method")
    allowed = getattr(scope.get("route"), "methods", None)
    if allowed is not None:
        return method if method in allowed else OTHER
    return method if method in HTTP_METHODS else OTHER


def route_label(scope: Scope) -> str:
    """The template of the route that matched (``/v1/policy``), else ``other`` (no route
    matched, or the request was answered before routing: 401, 413, 429, ...)."""
    path = getattr(scope.get("route"), "path", None)
    return path if isinstance(path, str) else OTHER


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
        yield CounterMetricFamily(
            "tupa_fleet_decisions_degraded",
            "Fleet decisions taken without every vehicle (degraded mode; 0 for one vehicle)",
            value=counters.get("decisions_degraded", 0),
        )
        sole = service.sole_vehicle_id()
        if sole is None:
            return
        # One vehicle: its link's families unlabelled too, as before there were fleets.
        state = service.links[sole].state()
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
    commanded, armed, setpoints sent, reconnects, who has it, the battery and the returns it
    caused, route holds, foreign MAVLink ignored."""
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
    control = GaugeMetricFamily(
        "tupa_vehicle_control",
        "Who has each vehicle (1 = current): service, pilot, autopilot or operator",
        labels=["vehicle", "holder"],
    )
    released = CounterMetricFamily(
        "tupa_vehicle_control_released",
        "Times each vehicle left the service's hands (a pilot, a failsafe, an operator)",
        labels=["vehicle"],
    )
    mode_requests = CounterMetricFamily(
        "tupa_vehicle_mode_requests",
        "Requests for the guided mode (GUIDED / OFFBOARD) sent to each vehicle",
        labels=["vehicle"],
    )
    battery = GaugeMetricFamily(
        "tupa_vehicle_battery_remaining_percent",
        "Each vehicle's remaining charge, % (only vehicles that report one)",
        labels=["vehicle"],
    )
    returns = CounterMetricFamily(
        "tupa_vehicle_battery_returns",
        "Times the service sent a vehicle home at its battery reserve",
        labels=["vehicle"],
    )
    route_holds = CounterMetricFamily(
        "tupa_vehicle_route_holds",
        "Times a vehicle held because its envelope left no legal route to the target",
        labels=["vehicle"],
    )
    foreign = CounterMetricFamily(
        "tupa_vehicle_foreign_mavlink",
        "MAVLink messages and datagrams from systems other than the vehicle's, ignored",
        labels=["vehicle"],
    )
    for view in views:
        state = view.state
        for name in LINK_STATES:
            link.add_metric([view.id, name], 1.0 if state.link == name else 0.0)
        commanded.add_metric([view.id], float(view.problem is None and view.decision is not None))
        armed.add_metric([view.id], float(state.armed))
        setpoints.add_metric([view.id], state.counters.get("setpoints_sent", 0))
        reconnects.add_metric([view.id], state.counters.get("reconnects", 0))
        for holder in CONTROL_HOLDERS:
            control.add_metric([view.id, holder], 1.0 if state.control == holder else 0.0)
        released.add_metric([view.id], state.counters.get("control_released", 0))
        mode_requests.add_metric([view.id], state.counters.get("mode_requests", 0))
        if state.battery_pct is not None:
            battery.add_metric([view.id], state.battery_pct)
        returns.add_metric([view.id], state.counters.get("battery_returns", 0))
        route_holds.add_metric([view.id], state.counters.get("route_holds", 0))
        foreign.add_metric(
            [view.id],
            state.counters.get("foreign_messages", 0) + state.counters.get("foreign_datagrams", 0),
        )
    yield from (
        link,
        commanded,
        armed,
        setpoints,
        reconnects,
        control,
        released,
        mode_requests,
        battery,
        returns,
        route_holds,
        foreign,
    )


class ConnectionCollector(Collector):
    """The server's open connections and why it closed some itself, read at scrape time from
    ``get_table()`` (an :class:`api.server.ConnectionTable`, ``None`` before a server runs)."""

    def __init__(self, get_table: Callable[[], Any]) -> None:
        self._get_table = get_table

    def collect(self) -> Iterator[Any]:
        table = self._get_table()
        if table is None:
            return
        yield GaugeMetricFamily(
            "tupa_http_connections", "HTTP connections open", value=float(table.total)
        )
        yield GaugeMetricFamily(
            "tupa_http_clients",
            "Clients (peer addresses) with a connection open",
            value=float(table.clients),
        )
        closed = CounterMetricFamily(
            "tupa_http_connections_closed",
            "HTTP connections the server closed itself, by reason",
            labels=["reason"],
        )
        for reason in CONNECTION_CLOSE_REASONS:
            closed.add_metric([reason], table.closed.get(reason, 0))
        yield closed


async def render_metrics(registry: CollectorRegistry) -> bytes:
    """The Prometheus text of ``registry``, rendered in a worker thread (collecting and
    formatting take the time they take: not on the event loop, where every other request
    waits for them)."""
    return await asyncio.to_thread(generate_latest, registry)


class HttpMetrics:
    """Request counter and latency histogram, labelled by route template, method and status,
    each from a closed set (bounded cardinality: :func:`method_label`, :func:`route_label`)."""

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
            template = route_label(scope)
            method = method_label(scope)
            self.metrics.requests.labels(template, method, str(status)).inc()
            self.metrics.latency.labels(template, method).observe(time.perf_counter() - started)
