"""The placement loop's rules: fresh vs stale reports, out-of-order reports, discrete moves from
the vehicle's zone, a failing policy, and the policy runtime (same observation as the environment,
valid masked moves).

The rules run on an in-memory vehicle link (:class:`tests.fakes.FakeLink`: no autopilot process);
the tests of what happens around the link (a report held while no vehicle answers, a restart that
must not arm) run end to end against a real in-process sitl_mock (PX4 flavour)."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from service.decisions import Report
from service.mavlink_link import MavlinkLink
from service.placement import OutOfOrderReportError, PlacementService
from service.policy_runtime import SHIPPED_DDQN, load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sim.config import AreaConfig
from sim.envs import FapDiscreteEnv
from sim.errors import InputError
from sim.geometry import MOVES, move_mask, zone_index, zone_position
from sim.observation import UserReports
from sitl_mock.server import MockAutopilot
from tests.fakes import FakeLink
from tests.helpers import wait_for

AREA = AreaConfig()


def reports(heavy_xy: tuple[float, float] = (100.0, 120.0)) -> UserReports:
    return UserReports(
        x_m=np.array([heavy_xy[0], 400.0, 420.0]),
        y_m=np.array([heavy_xy[1], 380.0, 90.0]),
        offered_bps=np.array([36e6, 2e6, 2e6]),
        throughput_bps=np.array([20e6, 2e6, 2e6]),
        delay_s=np.array([0.6, 0.01, 0.02]),
        plr=np.array([0.3, 0.0, 0.0]),
    )


@pytest.fixture
def make_service() -> Iterator[Callable[..., PlacementService]]:
    """Factory: ``make_service(policy, link=None, **settings)``: a started on-report service on
    ``link`` (default: a :class:`FakeLink` whose vehicle stands at home, the area's corner, as the
    mock's does), ready; stopped at teardown."""
    services: list[PlacementService] = []

    def _make(
        policy: str = "load-weighted", link: FakeLink | None = None, **settings: Any
    ) -> PlacementService:
        config = ServiceSettings(
            mavlink="tcp:127.0.0.1:1",
            api_token="t",
            policy=policy,
            decision_mode="on-report",
            **settings,
        )
        link = link if link is not None else FakeLink(LinkConfig(config.mavlink, area=AREA))
        service = PlacementService(config, link, load_policy(policy)).start()
        services.append(service)
        wait_for(lambda: service.readiness()[0], 15.0, message="link up with a position")
        return service

    yield _make
    for service in services:
        service.stop()


def test_fresh_report_decides_and_a_stale_one_holds(
    make_service: Callable[..., PlacementService],
) -> None:
    service = make_service(report_max_age_s=0.3)
    decision = service.submit_report(Report(1.0, ("a", "b", "c"), reports()))
    assert decision is not None and decision.source == "policy"
    # Nothing new arrives: once the report is older than report_max_age_s, the target is held.
    wait_for(
        lambda: (
            service.decide_once() is None
            and service.snapshot_counters().get("decisions_held_stale", 0) >= 1
        ),
        timeout_s=5.0,
        message="stale report held",
    )
    held = service.current_decision()
    assert held is not None and held.target_m == decision.target_m
    assert service.decide_once() is None
    assert service.current_decision() == held


def test_out_of_order_report_changes_nothing(
    make_service: Callable[..., PlacementService],
) -> None:
    service = make_service()
    first = service.submit_report(Report(10.0, ("a", "b", "c"), reports()))
    with pytest.raises(OutOfOrderReportError, match="older"):
        service.submit_report(Report(9.0, ("a", "b", "c"), reports((450.0, 450.0))))
    assert service.current_decision() == first
    assert service.snapshot_counters()["reports_out_of_order"] == 1


def test_users_come_and_go_each_report_replaces_the_last(
    make_service: Callable[..., PlacementService],
) -> None:
    service = make_service()
    west = service.submit_report(Report(1.0, ("a", "b", "c"), reports((60.0, 250.0))))
    east = service.submit_report(Report(2.0, ("a", "b", "c"), reports((450.0, 250.0))))
    assert west is not None and east is not None
    assert east.target_m[0] > west.target_m[0] + 100


@pytest.mark.skipif(not SHIPPED_DDQN.is_file(), reason="no shipped DDQN checkpoint")
def test_ddqn_decides_every_report_from_the_vehicles_zone(
    make_service: Callable[..., PlacementService],
) -> None:
    """Moves apply to the zone the vehicle is in, and the next report is decided at once,
    whether or not the vehicle has reached the last target (it flies while the policy acts)."""
    link = FakeLink(LinkConfig("tcp:127.0.0.1:1", area=AREA), position_m=(262.5, 262.5, 50.0))
    service = make_service(policy=str(SHIPPED_DDQN), link=link)
    for timestamp in (1.0, 2.0):
        decision = service.submit_report(Report(timestamp, ("a", "b", "c"), reports()))
        assert decision is not None and decision.decided_at > 0
        start = zone_index(np.asarray(service.vehicle().position_m), AREA)
        landing = zone_index(np.asarray(decision.target_m), AREA)
        assert any(np.array_equal(start + move, landing) for move in MOVES)
        link.advance(1.5)  # on its way (15 m at 10 m/s), not there: the next report comes
    assert service.snapshot_counters()["decisions"] == 2


@pytest.mark.skipif(not SHIPPED_DDQN.is_file(), reason="no shipped DDQN checkpoint")
def test_serving_sees_the_environments_observation_and_only_valid_moves() -> None:
    """One code path: the observation the service builds equals the environment's, and the
    chosen move is valid under the environment's own mask."""
    policy = load_policy(str(SHIPPED_DDQN))
    env = FapDiscreteEnv()
    rng = np.random.default_rng(0)
    for seed in range(5):
        obs, info = env.reset(
            seed=seed, options={"uav_xyz_m": rng.uniform([0, 0, 25], [500, 500, 100])}
        )
        scenario = env.unwrapped.scenario if hasattr(env, "unwrapped") else env.scenario
        served = UserReports.from_metrics(
            scenario.users_xy_m,
            scenario.load_bps,
            info["throughput_bps"],
            info["delay_s"],
            info["plr"],
        )
        uav = info["uav_xyz_m"]
        np.testing.assert_array_equal(policy.observe(served, uav), obs)  # type: ignore[attr-defined]
        target = policy.decide(served, uav)
        index = zone_index(info["target_xyz_m"], AREA)
        moves = [
            i for i, m in enumerate(MOVES) if np.allclose(zone_position(index + m, AREA), target)
        ]
        assert moves and info["action_mask"][moves[0]]
        assert np.array_equal(move_mask(index, AREA), info["action_mask"])


def test_unusable_policies_are_refused_with_the_reason(tmp_path: Any) -> None:
    with pytest.raises(InputError, match="no such checkpoint"):
        load_policy(str(tmp_path / "nope.zip"))
    with pytest.raises(InputError, match="policy"):
        load_policy("  ")


def test_a_failing_policy_holds_the_target_instead_of_failing_the_report(
    make_service: Callable[..., PlacementService],
) -> None:
    service = make_service()
    before = service.submit_report(Report(1.0, ("a", "b", "c"), reports()))

    def broken(*args: Any) -> np.ndarray:
        raise RuntimeError("a policy bug")

    service.policy.decide = broken  # type: ignore[method-assign]
    after = service.submit_report(Report(2.0, ("a", "b", "c"), reports((450.0, 450.0))))
    assert after == before
    assert service.snapshot_counters()["decision_errors"] == 1


def service_waiting_for_a_vehicle(
    start_mock: Callable[..., MockAutopilot], **settings: Any
) -> tuple[int, PlacementService]:
    """A started on-report service (load-weighted) linked to a free port where no vehicle listens
    yet: the link keeps reconnecting. Returns the port, for a mock to appear on later."""
    placeholder = start_mock("px4")
    port = placeholder.port
    placeholder.stop()
    config = ServiceSettings(
        mavlink=f"tcp:127.0.0.1:{port}",
        api_token="t",
        policy="load-weighted",
        decision_mode="on-report",
        **settings,
    )
    link = MavlinkLink(LinkConfig(config.mavlink))
    return port, PlacementService(config, link, load_policy("load-weighted")).start()


def test_a_report_held_for_the_link_is_decided_once_the_link_is_back(
    start_mock: Callable[..., MockAutopilot],
) -> None:
    port, service = service_waiting_for_a_vehicle(start_mock)
    try:
        assert service.submit_report(Report(1.0, ("a", "b", "c"), reports())) is None
        assert service.snapshot_counters()["decisions_waiting_link"] == 1
        start_mock("px4", listen=f"tcp:127.0.0.1:{port}")
        # No new report: the kept one is decided as soon as the vehicle is heard.
        decision = wait_for(service.current_decision, 20.0, message="decision after link up")
        assert decision.source == "policy"
        assert service.snapshot_counters()["decisions"] == 1
        assert service.vehicle().target_m == pytest.approx(decision.target_m)
    finally:
        service.stop()


def test_a_report_held_for_the_link_that_went_stale_meanwhile_is_not_flown(
    start_mock: Callable[..., MockAutopilot],
) -> None:
    port, service = service_waiting_for_a_vehicle(start_mock, report_max_age_s=0.5)
    try:
        assert service.submit_report(Report(1.0, ("a", "b", "c"), reports())) is None
        held_at = service.snapshot_counters()["decisions_waiting_link"]
        assert held_at == 1
        submitted = time.monotonic()
        wait_for(lambda: time.monotonic() - submitted > 0.6, 2.0, message="the report to age")
        mock = start_mock("px4", listen=f"tcp:127.0.0.1:{port}")
        # The link comes back; the watcher looks at the kept report, finds it stale, holds it.
        wait_for(
            lambda: service.snapshot_counters().get("decisions_held_stale", 0) >= 1,
            20.0,
            message="the stale report held once the link is back",
        )
        assert service.current_decision() is None
        assert service.snapshot_counters().get("decisions", 0) == 0
        assert service.vehicle().target_m is None
        assert mock.stats["setpoints_received"] == 0
    finally:
        service.stop()


@pytest.mark.parametrize(
    "content",
    ["{not json", '{"decision": {"target_m": ["nan", 1, 2], "policy": "x"}}', "[1, 2, 3]"],
    ids=["corrupt", "bad-target", "not-an-object"],
)
def test_an_unreadable_state_file_still_makes_the_start_a_restart_that_arms_nothing(
    start_mock: Callable[..., MockAutopilot], tmp_path: Any, content: str
) -> None:
    mock = start_mock("px4")
    state_file = tmp_path / "state.json"
    state_file.write_text(content)
    config = ServiceSettings(
        mavlink=f"tcp:127.0.0.1:{mock.port}",
        api_token="t",
        policy="load-weighted",
        arm_and_takeoff=True,
        state_file=state_file,
    )
    link = MavlinkLink(LinkConfig(config.mavlink))
    service = PlacementService(config, link, load_policy("load-weighted")).start()
    try:
        wait_for(lambda: service.vehicle().position_m is not None, 10.0, message="telemetry")
        connected = time.monotonic()
        wait_for(lambda: time.monotonic() - connected > 2.0, 5.0, message="two seconds connected")
        assert service.snapshot_counters()["state_restore_errors"] == 1
        assert link.state().takeoff == "idle"  # deferred to the first fresh decision
        assert mock.stats.get("arms", 0) == 0 and mock.stats.get("takeoffs", 0) == 0
        assert not mock.state().armed
    finally:
        service.stop()


def test_serving_a_checkpoint_outside_its_training_environments_is_warned(caplog) -> None:
    """The shipped checkpoints were trained in the open environment: serving one over a town
    still works, with one warning naming both; in the open field, none."""
    from dataclasses import replace

    from service.policy_runtime import SHIPPED_DDPG
    from sim.world import CLOSED_LOOP

    town = replace(CLOSED_LOOP, area=AreaConfig(environment="urban"))
    with caplog.at_level(logging.WARNING, logger="service.policy_runtime"):
        load_policy(str(SHIPPED_DDPG), town)
    warned = [r.getMessage() for r in caplog.records if "trained in" in r.getMessage()]
    assert warned == [
        "policy ddpg-residual-dr was trained in the open environment(s); serving it in urban"
    ]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="service.policy_runtime"):
        load_policy(str(SHIPPED_DDPG), CLOSED_LOOP)
    assert not [r for r in caplog.records if "trained in" in r.getMessage()]


