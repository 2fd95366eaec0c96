"""The HTTP contract of every route and every error, against a real sitl_mock autopilot.

One app per module (on an in-process sitl_mock, PX4 flavour, on a free loopback port); the
service is started by the app's lifespan and stopped at the end.
"""

from __future__ import annotations

import math
import shutil
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import token_matches
from service.placement import PlacementService
from service.policy_runtime import SHIPPED_CHECKPOINTS, SHIPPED_DDQN
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from tests.fakes import FakeLink
from tests.gated_policy import GatedPolicy
from tests.helpers import wait_for
from tests.offline import offline_service

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def user(i: int, **over: Any) -> dict[str, Any]:
    base = {
        "id": f"ue-{i}",
        "x_m": 50.0 + 40 * i,
        "y_m": 60.0 + 30 * i,
        "offered_bps": 10e6,
        "throughput_bps": 8e6,
        "delay_s": 0.05,
        "plr": 0.01,
    }
    return {**base, **over}


class Clock:
    """Increasing report timestamps."""

    def __init__(self) -> None:
        self.t = 1_000.0
        self.lock = threading.Lock()

    def __call__(self) -> float:
        with self.lock:
            self.t += 1.0
            return self.t


@pytest.fixture(scope="module")
def mock() -> Iterator[MockAutopilot]:
    autopilot = MockAutopilot("tcp:127.0.0.1:0", "px4", VehicleConfig(ready_delay_s=0.3))
    autopilot.start()
    yield autopilot
    autopilot.stop()


@pytest.fixture(scope="module")
def checkpoint_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory the module's service may load checkpoints from (besides the shipped ones)."""
    return tmp_path_factory.mktemp("checkpoints")


@pytest.fixture(scope="module")
def client(mock: MockAutopilot, checkpoint_dir: Path) -> Iterator[TestClient]:
    settings = ServiceSettings(
        policy_dirs=(SHIPPED_CHECKPOINTS, checkpoint_dir),
        mavlink=f"tcp:127.0.0.1:{mock.port}",
        api_token=TOKEN,
        policy="load-weighted",
        decision_mode="on-report",
        max_body_bytes=200_000,
        rate_limit_rps=0.0,  # the hot-swap test posts from three threads as fast as it can
    )
    with TestClient(create_app(settings)) as test_client:
        wait_for(lambda: test_client.get("/readyz").status_code == 200, 15.0, message="link up")
        yield test_client


@pytest.fixture(scope="module")
def clock() -> Clock:
    return Clock()


