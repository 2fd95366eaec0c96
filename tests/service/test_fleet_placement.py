"""The fleet's placement loop (:mod:`service.fleet_placement`) on in-memory vehicles
(:class:`tests.fakes.FakeLink`): one report, one separated target per vehicle; degraded mode
(a lost vehicle's users covered by the others at the next decision, its stream cleared, its last
position kept clear; it rejoins when its link returns); two connections to one vehicle; a system
id the fleet file does not name; fleet policy swaps and refusals."""

from __future__ import annotations

import itertools
import json
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policies.interface import ReportedUsers
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_scored import ScoredKMeansPlacement
from policies.training.fleet_training import FleetTrainConfig, train_fleet
from policies.training.training import zero_actor_output
from service.decisions import Report
from service.errors import InputError
from service.fleet_placement import FleetPlacementService, load_fleet_policy
from service.fleet_spec import FleetSpec, VehicleSpec
from service.policy_runtime import SHIPPED_CHECKPOINTS, SHIPPED_FLEET
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sim.association import associate_at
from sim.fleet import FleetConfig
from sim.geometry import assign_targets, volume_bounds
from sim.observation import UserReports
from sitl_mock.config import VehicleConfig
from sitl_mock.fleet import MockFleet
from tests.fakes import FakeLink
from tests.helpers import tiny_preset, wait_for

HOT_SPOTS = ((100.0, 100.0), (400.0, 400.0), (100.0, 400.0))
TINY_PRESET = tiny_preset(learning_starts=16, batch_size=16, train_episode_steps=5)


def hot_spot_report(timestamp_s: float, seed: int = 0) -> Report:
    """Ten users around each of three hot spots, 2 Mbit/s each."""
    rng = np.random.default_rng(seed)
    xy = np.concatenate([rng.normal(c, 15.0, (10, 2)) for c in HOT_SPOTS]).clip(0.0, 500.0)
    n = len(xy)
    users = UserReports(
        xy[:, 0], xy[:, 1], np.full(n, 2e6), np.full(n, 2e6), np.full(n, 0.01), np.zeros(n)
    )
    return Report(timestamp_s, tuple(f"u{i}" for i in range(n)), users)


Fleet = tuple[FleetPlacementService, dict[str, FakeLink]]


@pytest.fixture
def make_fleet() -> Iterator[Callable[..., Fleet]]:
    """Factory: ``make_fleet(k, policy=..., system_ids=..., expected=...)``: a started
    ``on-report`` fleet service over k FakeLinks airborne 60 m apart; stopped at teardown."""
    services: list[FleetPlacementService] = []

    def _make(
        k: int = 3,
        policy: str = "kmeans-load-weighted",
        system_ids: list[int] | None = None,
        expected: list[int | None] | None = None,
        **settings: Any,
    ) -> Fleet:
        urls = tuple(f"tcp:127.0.0.1:{5760 + i}" for i in range(k))
        config = ServiceSettings(
            fleet_mavlink=urls if k > 1 else (),
            mavlink=urls[0],
            insecure=True,
            decision_mode="on-report",
            **settings,
        )
        expected = expected or [None] * k
        fleet = FleetSpec(
            tuple(VehicleSpec(f"uav{i + 1}", urls[i], expected[i]) for i in range(k)),
            config.separation_m,
        )
        world = config.policy_world()
        system_ids = system_ids or list(range(1, k + 1))
        links = {
            v.id: FakeLink(
                LinkConfig(v.mavlink, area=world.area),
                position_m=(200.0 + 60.0 * i, 250.0, 30.0),
                system_id=system_ids[i],
            )
            for i, v in enumerate(fleet.vehicles)
        }
        policy_object = load_fleet_policy(policy, world, fleet.separation_m)
        service = FleetPlacementService(config, links, policy_object, fleet, world).start()
        services.append(service)
        return service, links

    yield _make
    for service in services:
        service.stop()


def _min_gap(points: list[tuple[float, float, float]]) -> float:
    return min(np.linalg.norm(np.subtract(a, b)) for a, b in itertools.combinations(points, 2))


