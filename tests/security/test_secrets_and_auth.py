"""Security: the token comparison is constant-time, every /v1 route refuses a wrong token, and
neither the API token nor the MAVLink signing key shows in logs, reprs or responses."""

from __future__ import annotations

import hmac
import secrets
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

import api.auth
from api.app import create_app
from closed_loop.processes import start_service
from service.settings import ServiceSettings
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from tests.helpers import wait_for
from tests.offline import offline_service

TOKEN = "sec-" + secrets.token_urlsafe(24)
SIGNING_KEY = secrets.token_hex(32)
V1_ROUTES = [
    ("post", "/v1/reports"),
    ("get", "/v1/setpoint"),
    ("get", "/v1/vehicle"),
    ("get", "/v1/policy"),
    ("put", "/v1/policy"),
    ("get", "/v1/live"),  # the operator view's data: a frame, and the stream of them
    ("get", "/v1/live/events"),
]


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    settings = ServiceSettings(api_token=TOKEN, policy="min-distance")
    with TestClient(create_app(settings, service_factory=offline_service)) as test_client:
        yield test_client


# --------------------------------------------------------------------------- timing-safe


def test_every_token_comparison_goes_through_hmac_compare_digest(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[bytes, bytes]] = []
    real = hmac.compare_digest

    def spy(a: Any, b: Any) -> bool:
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(hmac, "compare_digest", spy)
    assert api.auth.token_matches(TOKEN, TOKEN) and calls == [(TOKEN.encode(), TOKEN.encode())]
    calls.clear()
    # One character off (a random token may itself end in "x").
    off_by_one = TOKEN[:-1] + ("y" if TOKEN.endswith("x") else "x")
    assert not api.auth.token_matches(off_by_one, TOKEN) and len(calls) == 1
    # ... and over HTTP: the right token and a wrong one are both compared by it, nothing else.
    calls.clear()
    assert client.get("/v1/setpoint", headers={"Authorization": f"Bearer {TOKEN}"}).is_success
    assert calls and all(b == TOKEN.encode() for _, b in calls)
    calls.clear()
    wrong = client.get("/v1/setpoint", headers={"Authorization": f"Bearer {off_by_one}"})
    assert wrong.status_code == 401
    assert calls == [(off_by_one.encode(), TOKEN.encode())]


def test_no_plain_equality_on_the_token_in_the_auth_module() -> None:
    import inspect

    source = inspect.getsource(api.auth)
    for pattern in ("== expected", "expected ==", "== self.token", "self.token =="):
        assert pattern not in source


WRONG_TOKENS = [
    TOKEN[:-1],  # a prefix
    TOKEN + "x",  # longer
    TOKEN[:-1] + chr(ord(TOKEN[-1]) ^ 1),  # same length, last character differs
    "x" + TOKEN[1:],  # same length, first character differs
    TOKEN.upper() if TOKEN.upper() != TOKEN else TOKEN.lower(),
    "",
    " ",
]


@pytest.mark.parametrize("method_path", V1_ROUTES, ids=lambda mp: f"{mp[0]} {mp[1]}")
@pytest.mark.parametrize("token", WRONG_TOKENS, ids=range(len(WRONG_TOKENS)))
def test_wrong_tokens_are_refused_on_every_route(
    client: TestClient, method_path: tuple[str, str], token: str
) -> None:
    method, path = method_path
    for header in (f"Bearer {token}", f"Basic {TOKEN}", f"Token {TOKEN}", TOKEN):
        response = client.request(method, path, headers={"Authorization": header}, json={})
        assert response.status_code == 401, (header, response.text)
        assert response.headers["www-authenticate"] == "Bearer"
        assert TOKEN not in response.text


def test_the_scheme_is_case_insensitive_and_the_right_token_works(client: TestClient) -> None:
    for scheme in ("Bearer", "bearer", "BEARER"):
        response = client.get("/v1/policy", headers={"Authorization": f"{scheme} {TOKEN}"})
        assert response.status_code == 200, scheme


