"""The fleet's network controller (closed_loop/fleet_controller.py) and the fleet demo's parts
that need no service: metrics against the fleet model stepped directly, the report and the
targets it reads, the position reader of one vehicle of a mock fleet, the hot-spot users, the
fleet file, and ``tupa demo --uavs``'s bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from closed_loop.controller import TruePosition
from closed_loop.fleet_controller import (
    GroupedUsers,
    SimulatedFleetNetwork,
    parse_targets,
    run_fleet_scenario,
    summarise,
)
from closed_loop.fleet_demo import FleetDemoConfig, fleet_file, hot_spot_layout, hot_spot_users
from service.frames import FrameConfig, ned_to_area
from sim.config import AreaConfig, NetworkConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel
from sim.world import Demand, Mobility
from sitl_mock.config import VehicleConfig
from sitl_mock.fleet import MockFleet
from tests.helpers import wait_for

ROOT = Path(__file__).resolve().parents[2]
AREA = AreaConfig()
WALK = Mobility(model="group", speed_mps=(2.0, 2.0), pause_s=(0.0, 0.0))


def _groups() -> list[tuple[np.ndarray, np.ndarray, Mobility, Demand]]:
    """Two hot spots: one standing in the west, one walking in the east."""
    west = np.array([[80.0, 240.0], [90.0, 260.0], [70.0, 250.0]])
    east = np.array([[420.0, 240.0], [430.0, 255.0]])
    return [
        (west, np.array([8e6, 4e6, 2e6]), Mobility(), Demand()),
        (east, np.array([10e6, 6e6]), WALK, Demand()),
    ]


def _network(seed: int = 5) -> SimulatedFleetNetwork:
    rng = np.random.default_rng(11)
    return SimulatedFleetNetwork(
        GroupedUsers(_groups(), AREA, rng), FleetConfig(n_uavs=2), seed=seed, users_rng=rng
    )


# The two vehicles swap sides (vehicle 0 from the west hot spot to the east one, vehicle 1
# the other way), so every user's strongest AP changes: handovers happen.
PATH = [
    np.array([[100.0, 250.0, 25.0], [400.0, 250.0, 25.0]]),
    np.array([[200.0, 250.0, 25.0], [400.0, 250.0, 25.0]]),
    np.array([[300.0, 250.0, 25.0], [400.0, 250.0, 25.0]]),
    np.array([[420.0, 250.0, 25.0], [300.0, 250.0, 25.0]]),
    np.array([[430.0, 250.0, 25.0], [150.0, 250.0, 25.0]]),
    np.array([[430.0, 250.0, 25.0], [90.0, 250.0, 25.0]]),
]


def test_the_controllers_metrics_are_the_fleet_models() -> None:
    """Step by step, what the controller measures is FleetModel.step's, with the same users,
    the same fading draws and the state (queues, associations, handovers) carried over."""
    network = _network()
    reference_rng = np.random.default_rng(11)
    users = GroupedUsers(_groups(), AREA, reference_rng)
    model = FleetModel(FleetConfig(n_uavs=2), NetworkConfig(), AREA)
    fading = np.random.default_rng(5)
    state = None
    handovers = 0
    for t, positions in enumerate(PATH):
        measured = network.measure(positions, 1.0)
        if t:
            users.advance(1.0, reference_rng)
        result = model.step(positions, users.xy_m, users.load_bps, state, fading, 1.0)
        state = result.state
        np.testing.assert_array_equal(network.users.xy_m, users.xy_m)
        np.testing.assert_array_equal(measured.throughput_bps, result.throughput_bps[0])
        np.testing.assert_array_equal(measured.delay_s, result.delay_s[0])
        np.testing.assert_array_equal(measured.plr, result.plr[0])
        np.testing.assert_array_equal(measured.association, result.association[0])
        np.testing.assert_array_equal(measured.uav_utility, result.uav_utility[0])
        assert measured.utility == result.utility[0]
        assert measured.served_fraction == result.served_fraction[0]
        assert measured.jain_fairness == result.jain_fairness[0]
        assert measured.min_throughput_bps == result.min_throughput_bps[0]
        assert measured.handovers == int(result.handover[0].sum())
        handovers += measured.handovers
        assert measured.handovers_total == handovers == int(result.handovers[0])
    assert handovers > 0  # the vehicles swapped sides: users roamed
    east = users.groups[1]
    assert not np.allclose(east.xy_m, _groups()[1][0])  # the walking hot spot walked
    np.testing.assert_array_equal(users.groups[0].xy_m, _groups()[0][0])  # the other stood


def test_the_report_carries_every_user_as_measured() -> None:
    network = _network()
    measured = network.measure(PATH[0], 1.0)
    body = network.report(measured, 1234.5)
    assert body["timestamp"] == 1234.5
    assert [u["id"] for u in body["users"]] == [f"ue-{i}" for i in range(1, 6)]
    for i, user in enumerate(body["users"]):
        assert (user["x_m"], user["y_m"]) == tuple(network.users.xy_m[i])
        assert user["offered_bps"] == network.users.load_bps[i]
        assert user["throughput_bps"] == measured.throughput_bps[i]
        assert user["delay_s"] == measured.delay_s[i]
        assert user["plr"] == measured.plr[i]
        assert user["throughput_bps"] <= user["offered_bps"] + 1e-6


class _Fixed:
    def __init__(self, xyz: tuple[float, float, float]) -> None:
        self.xyz = xyz

    def wait(self, timeout_s: float) -> tuple[float, float, float]:
        return self.xyz


def test_one_report_of_all_users_per_step_and_every_vehicles_target_read_back() -> None:
    posted: list[dict[str, Any]] = []

    def service(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/v1/reports"
        assert request.headers["Authorization"] == "Bearer t0ken"
        posted.append(json.loads(request.content))
        if len(posted) == 1:  # no decision yet
            return httpx.Response(200, json={"target": None, "targets": None})
        targets = {
            "uav1": {"x_m": 80.0, "y_m": 250.0, "z_m": 25.0},
            "uav2": {"x_m": 425.0, "y_m": 248.0, "z_m": 30.0},
        }
        return httpx.Response(200, json={"target": None, "targets": targets})

    vehicles = {"uav1": _Fixed((100.0, 250.0, 25.0)), "uav2": _Fixed((400.0, 250.0, 25.0))}
    client = httpx.Client(
        base_url="http://fleet", transport=httpx.MockTransport(service),
        headers={"Authorization": "Bearer t0ken"},
    )  # fmt: skip
    seen = []
    records = run_fleet_scenario(_network(), vehicles, client, 3, 0.001, on_step=seen.append)
    assert seen == records and len(posted) == 3
    assert all(len(body["users"]) == 5 for body in posted)
    assert records[0].targets_m == {"uav1": None, "uav2": None}
    assert records[2].targets_m == {"uav1": (80.0, 250.0, 25.0), "uav2": (425.0, 248.0, 30.0)}
    assert records[1].positions_m == {"uav1": (100.0, 250.0, 25.0), "uav2": (400.0, 250.0, 25.0)}
    reference = _network()
    for record in records:
        expected = reference.measure(PATH[0], 0.001)
        assert record.utility == expected.utility
        assert record.association == expected.association.tolist()
        assert record.served_fraction == expected.served_fraction
    # Users near vehicle 1 (west) are served by it, those in the east by vehicle 2.
    assert records[-1].association == [0, 0, 0, 1, 1]
    summary = summarise(records)
    assert summary["utility"] == pytest.approx(np.mean([r.utility for r in records]))
    assert summary["min_throughput_bps"] == pytest.approx(
        np.mean([r.min_throughput_bps for r in records])
    )
    assert summary["handovers"] == records[-1].handovers_total and summary["steps"] == 3
    with pytest.raises(InputError, match="vehicles"):
        run_fleet_scenario(_network(), {"uav1": vehicles["uav1"]}, client, 1, 0.001)
    with pytest.raises(InputError, match="records"):
        summarise([])


def test_targets_of_vehicles_the_answer_does_not_name_are_none() -> None:
    answer = {"targets": {"uav1": {"x_m": 1, "y_m": 2, "z_m": 30}, "uav2": None}}
    assert parse_targets(answer, ["uav1", "uav2", "uav3"]) == {
        "uav1": (1.0, 2.0, 30.0),
        "uav2": None,
        "uav3": None,
    }


def test_each_vehicle_of_a_mock_fleet_is_read_in_the_shared_area_frame() -> None:
    """A mock fleet (ArduPilot: nothing streams until asked, so the request must reach system
    id 2 on the second port): with the demo's fleet file origins, vehicle i at its home lies
    15·i m east of the area's centre."""
    fleet = MockFleet(3, "tcp:127.0.0.1:0", "ardupilot", VehicleConfig(ready_delay_s=0.3))
    fleet.start()
    readers: list[TruePosition] = []
    try:
        spec, frames = fleet_file(fleet.ports, AREA, 10.0)
        assert [v["system_id"] for v in spec["vehicles"]] == [1, 2, 3]
        for v in spec["vehicles"]:
            readers.append(TruePosition(v["mavlink"], frames[v["id"]], system_id=v["system_id"]))
            readers[-1].start()
        for i, reader in enumerate(readers):
            x, y, z = reader.wait(20.0)
            assert (x, y) == pytest.approx((250.0 + 15.0 * i, 250.0), abs=0.5), i
            assert abs(z) < 1.0
        wait_for(lambda: all(r.latest() is not None for r in readers), 5.0)
    finally:
        for reader in readers:
            reader.close()
        fleet.stop()


