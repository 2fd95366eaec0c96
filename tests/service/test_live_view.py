"""The operator view inside the service: the publish/subscribe hub (bounded, never blocking the
publisher), the frames (utility and its parts from ``sim.utility``, track, link state), and the
placement loop publishing one frame per decision period in both decision modes."""

from __future__ import annotations

import json
import threading
import time
import warnings

import numpy as np
import pytest

from service.decisions import Report
from service.live_view import TRACK_POINTS, LiveView, Moment
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.pubsub import Hub, SubscriberLimitError
from service.settings import ServiceSettings
from service.vehicle_link import LinkState
from sim.config import AreaConfig, UtilityConfig
from sim.observation import UserReports
from sim.utility import network_utility
from tests.fakes import FakeLink
from tests.helpers import wait_for

# --------------------------------------------------------------------------- the hub


def test_a_full_queue_drops_its_oldest_frames_and_counts_them() -> None:
    hub: Hub[int] = Hub(max_subscribers=2, max_frames=3)
    slow, fast = hub.subscribe(), hub.subscribe()
    for frame in range(10):
        hub.publish(frame)
        assert fast.take() == [frame]
    assert slow.take() == [7, 8, 9]
    assert slow.dropped == 7 and fast.dropped == 0 and hub.dropped == 7
    assert slow.take() == []


def test_the_hub_refuses_subscribers_over_its_limit_and_frees_a_place_on_close() -> None:
    hub: Hub[int] = Hub(max_subscribers=1)
    first = hub.subscribe()
    with pytest.raises(SubscriberLimitError):
        hub.subscribe()
    first.close()
    first.close()  # twice is fine
    assert first.closed and len(hub) == 0
    hub.subscribe()


def test_publish_survives_a_broken_notify_and_close_all_tells_everyone() -> None:
    hub: Hub[int] = Hub()
    told = []

    def broken() -> None:
        raise RuntimeError("event loop is closed")

    hub.subscribe(broken)
    sub = hub.subscribe(lambda: told.append(1))
    hub.publish(1)  # no exception
    assert told == [1]
    hub.close_all()
    assert sub.closed and told == [1, 1] and len(hub) == 0


def test_publishing_never_waits_for_a_subscriber_that_does_not_read() -> None:
    hub: Hub[bytes] = Hub(max_subscribers=16, max_frames=4)
    subscribers = [hub.subscribe(lambda: None) for _ in range(16)]
    frame = b"x" * 100_000
    started = time.perf_counter()
    for _ in range(2000):
        hub.publish(frame)
    assert time.perf_counter() - started < 1.0  # about 10 us a publish to 16 subscribers
    assert all(s.pending() == 4 for s in subscribers)  # bounded: 4 shared frames each


# --------------------------------------------------------------------------- frames


def _state(**over: object) -> LinkState:
    base = dict(
        link="up", flavour="px4", mode="OFFBOARD", armed=True, position_m=(100.0, 200.0, 50.0),
        relative_alt_m=50.0, heartbeat_age_s=0.1, target_m=None, streaming=True,
        takeoff="airborne",
    )  # fmt: skip
    base.update(over)
    return LinkState(**base)  # type: ignore[arg-type]


def _report(timestamp: float = 1.0) -> Report:
    columns = {
        "x_m": np.array([10.0, 400.0]),
        "y_m": np.array([20.0, 300.0]),
        "offered_bps": np.array([30e6, 2e6]),
        "throughput_bps": np.array([15e6, 2e6]),
        "delay_s": np.array([0.8, 0.01]),
        "plr": np.array([0.2, 0.0]),
    }
    return Report.from_columns(timestamp, ("big", "small"), columns)


def _moment(state: LinkState, report: Report | None = None) -> Moment:
    return Moment(
        time_s=1000.0, link=state, policy_name="oracle", policy_spec="oracle",
        decision_period_s=1.0, decision=None, report=report, report_age_s=0.5,
        report_max_age_s=5.0,
    )  # fmt: skip


def test_a_frame_has_the_utility_of_the_report_and_its_three_parts() -> None:
    view = LiveView(AreaConfig(), UtilityConfig())
    report = _report()
    view.record(_moment(_state(), report))
    frame = json.loads(view.frame(_moment(_state(), report)).data)
    users = report.users
    expected = network_utility(
        users.throughput_bps, users.delay_s, users.plr, users.offered_bps, UtilityConfig()
    )
    utility = frame["utility"]
    assert utility["value"] == pytest.approx(float(expected), abs=1e-4)
    t = 17e6 / 32e6
    assert utility["throughput"] == pytest.approx(0.6 * t, abs=1e-4)
    assert utility["delay"] == pytest.approx(0.3 * (1 - 0.405), abs=1e-4)
    assert utility["loss"] == pytest.approx(0.1 * (1 - 0.1), abs=1e-4)
    assert frame["utility_history"] == [
        [1000.0, utility["value"], utility["throughput"], utility["delay"], utility["loss"]]
    ]
    assert [u["served"] for u in frame["users"]] == [0.5, 1.0]
    assert frame["report"] == {"timestamp": 1.0, "age_s": 0.5, "stale": False}


