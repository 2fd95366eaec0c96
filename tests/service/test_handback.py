"""Hand-back: the pilot and the autopilot's failsafes always win (:mod:`service.control`).

The rule itself is tested as the pure function it is; then the *paced placement loop* (a
:class:`~service.placement.PlacementService` deciding every period from a report that stays
fresh, so that it sets the same target again and again, as in service) flies the mock autopilot
on both flavours and both link backends through a flight with every kind of takeover in turn:
a pilot's RC mode switch, a ground station's RTL, a ground station's LAND, and the battery
failsafe. After each, the vehicle must stay in the mode it was put in: the mock counts every
mode command it receives, by mode, and no command for the guided mode may arrive until an
operator hands the vehicle back; meanwhile nothing streams and the service says who has the
vehicle. A hand-back is refused while the vehicle is in a return or landing mode or flags a
failsafe.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from service import links
from service.control import (
    Control,
    Observation,
    after_heartbeat,
    handback_refusal,
    is_failsafe_text,
)
from service.decisions import Report
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import ControlRefused, LinkConfig
from sitl_mock.server import MockAutopilot
from tests.fakes import FakeLink
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import FAST_VEHICLE, FRAMES

HELD = Control("service", "its take-off sequence", 0.0)


def seen(flavour: str, mode: str, previous: str | None, **fields: Any) -> Observation:
    fields.setdefault("armed", True)
    fields.setdefault("previous_armed", True)
    return Observation(flavour=flavour, mode=mode, previous_mode=previous, **fields)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("observation", "holder", "words"),
    [
        (seen("ardupilot", "LOITER", "GUIDED"), "pilot", "left GUIDED for LOITER"),
        (seen("px4", "POSCTL", "OFFBOARD"), "pilot", "left OFFBOARD for POSCTL"),
        (seen("ardupilot", "RTL", "GUIDED"), "autopilot", "left GUIDED for RTL"),
        (seen("px4", "AUTO.LAND", "OFFBOARD"), "autopilot", "left OFFBOARD for AUTO.LAND"),
        (
            seen("ardupilot", "LOITER", "GUIDED", failsafe_text="Radio Failsafe"),
            "autopilot",
            "vehicle said: Radio Failsafe",
        ),
        (
            seen("px4", "AUTO.LOITER", "OFFBOARD", after_link_loss=True),
            "autopilot",
            "while the link was lost",
        ),
        (
            seen("ardupilot", "LOITER", "GUIDED", failsafe_flagged=True),
            "autopilot",
            "failsafe flagged",
        ),
        (seen("ardupilot", "GUIDED", "GUIDED", armed=False), "pilot", "disarmed in GUIDED"),
        (seen("px4", "AUTO.RTL", None), "autopilot", "in AUTO.RTL"),  # found so at start-up
        (seen("ardupilot", "STABILIZE", "GUIDED", previous_armed=None), "pilot", "STABILIZE"),
        # Found armed, when the link starts, in a mode a pilot chose while no service flew it.
        (seen("px4", "POSCTL", None, at_start=True), "pilot", "found armed in POSCTL"),
        (seen("ardupilot", "LOITER", None, at_start=True), "pilot", "found armed in LOITER"),
        # A hold that starts before the link streamed anything, without a failsafe shown, is a
        # pilot's Hold; with one, after the link was lost, it is the autopilot's as before.
        (seen("px4", "AUTO.LOITER", "OFFBOARD", streamed=False), "pilot", "left OFFBOARD"),
        (
            seen(
                "px4",
                "AUTO.LOITER",
                "OFFBOARD",
                streamed=False,
                failsafe_flagged=True,
                after_link_loss=True,
            ),
            "autopilot",
            "while the link was lost",
        ),
        (
            seen("px4", "AUTO.LOITER", "OFFBOARD", failsafe_text="Failsafe activated"),
            "autopilot",
            "vehicle said: Failsafe activated",
        ),
    ],
)
def test_the_vehicle_leaves_the_service_on_its_own(
    observation: Observation, holder: str, words: str
) -> None:
    control = after_heartbeat(HELD, observation, 7.0)
    assert control.holder == holder
    assert words in control.reason
    assert control.since_s == 7.0


@pytest.mark.parametrize(
    "observation",
    [
        seen("ardupilot", "GUIDED", "GUIDED"),  # nothing changed
        seen("ardupilot", "GUIDED", "LOITER"),  # into the guided mode: the service asked
        seen("px4", "AUTO.LOITER", "AUTO.TAKEOFF"),  # PX4's own end of a take-off
        seen("px4", "AUTO.LOITER", None),  # the first HEARTBEAT, in a hold mode
        seen("px4", "AUTO.LOITER", "AUTO.LOITER", armed=False, previous_armed=False),
        # Found armed when the link starts: in the guided mode, a take-off or the hold that
        # PX4's offboard-loss failsafe puts a vehicle in when a restart stops the stream.
        seen("px4", "OFFBOARD", None, at_start=True),
        seen("ardupilot", "GUIDED", None, at_start=True),
        seen("px4", "AUTO.TAKEOFF", None, at_start=True),
        seen("px4", "AUTO.LOITER", None, at_start=True),
        seen("px4", "POSCTL", None, at_start=True, armed=False, previous_armed=None),  # landed
        seen("px4", "POSCTL", None),  # the baseline after an operator's hand-back
        # That hold starting a moment after the link started, before it streamed anything,
        # with the failsafe shown: the same case.
        seen("px4", "AUTO.LOITER", "OFFBOARD", streamed=False, failsafe_text="Failsafe activated"),
        seen("px4", "AUTO.LOITER", "OFFBOARD", streamed=False, failsafe_flagged=True),
    ],
)
def test_what_is_not_a_takeover_keeps_the_vehicle_with_the_service(
    observation: Observation,
) -> None:
    assert after_heartbeat(HELD, observation, 1.0) is HELD


def test_once_left_only_an_operator_brings_it_back() -> None:
    left = Control("pilot", "the vehicle left GUIDED for LOITER", 3.0)
    # Back in GUIDED by someone else's hand (a ground station's click-to-fly): still the pilot's.
    assert after_heartbeat(left, seen("ardupilot", "GUIDED", "LOITER"), 4.0) is left
    released = Control("operator", "released by an operator", 3.0)
    assert after_heartbeat(released, seen("px4", "OFFBOARD", "POSCTL"), 4.0) is released


def test_a_handback_is_refused_while_the_autopilot_returns_lands_or_flags_a_failsafe() -> None:
    assert handback_refusal("ardupilot", "LOITER", True, False) is None
    assert "RTL" in (handback_refusal("ardupilot", "RTL", True, False) or "")
    assert "AUTO.LAND" in (handback_refusal("px4", "AUTO.LAND", True, False) or "")
    assert "failsafe" in (handback_refusal("px4", "POSCTL", True, True) or "")
    assert "link" in (handback_refusal("px4", "POSCTL", False, False) or "")


def test_failsafe_texts_are_recognised() -> None:
    assert is_failsafe_text(6, "GCS Failsafe")
    assert is_failsafe_text(2, "Battery 1 is critical")
    assert not is_failsafe_text(6, "EKF3 IMU0 is using GPS")


@pytest.mark.parametrize("backend", links.LINK_BACKENDS)
def test_only_a_new_target_opens_a_mode_request_window(backend: str) -> None:
    """The paced loop sets the same target every period: that must not keep the window open
    (it did, and the service took the vehicle back from its pilot within a second)."""
    link = links.open_link(backend, LinkConfig("tcp:127.0.0.1:1", mode_request_window_s=15.0))
    assert link._mode_wanted_until == 0.0  # not started: no vehicle needed
    link.set_target((30.0, 30.0, 30.0))
    opened = link._mode_wanted_until
    assert opened > 0.0
    for _ in range(5):
        link.set_target((30.0, 30.0, 30.0))
        assert link._mode_wanted_until == opened
    link.set_target((40.0, 30.0, 30.0))
    assert link._mode_wanted_until > opened


# ---------------------------------------------------------------------- the paced loop


USERS = (("a", 20.0, 30.0), ("b", 40.0, 30.0), ("c", 30.0, 45.0))
PERIOD_S = 0.2
QUIET_DECISIONS = 8
"""Periods the paced loop must run after a takeover without any guided-mode command."""


def report() -> Report:
    columns = {
        "x_m": np.array([u[1] for u in USERS]),
        "y_m": np.array([u[2] for u in USERS]),
        "offered_bps": np.full(3, 5e6),
        "throughput_bps": np.full(3, 5e6),
        "delay_s": np.full(3, 0.01),
        "plr": np.zeros(3),
    }
    return Report.from_columns(1.0, tuple(u[0] for u in USERS), columns)


@pytest.fixture
def paced_service() -> Iterator[Callable[..., PlacementService]]:
    """Factory: a started paced service (min-distance, one fresh report) whose link flies the
    mock, airborne at 10 m; stopped (with its link) at teardown."""
    started: list[PlacementService] = []

    def _start(mock: MockAutopilot, backend: str) -> PlacementService:
        config = LinkConfig(tcp_url(mock), frames=FRAMES, mode_retry_s=0.2)
        link = links.open_link(backend, config)
        settings = ServiceSettings(
            mavlink=config.url,
            api_token="t",
            policy="min-distance",
            step_s=PERIOD_S,
            report_max_age_s=3600.0,
        )
        service = PlacementService(settings, link, load_policy("min-distance"))
        started.append(service.start())
        link.arm_and_takeoff(z_m=10.0).result(timeout=40.0)
        service.submit_report(report())
        return service

    yield _start
    for service in started:
        service.stop()


def guided_commands(mock: MockAutopilot, guided: str) -> int:
    return mock.stats.get(f"mode_commands_{guided}", 0)


def loop_passes(service: PlacementService) -> int:
    """The paced loop's passes that had a fresh report: decided, or held for the vehicle."""
    counters = service.snapshot_counters()
    return counters.get("decisions", 0) + counters.get("decisions_waiting_link", 0)