def test_an_envelope_put_in_flight_is_flown_again_after_a_restart(
    make_service: Callable[..., PlacementService], tmp_path: Any
) -> None:
    """Issue 39: an operator's envelope is kept in the state file; the restarted service's
    vehicle flies in it (not the configured one); a saved envelope that no longer fits is
    ignored and counted, and the configured one stays."""
    state_file = tmp_path / "state.json"
    first = make_service(state_file=state_file)
    document = {
        "format": "tupa-envelope/1",
        "exclusions": [
            {"name": "mast", "polygon": [[200, 200], [260, 200], [260, 260]], "ceiling_m": 80}
        ],
        "ceiling_m": 90,
    }
    first.set_envelope("uav1", document)
    first.stop()
    saved = json.loads(state_file.read_text())
    assert saved["envelopes"] == {"uav1": document}
    second = make_service(state_file=state_file)
    envelope = second.link.envelope
    assert envelope.ceiling_m == 90 and [e.name for e in envelope.exclusions] == ["mast"]
    assert second.snapshot_counters().get("state_restore_errors", 0) == 0
    second.stop()
    saved["envelopes"]["uav1"]["ceiling_m"] = 5  # below the floor: cannot be flown
    saved["envelopes"]["uav9"] = document  # no such vehicle
    state_file.write_text(json.dumps(saved))
    third = make_service(state_file=state_file)
    assert third.link.envelope.ceiling_m == AREA.z_max_m and not third.link.envelope.exclusions
    assert third.snapshot_counters()["state_restore_errors"] == 2