def test_the_fleet_files_origins_put_every_home_in_one_area() -> None:
    spec, frames = fleet_file([5760, 5761, 5762, 5763], AREA, 12.0)
    assert spec["separation_m"] == 12.0
    for i, v in enumerate(spec["vehicles"]):
        assert v["id"] == f"uav{i + 1}" and v["mavlink"] == f"tcp:127.0.0.1:{5760 + i}"
        assert v["area_origin_east_m"] == -250.0 - 15.0 * i
        assert v["area_origin_north_m"] == -250.0
        # A point 40 m north and 30 m east of vehicle 0's home, seen from vehicle i's home:
        seen = ned_to_area(40.0, 30.0 - 15.0 * i, -25.0, frames[v["id"]])
        assert seen == pytest.approx((280.0, 290.0, 25.0))
    assert frames["uav1"] == FrameConfig(-250.0, -250.0)


def test_hot_spots_are_reproducible_and_one_of_them_walks() -> None:
    layout = hot_spot_layout(3, 7, AREA, users_per_spot=5, load_per_uav_bps=20e6)
    again = hot_spot_layout(3, 7, AREA, users_per_spot=5, load_per_uav_bps=20e6)
    np.testing.assert_array_equal(layout.users_xy_m, again.users_xy_m)
    np.testing.assert_array_equal(layout.load_bps, again.load_bps)
    assert layout.n_spots == 4 and len(layout.load_bps) == 20
    assert layout.load_bps.sum() == pytest.approx(60e6)
    assert np.all(layout.load_bps > 0)
    assert np.all((layout.users_xy_m > 0) & (layout.users_xy_m < 500))
    distance = np.linalg.norm(layout.centres_m - 250.0, axis=1)
    assert np.all((distance >= 119.0) & (distance <= 201.0))
    assert len(np.unique(layout.spot_loads_bps().round())) == 4  # heavy and light hot spots
    walks = [hot_spot_users(layout, AREA, np.random.default_rng(3)) for _ in range(2)]
    start = walks[0].xy_m.copy()
    for users in walks:
        rng = np.random.default_rng(4)
        for _ in range(20):
            users.advance(1.0, rng)
    np.testing.assert_array_equal(walks[0].xy_m, walks[1].xy_m)  # the same walk
    moved = np.linalg.norm(walks[0].xy_m - start, axis=1) > 1e-9
    assert np.array_equal(moved, layout.spot == layout.moving_spot)
    centre_moved = np.linalg.norm(
        walks[0].centres_m()[layout.moving_spot] - start[moved].mean(axis=0)
    )
    assert 25.0 <= centre_moved <= 51.0  # 20 s at 1.5-2.5 m/s (less where it hit an edge)