@pytest.fixture(autouse=True)
def serving_load_weighted(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every test that uses the module's service starts with ``load-weighted`` serving (asserted,
    so no test leans on another having restored it) and leaves it so, in any order."""
    if "client" not in request.fixturenames:
        yield
        return
    client: TestClient = request.getfixturevalue("client")
    assert client.get("/v1/policy", headers=AUTH).json()["name"] == "load-weighted"
    yield
    if client.get("/v1/policy", headers=AUTH).json()["name"] != "load-weighted":
        restored = client.put("/v1/policy", json={"policy": "load-weighted"}, headers=AUTH)
        assert restored.status_code == 200


def post(client: TestClient, clock: Clock, users: list[dict[str, Any]], **kw: Any) -> Any:
    return client.post("/v1/reports", json={"timestamp": clock(), "users": users}, **kw)


# --------------------------------------------------------------------------- probes, auth


def test_health_and_readiness(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["ready"] is True and ready.json()["link"] == "up"


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("post", "/v1/reports"),
        ("get", "/v1/setpoint"),
        ("get", "/v1/vehicle"),
        ("get", "/v1/policy"),
        ("put", "/v1/policy"),
    ],
)
@pytest.mark.parametrize("header", [None, "Bearer wrong-token", "Basic abc", f"Bearer {TOKEN}x"])
def test_every_v1_route_needs_the_token(
    client: TestClient, method: str, path: str, header: str | None
) -> None:
    headers = {"Authorization": header} if header else {}
    response = client.request(method, path, headers=headers, json={})
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"


def test_token_comparison_is_exact() -> None:
    assert token_matches("abc", "abc")
    assert not token_matches("abc", "abd")
    assert not token_matches("abc", "abcd")
    assert not token_matches("", "abc")


def test_refuses_to_start_without_a_token_unless_insecure() -> None:
    with pytest.raises(ValueError, match="api_token"):
        create_app(ServiceSettings(api_token=None, policy="min-distance"))
    create_app(ServiceSettings(api_token=None, insecure=True, policy="min-distance"))


# --------------------------------------------------------------------------- reports


def test_report_triggers_a_decision_inside_the_geofence(client: TestClient, clock: Clock) -> None:
    response = post(client, clock, [user(1), user(2, offered_bps=30e6)], headers=AUTH)
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["source"] == "policy" and body["policy"] == "load-weighted"
    assert body["report_outcome"] == "decided"  # the decision taken from this report
    target = body["target"]
    assert 0 <= target["x_m"] <= 500 and 0 <= target["y_m"] <= 500
    assert 25 <= target["z_m"] <= 100
    setpoint = client.get("/v1/setpoint", headers=AUTH).json()
    assert setpoint["target"] == target and setpoint["decided_at"] == body["decided_at"]


BAD_USERS = [
    ({"offered_bps": -1.0}, ["users", 0, "offered_bps"]),
    ({"throughput_bps": -5.0}, ["users", 0, "throughput_bps"]),
    ({"delay_s": -0.1}, ["users", 0, "delay_s"]),
    ({"plr": 1.5}, ["users", 0, "plr"]),
    ({"plr": -0.1}, ["users", 0, "plr"]),
    ({"x_m": 501.0}, ["users", 0, "x_m"]),
    ({"y_m": -3.0}, ["users", 0, "y_m"]),
    ({"x_m": "east"}, ["users", 0, "x_m"]),
    ({"id": ""}, ["users", 0, "id"]),
]


@pytest.mark.parametrize(("override", "loc"), BAD_USERS)
def test_bad_user_fields_are_named_and_change_nothing(
    client: TestClient, clock: Clock, override: dict[str, Any], loc: list[Any]
) -> None:
    before = client.get("/v1/setpoint", headers=AUTH).json()
    response = post(client, clock, [user(0, **override), user(1)], headers=AUTH)
    assert response.status_code == 422, response.text
    assert ["body", *loc] in [err["loc"] for err in response.json()["detail"]]
    assert client.get("/v1/setpoint", headers=AUTH).json() == before


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_are_refused(client: TestClient, value: str) -> None:
    before = client.get("/v1/setpoint", headers=AUTH).json()
    raw = (
        '{"timestamp": 5e9, "users": [{"id": "a", "x_m": 1, "y_m": 1, "offered_bps": VALUE, '
        '"throughput_bps": 1, "delay_s": 0, "plr": 0}]}'
    ).replace("VALUE", value)
    response = client.post(
        "/v1/reports", content=raw, headers={**AUTH, "content-type": "application/json"}
    )
    assert response.status_code == 422
    assert ["body", "users", 0, "offered_bps"] in [e["loc"] for e in response.json()["detail"]]
    assert client.get("/v1/setpoint", headers=AUTH).json() == before


def test_duplicate_ids_no_users_and_too_many_users(client: TestClient, clock: Clock) -> None:
    dup = post(client, clock, [user(1), user(1)], headers=AUTH)
    assert dup.status_code == 422
    assert dup.json()["detail"][0]["loc"] == ["body", "users", 1, "id"]
    empty = post(client, clock, [], headers=AUTH)
    assert empty.status_code == 422
    assert empty.json()["detail"][0]["loc"] == ["body", "users"]
    many = [user(0, id=f"u{i}", x_m=1.0, y_m=1.0) for i in range(2000)]
    # Over this app's 200 kB body limit: refused before it is parsed (the user-count limit has
    # its own test below, with the default 1 MB body limit).
    too_big = post(client, clock, many, headers=AUTH)
    assert too_big.status_code == 413
    assert "limit" in too_big.json()["detail"]


def test_user_count_limit() -> None:
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance", max_users=1000)
    app = create_app(settings, service_factory=offline_service)
    with TestClient(app) as test_client:
        users = [user(0, id=f"u{i}", x_m=1.0, y_m=1.0) for i in range(1001)]
        response = test_client.post(
            "/v1/reports", json={"timestamp": 1.0, "users": users}, headers=AUTH
        )
        assert response.status_code == 422
        assert response.json()["detail"][0]["loc"] == ["body", "users"]
        assert "1000" in response.json()["detail"][0]["msg"]


def test_out_of_order_reports_are_ignored_and_counted(client: TestClient, clock: Clock) -> None:
    newer = clock() + 100.0
    assert (
        client.post(
            "/v1/reports", json={"timestamp": newer, "users": [user(1)]}, headers=AUTH
        ).status_code
        == 200
    )
    before = client.get("/v1/setpoint", headers=AUTH).json()
    older = client.post(
        "/v1/reports", json={"timestamp": newer - 50, "users": [user(3)]}, headers=AUTH
    )
    assert older.status_code == 409 and "older" in older.json()["detail"]
    assert client.get("/v1/setpoint", headers=AUTH).json() == before
    metrics = client.get("/metrics").text
    line = next(x for x in metrics.splitlines() if 'result="out_of_order"' in x)
    assert float(line.split()[-1]) >= 1
    clock.t = newer + 1


def test_body_over_the_size_limit(client: TestClient) -> None:
    response = client.post(
        "/v1/reports",
        content=b"{" + b" " * 300_000 + b"}",
        headers={**AUTH, "content-type": "application/json"},
    )
    assert response.status_code == 413


# --------------------------------------------------------------------------- vehicle, policy


def test_vehicle_in_the_area_frame(client: TestClient) -> None:
    body = client.get("/v1/vehicle", headers=AUTH).json()
    assert body["link"] == "up" and body["flavour"] == "px4"
    assert set(body["position"]) == {"x_m", "y_m", "z_m"}
    assert all(math.isfinite(v) for v in body["position"].values())


def test_policy_get_and_switch(client: TestClient) -> None:
    serving = client.get("/v1/policy", headers=AUTH).json()
    assert serving["name"] == "load-weighted"
    timing = serving["decisions"]  # how long decisions take against the period
    assert timing["mode"] == "on-report" and timing["period_s"] == 1.0
    assert timing["timed"] >= 0 and timing["overruns"] >= 0
    switched = client.put("/v1/policy", json={"policy": "min-distance"}, headers=AUTH)
    assert switched.status_code == 200 and switched.json()["name"] == "min-distance"
    assert client.get("/v1/policy", headers=AUTH).json()["kind"] == "placement"


def test_bad_policies_are_refused_and_the_old_one_stays(
    client: TestClient, clock: Clock, checkpoint_dir: Path
) -> None:
    tmp_path = checkpoint_dir
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"not a zip at all")
    corrupt.with_suffix(".json").write_text('{"format": "tupa-checkpoint/1"}')
    wrong_shape = tmp_path / "wrong.zip"
    with zipfile.ZipFile(wrong_shape, "w") as z:
        z.writestr("data", "{}")
    wrong_shape.with_suffix(".json").write_text(
        '{"format": "tupa-checkpoint/1", "algorithm": "ddqn", "observation_shape": [6, 10, 10]}'
    )
    for spec in [str(tmp_path / "missing.zip"), str(corrupt), str(wrong_shape), "best-policy"]:
        response = client.put("/v1/policy", json={"policy": spec}, headers=AUTH)
        assert response.status_code == 422, (spec, response.text)
        assert response.json()["detail"][0]["loc"] == ["body", "policy"]
        assert client.get("/v1/policy", headers=AUTH).json()["name"] == "load-weighted"
    assert post(client, clock, [user(1)], headers=AUTH).status_code == 200


@pytest.mark.skipif(not SHIPPED_DDQN.is_file(), reason="no shipped DDQN checkpoint")
def test_checkpoints_load_only_from_the_allowed_directories(
    client: TestClient, tmp_path: Path, checkpoint_dir: Path
) -> None:
    outside = tmp_path / "ddqn.zip"  # a perfectly good checkpoint, in the wrong place
    shutil.copyfile(SHIPPED_DDQN, outside)
    shutil.copyfile(SHIPPED_DDQN.with_suffix(".json"), outside.with_suffix(".json"))
    escape = str(checkpoint_dir / ".." / tmp_path.name / "ddqn.zip")
    link = checkpoint_dir / "link.zip"
    link.symlink_to(outside)
    for spec in (str(outside), escape, str(link)):
        response = client.put("/v1/policy", json={"policy": spec}, headers=AUTH)
        assert response.status_code == 422, spec
        assert "outside the checkpoint directories" in response.json()["detail"][0]["msg"]
        assert client.get("/v1/policy", headers=AUTH).json()["name"] == "load-weighted"
    # Inside the allowed directories: served, unless its metadata says it is not for serving
    # (the shipped DDQN dithers on a real vehicle: tests/policies/test_shipped.py).
    refused = client.put("/v1/policy", json={"policy": str(SHIPPED_DDQN)}, headers=AUTH)
    assert refused.status_code == 422
    assert "is not for serving" in refused.json()["detail"][0]["msg"]
    servable = SHIPPED_CHECKPOINTS / "ddpg-residual-dr.zip"
    shipped = client.put("/v1/policy", json={"policy": str(servable)}, headers=AUTH)
    assert shipped.status_code == 200 and shipped.json()["kind"] == "coordinates"


def test_hot_swap_under_concurrent_reports(client: TestClient, clock: Clock) -> None:
    """Reports keep being decided while the policy is switched under them. A reporter thread
    records every unexpected answer *and* every exception (TestClient re-raises the server's own
    exceptions in the calling thread, which a bare thread would swallow)."""
    failures: list[object] = []
    decided_per_swap: list[int] = []
    decided = [0]
    lock = threading.Lock()
    stop = threading.Event()

    def reporter() -> None:
        while not stop.is_set():
            try:
                users = [user(1), user(2, offered_bps=25e6)]
                response = post(client, clock, users, headers=AUTH)
            except BaseException as exc:  # a server bug surfaces here
                failures.append(repr(exc))
                return
            if response.status_code == 200:
                with lock:
                    decided[0] += 1
            elif response.status_code != 409:  # 409: a thread lost the timestamp race
                failures.append((response.status_code, response.text))

    threads = [threading.Thread(target=reporter) for _ in range(3)]
    for thread in threads:
        thread.start()
    try:
        for name in ["min-distance", "load-weighted", "oracle", "load-weighted"] * 2:
            with lock:
                before = decided[0]
            response = client.put("/v1/policy", json={"policy": name}, headers=AUTH)
            assert response.status_code == 200
            wait_for(lambda b=before: decided[0] > b + 2, 10.0, message="reports decided")
            decided_per_swap.append(decided[0] - before)
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
    assert failures == []
    assert all(n > 2 for n in decided_per_swap), decided_per_swap
    assert client.get("/v1/policy", headers=AUTH).json()["name"] == "load-weighted"


# --------------------------------------------------------------------------- metrics, docs


def test_metrics_in_prometheus_text(client: TestClient) -> None:
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    for name in (
        "tupa_http_requests_total",
        "tupa_http_request_duration_seconds_bucket",
        "tupa_decisions_total",
        "tupa_setpoints_sent_total",
        "tupa_geofence_clamps_total",
        'tupa_link_state{state="up"} 1.0',
        "tupa_fleet_decisions_degraded_total 0.0",  # the same families for any number
    ):
        assert name in text


def test_openapi_documents_every_route_with_examples(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    paths = schema["paths"]
    for path in ("/v1/reports", "/v1/setpoint", "/v1/vehicle", "/v1/vehicles", "/v1/policy",
                 "/v1/vehicles/{vehicle_id}", "/healthz"):  # fmt: skip
        assert path in paths
    components = schema["components"]["schemas"]
    for model in ("ReportIn", "DecisionOut", "VehicleOut", "PolicyOut", "PolicyIn"):
        assert components[model].get("examples"), model
    assert "401" in paths["/v1/setpoint"]["get"]["responses"]


def test_report_while_the_link_is_down_is_accepted_and_waits() -> None:
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance", decision_mode="on-report")
    with TestClient(create_app(settings, service_factory=offline_service)) as test_client:
        response = test_client.post(
            "/v1/reports", json={"timestamp": 1.0, "users": [user(1)]}, headers=AUTH
        )
        assert response.status_code == 200
        assert response.json() == {
            "target": None,
            "source": "none",
            "policy": None,
            "decided_at": None,
            "targets": {},
            "report_outcome": "held",  # kept, and decided once the link is back
        }
        ready = test_client.get("/readyz")
        assert ready.status_code == 503
        assert any("link" in reason for reason in ready.json()["reasons"])


def test_a_report_behind_a_slow_decision_is_answered_pending_within_two_periods() -> None:
    """A decision slower than the period (a policy held by the test) does not hold the report's
    answer: ``pending`` with the current target, and ``GET /v1/policy`` counts the overrun."""
    policy = GatedPolicy()
    settings = ServiceSettings(api_token=TOKEN, decision_mode="on-report", step_s=0.2)
    link = FakeLink(LinkConfig("tcp:127.0.0.1:1"), position_m=(250.0, 250.0, 30.0))

    def factory(s: ServiceSettings) -> PlacementService:
        return PlacementService(s, link, policy)

    try:
        with TestClient(create_app(settings, service_factory=factory)) as test_client:
            answer = test_client.post(
                "/v1/reports", json={"timestamp": 1.0, "users": [user(1)]}, headers=AUTH
            )
            assert answer.status_code == 200
            assert answer.json()["report_outcome"] == "pending"
            assert answer.json()["target"] is None  # nothing decided yet
            policy.wait_started(1)
            wait_for(  # the decision has been running longer than the period
                lambda: time.monotonic() - policy.started_at[0] > 0.2, 15.0, message="overrun"
            )
            policy.open()
            wait_for(
                lambda: test_client.get("/v1/setpoint", headers=AUTH).json()["target"],
                15.0,
                message="the pending report decided",
            )
            timing = test_client.get("/v1/policy", headers=AUTH).json()["decisions"]
            assert timing["timed"] == 1 and timing["overruns"] == 1
            assert timing["max_s"] > timing["period_s"] == 0.2
    finally:
        policy.open()


def test_paced_mode_answers_stored() -> None:
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance")
    with TestClient(create_app(settings, service_factory=offline_service)) as test_client:
        answer = test_client.post(
            "/v1/reports", json={"timestamp": 1.0, "users": [user(1)]}, headers=AUTH
        )
        assert answer.status_code == 200 and answer.json()["report_outcome"] == "stored"