def test_one_report_gives_every_vehicle_a_separated_target_on_a_hot_spot(
    make_fleet: Callable[..., Fleet],
) -> None:
    service, links = make_fleet(3)
    service.submit_report(hot_spot_report(time.time()))
    decisions = service.decisions()
    assert list(decisions) == ["uav1", "uav2", "uav3"]
    targets = [d.target_m for d in decisions.values()]
    assert _min_gap(targets) >= 10.0
    # One vehicle per hot spot (the load-weighted k-means clusters), each within 30 m of it.
    for spot in HOT_SPOTS:
        assert min(np.hypot(t[0] - spot[0], t[1] - spot[1]) for t in targets) < 30.0
    # What each link streams is its decision.
    for vid, link in links.items():
        assert link.state().target_m == decisions[vid].target_m
    assert service.readiness() == (True, [])


def test_a_lost_vehicle_is_covered_by_the_others_and_rejoins_when_it_returns(
    make_fleet: Callable[..., Fleet],
) -> None:
    service, links = make_fleet(3)
    report = hot_spot_report(time.time())
    service.submit_report(report)
    full = service.decisions()
    lost_at = links["uav2"].state().position_m

    links["uav2"].set_link(False)
    service.submit_report(hot_spot_report(time.time(), seed=0))
    degraded = service.decisions()
    assert list(degraded) == ["uav1", "uav3"]
    # The two that fly now take the placement the same policy gives two vehicles, for all users.
    wanted = KMeansPlacement(2, service.area, load_weighted=True).place(
        ReportedUsers.of(report.users)
    )
    got = np.array([d.target_m for d in degraded.values()])
    assert sorted(map(tuple, np.round(got, 6))) == sorted(map(tuple, np.round(wanted, 6)))
    # Its stream is cleared (nothing stale flies when its link returns) and it is kept clear of.
    assert links["uav2"].state().target_m is None
    assert all(np.linalg.norm(np.subtract(t, lost_at)) >= 10.0 for t in got)
    ready, reasons = service.readiness()
    assert ready and reasons == ["uav2: mavlink link is link_lost"]
    views = {v.id: v for v in service.vehicles()}
    assert views["uav2"].problem == "mavlink link is link_lost" and views["uav2"].decision is None
    assert service.snapshot_counters()["decisions_degraded"] == 1

    links["uav2"].set_link(True)
    service.submit_report(hot_spot_report(time.time()))
    rejoined = service.decisions()
    assert list(rejoined) == ["uav1", "uav2", "uav3"]
    assert sorted(d.target_m for d in rejoined.values()) == sorted(
        d.target_m for d in full.values()
    )


def test_a_fleets_readiness_names_what_a_single_vehicles_names_for_each_vehicle(
    make_fleet: Callable[..., Fleet],
) -> None:
    # One readiness for one vehicle and for each of a fleet's (service.placement.vehicle_notes):
    # signing failures and a vehicle that signs without our key are named per vehicle too.
    service, links = make_fleet(3)
    links["uav2"].counters["signed_vehicle_without_key"] = 4
    links["uav3"].set_link(False)
    links["uav3"].counters["signing_failures"] = 7
    ready, reasons = service.readiness()
    assert ready  # two vehicles can be commanded (uav2 is up: it is commanded, and deaf)
    assert reasons == [
        "uav3: mavlink link is link_lost",
        "uav2: mavlink signing: the vehicle signs its messages but no signing key is configured "
        "(TUPA_MAVLINK_SIGNING_KEY); it will ignore our setpoints",
        "uav3: mavlink signing failed: 7 messages from the vehicle failed the signature check "
        "(check TUPA_MAVLINK_SIGNING_KEY against the vehicle's key); the vehicle is not commanded",
    ]


