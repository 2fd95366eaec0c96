"""The battery reserve (:mod:`service.battery`): the service sends the vehicle home before the
autopilot's own low-battery failsafe has to, lets go of it, and never overrides that failsafe.

The arithmetic is tested as the pure functions it is; then the pymavlink link flies the mock
autopilot (both flavours): the battery knob (as ``SIM_BATT_VOLTAGE`` on ArduPilot SITL) puts the
pack just under the reserve and the link must command the return, hand the vehicle to the
autopilot and stream nothing more; put under the autopilot's own failsafe level at once, the
autopilot lands by itself and the link must not send it home instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import pytest

from service.battery import BatteryConfig, DrainEstimate, reserve_reached, return_needs_pct
from sitl_mock.server import MockAutopilot
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import FAST_VEHICLE

RTL = {"ardupilot": "RTL", "px4": "AUTO.RTL"}
GUIDED = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
LAND = {"ardupilot": "LAND", "px4": "AUTO.LAND"}


def test_the_drain_is_the_slope_of_the_readings_once_they_span_the_window() -> None:
    config = BatteryConfig(min_window_s=20.0, window_s=60.0)
    drain = DrainEstimate(config)
    for t in range(0, 15):
        drain.add(float(t), 90.0 - 0.1 * t)
    assert drain.measured_pct_per_s is None  # 14 s of readings: not yet
    assert drain.pct_per_s == config.assumed_drain_pct_per_s
    for t in range(15, 100):
        drain.add(float(t), 90.0 - 0.1 * t)
    assert drain.measured_pct_per_s == pytest.approx(0.1)
    drain.add(100.0, 100.0)  # a new pack: the history starts afresh
    assert drain.measured_pct_per_s is None


def test_the_reserve_is_what_flying_home_takes_plus_what_must_be_left() -> None:
    config = BatteryConfig(reserve_pct=20.0, return_speed_mps=5.0, descent_speed_mps=2.0)
    # 250 m home at 5 m/s (50 s), 30 m down at 2 m/s (15 s) and the last 10 m at 0.5 m/s
    # (20 s: as ArduCopter lands), the 20 s margin: 105 s at 0.1 %/s = 10.5 %.
    assert return_needs_pct(0.1, 250.0, 40.0, config) == pytest.approx(10.5)
    assert reserve_reached(31.0, 0.1, 250.0, 40.0, config) is None
    why = reserve_reached(30.0, 0.1, 250.0, 40.0, config)
    assert why is not None and "30 % left" in why and "250 m" in why
    assert reserve_reached(1.0, 0.1, 250.0, 40.0, BatteryConfig(reserve_pct=None)) is None
    with pytest.raises(ValueError, match="reserve_pct"):
        BatteryConfig(reserve_pct=100.0)


QUICK_RETURN = {"rtl_alt_m": 10.0, "land_speed_mps": 2.0}
"""A vehicle whose return and landing take seconds, not half a minute (the flavours' defaults:
RTL at 15 or 30 m, the last metres at 0.5 or 0.7 m/s): what is checked is what the service does
(nothing) until the vehicle is down, not how long that takes."""


def fly_to_target(mock: MockAutopilot, link: Any) -> tuple[float, float, float]:
    link.arm_and_takeoff().result(timeout=30.0)
    target = (25.0, 35.0, 8.0)
    link.set_target(target)
    wait_for(
        lambda: (p := link.state().position_m) is not None and math.dist(p, target) < 1.5,
        30.0,
        message="the vehicle at its target",
    )
    return target


@pytest.mark.slow
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_at_its_reserve_the_vehicle_is_sent_home_and_let_go(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], flavour: str
) -> None:
    mock = start_mock(flavour, gcs_failsafe_action="none", **QUICK_RETURN, **FAST_VEHICLE)
    link = open_link(tcp_url(mock), battery=BatteryConfig(reserve_pct=20.0))
    fly_to_target(mock, link)
    state = wait_for(lambda: (s := link.state()).battery_pct is not None and s, 5.0)
    assert state.battery_pct > 90 and state.battery_return_at_pct is not None
    assert state.battery_return_at_pct > 20.0  # the reserve plus flying home

    # Just under what the return from here needs plus the reserve, above the mock's own
    # failsafe level (10 %).
    mock.with_vehicle(lambda v: v.set_battery_remaining(21.0))
    state = wait_for(lambda: (s := link.state()).control == "autopilot" and s, 5.0)
    assert "battery reserve reached" in state.control_reason
    guided_asked = mock.stats.get(f"mode_commands_{GUIDED[flavour]}", 0)
    wait_for(lambda: mock.state().mode == RTL[flavour], 10.0, message=RTL[flavour])
    assert not link.state().streaming
    assert link.state().counters["battery_returns"] == 1
    stats = mock.stats
    assert stats["failsafe_battery"] == 0  # the service acted before the autopilot had to
    setpoints = stats["setpoints_received"]
    wait_for(
        lambda: mock.state().alt_m < 1.0 or mock.state().mode != RTL[flavour],
        60.0,
        0.1,
        message="the return home",
    )
    assert mock.stats["setpoints_received"] == setpoints  # nothing streamed after it
    assert mock.stats.get(f"mode_commands_{GUIDED[flavour]}", 0) == guided_asked


@pytest.mark.slow
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_the_autopilots_own_battery_failsafe_is_never_overridden(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], flavour: str
) -> None:
    mock = start_mock(flavour, gcs_failsafe_action="none", **QUICK_RETURN, **FAST_VEHICLE)
    link = open_link(tcp_url(mock), battery=BatteryConfig(reserve_pct=20.0))
    fly_to_target(mock, link)
    # Under the autopilot's own failsafe level at once: it lands by itself.
    mock.with_vehicle(lambda v: v.set_battery_remaining(5.0))
    wait_for(lambda: mock.state().mode == LAND[flavour], 5.0, message=LAND[flavour])
    wait_for(lambda: link.state().control == "autopilot", 5.0, message="the autopilot has it")
    # Long enough for any return the link might still send (two heartbeats and an ACK).
    wait_for(
        lambda: mock.state().alt_m < 3.0,
        30.0,
        0.1,
        message="the landing",
    )
    assert mock.state().mode == LAND[flavour]
    assert mock.stats.get(f"mode_commands_{RTL[flavour]}", 0) == 0
    assert mock.stats["failsafe_battery"] == 1