def takeover_holds(
    service: PlacementService, mock: MockAutopilot, guided: str, mode: str, holder: str
) -> None:
    """The vehicle was just put in ``mode``: the service lets go (``holder`` has it, nothing
    streams, not ready) and the paced loop runs on for :data:`QUIET_DECISIONS` periods without
    one guided-mode command reaching the vehicle, which stays in ``mode``."""
    link = service.link
    state = wait_for(
        lambda: (s := link.state()).control != "service" and s, 5.0, message="the service lets go"
    )
    assert state.control == holder, state.control_reason
    commands = guided_commands(mock, guided)
    sent = link.counters["setpoints_sent"]
    requests = link.counters.get("mode_requests", 0)
    start = loop_passes(service)
    wait_for(
        lambda: loop_passes(service) >= start + QUIET_DECISIONS,
        QUIET_DECISIONS * PERIOD_S + 10.0,
        message="the paced loop to run on",
    )
    assert guided_commands(mock, guided) == commands
    assert link.counters.get("mode_requests", 0) == requests
    assert mock.state().mode == mode
    state = link.state()
    assert not state.streaming and state.control == holder
    assert link.counters["setpoints_sent"] <= sent + 1  # at most one already on its way
    ready, reasons = service.readiness()
    assert not ready and any(f"the {holder} has the vehicle" in r for r in reasons)


