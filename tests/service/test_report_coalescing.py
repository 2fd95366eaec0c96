"""Decisions never queue: in ``on-report`` mode a burst of reports costs one decision after the
running one, a report is answered with the decision taken from it, at once when a newer one
replaces it, or ``pending`` within two decision periods when decisions are slower than the period;
slow decisions are timed and counted. Reports are ordered by ``min(timestamp, arrival)``, so one
stamped ahead of the service's clock cannot lock honest reports out.

A deliberately slow policy (:class:`tests.gated_policy.GatedPolicy`: each decision waits until
the test lets it through) makes "slow" a matter of the test's order of events, not of the
machine's speed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest

from service.decisions import Report, ReportReceipt
from service.fleet_placement import FleetPlacementService, load_fleet_policy
from service.fleet_spec import FleetSpec, VehicleSpec
from service.placement import REPORT_WAIT_PERIODS, OutOfOrderReportError, PlacementService
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sim.config import AreaConfig
from sim.observation import UserReports
from tests.fakes import FakeLink
from tests.gated_policy import WAIT_S, GatedFleetPolicy, GatedPolicy
from tests.helpers import wait_for

AREA = AreaConfig()


def report(timestamp_s: float, marker: float) -> Report:
    """Three users; the first one's ``x_m`` is ``marker`` (what :class:`GatedPolicy` records)."""
    users = UserReports(
        x_m=np.array([marker, 100.0, 400.0]),
        y_m=np.array([250.0, 100.0, 400.0]),
        offered_bps=np.array([10e6, 2e6, 2e6]),
        throughput_bps=np.array([8e6, 2e6, 2e6]),
        delay_s=np.array([0.05, 0.01, 0.01]),
        plr=np.array([0.01, 0.0, 0.0]),
    )
    return Report(timestamp_s, ("a", "b", "c"), users)


@pytest.fixture
def make_service() -> Iterator[Callable[..., tuple[PlacementService, FakeLink]]]:
    """Factory: ``make_service(policy, **settings)``: a started ``on-report`` service (unless
    ``decision_mode`` says otherwise) on an airborne :class:`FakeLink`; stopped at teardown
    (every gate opened first, so that no decision thread is left waiting)."""
    made: list[tuple[PlacementService, Any]] = []

    def _make(policy: Any, **settings: Any) -> tuple[PlacementService, FakeLink]:
        settings.setdefault("decision_mode", "on-report")
        config = ServiceSettings(
            mavlink="tcp:127.0.0.1:1", api_token="t", policy="load-weighted", **settings
        )
        link = FakeLink(LinkConfig(config.mavlink, area=AREA), position_m=(250.0, 250.0, 30.0))
        service = PlacementService(config, link, policy).start()
        made.append((service, policy))
        wait_for(lambda: service.readiness()[0], WAIT_S, message="link up with a position")
        return service, link

    yield _make
    for service, policy in made:
        if isinstance(policy, GatedPolicy):
            policy.open()
        service.stop()


def _outcome(future: Future[ReportReceipt]) -> str:
    return future.result(timeout=WAIT_S).outcome


