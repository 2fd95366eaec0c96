"""The per-client rate limit: a token bucket per peer address, 429 with Retry-After."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.ratelimit import TokenBuckets
from service.settings import ServiceSettings
from tests.offline import offline_service

TOKEN = "rate-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _app(**settings: Any) -> Any:
    return create_app(
        ServiceSettings(api_token=TOKEN, policy="min-distance", **settings),
        service_factory=offline_service,
    )


# --------------------------------------------------------------------------- the bucket


def test_bucket_allows_the_burst_then_the_rate() -> None:
    clock = FakeClock()
    buckets = TokenBuckets(rate_per_s=10.0, burst=3, clock=clock)
    assert [buckets.take("a") for _ in range(3)] == [0.0, 0.0, 0.0]
    assert buckets.take("a") == pytest.approx(0.1)  # empty: one token in 1/10 s
    clock.t += 0.1
    assert buckets.take("a") == 0.0
    assert buckets.take("a") > 0.0
    clock.t += 10.0  # refills to the burst, not beyond
    assert [buckets.take("a") for _ in range(4)][-1] > 0.0


def test_clients_have_their_own_buckets_and_memory_stays_bounded() -> None:
    clock = FakeClock()
    buckets = TokenBuckets(rate_per_s=1.0, burst=1, max_clients=100, clock=clock)
    assert buckets.take("a") == 0.0
    assert buckets.take("a") > 0.0
    assert buckets.take("b") == 0.0  # "a" being limited does not touch "b"
    for i in range(1000):
        buckets.take(f"10.0.{i // 256}.{i % 256}")
    assert len(buckets) == 100


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan"), float("inf")])
def test_bucket_refuses_a_meaningless_rate(rate: float) -> None:
    with pytest.raises(ValueError, match="rate_per_s"):
        TokenBuckets(rate_per_s=rate, burst=1)


def test_the_default_limits_a_flood_and_never_the_controller() -> None:
    """The default is below what one core serves (a few hundred requests/s leaves the rest of
    it to the other clients) and far above what a network controller sends: a report per
    vehicle per decision period, 8 vehicles at 10 per second each, never limited, even after
    an instantaneous burst of a few dozen."""
    defaults = ServiceSettings(policy="min-distance")
    assert 50 <= defaults.rate_limit_rps <= 300, defaults.rate_limit_rps
    assert defaults.rate_limit_burst >= defaults.rate_limit_rps
    clock = FakeClock()
    buckets = TokenBuckets(defaults.rate_limit_rps, defaults.rate_limit_burst, clock=clock)
    assert all(buckets.take("controller") == 0.0 for _ in range(50))
    refused = 0
    for _ in range(60 * 80):  # 80 requests/s for 60 s
        refused += buckets.take("controller") > 0.0
        clock.t += 1 / 80
    assert refused == 0
    # A client at 1,000 requests/s: through for about its burst, then at the rate.
    passed = 0
    for _ in range(10_000):  # 10 s
        passed += buckets.take("flood") == 0.0
        clock.t += 0.001
    expected = defaults.rate_limit_burst + 10 * defaults.rate_limit_rps
    assert expected - 2 <= passed <= expected + 2, (passed, expected)


# --------------------------------------------------------------------------- over HTTP


def test_over_the_rate_gets_429_with_retry_after() -> None:
    with TestClient(_app(rate_limit_rps=0.5, rate_limit_burst=3)) as client:
        codes = [client.get("/v1/setpoint", headers=AUTH).status_code for _ in range(3)]
        assert codes == [200, 200, 200]
        limited = client.get("/v1/setpoint", headers=AUTH)
        assert limited.status_code == 429
        assert int(limited.headers["retry-after"]) == 2  # one token at 0.5/s
        assert "rate limit" in limited.json()["detail"]
        # Requests without a valid token have a bucket of their own (per address): they are
        # limited too, and spend nothing of the authenticated client's budget.
        assert client.get("/v1/setpoint").status_code == 401
        assert client.get("/metrics").status_code == 200
        assert client.get("/v1/setpoint", headers={"Authorization": "Bearer x"}).status_code == 401
        assert client.get("/v1/setpoint").status_code == 429
        assert client.get("/metrics").status_code == 429


def test_an_unauthenticated_flood_does_not_starve_the_authenticated_client() -> None:
    """A flood of wrong tokens (and no tokens) from the controller's own address: it is
    limited, and the controller's reports still go through."""
    with TestClient(_app(rate_limit_rps=0.5, rate_limit_burst=3)) as client:
        flood = [
            client.post("/v1/reports", json={}, headers={"Authorization": f"Bearer wrong{i}"})
            for i in range(50)
        ]
        codes = [response.status_code for response in flood]
        assert codes[:3] == [401, 401, 401] and set(codes[3:]) == {429}
        assert client.get("/v1/setpoint").status_code == 429
        ok = [client.get("/v1/setpoint", headers=AUTH).status_code for _ in range(3)]
        assert ok == [200, 200, 200]


