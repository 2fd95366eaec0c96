"""MAVLink 2 signing failures are visible and the vehicle is never commanded.

A PX4-flavoured mock signs with one key, ``tupa serve --arm-and-takeoff`` with another: every
message of the vehicle fails the service's signature check, so the link never comes up,
``/readyz`` answers 503 with a reason naming signing, and nothing reaches the vehicle as a
command or a setpoint (the mock's own counters), even with reports coming in and
``--arm-and-takeoff`` given. With the same key
on both sides (the control) the service is ready. A vehicle that signs while the service has no
key is named too: its setpoints would be ignored.
"""

from __future__ import annotations

import secrets

import pytest

from tests.faults.harness import PX4_FAST, USERS_EAST, Harness
from tests.helpers import wait_for

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("same_key", [False, True], ids=["wrong-key", "same-key"])
def test_a_vehicle_that_fails_signing_is_named_in_readyz_and_never_commanded(
    harness: Harness, same_key: bool
) -> None:
    vehicle_key = secrets.token_hex(32)
    service_key = vehicle_key if same_key else secrets.token_hex(32)
    mock = harness.mock(*PX4_FAST, "--signing-key", vehicle_key, "--listen", "tcp:127.0.0.1:0")
    api = harness.placing_service(
        f"tcp:127.0.0.1:{mock.port}",
        env={"TUPA_MAVLINK_SIGNING_KEY": service_key},
    )
    if same_key:
        api.wait_ready()
        assert mock.stats()["signing_rejected"] == 0
        return

    readyz = wait_for(
        lambda: (
            (r := api.readyz()).status_code == 503
            and any("signing" in reason for reason in r.json()["reasons"])
            and r
        ),
        10.0,
        0.1,
        "/readyz naming signing",
    )
    print("readyz:", readyz.json())
    assert api.vehicle()["link"] == "connecting"
    response = api.report(USERS_EAST)
    assert response.status_code == 200 and response.json()["target"] is None  # decision waits
    # The service keeps talking (its HEARTBEAT, which the vehicle accepts unsigned-or-not, as
    # PX4 and ArduPilot do) for a few seconds, and never sends a command or a setpoint.
    wait_for(lambda: mock.stats()["gcs_heartbeats"] >= 3, 10.0, 0.1, "the service's heartbeats")
    stats = mock.stats()
    assert stats["setpoints_received"] == 0 and stats["commands"] == 0
    state = mock.state()
    assert state["armed"] is False and state["landed"] is True
    assert api.readyz().status_code == 503


def test_a_signing_vehicle_without_a_key_on_our_side_is_named_in_readyz(harness: Harness) -> None:
    mock = harness.mock(
        *PX4_FAST, "--signing-key", secrets.token_hex(32), "--listen", "tcp:127.0.0.1:0"
    )
    api = harness.placing_service(
        f"tcp:127.0.0.1:{mock.port}",
        arm_and_takeoff=False,
    )
    readyz = wait_for(
        lambda: (
            (r := api.readyz()).status_code == 503
            and any("no signing key" in reason for reason in r.json()["reasons"])
            and r
        ),
        10.0,
        0.1,
        "/readyz naming the missing key",
    )
    print("readyz:", readyz.json())
    assert api.report(USERS_EAST).status_code == 200
    # What the service sends unsigned is refused by the vehicle, which stays where it is.
    wait_for(lambda: mock.stats()["signing_rejected"] >= 3, 10.0, 0.1, "rejected at the mock")
    state = mock.state()
    assert state["armed"] is False and state["target_ned_m"] is None