def hand_back(service: PlacementService, mock: MockAutopilot, guided: str) -> None:
    """An operator hands the vehicle back: the loop's next decision streams, GUIDED is asked
    for and granted."""
    service.link.hand_back()
    wait_for(lambda: mock.state().mode == guided, 10.0, message=f"{guided} again")
    wait_for(lambda: service.link.state().mode == guided, 5.0, message=f"{guided} heard")
    assert service.link.state().control == "service"


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_the_paced_loop_lets_go_for_pilots_and_failsafes_and_waits_for_an_operator(
    start_mock: Callable[..., MockAutopilot],
    paced_service: Callable[..., PlacementService],
    flavour: str,
    backend: str,
) -> None:
    mock = start_mock(flavour, gcs_failsafe_action="none", **FAST_VEHICLE)
    guided = "GUIDED" if flavour == "ardupilot" else "OFFBOARD"
    pilot_mode = "LOITER" if flavour == "ardupilot" else "POSCTL"
    rtl, land = ("RTL", "LAND") if flavour == "ardupilot" else ("AUTO.RTL", "AUTO.LAND")
    service = paced_service(mock, backend)
    wait_for(lambda: mock.state().mode == guided, 10.0, message=guided)

    # 1. The pilot's RC mode switch.
    mock.with_vehicle(lambda v: v.rc_mode_switch(pilot_mode))
    takeover_holds(service, mock, guided, pilot_mode, "pilot")
    hand_back(service, mock, guided)

    # 2. A ground station's RTL: the hand-back is refused until the pilot leaves RTL.
    mock.with_vehicle(lambda v: v.set_mode_by_name(rtl))
    takeover_holds(service, mock, guided, rtl, "autopilot")
    with pytest.raises(ControlRefused, match=rtl):
        service.link.hand_back()
    mock.with_vehicle(lambda v: v.rc_mode_switch(pilot_mode))
    wait_for(lambda: service.link.state().mode == pilot_mode, 5.0, message=pilot_mode)
    hand_back(service, mock, guided)

    # 3. A ground station's LAND, taken back by the pilot in the air.
    mock.with_vehicle(lambda v: v.land())
    takeover_holds(service, mock, guided, land, "autopilot")
    mock.with_vehicle(lambda v: v.rc_mode_switch(pilot_mode))
    wait_for(lambda: service.link.state().mode == pilot_mode, 5.0, message=pilot_mode)
    hand_back(service, mock, guided)

    # 4. The battery failsafe: LAND, failsafe flagged; no hand-back while it lasts.
    mock.with_vehicle(lambda v: v.set_battery_remaining(5.0))
    takeover_holds(service, mock, guided, land, "autopilot")
    assert mock.stats["failsafe_battery"] == 1
    with pytest.raises(ControlRefused):
        service.link.hand_back()


