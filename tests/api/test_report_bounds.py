"""Reports at the edges (issue 21, items 6 and 9): timestamps from the future, and numbers that
are finite but absurd. Every report field is bounded to a physical range, and every baseline
policy gives a finite target inside the area for every report those bounds let through."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st

from api.app import create_app
from api.schemas import MAX_BPS, MAX_DELAY_S, ReportIn
from policies.registry import resolve_policy
from service.settings import ServiceSettings
from sim.config import AreaConfig
from sim.observation import UserReports
from tests.offline import offline_service

TOKEN = "bounds-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
AREA = AreaConfig()


def user(**over: Any) -> dict[str, Any]:
    base = {
        "id": "ue-1",
        "x_m": 120.0,
        "y_m": 80.0,
        "offered_bps": 30e6,
        "throughput_bps": 21.5e6,
        "delay_s": 0.42,
        "plr": 0.18,
    }
    return {**base, **over}


@pytest.fixture
def client() -> Iterator[TestClient]:
    app = create_app(
        ServiceSettings(api_token=TOKEN, policy="load-weighted", decision_mode="on-report"),
        service_factory=offline_service,
    )
    with TestClient(app) as test_client:
        yield test_client


def _post(client: TestClient, timestamp: float, **over: Any) -> Any:
    body = {"timestamp": timestamp, "users": [user(**over)]}
    return client.post("/v1/reports", json=body, headers=AUTH)


# --------------------------------------------------------------------------- 6: the future


@pytest.mark.parametrize("ahead_s", [3600.0, 60.0, 6.0])
def test_a_report_from_the_future_is_refused_and_locks_nobody_out(
    client: TestClient, ahead_s: float
) -> None:
    response = _post(client, time.time() + ahead_s)
    assert response.status_code == 422, response.text
    error = response.json()["detail"][0]
    assert error["loc"] == ["body", "timestamp"]
    assert "future" in error["msg"] and "report_max_future_s" in error["msg"]
    # The next honest report is accepted: the refused one did not move the clock.
    assert _post(client, time.time()).status_code == 200


def test_a_report_stamped_ahead_within_the_tolerance_locks_no_honest_report_out(
    client: TestClient,
) -> None:
    """Reports are ordered by min(timestamp, arrival time): one stamped 4.9 s ahead (accepted,
    clock skew) counts as stamped when it arrived, so every honest report after it is in order;
    one older than the last honest report is still refused."""
    assert _post(client, time.time() + 4.9).status_code == 200
    for _ in range(5):
        response = _post(client, time.time())
        assert response.status_code == 200, response.text
    late = _post(client, time.time() - 30.0)
    assert late.status_code == 409 and "older" in late.json()["detail"]


@pytest.mark.parametrize("timestamp", [1e300, 1.7976931348623157e308])
def test_an_absurd_timestamp_is_refused_naming_the_field(
    client: TestClient, timestamp: float
) -> None:
    response = _post(client, timestamp)
    assert response.status_code == 422
    assert ["body", "timestamp"] in [e["loc"] for e in response.json()["detail"]]
    assert _post(client, time.time()).status_code == 200


def test_a_little_clock_skew_is_tolerated_and_the_tolerance_is_a_setting() -> None:
    assert ServiceSettings(policy="min-distance").report_max_future_s == 5.0
    assert _post_one(report_max_future_s=5.0, ahead_s=2.0) == 200
    assert _post_one(report_max_future_s=0.5, ahead_s=2.0) == 422


def _post_one(ahead_s: float, **settings: Any) -> int:
    app = create_app(
        ServiceSettings(api_token=TOKEN, policy="min-distance", **settings),
        service_factory=offline_service,
    )
    with TestClient(app) as test_client:
        return _post(test_client, time.time() + ahead_s).status_code


# --------------------------------------------------------------------------- 9: numbers


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("offered_bps", 1e308),
        ("throughput_bps", 1e308),
        ("offered_bps", MAX_BPS * 1.01),
        ("delay_s", 1e308),
        ("delay_s", MAX_DELAY_S + 1),
        ("x_m", 1e308),
        ("y_m", 1e308),
    ],
)
def test_absurd_but_finite_numbers_are_refused_naming_the_field(
    client: TestClient, field: str, value: float
) -> None:
    before = client.get("/v1/setpoint", headers=AUTH).json()
    response = _post(client, time.time(), **{field: value})
    assert response.status_code == 422, response.text
    assert ["body", "users", 0, field] in [e["loc"] for e in response.json()["detail"]]
    assert client.get("/v1/setpoint", headers=AUTH).json() == before


def test_the_largest_accepted_values_are_accepted(client: TestClient) -> None:
    response = _post(
        client,
        time.time(),
        offered_bps=MAX_BPS,
        throughput_bps=MAX_BPS,
        delay_s=MAX_DELAY_S,
        plr=1.0,
        x_m=AREA.size_x_m,
        y_m=AREA.size_y_m,
    )
    assert response.status_code == 200, response.text


_POLICIES = {name: resolve_policy(name) for name in ("min-distance", "load-weighted")}
_bps = st.floats(0.0, MAX_BPS)
_user = st.fixed_dictionaries(
    {
        "x_m": st.floats(0.0, AREA.size_x_m),
        "y_m": st.floats(0.0, AREA.size_y_m),
        "offered_bps": st.one_of(_bps, st.sampled_from([0.0, 5e-324, 1.0, MAX_BPS])),
        "throughput_bps": _bps,
        "delay_s": st.floats(0.0, MAX_DELAY_S),
        "plr": st.floats(0.0, 1.0),
    }
)


@settings(max_examples=300, deadline=None)
@given(users=st.lists(_user, min_size=1, max_size=12), name=st.sampled_from(sorted(_POLICIES)))
def test_baselines_give_a_finite_target_inside_the_area_for_every_accepted_report(
    users: list[dict[str, float]], name: str
) -> None:
    body = {"timestamp": 1.0, "users": [{"id": f"u{i}", **u} for i, u in enumerate(users)]}
    ReportIn.model_validate(body)  # the schema accepts it: the property covers what is served
    reports = UserReports(**{k: np.array([u[k] for u in users], dtype=float) for k in users[0]})
    centre = np.array([AREA.size_x_m / 2, AREA.size_y_m / 2, AREA.z_min_m])
    target = _POLICIES[name].decide(reports, centre)
    assert target.shape == (3,) and all(math.isfinite(v) for v in target), target
    assert 0.0 <= target[0] <= AREA.size_x_m and 0.0 <= target[1] <= AREA.size_y_m
    assert AREA.z_min_m <= target[2] <= AREA.z_max_m


def test_many_users_at_the_largest_loads_stay_finite() -> None:
    n = 1000
    rng = np.random.default_rng(7)
    reports = UserReports(
        x_m=rng.uniform(0, AREA.size_x_m, n),
        y_m=rng.uniform(0, AREA.size_y_m, n),
        offered_bps=np.full(n, MAX_BPS),
        throughput_bps=np.full(n, MAX_BPS),
        delay_s=np.full(n, MAX_DELAY_S),
        plr=np.ones(n),
    )
    centre = np.array([AREA.size_x_m / 2, AREA.size_y_m / 2, AREA.z_min_m])
    for policy in _POLICIES.values():
        target = policy.decide(reports, centre)
        assert np.all(np.isfinite(target)) and 0 <= target[0] <= AREA.size_x_m
