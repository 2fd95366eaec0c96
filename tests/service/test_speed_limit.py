"""The envelope's speed limit on the autopilot (issue 39): on ArduPilot the link sends
MAV_CMD_DO_CHANGE_SPEED with the envelope's ``max_speed_mps`` once the vehicle is in GUIDED with
the service's stream, and again for a new envelope's; PX4's offboard mode ignores the command, so
it is not sent there."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from sim.envelope import Envelope
from sitl_mock.server import MockAutopilot
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA, FAST_VEHICLE

pytestmark = pytest.mark.slow


def _speed(mock: MockAutopilot) -> float:
    return mock.with_vehicle(lambda v: v.max_speed_h_mps)


def test_arducopter_flies_guided_at_the_envelopes_speed_and_takes_a_new_one(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any]
) -> None:
    mock = start_mock("ardupilot", gcs_failsafe_action="none", **FAST_VEHICLE)
    before = _speed(mock)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    link.arm_and_takeoff().result(timeout=30.0)
    assert _speed(mock) == before  # nothing before the service streams in GUIDED
    link.set_target((40.0, 40.0, 15.0))
    wait_for(lambda: _speed(mock) == 4.0, 10.0, message="the envelope's speed on the vehicle")
    # The vehicle takes the speed before its ACK reaches the link: wait for the link to count it.
    wait_for(lambda: link.counters["speed_limits_set"] == 1, 5.0, message="the ACK counted")
    link.set_envelope(Envelope.for_area(AREA, max_speed_mps=6.0))
    wait_for(lambda: _speed(mock) == 6.0, 10.0, message="the new envelope's speed")
    wait_for(lambda: link.counters["speed_limits_set"] == 2, 5.0, message="the ACK counted")
    assert link.counters["speed_limit_failures"] == 0


def test_px4_is_not_asked(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any]
) -> None:
    mock = start_mock("px4", **FAST_VEHICLE)
    before = _speed(mock)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    link.arm_and_takeoff().result(timeout=30.0)
    link.set_target((40.0, 40.0, 15.0))
    wait_for(lambda: link.state().mode == "OFFBOARD", 15.0, message="OFFBOARD")
    wait_for(lambda: mock.stats["setpoints_received"] >= 20, 10.0, message="20 setpoints")
    assert _speed(mock) == before
    assert link.counters["speed_limits_set"] == 0 and link.counters["speed_limit_failures"] == 0