def test_a_vehicle_sent_home_by_its_battery_is_covered_by_the_others_until_handed_back(
    make_fleet: Callable[..., Fleet],
) -> None:
    """Issue 39: a vehicle whose link let go at its battery reserve (the autopilot has it,
    returning home: service/link_safety.py) is out of the fleet's placement, as a lost one is,
    and kept clear of; an operator's hand-back after the recharge takes it in again."""
    service, links = make_fleet(3)
    service.submit_report(hot_spot_report(time.time()))
    returning_from = links["uav3"].state().position_m
    links["uav3"].vehicle_leaves("autopilot", "battery reserve reached: returning home (RTL)")
    service.submit_report(hot_spot_report(time.time()))
    degraded = service.decisions()
    assert list(degraded) == ["uav1", "uav2"]
    assert all(
        np.linalg.norm(np.subtract(d.target_m, returning_from)) >= 10.0 for d in degraded.values()
    )
    views = {v.id: v for v in service.vehicles()}
    assert "battery reserve reached" in (views["uav3"].problem or "")
    links["uav3"].hand_back()
    service.submit_report(hot_spot_report(time.time()))
    assert list(service.decisions()) == ["uav1", "uav2", "uav3"]


def test_all_vehicles_lost_holds_and_the_report_is_decided_when_one_returns(
    make_fleet: Callable[..., Fleet],
) -> None:
    service, links = make_fleet(2)
    for link in links.values():
        link.set_link(False)
    service.submit_report(hot_spot_report(time.time()))
    assert service.decisions() == {}
    assert service.snapshot_counters()["decisions_waiting_link"] == 1
    assert service.readiness()[0] is False
    links["uav2"].set_link(True)
    # The on-report watcher decides the waiting report once a vehicle can be commanded.
    deadline = time.monotonic() + 10.0
    while not service.decisions() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert list(service.decisions()) == ["uav2"]


def test_two_connections_to_one_vehicle_command_it_once(
    make_fleet: Callable[..., Fleet],
) -> None:
    service, links = make_fleet(3, system_ids=[1, 2, 1])
    service.submit_report(hot_spot_report(time.time()))
    assert list(service.decisions()) == ["uav1", "uav2"]
    assert links["uav3"].state().target_m is None
    ready, reasons = service.readiness()
    assert ready and reasons == [
        "uav3: system id 1 is also uav1's: two connections reach one vehicle; not commanded"
    ]
    assert service.snapshot_counters()["duplicate_system_id"] == 1


def test_a_vehicle_with_another_system_id_than_the_fleet_files_is_not_commanded(
    make_fleet: Callable[..., Fleet],
) -> None:
    service, _ = make_fleet(2, system_ids=[1, 7], expected=[1, 2])
    service.submit_report(hot_spot_report(time.time()))
    assert list(service.decisions()) == ["uav1"]
    assert service.readiness()[1] == [
        "uav2: system id 7 heard, the fleet file says 2: not commanded"
    ]


def test_fleet_policies_swap_and_bad_ones_are_refused(make_fleet: Callable[..., Fleet]) -> None:
    service, _ = make_fleet(2)
    assert service.swap_policy("kmeans-min-distance").name == "kmeans-min-distance"
    for spec in ("oracle", "min-distance", ""):
        with pytest.raises(InputError, match="policy: a fleet is served by one of"):
            service.swap_policy(spec)
    # Single-vehicle checkpoints are not fleet ones (and only the allowed dirs are read).
    for name in ("ddqn-dr", "ddpg-residual-dr"):
        with pytest.raises(InputError, match="policy: observation_shape: built for another"):
            service.swap_policy(str(SHIPPED_CHECKPOINTS / f"{name}.zip"))
    assert service.policy.name == "kmeans-min-distance"
    service.submit_report(hot_spot_report(time.time()))
    assert len(service.decisions()) == 2


def test_a_fleet_uses_its_own_default_policy_unless_one_is_named(tmp_path: Any) -> None:
    path = tmp_path / "fleet.yaml"
    path.write_text("vehicles: [{id: a, mavlink: 'tcp:127.0.0.1:1'}]\n")
    service = FleetPlacementService.from_settings(ServiceSettings(fleet_file=path, insecure=True))
    try:
        assert service.policy.name == "kmeans-scored"
        assert service.sole_vehicle_id() == "a"  # a fleet file of one vehicle: one vehicle
    finally:
        service.close_links()
    with pytest.raises(InputError, match="policy: a fleet is served by one of"):
        FleetPlacementService.from_settings(
            ServiceSettings(fleet_file=path, insecure=True, policy="oracle")
        )