def test_reports_during_a_slow_decision_make_one_pending_decision_the_latest_wins(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    policy = GatedPolicy()
    service, _ = make_service(policy, step_s=600.0)  # pending after 20 min: never, here
    with ThreadPoolExecutor(4) as pool:
        first = pool.submit(service.submit, report(1.0, 10.0))
        policy.wait_started(1)  # the decision on the first report runs, held by the gate
        later = []
        for i, marker in enumerate((20.0, 30.0, 40.0)):
            later.append(pool.submit(service.submit, report(2.0 + i, marker)))
            wait_for(
                lambda i=i: service.snapshot_counters()["reports_accepted"] == 2 + i,
                WAIT_S,
                message=f"report {2 + i} accepted",
            )
        # Each report replaced by a newer one is answered at once, the decision still running.
        assert [_outcome(f) for f in later[:2]] == ["superseded", "superseded"]
        assert not first.done() and not later[2].done()
        assert policy.seen == [10.0]

        policy.release()
        decided = first.result(timeout=WAIT_S)
        assert decided.outcome == "decided"
        assert decided.decision is not None and decided.decision.target_m[0] == 10.0
        policy.wait_started(2)
        assert policy.seen == [10.0, 40.0]  # one decision for the three, on the latest
        policy.release()
        last = later[2].result(timeout=WAIT_S)
        assert last.outcome == "decided"
        assert last.decision is not None and last.decision.target_m[0] == 40.0
    counters = service.snapshot_counters()
    assert counters["decisions"] == 2 and counters["reports_superseded"] == 2
    assert service.current_decision() == last.decision


def test_a_burst_of_concurrent_reports_costs_one_decision_after_the_running_one(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    policy = GatedPolicy()
    service, _ = make_service(policy, step_s=600.0)
    n = 16
    with ThreadPoolExecutor(n + 1) as pool:
        first = pool.submit(service.submit, report(1.0, 5.0))
        policy.wait_started(1)
        # One timestamp for the burst (a repeat is in order), whichever thread comes first.
        burst = [pool.submit(service.submit, report(2.0, 100.0 + i)) for i in range(n)]
        wait_for(
            lambda: sum(f.done() for f in burst) == n - 1, WAIT_S, message="all but one answered"
        )
        assert all(_outcome(f) == "superseded" for f in burst if f.done())
        assert policy.seen == [5.0]  # none of them waited for, or ran, a decision of its own
        policy.open()
        assert _outcome(first) == "decided"
        (latest,) = [f for f in burst if _outcome(f) == "decided"]
        marker = latest.result().decision.target_m[0]  # type: ignore[union-attr]
    assert policy.seen == [5.0, marker]
    assert service.snapshot_counters()["reports_superseded"] == n - 1


def test_decisions_slower_than_the_period_answer_pending_and_are_timed_and_counted(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    policy = GatedPolicy()
    period_s = 0.2
    service, _ = make_service(policy, step_s=period_s)
    assert service.report_wait_s == pytest.approx(REPORT_WAIT_PERIODS * period_s)
    with caplog.at_level(logging.WARNING, logger="service.placement"):
        # The decision on the report is held: the report is answered without it.
        first = service.submit(report(1.0, 10.0))
        assert first == ReportReceipt("pending", None)
        policy.wait_started(1)
        # A report behind the running decision waits for it no longer either.
        second = service.submit(report(2.0, 20.0))
        assert second == ReportReceipt("pending", None)
        assert policy.seen == [10.0]
        policy.open()
        wait_for(
            lambda: (d := service.current_decision()) is not None and d.target_m[0] == 20.0,
            WAIT_S,
            message="the pending report decided",
        )
    assert policy.seen == [10.0, 20.0]
    counters = service.snapshot_counters()
    assert counters["reports_pending"] == 2 and counters["decisions"] == 2
    timing = service.decision_timing()
    assert timing.mode == "on-report" and timing.period_s == period_s and timing.timed == 2
    # The first decision ran from before the second report came until after its answer, 1.75
    # periods later: longer than a period.
    assert timing.overruns >= 1 and timing.max_s is not None and timing.max_s > period_s
    assert timing.last_s is not None and counters["decision_overruns"] == timing.overruns
    assert "longer than the decision period" in caplog.text


def test_a_report_is_answered_with_the_decision_taken_from_it(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    service, _ = make_service(GatedPolicy(opened=True))
    for i, marker in enumerate((50.0, 60.0, 70.0)):
        receipt = service.submit(report(1.0 + i, marker))
        assert receipt.outcome == "decided"
        assert receipt.decision is not None and receipt.decision.target_m[0] == marker
    timing = service.decision_timing()
    assert timing.timed == 3 and timing.last_s is not None and timing.overruns == 0


def test_a_report_while_the_link_is_down_is_held_then_decided_when_it_returns(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    policy = GatedPolicy(opened=True)
    service, link = make_service(policy)
    link.set_link(False)
    wait_for(lambda: not service.readiness()[0], WAIT_S, message="link down")
    held = service.submit(report(time.time(), 80.0))
    assert held == ReportReceipt("held", None)
    assert service.snapshot_counters()["decisions_waiting_link"] == 1
    link.set_link(True)
    decision = wait_for(service.current_decision, WAIT_S, message="decided once the link is back")
    assert decision.target_m[0] == 80.0 and policy.seen == [80.0]


def test_paced_mode_stores_the_report_and_answers_at_once(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    policy = GatedPolicy()
    service, _ = make_service(policy, decision_mode="paced", step_s=600.0)
    receipt = service.submit(report(1.0, 10.0))  # the paced thread's decision is held
    assert receipt.outcome == "stored"


def test_a_report_stamped_ahead_does_not_lock_out_honest_reports(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    service, _ = make_service(GatedPolicy(opened=True))
    ahead = service.submit(report(time.time() + 4.9, 10.0))  # within report_max_future_s
    assert ahead.outcome == "decided"
    for marker in (20.0, 30.0, 40.0):
        honest = service.submit(report(time.time(), marker))
        assert honest.outcome == "decided"
        assert honest.decision is not None and honest.decision.target_m[0] == marker
    assert service.snapshot_counters().get("reports_out_of_order", 0) == 0
    # A report older than the last honest one is still out of order.
    with pytest.raises(OutOfOrderReportError, match="older"):
        service.submit(report(time.time() - 60.0, 50.0))
    assert service.current_decision().target_m[0] == 40.0  # type: ignore[union-attr]


def test_a_fleet_coalesces_reports_and_times_its_decisions() -> None:
    urls = ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5761")
    config = ServiceSettings(
        fleet_mavlink=urls, mavlink=urls[0], insecure=True, decision_mode="on-report", step_s=600
    )
    fleet = FleetSpec(tuple(VehicleSpec(f"uav{i + 1}", u, None) for i, u in enumerate(urls)), 10.0)
    world = config.policy_world()
    links = {
        v.id: FakeLink(
            LinkConfig(v.mavlink, area=world.area),
            position_m=(200.0 + 60.0 * i, 250.0, 30.0),
            system_id=i + 1,
        )
        for i, v in enumerate(fleet.vehicles)
    }
    policy = GatedFleetPolicy(load_fleet_policy("kmeans-load-weighted", world, 10.0))
    service = FleetPlacementService(config, links, policy, fleet, world).start()  # type: ignore[arg-type]
    try:
        with ThreadPoolExecutor(4) as pool:
            first = pool.submit(service.submit, report(1.0, 10.0))
            policy.wait_started(1)
            second = pool.submit(service.submit, report(2.0, 20.0))
            wait_for(lambda: service.snapshot_counters()["reports_accepted"] == 2, WAIT_S)
            third = pool.submit(service.submit, report(3.0, 30.0))
            assert _outcome(second) == "superseded"
            policy.open()
            assert _outcome(first) == "decided" and _outcome(third) == "decided"
        assert policy.seen == [10.0, 30.0]
        assert sorted(service.decisions()) == ["uav1", "uav2"]
        assert service.decision_timing().timed == 2
    finally:
        policy.open()
        service.stop()


def test_accepting_a_report_never_waits_for_a_decision(
    make_service: Callable[..., tuple[PlacementService, FakeLink]],
) -> None:
    """``accept`` (what the HTTP side calls on its event loop, in the order reports come) only
    takes the report; ``receipt`` is what waits."""
    policy = GatedPolicy()
    service, _ = make_service(policy, step_s=600.0)
    first = service.accept(report(1.0, 10.0))
    policy.wait_started(1)  # held by the gate
    second = service.accept(report(2.0, 20.0))
    third = service.accept(report(3.0, 30.0))
    assert (first.seq, second.seq, third.seq) == (1, 2, 3)
    assert service.receipt(second).outcome == "superseded"
    policy.open()
    assert service.receipt(first).outcome == "decided"
    assert service.receipt(third).outcome == "decided"
    assert policy.seen == [10.0, 30.0]
