"""A misspelt policy name in ``PUT /v1/policy`` is answered 422 naming the field and the close
name, not as a checkpoint path outside the allowed directories; paths keep their checks."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import ServiceSettings
from tests.api.fleet_helpers import AUTH as FLEET_AUTH
from tests.offline import offline_service

TOKEN = "policy-names-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    settings = ServiceSettings(api_token=TOKEN, policy="load-weighted")
    with TestClient(create_app(settings, service_factory=offline_service)) as test_client:
        yield test_client


def _refusal(client: TestClient, spec: str, auth: dict[str, str] = AUTH) -> str:
    response = client.put("/v1/policy", json={"policy": spec}, headers=auth)
    assert response.status_code == 422, response.text
    (error,) = response.json()["detail"]
    assert error["loc"] == ["body", "policy"]
    return error["msg"]


@pytest.mark.parametrize(
    ("spec", "meant"),
    [
        ("min-distnace", "min-distance"),
        ("Oracle", "oracle"),
        ("load_weighted", "load-weighted"),
        ("planing-oracle", "planning-oracle"),
    ],
)
def test_a_misspelt_baseline_is_named_with_the_close_name(client, spec, meant):
    message = _refusal(client, spec)
    assert message.startswith(f"policy: unknown policy {spec!r}: did you mean {meant!r}?")
    assert "outside the checkpoint directories" not in message
    assert client.get("/v1/policy", headers=AUTH).json()["name"] == "load-weighted"


def test_the_planning_oracle_is_served_by_name(client):
    response = client.put("/v1/policy", json={"policy": "planning-oracle"}, headers=AUTH)
    assert response.status_code == 200, response.text
    try:
        assert client.get("/v1/policy", headers=AUTH).json()["name"] == "planning-oracle"
    finally:
        restored = client.put("/v1/policy", json={"policy": "load-weighted"}, headers=AUTH)
        assert restored.status_code == 200, restored.text


def test_paths_keep_their_checks(client, tmp_path):
    """A path, even one whose name is close to a baseline's, is a checkpoint path: the
    directory checks answer, and nothing is suggested."""
    for spec in (str(tmp_path / "min-distnace"), "../min-distnace.zip", "/etc/passwd"):
        message = _refusal(client, spec)
        assert "outside the checkpoint directories" in message
        assert "did you mean" not in message


def test_a_name_close_to_nothing_is_refused_as_before(client):
    message = _refusal(client, "best-policy")
    assert "did you mean" not in message


def test_a_misspelt_fleet_policy_is_named_with_the_close_name():
    from tests.api.fleet_helpers import fleet_app

    for test_client, _links in fleet_app():
        message = _refusal(test_client, "kmeans-scord", FLEET_AUTH)
        assert message.startswith("policy: unknown policy 'kmeans-scord': did you mean")
        assert "'kmeans-scored'" in message