def test_unknown_v1_paths_and_bad_bodies_need_the_token_first(client: TestClient) -> None:
    """Without the token nothing about the route or the body is revealed."""
    assert client.get("/v1/does-not-exist").status_code == 401
    assert client.post("/v1/reports", content=b"{not json").status_code == 401
    assert client.delete("/v1/policy").status_code == 401
    auth = {"Authorization": f"Bearer {TOKEN}"}
    assert client.get("/v1/does-not-exist", headers=auth).status_code == 404
    bad = client.post("/v1/reports", content=b"{not json", headers=auth)
    assert bad.status_code == 422


# --------------------------------------------------------------------------- no secrets shown


def _secret_forms() -> list[str]:
    key = bytes.fromhex(SIGNING_KEY)
    return [TOKEN, SIGNING_KEY, SIGNING_KEY.upper(), repr(key), key.hex(" ")]


def test_settings_repr_and_dumps_hide_the_secrets() -> None:
    settings = ServiceSettings(
        api_token=TOKEN, mavlink_signing_key=SIGNING_KEY, policy="min-distance"
    )
    shown = [repr(settings), str(settings), settings.model_dump_json(), str(settings.model_dump())]
    for text in shown:
        for secret in _secret_forms():
            assert secret not in text
    assert settings.signing_key_bytes() == bytes.fromhex(SIGNING_KEY)  # still usable


def test_settings_errors_do_not_echo_a_bad_key() -> None:
    from pydantic import ValidationError

    bad = SIGNING_KEY[:-2] + "zz"  # not hex
    with pytest.raises(ValidationError) as info:
        ServiceSettings(mavlink_signing_key=bad, policy="min-distance")
    assert bad not in str(info.value)


@pytest.mark.slow
@pytest.mark.process
def test_tupa_serve_logs_no_secret_at_debug_level() -> None:
    """``tupa serve --log-level debug`` with both secrets in its environment, against an
    in-process mock that signs with the same key: requests with the right token, wrong ones
    (including the token with a character added) and bad bodies; then its whole output is
    searched for either secret."""
    mock = MockAutopilot(
        "tcp:127.0.0.1:0",
        "px4",
        VehicleConfig(ready_delay_s=0.3),
        signing_key=bytes.fromhex(SIGNING_KEY),
    )
    mock.start()
    service = None
    try:
        service, port = start_service(
            [
                "--mavlink",
                f"tcp:127.0.0.1:{mock.port}",
                "--port",
                "0",
                "--policy",
                "min-distance",
                "--decision-mode",
                "on-report",
                "--log-level",
                "debug",
            ],
            env={"TUPA_API_TOKEN": TOKEN, "TUPA_MAVLINK_SIGNING_KEY": SIGNING_KEY},
        )
        base = f"http://127.0.0.1:{port}"
        auth = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=base, timeout=10.0) as http:
            wait_for(lambda: http.get("/readyz").status_code == 200, 30.0, message="signed link up")
            report = {
                "timestamp": 1.0,
                "users": [
                    {
                        "id": "ue-1",
                        "x_m": 100.0,
                        "y_m": 100.0,
                        "offered_bps": 1e6,
                        "throughput_bps": 1e6,
                        "delay_s": 0.01,
                        "plr": 0.0,
                    }
                ],
            }
            assert http.post("/v1/reports", json=report, headers=auth).status_code == 200
            for wrong in (f"Bearer {TOKEN}x", f"Bearer {TOKEN[:-1]}", f"Basic {TOKEN}", ""):
                response = http.get("/v1/setpoint", headers={"Authorization": wrong})
                assert response.status_code == 401
            bad = {**report, "users": [{**report["users"][0], "plr": 2.0}]}
            assert http.post("/v1/reports", json=bad, headers=auth).status_code == 422
            put = http.put("/v1/policy", json={"policy": "/nonexistent.zip"}, headers=auth)
            assert put.status_code == 422
            assert http.get("/v1/vehicle", headers=auth).json()["link"] == "up"
            assert http.get("/metrics").status_code == 200
        service.stop()
        output = service.tail(n=2000)
        # Debug logging and the access log (on only at debug) ran, refusals included.
        assert "DEBUG api.auth: 401 for GET /v1/setpoint" in output
        assert '"GET /v1/setpoint HTTP/1.1" 401' in output
        for secret in _secret_forms():
            assert secret not in output, "a secret appears in the service's output"
    finally:
        if service is not None:
            service.stop()
        mock.stop()
