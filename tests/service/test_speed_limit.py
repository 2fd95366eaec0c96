"""The envelope's speed limit on the autopilot: on ArduPilot the link sends
MAV_CMD_DO_CHANGE_SPEED with the envelope's ``max_speed_mps`` once the vehicle is in GUIDED with
the service's stream, and again for a new envelope's; PX4's offboard mode ignores the command, so
there the link sets MPC_XY_VEL_MAX while it flies the vehicle and gives the vehicle's own value
back when it stops."""

from __future__ import annotations

import math
import time
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


def _capped(mock: MockAutopilot) -> dict[str, float]:
    return mock.with_vehicle(lambda v: dict(v.px4_capped_speeds_mps))


def _fly_px4_offboard(mock: MockAutopilot, link: Any) -> None:
    link.arm_and_takeoff().result(timeout=30.0)
    link.set_target((60.0, 60.0, 15.0))
    wait_for(lambda: link.state().mode == "OFFBOARD", 15.0, message="OFFBOARD")


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_px4_flies_offboard_at_the_envelopes_speed_and_gets_its_own_back(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], backend: str
) -> None:
    """PX4's offboard mode flies at MPC_XY_VEL_MAX: the service puts the envelope's limit there
    while it flies the vehicle, a new envelope's at once, and the vehicle's own value back the
    moment an operator takes the vehicle."""
    mock = start_mock("px4", speedup=1.0, **FAST_VEHICLE)
    own = _speed(mock)
    assert own == 10.0
    link = open_link(
        tcp_url(mock), backend=backend, envelope=Envelope.for_area(AREA, max_speed_mps=4.0)
    )
    link.arm_and_takeoff().result(timeout=30.0)
    assert _speed(mock) == own  # nothing before the service flies it in OFFBOARD
    link.set_target((60.0, 60.0, 15.0))
    wait_for(lambda: _speed(mock) == 4.0, 15.0, message="the envelope's speed on the vehicle")
    wait_for(lambda: link.counters["speed_limits_set"] == 1, 5.0, message="the answer counted")
    fastest_mps = 0.0
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:  # flying: 60 m away at 4 m/s
        fastest_mps = max(fastest_mps, math.hypot(*mock.state().velocity_ned_mps[:2]))
        time.sleep(0.05)
    assert 3.0 < fastest_mps <= 4.0 + 1e-6, fastest_mps
    link.set_envelope(Envelope.for_area(AREA, max_speed_mps=6.0))
    wait_for(lambda: _speed(mock) == 6.0, 10.0, message="the new envelope's speed")
    # As PX4 does, the lower limit lowered the cruise and the pilot's speeds to it.
    assert _capped(mock) == {"MPC_XY_CRUISE": 4.0, "MPC_VEL_MANUAL": 4.0}
    link.release()
    wait_for(lambda: link.counters["speed_limits_given_back"] == 1, 10.0, message="given back")
    assert _speed(mock) == own
    assert _capped(mock) == {"MPC_XY_CRUISE": 5.0, "MPC_VEL_MANUAL": 10.0}  # its own again
    assert link.counters["speed_limit_failures"] == 0


def test_closing_the_link_gives_px4_its_own_speed_back(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any]
) -> None:
    mock = start_mock("px4", **FAST_VEHICLE)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    _fly_px4_offboard(mock, link)
    wait_for(lambda: _speed(mock) == 4.0, 15.0, message="the envelope's speed on the vehicle")
    link.close()
    assert _speed(mock) == 10.0
    assert _capped(mock) == {"MPC_XY_CRUISE": 5.0, "MPC_VEL_MANUAL": 10.0}


def _lose_the_answers_to(mock: MockAutopilot, name: str, value: float) -> None:
    """The mock takes every PARAM_SET but its PARAM_VALUE answers for ``name`` at ``value`` are
    lost on the way (the link never hears that the vehicle took it)."""
    send = mock.protocol._send_param

    def lossy(link: Any, param: str, index: int) -> None:
        if param == name and mock.with_vehicle(lambda v: v.max_speed_h_mps) == value:
            return
        send(link, param, index)

    mock.protocol._send_param = lossy  # type: ignore[method-assign]