@pytest.mark.training
@pytest.mark.parametrize("prior", ["kmeans-load-weighted", "kmeans-scored"])
def test_a_fleet_checkpoint_is_served_from_the_allowed_dirs(
    make_fleet: Callable[..., Fleet], tmp_path: Path, prior: str
) -> None:
    """A residual fleet checkpoint (tiny, trained here) flies the fleet through the service's
    observation path; with its actor's output at zero it places as its prior: load-weighted
    k-means, or ``kmeans-scored`` flown from where the vehicles are with the users on the APs
    the service estimates (the strongest, as the model associates) and the world's step."""
    out = tmp_path / "allowed" / "fleet-run"
    train_fleet(
        FleetTrainConfig(
            n_uavs=2, episodes=4, out_dir=out, preset=TINY_PRESET, users=(10, 12),
            action="residual", prior=prior, command="test",
        )
    )  # fmt: skip
    service, links = make_fleet(3, policy_dirs=(tmp_path / "allowed",))
    outside = shutil.copytree(out, tmp_path / "outside")
    with pytest.raises(InputError, match="outside the checkpoint directories"):
        service.swap_policy(str(outside))
    policy = service.swap_policy(str(out))
    assert policy.describe()["metadata"]["action"] == "residual"
    assert policy.describe()["metadata"]["prior"] == prior
    service.submit_report(hot_spot_report(time.time()))
    targets = np.array([d.target_m for d in service.decisions().values()])
    assert targets.shape == (3, 3) and _min_gap([tuple(t) for t in targets]) >= 10.0
    policy = service.swap_policy(str(out))  # afresh: no association remembered
    zero_actor_output(policy.policy.model)  # type: ignore[attr-defined]
    report = hot_spot_report(time.time() + 0.001)
    service.submit_report(report)
    got = np.array([d.target_m for d in service.decisions().values()])
    here = np.array([link.state().position_m for link in links.values()])
    users = ReportedUsers.of(report.users)
    world = service.world
    if prior == "kmeans-load-weighted":
        wanted = KMeansPlacement(3, service.area, load_weighted=True).place(users)
        np.testing.assert_allclose(got, assign_targets(here, wanted), atol=1e-9)
        return
    association, _ = associate_at(
        here[None], users.users_xy_m, world.area, world.network.radio, None,
        FleetConfig().hysteresis_db,
    )  # fmt: skip
    scored = ScoredKMeansPlacement(
        FleetConfig(n_uavs=3), world.area, world.network, world.utility, 100, world.step_s
    )
    wanted = scored.place_from(users, here, association[0], world.flight)
    np.testing.assert_allclose(got, assign_targets(here, wanted), atol=1e-9)


def test_the_shipped_fleet_checkpoint_is_served_for_any_fleet_size(
    make_fleet: Callable[..., Fleet],
) -> None:
    """The shipped checkpoint (trained with K = 3) loads from the default checkpoint
    directories and places fleets of 2 and 4: separated targets inside the fence."""
    for k in (2, 4):
        service, _ = make_fleet(k)
        policy = service.swap_policy(str(SHIPPED_FLEET))
        meta = policy.describe()["metadata"]
        assert (meta["fleet"], meta["prior"], meta["n_uavs_trained"]) == (True, "kmeans-scored", 3)
        service.submit_report(hot_spot_report(time.time()))
        targets = np.array([d.target_m for d in service.decisions().values()])
        assert targets.shape == (k, 3) and _min_gap([tuple(t) for t in targets]) >= 10.0
        lower, upper = volume_bounds(service.area)
        assert np.all(targets >= lower - 1e-9) and np.all(targets <= upper + 1e-9)


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_a_fleet_of_real_links_streams_each_vehicle_its_target(backend: str) -> None:
    """Real MAVLink links on either backend (one per vehicle, each its own MAVSDK instance) to
    an in-process mock fleet: every vehicle heard with its own system id and streamed its own
    target."""
    config = VehicleConfig(ready_delay_s=0.3)
    with MockFleet(2, "tcp:127.0.0.1:0", flavour="px4", config=config) as mocks:
        urls = tuple(f"tcp:127.0.0.1:{port}" for port in mocks.ports)
        settings = ServiceSettings(
            fleet_mavlink=urls, insecure=True, mavlink_backend=backend, decision_mode="on-report"
        )
        service = FleetPlacementService.from_settings(settings).start()
        try:
            wait_for(
                lambda: all(
                    v.state.link == "up" and v.state.position_m for v in service.vehicles()
                ),
                30.0,
                message="both links up with positions",
            )
            assert [v.state.system_id for v in service.vehicles()] == list(mocks.system_ids)
            service.submit_report(hot_spot_report(time.time()))
            decisions = service.decisions()
            assert list(decisions) == ["uav1", "uav2"]
            wait_for(
                lambda: all(v.state.streaming for v in service.vehicles()),
                15.0,
                message="both targets streaming",
            )
            for view in service.vehicles():
                assert view.state.target_m == decisions[view.id].target_m
        finally:
            service.stop()


