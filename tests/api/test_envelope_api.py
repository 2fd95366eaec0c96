"""The envelope, the route and the battery as the API, the metrics and the operator view's frame
show them (issue 39). In memory: a FakeLink (the same routing as the real links), TestClient."""

from __future__ import annotations

import math

from fastapi.testclient import TestClient
from shapely.geometry import box

from api.live_schemas import LiveFrameOut
from sim.envelope import Envelope, Exclusion
from tests.api.fleet_helpers import AUTH, report_body
from tests.fakes import FakeLink


def test_a_new_envelope_around_the_vehicle_holds_it_and_says_why_everywhere(
    single: tuple[TestClient, FakeLink],
) -> None:
    client, link = single
    assert client.post("/v1/reports", json=report_body(), headers=AUTH).status_code == 200
    link.advance(0.1)
    route = client.get("/v1/vehicle", headers=AUTH).json()["route"]
    assert route["kind"] == "direct" and route["hold_reason"] is None

    stadium = Exclusion(box(200, 200, 300, 300), 0.0, 120.0, "stadium")
    link.set_envelope(Envelope.for_area(link.config.area, [stadium]))
    link.advance(0.1)
    held_at = link.state().position_m
    link.advance(5.0)
    assert link.state().position_m == held_at  # it holds: never jumps out
    vehicle = client.get("/v1/vehicle", headers=AUTH).json()
    assert vehicle["route"]["kind"] == "hold"
    assert "outside its envelope" in vehicle["route"]["hold_reason"]
    assert "'stadium'" in vehicle["route"]["hold_reason"]
    assert vehicle["battery"] == {
        "remaining_pct": None,
        "voltage_v": None,
        "drain_pct_per_min": None,
        "return_at_pct": None,
    }
    assert 'tupa_vehicle_route_holds_total{vehicle="uav1"} 1.0' in client.get("/metrics").text
    frame = LiveFrameOut.model_validate(client.get("/v1/live", headers=AUTH).json())
    (envelope,) = frame.envelopes
    assert [e.name for e in envelope.exclusions] == ["stadium"]
    assert frame.vehicles[0].envelope == 0
    assert frame.vehicles[0].route is not None and frame.vehicles[0].route.kind == "hold"


STADIUM_DOC = {
    "format": "tupa-envelope/1",
    "exclusions": [
        {"name": "stadium", "polygon": [[200, 200], [300, 200], [300, 300], [200, 300]],
         "floor_m": 0, "ceiling_m": 120}
    ],
}  # fmt: skip


def test_an_operator_puts_a_new_envelope_and_a_bad_one_is_refused_naming_the_field(
    single: tuple[TestClient, FakeLink],
) -> None:
    client, link = single
    client.post("/v1/reports", json=report_body(), headers=AUTH)
    link.advance(0.1)
    bad = {**STADIUM_DOC, "ceiling_m": 10}
    answer = client.put("/v1/vehicle/envelope", json=bad, headers=AUTH)
    assert answer.status_code == 422
    (error,) = answer.json()["detail"]
    assert error["loc"] == ["body", "ceiling_m"]
    assert error["msg"].startswith("envelope.ceiling_m: 10 m must be above")
    assert link.envelope.exclusions == ()  # nothing changed
    # The home (the area's south-west corner here) inside a no-fly volume: refused.
    at_home = {"name": "pad", "polygon": [[-5, -5], [20, -5], [20, 20], [-5, 20]],
               "floor_m": 0, "ceiling_m": 120}  # fmt: skip
    corner = {**STADIUM_DOC, "exclusions": [at_home]}
    answer = client.put("/v1/vehicle/envelope", json=corner, headers=AUTH)
    assert answer.status_code == 422
    assert "home (0.0, 0.0) is inside" in answer.json()["detail"][0]["msg"]
    # More corners than routes may be planned round (each polygon within the schema's limit).
    square = [[300, 300], [301, 300], [301, 301], [300, 301]]
    ring = [[400 + 20 * math.cos(k / 32), 400 + 20 * math.sin(k / 32)] for k in range(200)]
    many = {"format": "tupa-envelope/1", "exclusions": [
        {"polygon": ring, "floor_m": 0, "ceiling_m": 120}] * 5 + [
        {"polygon": square, "floor_m": 0, "ceiling_m": 120}]}  # fmt: skip
    answer = client.put("/v1/vehicle/envelope", json=many, headers=AUTH)
    assert answer.status_code == 422
    (error,) = answer.json()["detail"]
    assert error["loc"] == ["body", "exclusions"]
    assert error["msg"].startswith("envelope.exclusions: 1004 corners in all, at most 1000")

    answer = client.put("/v1/vehicle/envelope", json=STADIUM_DOC, headers=AUTH)
    assert answer.status_code == 200, answer.text
    link.advance(0.1)
    route = client.get("/v1/vehicle", headers=AUTH).json()["route"]
    assert route["kind"] == "hold" and "'stadium'" in route["hold_reason"]
    assert client.put("/v1/vehicle/envelope", json=STADIUM_DOC).status_code == 401