def _forwarded(client: TestClient, i: int) -> int:
    headers = {**AUTH, "X-Forwarded-For": f"198.51.100.{i}"}
    return client.get("/v1/setpoint", headers=headers).status_code


def test_x_forwarded_for_counts_only_from_a_trusted_proxy() -> None:
    """With ``trusted_proxies`` the address a trusted proxy forwards is the client's (its own
    bucket); from any other peer the header is ignored. Without it (the default) it is ignored
    from everyone: see tests/security/test_hostile_clients.py for uvicorn's side."""
    assert ServiceSettings(policy="min-distance").trusted_proxies == ()
    app = _app(rate_limit_rps=0.5, rate_limit_burst=2, trusted_proxies=("127.0.0.1",))
    with TestClient(app, client=("127.0.0.1", 40000)) as proxy:
        assert [_forwarded(proxy, i) for i in range(1, 9)] == [200] * 8
        assert {_forwarded(proxy, 1) for _ in range(3)} == {200, 429}
        stranger = TestClient(app, client=("192.0.2.9", 40000))
        assert [_forwarded(stranger, i) for i in range(1, 5)] == [200, 200, 429, 429]
    with TestClient(_app(rate_limit_rps=0.5, rate_limit_burst=2), client=("127.0.0.1", 1)) as c:
        assert [_forwarded(c, i) for i in range(1, 5)] == [200, 200, 429, 429]


def test_probes_are_never_limited_and_rejections_are_counted() -> None:
    with TestClient(_app(rate_limit_rps=0.5, rate_limit_burst=2)) as client:
        for _ in range(5):
            client.get("/v1/policy", headers=AUTH)
        for _ in range(20):
            assert client.get("/healthz").status_code == 200
            assert client.get("/readyz").status_code in (200, 503)
        other = TestClient(client.app, client=("192.0.2.7", 40000))
        metrics = other.get("/metrics")  # another client: its own bucket
        assert metrics.status_code == 200
        line = next(
            x for x in metrics.text.splitlines() if x.startswith("tupa_http_rate_limited_total")
        )
        assert float(line.split()[-1]) == 3.0


def test_only_get_and_head_on_the_probes_are_exempt() -> None:
    """A made-up method on ``/healthz`` is no probe: it is limited like any request (else a
    flood of them would pass the limit by naming a probe's path)."""
    with TestClient(_app(rate_limit_rps=0.5, rate_limit_burst=2)) as client:
        codes = [client.request("FOO", "/healthz").status_code for _ in range(4)]
        assert codes == [405, 405, 429, 429]
        assert client.post("/readyz").status_code == 429
        assert all(client.get("/healthz").status_code == 200 for _ in range(10))
        assert all(client.head("/healthz").status_code in (200, 405) for _ in range(5))


def test_zero_disables_the_limit() -> None:
    with TestClient(_app(rate_limit_rps=0, rate_limit_burst=1)) as client:
        assert all(client.get("/v1/setpoint", headers=AUTH).status_code == 200 for _ in range(50))


def test_429_is_documented_on_every_limited_route() -> None:
    schema = _app().openapi()
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            if path in ("/healthz", "/readyz"):
                assert "429" not in operation["responses"], (method, path)
            else:
                assert "429" in operation["responses"], (method, path)
                assert "Retry-After" in operation["responses"]["429"]["headers"]


def test_cli_options_and_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from api.cli import register, settings_from_args
    from sim.errors import InputError

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["serve", "--policy", "min-distance"]
    args = parser.parse_args([*base, "--rate-limit-rps", "5", "--rate-limit-burst", "3"])
    settings = settings_from_args(args)
    assert (settings.rate_limit_rps, settings.rate_limit_burst) == (5.0, 3)
    monkeypatch.setenv("TUPA_RATE_LIMIT_RPS", "0")
    assert settings_from_args(parser.parse_args(base)).rate_limit_rps == 0.0
    with pytest.raises(InputError, match="rate_limit_rps"):
        settings_from_args(parser.parse_args([*base, "--rate-limit-rps", "-1"]))