@pytest.mark.slow
def test_an_operator_release_stops_the_stream_until_the_hand_back(
    start_mock: Callable[..., MockAutopilot], paced_service: Callable[..., PlacementService]
) -> None:
    mock = start_mock("px4", gcs_failsafe_action="none", **FAST_VEHICLE)
    service = paced_service(mock, "pymavlink")
    wait_for(lambda: mock.state().mode == "OFFBOARD", 10.0, message="OFFBOARD")
    service.link.release()
    state = service.link.state()
    assert state.control == "operator" and not state.streaming
    # Without setpoints PX4's own offboard-loss failsafe holds the vehicle; nobody fights it.
    takeover_holds(service, mock, "OFFBOARD", "AUTO.LOITER", "operator")
    hand_back(service, mock, "OFFBOARD")


@pytest.mark.slow
def test_a_forced_disarm_in_the_air_ends_the_take_off_and_readiness(
    start_mock: Callable[..., MockAutopilot], paced_service: Callable[..., PlacementService]
) -> None:
    mock = start_mock("ardupilot", gcs_failsafe_action="none", **FAST_VEHICLE)
    service = paced_service(mock, "pymavlink")
    wait_for(lambda: mock.state().mode == "GUIDED", 10.0, message="GUIDED")
    mock.with_vehicle(lambda v: v.disarm(force=True))
    state = wait_for(
        lambda: (s := service.link.state()).control != "service" and s, 5.0, message="let go"
    )
    assert "disarmed" in state.control_reason
    assert state.takeoff == "idle" and not state.streaming
    ready, reasons = service.readiness()
    assert not ready and any("disarmed" in r for r in reasons)