def _fleet_with_state(
    state_file: Path, policy: str = "kmeans-load-weighted", **settings: Any
) -> tuple[FleetPlacementService, dict[str, FakeLink], list[str]]:
    """An ``on-report`` fleet of three airborne FakeLinks with a state file, not started; the
    third item lists the vehicles ``arm_and_takeoff`` was called on, in order."""
    urls = tuple(f"tcp:127.0.0.1:{5760 + i}" for i in range(3))
    config = ServiceSettings(
        fleet_mavlink=urls,
        mavlink=urls[0],
        insecure=True,
        decision_mode="on-report",
        state_file=state_file,
        **settings,
    )
    fleet = FleetSpec(
        tuple(VehicleSpec(f"uav{i + 1}", url, None) for i, url in enumerate(urls)),
        config.separation_m,
    )
    world = config.policy_world()
    armed: list[str] = []
    links = {}
    for i, vehicle in enumerate(fleet.vehicles):
        link = FakeLink(
            LinkConfig(vehicle.mavlink, area=world.area),
            position_m=(200.0 + 60.0 * i, 250.0, 30.0),
            system_id=i + 1,
        )
        arm = link.arm_and_takeoff

        def record(*args: Any, _vid: str = vehicle.id, _arm: Any = arm, **kwargs: Any) -> Any:
            armed.append(_vid)
            return _arm(*args, **kwargs)

        link.arm_and_takeoff = record  # type: ignore[method-assign]
        links[vehicle.id] = link
    policy_object = load_fleet_policy(policy, world, fleet.separation_m)
    return FleetPlacementService(config, links, policy_object, fleet, world), links, armed


def test_a_restarted_fleet_shows_its_saved_targets_streams_nothing_and_arms_on_a_decision(
    tmp_path: Path,
) -> None:
    state_file = tmp_path / "state.json"
    first, _, armed = _fleet_with_state(state_file, arm_and_takeoff=True)
    first.start()
    try:
        assert armed == ["uav1", "uav2", "uav3"]  # a cold start arms at once
        first.submit_report(hot_spot_report(time.time()))
        first.swap_policy("kmeans-min-distance")
        saved = first.decisions()
    finally:
        first.stop()
    assert set(saved) == {"uav1", "uav2", "uav3"}

    again, links, armed = _fleet_with_state(state_file, arm_and_takeoff=True)
    again.start()
    try:
        assert again.policy.spec == "kmeans-min-distance"  # the swap survived the restart
        restored = again.decisions()
        assert {vid: d.target_m for vid, d in restored.items()} == {
            vid: d.target_m for vid, d in saved.items()
        }
        assert {d.source for d in restored.values()} == {"restored"}
        for view in again.vehicles():
            assert view.decision is not None and view.decision.source == "restored"
            assert view.problem is not None and "not streamed" in view.problem
        assert all(link.state().target_m is None for link in links.values())
        assert armed == []  # a restart arms nothing by itself
        again.submit_report(hot_spot_report(time.time(), seed=1))
        assert armed == ["uav1", "uav2", "uav3"]
        fresh = again.decisions()
        assert {d.source for d in fresh.values()} == {"policy"}
        for vid, link in links.items():
            assert link.state().target_m == fresh[vid].target_m
    finally:
        again.stop()


