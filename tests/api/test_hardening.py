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


def test_a_chunked_body_over_the_limit_is_413_not_400(client: TestClient) -> None:
    """No ``Content-Length`` (chunked): the limit is found while the body is read."""
    limit = ServiceSettings(policy="min-distance").max_body_bytes

    def chunks() -> Iterator[bytes]:
        sent = 0
        while sent <= limit:
            yield b" " * 65536
            sent += 65536

    response = client.post(
        "/v1/reports", content=chunks(), headers={**AUTH, "content-type": "application/json"}
    )
    assert response.status_code == 413, response.text
    assert response.json() == {"detail": f"body: over the {limit}-byte limit"}
    assert response.headers["connection"] == "close"
    declared = client.post(
        "/v1/reports",
        content=b" " * (limit + 1),
        headers={**AUTH, "content-type": "application/json"},
    )
    assert declared.status_code == 413 and declared.headers["connection"] == "close"
    ok = client.post("/v1/reports", json={"timestamp": 2e9, "users": [USER]}, headers=AUTH)
    assert ok.status_code in (200, 422), ok.text  # not limited: a small body passes


@pytest.mark.parametrize("path", ["/healthz", "/nowhere/x", "/v1/policy"])
def test_metrics_labels_stay_in_a_closed_set_whatever_the_method_and_path(path: str) -> None:
    """Made-up methods and paths, with and without the token: every label value of
    ``tupa_http_requests_total`` is a standard method or ``other``, a route template or
    ``other``, and the text does not grow with the number of odd requests."""
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance", rate_limit_rps=0)
    with TestClient(create_app(settings, service_factory=offline_service)) as fresh:
        for i in range(5):
            fresh.request(f"M{i}{'X' * 200}", f"{path}/{'y' * i}", headers=AUTH)
        before = len(fresh.get("/metrics").content)
        for i in range(5, 105):
            fresh.request(f"M{i}{'X' * 200}", f"{path}/{'y' * i}")
            fresh.request(f"M{i}{'X' * 200}", f"{path}/{'y' * i}", headers=AUTH)
        text = fresh.get("/metrics").text
    assert len(text) - before < 2000, len(text) - before
    templates = {"other", "/healthz", "/v1/policy", "/metrics"}
    for line in text.splitlines():
        if line.startswith("tupa_http_requests_total{"):
            inside = line[line.index("{") + 1 : line.index("}")]
            labels = dict(part.split("=", 1) for part in inside.split(","))
            assert labels["method"].strip('"') in {"GET", "other"}, line
            assert labels["route"].strip('"') in templates, line
    assert "XXXX" not in text and "yyyy" not in text