def test_a_restart_keeps_the_vehicle_with_whoever_had_it(tmp_path: Any) -> None:
    """A service restarted with its state file must not take back a vehicle that its pilot (or
    a failsafe, or an operator) had when it stopped; a vehicle it held is the new one's."""
    state_file = tmp_path / "state.json"
    settings = ServiceSettings(
        mavlink="fake:", api_token="t", policy="min-distance", decision_mode="on-report",
        state_file=state_file, report_max_age_s=3600.0,
    )  # fmt: skip
    first_link = FakeLink(position_m=(100.0, 100.0, 30.0))
    first = PlacementService(settings, first_link, load_policy("min-distance")).start()
    try:
        first.submit_report(report())
        first_link.vehicle_leaves("pilot", "the vehicle left OFFBOARD for POSCTL")
        wait_for(
            lambda: json.loads(state_file.read_text()).get("control", {}).get("uav1"),
            5.0,
            message="the pilot's control in the state file",
        )
    finally:
        first.stop()

    link = FakeLink(position_m=(100.0, 100.0, 30.0))
    service = PlacementService(settings, link, load_policy("min-distance")).start()
    try:
        state = link.state()
        assert state.control == "pilot"
        assert state.control_reason == (
            "the vehicle left OFFBOARD for POSCTL (before the service restarted)"
        )
        later = report()
        service.submit_report(Report(later.timestamp_s + 1.0, later.user_ids, later.users))
        assert not link.state().streaming and link.targets == []
        link.hand_back()
        wait_for(
            lambda: json.loads(state_file.read_text()).get("control") == {},
            5.0,
            message="the hand-back in the state file",
        )
    finally:
        service.stop()


def _service_with_state(
    mock: MockAutopilot, state_file: Any, backend: str = "pymavlink"
) -> PlacementService:
    config = LinkConfig(tcp_url(mock), frames=FRAMES, mode_retry_s=0.2)
    settings = ServiceSettings(
        mavlink=config.url, api_token="t", policy="min-distance", step_s=PERIOD_S,
        report_max_age_s=3600.0, state_file=state_file, arm_and_takeoff=True,
    )  # fmt: skip
    link = links.open_link(backend, config)
    return PlacementService(settings, link, load_policy("min-distance")).start()


@pytest.mark.slow
@pytest.mark.parametrize("restart", ["with its state file", "afresh"])
def test_a_service_started_beside_a_vehicle_its_pilot_flies_leaves_it_to_the_pilot(
    start_mock: Callable[..., MockAutopilot], tmp_path: Any, restart: str
) -> None:
    """The service stops (a crash, an update) while it flies the vehicle; its pilot takes the
    vehicle meanwhile (PX4's POSCTL). A service started then, with the state file that says it
    had the vehicle or without one, must not take the vehicle back on its first decision: it
    leaves it with the pilot, asks for no mode, and says so, until an operator hands it back."""
    mock = start_mock("px4", gcs_failsafe_action="none", **FAST_VEHICLE)
    state_file = tmp_path / "state.json"
    first = _service_with_state(mock, state_file)
    try:
        first.submit_report(report())
        wait_for(lambda: mock.state().mode == "OFFBOARD", 30.0, message="OFFBOARD")
    finally:
        first.stop()
    mock.with_vehicle(lambda v: v.rc_mode_switch("POSCTL"))
    if restart == "afresh":
        state_file.unlink()
    commands = guided_commands(mock, "OFFBOARD")
    second = _service_with_state(mock, state_file)
    try:
        second.submit_report(report())
        state = wait_for(
            lambda: (s := second.link.state()).control != "service" and s, 10.0, message="let go"
        )
        assert state.control == "pilot" and "POSCTL" in state.control_reason, state
        start = loop_passes(second)
        wait_for(
            lambda: loop_passes(second) >= start + QUIET_DECISIONS,
            QUIET_DECISIONS * PERIOD_S + 10.0,
            message="the paced loop to run on",
        )
        assert guided_commands(mock, "OFFBOARD") == commands
        assert mock.state().mode == "POSCTL"
        assert not second.link.state().streaming
        ready, reasons = second.readiness()
        assert not ready and any("the pilot has the vehicle" in r for r in reasons), reasons
        assert mock.stats["arms"] == 1  # never armed again
    finally:
        second.stop()
