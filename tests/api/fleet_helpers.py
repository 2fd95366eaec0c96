"""A fleet of three FakeLinks behind the HTTP app, for the API tests: the constants, a report
of users in three hot spots, and the ``fleet`` fixture (tests/api/conftest.py)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from api.app import create_app
from service.fleet_placement import FleetPlacementService, load_fleet_policy
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from tests.fakes import FakeLink

TOKEN = "fleet-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
URLS = ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5761", "tcp:127.0.0.1:5762")


def report_body() -> dict[str, Any]:
    rng = np.random.default_rng(3)
    users = []
    for c, (cx, cy) in enumerate(((100.0, 100.0), (400.0, 400.0), (100.0, 400.0))):
        for i, (x, y) in enumerate(rng.normal((cx, cy), 15.0, (5, 2)).clip(0, 500)):
            users.append({"id": f"u{c}-{i}", "x_m": x, "y_m": y, "offered_bps": 2e6,
                          "throughput_bps": 2e6, "delay_s": 0.01, "plr": 0.0})  # fmt: skip
    return {"timestamp": time.time(), "users": users}


def single_app(
    position_m: tuple[float, float, float] = (250.0, 250.0, 30.0),
) -> Iterator[tuple[TestClient, FakeLink]]:
    """A one-vehicle service (load-weighted, on-report) over a FakeLink at ``position_m``
    behind a TestClient, started while the generator runs."""
    settings = ServiceSettings(mavlink=URLS[0], api_token=TOKEN, decision_mode="on-report")
    world = settings.policy_world()
    link = FakeLink(LinkConfig(URLS[0], area=world.area), position_m=position_m)

    def factory(s: ServiceSettings) -> PlacementService:
        return PlacementService(s, link, load_policy("load-weighted", world), world)

    with TestClient(create_app(settings, service_factory=factory)) as client:
        yield client, link


def fleet_app() -> Iterator[tuple[TestClient, dict[str, FakeLink]]]:
    """The fleet service behind a TestClient, started while the generator runs."""
    settings = ServiceSettings(fleet_mavlink=URLS, api_token=TOKEN, decision_mode="on-report")
    world = settings.policy_world()
    links = {
        f"uav{i + 1}": FakeLink(
            LinkConfig(url, area=world.area), position_m=(200.0 + 60 * i, 250.0, 30.0),
            system_id=i + 1,
        )
        for i, url in enumerate(URLS)
    }  # fmt: skip

    def factory(s: ServiceSettings) -> PlacementService:
        spec = s.fleet_spec()
        policy = load_fleet_policy("kmeans-load-weighted", world, spec.separation_m)
        return FleetPlacementService(s, links, policy, spec, world)

    with TestClient(create_app(settings, service_factory=factory)) as client:
        yield client, links