def test_a_report_with_numbers_the_api_refuses_gives_no_utility_and_no_warning() -> None:
    """Infinite loads of both signs (a Python caller can submit what the API refuses): the
    utility is null, nothing enters the history, and the frame is strict JSON."""
    view = LiveView(AreaConfig(), UtilityConfig())
    users = _report().users
    hostile = UserReports(
        users.x_m, users.y_m, np.array([np.inf, -np.inf]), users.throughput_bps, users.delay_s,
        users.plr,
    )  # fmt: skip
    report = Report(1.0, ("big", "small"), hostile)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "invalid value" would be raised here
        view.record(_moment(_state(), report))
        data = view.frame(_moment(_state(), report)).data

    def refuse(constant: str) -> None:
        raise AssertionError(f"not strict JSON: {constant}")

    frame = json.loads(data, parse_constant=refuse)
    assert frame["utility"] is None and frame["utility_history"] == []
    assert [u["offered_bps"] for u in frame["users"]] == [None, None]  # unknown, not NaN
    throughput = [u["throughput_bps"] for u in frame["users"]]
    assert throughput == [15_000_000, 2_000_000] and all(isinstance(t, int) for t in throughput)


def test_the_history_takes_each_report_once_and_the_track_is_bounded() -> None:
    view = LiveView(AreaConfig(), UtilityConfig())
    report = _report()
    for i in range(TRACK_POINTS + 50):
        view.record(_moment(_state(position_m=(float(i), 0.0, 30.0)), report))
    frame = json.loads(view.frame(_moment(_state(), report)).data)
    assert len(frame["utility_history"]) == 1
    track = frame["vehicles"][0]["track_m"]
    assert len(track) == TRACK_POINTS and track[-1] == [TRACK_POINTS + 49.0, 0.0, 30.0]


def test_a_frame_shows_a_lost_link_and_no_numbers_it_cannot_carry() -> None:
    view = LiveView(AreaConfig(), UtilityConfig())
    state = _state(link="link_lost", heading_deg=float("nan"), heartbeat_age_s=float("inf"))
    frame = json.loads(view.frame(_moment(state)).data)
    (vehicle,) = frame["vehicles"]
    assert vehicle["link"] == "link_lost" and vehicle["id"] == "uav1"
    assert vehicle["heading_deg"] is None and vehicle["heartbeat_age_s"] is None
    assert frame["utility"] is None and frame["users"] == [] and frame["report"] is None


def test_the_heading_comes_from_telemetry() -> None:
    view = LiveView(AreaConfig(), UtilityConfig())
    frame = json.loads(view.frame(_moment(_state(heading_deg=271.34))).data)
    assert frame["vehicles"][0]["heading_deg"] == 271.3


# --------------------------------------------------------------------------- the loop


@pytest.mark.parametrize("mode", ["paced", "on-report"])
def test_the_loop_publishes_once_per_decision_period(mode: str) -> None:
    settings = ServiceSettings(
        insecure=True, policy="load-weighted", step_s=0.05, decision_mode=mode
    )
    link = FakeLink(position_m=(250.0, 250.0, 50.0), realtime=True)
    service = PlacementService(settings, link, load_policy("load-weighted")).start()
    frames = []
    arrived = threading.Event()
    sub = service.live.hub.subscribe(arrived.set)
    try:
        service.submit_report(_report(time.time()))
        started = time.monotonic()
        wait_for(lambda: len(frames.extend(sub.take()) or frames) >= 10, 5.0, message="frames")
        elapsed = time.monotonic() - started
        assert elapsed > 8 * 0.05  # not faster than the period
        last = json.loads(frames[-1].data)
        assert last["vehicles"][0]["decision"] is not None
        assert [u["id"] for u in last["users"]] == ["big", "small"]
        assert [f.seq for f in frames] == sorted(f.seq for f in frames)
    finally:
        service.stop()
    assert sub.closed  # stopping the service ends the streams


def test_on_a_site_the_frame_carries_the_buildings_and_what_the_vehicle_covers(
    tmp_path,
) -> None:
    """Issue 38, seen: the buildings (the tallest in each 10 m square) once per frame, and each
    vehicle's coverage from where it is (the site's path loss to each 20 m square, null where
    no ray reaches); the frame still matches the published schema."""
    from api.live_schemas import LiveFrameOut
    from sim.sites import save_site
    from tests.sim.test_sites_channel import _site

    save_site(_site(100.0), tmp_path / "s")  # a 30 m block on x 40-60 m; no path from (0, 0, 25)
    area = AreaConfig(size_x_m=100, size_y_m=100, environment=f"site:{tmp_path / 's'}")
    view = LiveView(area, UtilityConfig())
    frame = json.loads(view.frame(_moment(_state(position_m=(10.0, 50.0, 50.0)))).data)
    LiveFrameOut.model_validate(frame)
    site = frame["site"]
    assert (site["cell_m"], site["nx"], site["ny"]) == (10.0, 10, 10)
    row = site["heights_m"][:10]
    assert row == [0.0] * 4 + [30.0, 30.0] + [0.0] * 4
    coverage = frame["vehicles"][0]["coverage"]
    assert (coverage["nx"], coverage["ny"]) == (5, 5)
    assert coverage["loss_db"] == [90.0] * 25
    shadow = json.loads(view.frame(_moment(_state(position_m=(0.0, 0.0, 25.0)))).data)
    assert shadow["vehicles"][0]["coverage"]["loss_db"] == [None] * 25
    open_field = json.loads(LiveView(AreaConfig(), UtilityConfig()).frame(_moment(_state())).data)
    assert open_field["site"] is None and open_field["vehicles"][0]["coverage"] is None