def test_a_fleet_state_file_naming_other_vehicles_or_bad_targets_restores_the_rest(
    tmp_path: Path,
) -> None:
    state_file = tmp_path / "state.json"
    good = {"target_m": [120.0, 130.0, 40.0], "source": "policy", "policy": "x", "decided_at": 1}
    state_file.write_text(
        json.dumps(
            {
                "format": "tupa-service-state/1",
                "policy": "kmeans-load-weighted",
                "decisions": {
                    "uav1": good,
                    "uav2": {**good, "target_m": ["nan", 1, 2]},
                    "gone": good,
                },
            }
        )
    )
    service, links, _ = _fleet_with_state(state_file)
    service.start()
    try:
        assert list(service.decisions()) == ["uav1"]
        assert service.decisions()["uav1"].target_m == (120.0, 130.0, 40.0)
        assert service.snapshot_counters()["state_restore_errors"] == 2
        assert all(link.state().target_m is None for link in links.values())
    finally:
        service.stop()
    # A single vehicle's state file: its one target is no fleet's; ignored and counted.
    state_file.write_text(json.dumps({"policy": "kmeans-load-weighted", "decision": good}))
    service, _, _ = _fleet_with_state(state_file)
    service.start()
    try:
        assert service.decisions() == {}
        assert service.snapshot_counters()["state_restore_errors"] == 1
    finally:
        service.stop()


def test_targets_moved_out_of_a_no_fly_volume_stay_apart(make_fleet: Callable[..., Fleet]) -> None:
    """Issue 39: two targets inside a no-fly volume are each moved to its nearest legal point
    (the same edge) and then separated again, as the links will stream them."""
    from shapely.geometry import box

    from sim.envelope import Envelope, Exclusion

    service, links = make_fleet(2)
    tower = Exclusion(box(200, 200, 300, 300), 0.0, 120.0, "tower")
    for link in links.values():
        link.set_envelope(Envelope.for_area(link.config.area, [tower]))
    wanted = np.array([[210.0, 250.0, 50.0], [212.0, 250.0, 50.0]])  # 2 m apart, inside it
    targets = service._legal_targets(["uav1", "uav2"], wanted, np.zeros((0, 3)))
    assert np.linalg.norm(targets[0] - targets[1]) >= service.fleet.separation_m - 1e-9
    for target, link in zip(targets, links.values(), strict=True):
        assert link.envelope.violation(target) is None


def test_a_vehicle_whose_flight_would_cross_anothers_holds_where_it_is(
    make_fleet: Callable[..., Fleet],
) -> None:
    """Issue 39: the paths, not only the targets. uav2's flight would cross uav1's at the same
    moment: it holds where it is (a legal point of its envelope) for this decision, and is
    counted; targets whose flights keep apart go out as decided; and two vehicles that already
    met closer than the separation are not held in place by each other (the guard's separated
    targets go out: a clean-clone CI run caught that in tests/e2e/test_fleet_degraded.py)."""
    service, _ = make_fleet(2)
    none = np.zeros((0, 3))
    positions = np.array([[200.0, 250.0, 30.0], [250.0, 200.0, 30.0]])
    crossing = np.array([[300.0, 250.0, 30.0], [250.0, 300.0, 30.0]])
    out = service._hold_crossing_paths(["uav1", "uav2"], positions, crossing, none)
    assert out[0].tolist() == crossing[0].tolist() and out[1].tolist() == positions[1].tolist()
    assert service.counters["path_holds"] == 1
    apart = np.array([[150.0, 250.0, 30.0], [250.0, 150.0, 30.0]])
    kept = service._hold_crossing_paths(["uav1", "uav2"], positions, apart, none)
    assert kept.tolist() == apart.tolist() and service.counters["path_holds"] == 1
    met = np.array([[250.0, 400.0, 25.0], [249.2, 409.2, 25.0]])  # 9.2 m apart
    swapped = met[::-1] + np.array([[0.0, 5.0, 0.0], [0.0, -5.0, 0.0]])  # separated targets
    assert np.linalg.norm(swapped[0] - swapped[1]) >= service.fleet.separation_m
    out = service._hold_crossing_paths(["uav1", "uav2"], met, swapped, none)
    assert out.tolist() == swapped.tolist()
    assert service.counters["path_holds_skipped"] == 1 and service.counters["path_holds"] == 1