@pytest.mark.parametrize("close_at", ["while the set waits", "after it was refused"])
def test_a_limit_whose_answer_is_lost_is_still_given_back(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], close_at: str
) -> None:
    # The vehicle took 4 m/s but the link never heard it: the limit on the vehicle is unknown,
    # so the link gives the vehicle its own back when it stops flying it (here: at close),
    # rather than leaving it at a limit it cannot see.
    mock = start_mock("px4", **FAST_VEHICLE)
    _lose_the_answers_to(mock, "MPC_XY_VEL_MAX", 4.0)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    _fly_px4_offboard(mock, link)
    wait_for(lambda: _speed(mock) == 4.0, 15.0, message="the envelope's speed on the vehicle")
    if close_at == "after it was refused":
        wait_for(lambda: link.counters["speed_limit_failures"] >= 1, 10.0, message="not taken")
    link.close()
    assert _speed(mock) == 10.0
    assert _capped(mock) == {"MPC_XY_CRUISE": 5.0, "MPC_VEL_MANUAL": 10.0}


def test_a_px4_slower_than_the_envelope_is_left_alone(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any]
) -> None:
    mock = start_mock("px4", max_speed_h_mps=3.0, **FAST_VEHICLE)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    _fly_px4_offboard(mock, link)
    wait_for(lambda: mock.stats["setpoints_received"] >= 40, 10.0, message="40 setpoints")
    assert _speed(mock) == 3.0
    assert mock.stats.get("param_sets", 0) == 0  # not even its own value set again
    assert link.counters["speed_limits_set"] == 0 and link.counters["speed_limit_failures"] == 0


def _fastest_until_there(
    mock: MockAutopilot, link: Any, target_m: tuple[float, float, float], timeout_s: float
) -> float:
    """Set ``target_m`` and sample the vehicle's horizontal speed (every 20 ms of wall time)
    until it is within 1 m of it; the fastest seen (fails when it does not get there)."""
    link.set_target(target_m)
    fastest = 0.0
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = mock.state()
        fastest = max(fastest, math.hypot(*state.velocity_ned_mps[:2]))
        here = link.state().position_m
        if here is not None and math.dist(here, link.state().target_m or target_m) < 1.0:
            return fastest
        time.sleep(0.02)
    raise AssertionError(f"not at {target_m} after {timeout_s} s (fastest {fastest:.2f} m/s)")


def _refuse_px4_speed_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every mock of this test keeps its own MPC_XY_VEL_MAX (a PARAM_SET of it is refused)."""
    import sitl_mock.protocol

    take = sitl_mock.protocol.set_parameter

    def refuse(vehicle: Any, name: str, value: float, param_type: int) -> bool:
        return False if name == "MPC_XY_VEL_MAX" else take(vehicle, name, value, param_type)

    monkeypatch.setattr(sitl_mock.protocol, "set_parameter", refuse)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_that_does_not_take_the_limit_still_flies_no_faster_than_it(
    start_mock: Callable[..., MockAutopilot],
    open_link: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
    flavour: str,
) -> None:
    """Until the vehicle has confirmed the envelope's speed limit (and for good when it refuses
    it) the link streams setpoints no further ahead than the limit allows, so the vehicle,
    flying at its own 10 m/s, still keeps to the envelope's 4 m/s — from the first moment of the
    flight — and gets where it was sent."""
    from sitl_mock.flavours import MavResult
    from sitl_mock.vehicle import CommandOutcome

    if flavour == "px4":
        _refuse_px4_speed_limit(monkeypatch)
    mock = start_mock(flavour, **FAST_VEHICLE)
    if flavour == "ardupilot":
        denied = CommandOutcome(MavResult.DENIED, "no speed changes here")
        mock.with_vehicle(lambda v: setattr(v, "change_speed", lambda *_: denied))
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    link.arm_and_takeoff().result(timeout=30.0)
    fastest = _fastest_until_there(mock, link, (55.0, 55.0, 15.0), 40.0)
    assert _speed(mock) == 10.0  # the vehicle never took the limit
    wait_for(lambda: link.counters["speed_limit_failures"] >= 1, 10.0, message="refused")
    assert 2.0 < fastest <= 4.0 + 0.05, fastest


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_the_first_moments_of_a_flight_keep_to_the_limit_too(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], flavour: str
) -> None:
    """The limit on the autopilot is set only once the service flies the vehicle (ArduPilot:
    a second into GUIDED; PX4: after its own speeds were read); the stream keeps the vehicle
    to it meanwhile, and flies at the limit once it is in force."""
    mock = start_mock(flavour, **FAST_VEHICLE)
    link = open_link(tcp_url(mock), envelope=Envelope.for_area(AREA, max_speed_mps=4.0))
    link.arm_and_takeoff().result(timeout=30.0)
    fastest = _fastest_until_there(mock, link, (55.0, 55.0, 15.0), 40.0)
    assert _speed(mock) == 4.0 and link.counters["speed_limits_set"] == 1
    assert 3.5 < fastest <= 4.0 + 0.05, fastest
