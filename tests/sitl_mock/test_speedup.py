"""The mock's clock may run faster than the wall clock (``MockAutopilot(speedup=...)``, as
ArduPilot SITL's ``--speedup``): the vehicle's physics, boot and telemetry all follow it."""

from __future__ import annotations

import math
import time

import pytest

from sitl_mock.config import VehicleConfig
from sitl_mock.fleet import MockFleet
from sitl_mock.server import MAX_SPEEDUP, MockAutopilot
from tests.conftest import GROUND_STATION_TIMERS, MOCK_SPEEDUP


@pytest.mark.parametrize("speedup", [0.0, -1.0, math.nan, math.inf, MAX_SPEEDUP + 1])
def test_an_impossible_speedup_is_refused_naming_it(speedup: float) -> None:
    with pytest.raises(ValueError, match=r"^speedup: must be in"):
        MockAutopilot("tcp:127.0.0.1:0", speedup=speedup)


def test_a_fleet_runs_every_vehicle_at_its_speedup() -> None:
    fleet = MockFleet(3, speedup=2.5)  # constructed only: nothing bound
    assert [mock.speedup for mock in fleet] == [2.5, 2.5, 2.5]
    with pytest.raises(ValueError, match=r"^speedup: must be in"):
        MockFleet(2, speedup=0.0)


def test_a_faster_clock_runs_the_vehicle_and_its_heartbeats_that_much_faster(
    start_mock, connect
) -> None:
    """Two mocks side by side, one at real time and one at 3x: over the same three wall-clock
    seconds the fast one's clock advances about three times as far and sends at least twice as
    many of its 1 Hz heartbeats (2-4 against 8-10, by where the window falls: ratios measured
    in one run, so the machine's load cancels out)."""
    mocks = {
        "real": start_mock("ardupilot", speedup=1.0),
        "fast": start_mock("ardupilot", speedup=3.0),
    }
    clients = {name: connect(mock) for name, mock in mocks.items()}
    for client in clients.values():
        client.wait("HEARTBEAT")
        client.mark()
    clock_s = {name: mock.vehicle.time_s for name, mock in mocks.items()}
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        for client in clients.values():
            client.pump(timeout_s=0.01)
    advanced_s = {name: mock.vehicle.time_s - clock_s[name] for name, mock in mocks.items()}
    beats = {
        name: sum(m.get_type() == "HEARTBEAT" for m in client.received[client._cursor :])
        for name, client in clients.items()
    }
    assert 2.5 <= advanced_s["fast"] / advanced_s["real"] <= 3.2, advanced_s
    assert beats["fast"] >= 2 * beats["real"] >= 4, beats


def test_start_mock_keeps_the_ground_stations_wall_clock_timers(start_mock) -> None:
    """The fixture's faster vehicles judge the service's stream and heartbeats over as many
    wall-clock seconds as a real-time one would; a test's own value is kept as given."""
    fast = start_mock("px4")
    given = start_mock("px4", offboard_timeout_s=0.5)
    defaults = VehicleConfig()
    assert fast.speedup == MOCK_SPEEDUP > 1.0
    for name in GROUND_STATION_TIMERS:
        assert getattr(fast.vehicle.config, name) == getattr(defaults, name) * MOCK_SPEEDUP, name
    assert given.vehicle.config.offboard_timeout_s == 0.5
    assert given.vehicle.config.gcs_failsafe_s == defaults.gcs_failsafe_s * MOCK_SPEEDUP
