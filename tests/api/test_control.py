"""``PUT /v1/vehicle/control`` and ``PUT /v1/vehicles/{id}/control``: who has the vehicle, as
the API, readiness, the metrics and the operator view's frame say it, and how an operator hands
a vehicle back or takes it (:mod:`service.control` has the rule). In memory: FakeLinks whose
vehicle leaves the service's hands when told, TestClient."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
from fastapi.testclient import TestClient

from api.live_schemas import LiveFrameOut
from tests.api.fleet_helpers import AUTH, report_body, single_app
from tests.fakes import FakeLink


def control(client: TestClient) -> dict[str, object]:
    return client.get("/v1/vehicle", headers=AUTH).json()["control"]


def test_a_pilot_takeover_is_shown_everywhere_and_only_an_operator_hands_back(
    single: tuple[TestClient, FakeLink],
) -> None:
    client, link = single
    assert client.post("/v1/reports", json=report_body(), headers=AUTH).status_code == 200
    assert control(client)["holder"] == "service"
    assert client.get("/v1/vehicle", headers=AUTH).json()["streaming"] is True

    link.vehicle_leaves("pilot", "the vehicle left OFFBOARD for POSCTL")
    vehicle = client.get("/v1/vehicle", headers=AUTH).json()
    assert vehicle["control"]["holder"] == "pilot"
    assert vehicle["control"]["reason"] == "the vehicle left OFFBOARD for POSCTL"
    assert vehicle["streaming"] is False
    readyz = client.get("/readyz")
    assert readyz.status_code == 503
    assert any("the pilot has the vehicle" in r for r in readyz.json()["reasons"])
    frame = LiveFrameOut.model_validate(client.get("/v1/live", headers=AUTH).json())
    assert frame.vehicles[0].control.holder == "pilot"
    metrics = client.get("/metrics").text
    assert 'tupa_vehicle_control{holder="pilot",vehicle="uav1"} 1.0' in metrics
    assert 'tupa_vehicle_control{holder="service",vehicle="uav1"} 0.0' in metrics
    assert 'tupa_vehicle_mode_requests_total{vehicle="uav1"} 0.0' in metrics
    # Reports keep being accepted; nothing is streamed.
    assert client.post("/v1/reports", json=report_body(), headers=AUTH).status_code == 200
    assert link.state().streaming is False

    answer = client.put("/v1/vehicle/control", json={"holder": "service"}, headers=AUTH)
    assert answer.status_code == 200, answer.text
    assert answer.json()["control"]["holder"] == "service"
    assert answer.json()["control"]["reason"] == "handed back by an operator"
    client.post("/v1/reports", json=report_body(), headers=AUTH)
    assert link.state().streaming is True
    assert client.get("/readyz").status_code == 200


def test_an_operator_can_release_the_vehicle_with_a_reason(
    single: tuple[TestClient, FakeLink],
) -> None:
    client, link = single
    client.post("/v1/reports", json=report_body(), headers=AUTH)
    body = {"holder": "operator", "reason": "manual survey"}
    answer = client.put("/v1/vehicle/control", json=body, headers=AUTH)
    assert answer.status_code == 200
    assert answer.json()["control"] == {
        "holder": "operator",
        "reason": "manual survey",
        "age_s": pytest.approx(0.0, abs=1.0),
    }
    assert link.state().streaming is False


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"holder": "pilot"}, "holder"),
        ({}, "holder"),
        ({"holder": "service", "extra": 1}, "extra"),
        ({"holder": "service", "reason": "x" * 201}, "reason"),
    ],
)
def test_a_bad_control_body_is_refused_naming_the_field(
    single: tuple[TestClient, FakeLink], body: dict[str, object], field: str
) -> None:
    client, link = single
    answer = client.put("/v1/vehicle/control", json=body, headers=AUTH)
    assert answer.status_code == 422
    assert field in str(answer.json())
    assert link.state().control == "service"


def test_control_needs_the_token_and_a_handback_needs_the_link(
    single: tuple[TestClient, FakeLink],
) -> None:
    client, link = single
    assert client.put("/v1/vehicle/control", json={"holder": "operator"}).status_code == 401
    link.vehicle_leaves("autopilot", "the vehicle left OFFBOARD for AUTO.RTL")
    link.set_link(False)
    answer = client.put("/v1/vehicle/control", json={"holder": "service"}, headers=AUTH)
    assert answer.status_code == 409
    assert answer.json()["detail"] == "control: the vehicle's link is not up"
    assert link.state().control == "autopilot"


def test_a_fleet_vehicle_released_is_left_alone_and_the_others_cover_its_users(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, links = fleet
    client.post("/v1/reports", json=report_body(), headers=AUTH)
    answer = client.put("/v1/vehicles/uav2/control", json={"holder": "operator"}, headers=AUTH)
    assert answer.status_code == 200, answer.text
    view = answer.json()
    assert view["vehicle"]["control"]["holder"] == "operator"
    assert view["commanded"] is False and "the operator has the vehicle" in view["problem"]
    decision = client.post("/v1/reports", json=report_body(), headers=AUTH).json()
    assert sorted(decision["targets"]) == ["uav1", "uav3"]
    assert links["uav2"].state().streaming is False
    assert client.get("/readyz").status_code == 200  # degraded: two vehicles still fly

    back = client.put("/v1/vehicles/uav2/control", json={"holder": "service"}, headers=AUTH)
    assert back.status_code == 200
    decision = client.post("/v1/reports", json=report_body(), headers=AUTH).json()
    assert sorted(decision["targets"]) == ["uav1", "uav2", "uav3"]


def test_fleet_control_routes_name_the_vehicle(
    fleet: tuple[TestClient, dict[str, FakeLink]],
) -> None:
    client, _ = fleet
    missing = client.put("/v1/vehicles/uav9/control", json={"holder": "service"}, headers=AUTH)
    assert missing.status_code == 404 and "uav9" in missing.json()["detail"]
    single = client.put("/v1/vehicle/control", json={"holder": "service"}, headers=AUTH)
    assert single.status_code == 409 and "/v1/vehicles/" in single.json()["detail"]


def test_a_vehicle_handed_back_on_the_ground_takes_off_only_when_asked() -> None:
    """Issue 39: a vehicle back from its battery return, recharged, is taken back in by an
    operator; the service arms it only at the operator's explicit request."""
    with contextmanager(single_app)(position_m=(0.0, 0.0, 0.0)) as (client, link):
        link.vehicle_leaves("autopilot", "battery reserve reached: returning home (RTL)")
        body = {"holder": "operator", "takeoff": True}
        answer = client.put("/v1/vehicle/control", json=body, headers=AUTH)
        assert answer.status_code == 422 and answer.json()["detail"][0]["loc"][-1] == "takeoff"
        answer = client.put("/v1/vehicle/control", json={"holder": "service"}, headers=AUTH)
        assert answer.status_code == 200 and link.arms == 0
        assert link.state().takeoff == "idle"
        link.vehicle_leaves("autopilot", "battery reserve reached: returning home (RTL)")
        body = {"holder": "service", "takeoff": True}
        answer = client.put("/v1/vehicle/control", json=body, headers=AUTH)
        assert answer.status_code == 200, answer.text
        link.advance(20.0)
        assert link.arms == 1 and link.state().takeoff == "airborne"
