"""The HTTP side of a fleet: ``/v1/vehicles`` (every vehicle's state, target and why it is not
commanded), one report of all users giving every vehicle's target, per-vehicle readiness and
metrics, and the single-vehicle routes that do not apply to a fleet answering 409. A
single-vehicle service lists its one vehicle the same way. In memory: FakeLinks, TestClient."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.live_schemas import LiveFrameOut
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from tests.api.fleet_helpers import AUTH, TOKEN, URLS, report_body
from tests.fakes import FakeLink


def test_one_report_gives_each_vehicle_its_target_and_vehicles_shows_them(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, _ = fleet
    answer = client.post("/v1/reports", json=report_body(), headers=AUTH)
    assert answer.status_code == 200, answer.text
    decision = answer.json()
    assert decision["target"] is None and decision["policy"] == "kmeans-load-weighted"
    assert sorted(decision["targets"]) == ["uav1", "uav2", "uav3"]
    assert client.get("/v1/setpoint", headers=AUTH).json()["targets"] == decision["targets"]

    vehicles = client.get("/v1/vehicles", headers=AUTH).json()
    assert vehicles["separation_m"] == 10.0
    assert [v["id"] for v in vehicles["vehicles"]] == ["uav1", "uav2", "uav3"]
    for i, v in enumerate(vehicles["vehicles"]):
        assert v["system_id"] == i + 1 and v["commanded"] and v["problem"] is None
        assert v["setpoint"]["target"] == decision["targets"][v["id"]]
        assert v["vehicle"]["link"] == "up" and v["vehicle"]["position"]["z_m"] == 30.0
    one = client.get("/v1/vehicles/uav2", headers=AUTH).json()
    for entry in (one, vehicles["vehicles"][1]):  # the only fields that move with time
        entry["vehicle"].pop("heartbeat_age_s")
        assert entry["vehicle"]["control"].pop("age_s") >= 0.0
    assert one == vehicles["vehicles"][1]
    setpoint = client.get("/v1/vehicles/uav3/setpoint", headers=AUTH).json()
    assert setpoint["target"] == decision["targets"]["uav3"]


def test_a_lost_vehicle_shows_why_and_the_fleet_stays_ready(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, links = fleet
    links["uav3"].set_link(False)
    decision = client.post("/v1/reports", json=report_body(), headers=AUTH).json()
    assert sorted(decision["targets"]) == ["uav1", "uav2"]
    lost = client.get("/v1/vehicles/uav3", headers=AUTH).json()
    assert lost["commanded"] is False and lost["problem"] == "mavlink link is link_lost"
    assert lost["setpoint"]["target"] is None
    ready = client.get("/readyz")
    assert ready.status_code == 200
    body = ready.json()
    assert body["vehicles"] == {"uav1": "up", "uav2": "up", "uav3": "link_lost"}
    assert body["reasons"] == ["uav3: mavlink link is link_lost"]
    metrics = client.get("/metrics").text
    assert 'tupa_vehicle_link_state{state="link_lost",vehicle="uav3"} 1.0' in metrics
    assert 'tupa_vehicle_commanded{vehicle="uav3"} 0.0' in metrics
    assert 'tupa_vehicle_commanded{vehicle="uav1"} 1.0' in metrics
    assert "tupa_fleet_decisions_degraded_total 1.0" in metrics
    assert "tupa_setpoints_sent_total" not in metrics  # one vehicle's unlabelled families


def test_routes_for_one_vehicle_point_a_fleet_to_vehicles(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, _ = fleet
    answer = client.get("/v1/vehicle", headers=AUTH)
    assert answer.status_code == 409 and "/v1/vehicles" in answer.json()["detail"]
    missing = client.get("/v1/vehicles/uav9", headers=AUTH)
    assert missing.status_code == 404 and "uav9" in missing.json()["detail"]
    assert client.get("/v1/vehicles").status_code == 401


def test_a_single_vehicle_service_lists_its_one_vehicle() -> None:
    settings = ServiceSettings(mavlink=URLS[0], api_token=TOKEN, decision_mode="on-report")
    world = settings.policy_world()
    link = FakeLink(LinkConfig(URLS[0], area=world.area), position_m=(250.0, 250.0, 30.0))

    def factory(s: ServiceSettings) -> PlacementService:
        return PlacementService(s, link, load_policy("load-weighted", world), world)

    with TestClient(create_app(settings, service_factory=factory)) as client:
        decision = client.post("/v1/reports", json=report_body(), headers=AUTH).json()
        # One shape for any number of vehicles: targets by id, and the one vehicle's target.
        assert decision["target"] is not None and decision["targets"] == {
            "uav1": decision["target"]
        }
        assert client.get("/v1/setpoint", headers=AUTH).json() == {
            k: v for k, v in decision.items() if k != "report_outcome"
        }
        vehicles = client.get("/v1/vehicles", headers=AUTH).json()
        assert vehicles["separation_m"] is None
        (only,) = vehicles["vehicles"]
        assert only["id"] == "uav1" and only["commanded"] and only["system_id"] == 1
        assert decision.pop("report_outcome") == "decided"  # the report's answer only
        assert only["setpoint"] == decision
        assert client.get("/readyz").json()["vehicles"] == {"uav1": "up"}


def test_the_operator_view_shows_every_vehicle_with_its_target(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, links = fleet
    decision = client.post("/v1/reports", json=report_body(), headers=AUTH).json()
    frame = LiveFrameOut.model_validate(client.get("/v1/live", headers=AUTH).json())
    assert [v.id for v in frame.vehicles] == ["uav1", "uav2", "uav3"]
    for vehicle in frame.vehicles:
        target = decision["targets"][vehicle.id]
        wanted = [target["x_m"], target["y_m"], target["z_m"]]
        assert vehicle.target_m == pytest.approx(wanted, abs=0.01)  # frames round to cm
        assert vehicle.position_m == pytest.approx(links[vehicle.id].state().position_m)
    assert len(frame.users) == 15