@pytest.mark.parametrize(
    ("field", "value"),
    [("uavs", 1), ("uavs", 9), ("policies", ("oracle",)), ("policies", ()), ("steps", 0)],
)
def test_bad_fleet_demo_settings_name_the_field(field: str, value: Any) -> None:
    with pytest.raises(InputError) as caught:
        FleetDemoConfig(**{field: value})
    name = {"uavs": "--uavs", "policies": "--policy", "steps": "steps"}[field]
    assert str(caught.value).startswith(name)


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--uavs", "0"], "--uavs"),
        (["--uavs", "9"], "--uavs"),
        (["--uavs", "3", "--scenarios", "2"], "--scenarios"),
        (["--uavs", "3", "--policy", "min-distance"], "--policy"),
    ],
)
@pytest.mark.process
def test_tupa_demo_refuses_bad_fleet_input_in_one_line(args: list[str], named: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"tupa demo: error: {named}:"), result.stderr
    assert result.stdout == ""


def test_the_demo_flies_exactly_the_policies_a_fleet_service_serves() -> None:
    from closed_loop.fleet_demo import ALWAYS_FLOWN, parse_policies
    from policies.fleet_policy import FLEET_POLICIES

    assert set(ALWAYS_FLOWN) < set(FLEET_POLICIES)
    assert parse_policies(" kmeans-min-distance , fleet-oracle ") == (
        "kmeans-min-distance",
        "fleet-oracle",
    )
    assert parse_policies(None) is None
    with pytest.raises(InputError, match=r"^--policy"):
        FleetDemoConfig(policies=("fleet-oracle", "fleet-oracle"))
