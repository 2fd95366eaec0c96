"""Regressions for what schemathesis found (tests/fuzz/test_openapi.py), pinned one by one."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import ServiceSettings
from tests.offline import offline_service

TOKEN = "hardening-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
USER = {
    "id": "ue-1",
    "x_m": 120,
    "y_m": 80,
    "offered_bps": 30e6,
    "throughput_bps": 21.5e6,
    "delay_s": 0.42,
    "plr": 0,
}


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance")
    with TestClient(create_app(settings, service_factory=offline_service)) as test_client:
        yield test_client


@pytest.mark.parametrize(
    "spec", ["0" * 5000, "a/" + "b" * 300 + ".zip", "policy\x00.zip"], ids=["long", "part", "nul"]
)
def test_unusable_policy_paths_are_422_not_500(client: TestClient, spec: str) -> None:
    response = client.put("/v1/policy", json={"policy": spec[:4096]}, headers=AUTH)
    assert response.status_code == 422, response.text
    assert response.json()["detail"][0]["loc"] == ["body", "policy"]
    assert client.get("/v1/policy", headers=AUTH).json()["name"] == "min-distance"


@pytest.mark.parametrize(
    ("field", "value"),
    [("plr", False), ("plr", True), ("x_m", "120"), ("delay_s", "0.1"), ("id", 5)],
)
def test_numbers_must_be_json_numbers_and_ids_strings(
    client: TestClient, field: str, value: Any
) -> None:
    body = {"timestamp": 1.0, "users": [{**USER, field: value}]}
    response = client.post("/v1/reports", json=body, headers=AUTH)
    assert response.status_code == 422
    assert ["body", "users", 0, field] in [e["loc"] for e in response.json()["detail"]]


def test_integers_are_numbers(client: TestClient) -> None:
    """The README's curl example (integer coordinates and loss) is accepted."""
    response = client.post(
        "/v1/reports", json={"timestamp": 1764000000, "users": [USER]}, headers=AUTH
    )
    assert response.status_code == 200, response.text


def test_405_allow_lists_every_method_of_the_path(client: TestClient) -> None:
    response = client.request("OPTIONS", "/v1/policy", headers=AUTH)
    assert response.status_code == 405
    allowed = {m.strip() for m in response.headers["allow"].split(",")}
    assert {"GET", "PUT"} <= allowed
    assert response.json() == {"detail": "Method Not Allowed"}


def test_a_body_that_is_not_utf8_is_a_documented_4xx(client: TestClient) -> None:
    response = client.post(
        "/v1/reports",
        content=b'{"timestamp": 1, "users": ["\xff\xfe"]}',
        headers={**AUTH, "content-type": "application/json"},
    )
    documented = client.get("/openapi.json").json()["paths"]["/v1/reports"]["post"]
    assert str(response.status_code) in documented["responses"], response.status_code
    assert response.status_code in (400, 422)


def test_error_responses_are_documented_with_models(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    post = paths["/v1/reports"]["post"]["responses"]
    for code in ("400", "401", "409", "413", "422", "429"):
        assert "application/json" in post[code]["content"], code
    assert paths["/v1/setpoint"]["get"]["security"] == [{"HTTPBearer": []}]
