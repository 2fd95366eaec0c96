"""The service dies (SIGKILL) and is restarted with the same ``--state-file``.

While it is gone, the vehicle's own OFFBOARD failsafe must hold it (PX4: AUTO.LOITER about
COM_OF_LOSS_T = 1 s after the last setpoint). After the restart the service shows its persisted
target (source ``restored``) and serves its persisted policy (switched over HTTP before the
kill, so it differs from ``--policy``), but moves nothing: no setpoint reaches the vehicle, the
mode stays AUTO.LOITER and the vehicle stays within a metre of where it held, until a fresh
report leads to a decision, which then flies it again. A second test starts the service with
``--arm-and-takeoff`` and a persisted target next to a vehicle on the ground: it must not arm
until a fresh report.

The mocks' ground-station failsafe is switched off here (``--gcs-failsafe-action none``): it
watches the ground station's HEARTBEAT, and the service is the only MAVLink peer in these tests.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest

from tests.faults.harness import (
    PX4_FAST,
    USERS_EAST,
    USERS_NORTH,
    Harness,
    ned_to_area,
    report_recovery,
    target_xyz,
    wait_airborne,
    wait_at,
)
from tests.helpers import wait_for

pytestmark = pytest.mark.slow

OFFBOARD_TIMEOUT_S = 1.0
FAILSAFE_MARGIN_S = 1.5
NO_GCS_FAILSAFE = ("--gcs-failsafe-action", "none")


def quiet_for_heartbeats(mock, n: int = 3) -> None:
    """Wait until the mock has had ``n`` more HEARTBEATs from the service (about ``n`` seconds of
    a connected, alive service): the window in which it must do nothing by itself."""
    start = mock.stats()["gcs_heartbeats"]
    wait_for(lambda: mock.stats()["gcs_heartbeats"] >= start + n, n + 5.0, 0.1, "heartbeats")


def test_service_killed_failsafe_holds_and_restart_moves_nothing(
    harness: Harness, tmp_path: Path
) -> None:
    state_file = tmp_path / "state.json"
    mock = harness.mock(*PX4_FAST, *NO_GCS_FAILSAFE, "--listen", "tcp:127.0.0.1:0")
    args = (f"tcp:127.0.0.1:{mock.port}", "--state-file", str(state_file))
    api = harness.placing_service(*args)
    api.wait_ready()
    wait_airborne(mock)
    assert api.client.put("/v1/policy", json={"policy": "min-distance"}).status_code == 200
    decision = api.report(USERS_EAST).json()
    assert decision["policy"] == "min-distance"
    target = target_xyz(decision)
    wait_at(mock, target)
    wait_for(lambda: mock.state()["mode"] == "OFFBOARD", 5.0, 0.1, "OFFBOARD")
    saved = json.loads(state_file.read_text())
    assert saved["policy"] == "min-distance"

    api.kill()
    killed = time.monotonic()
    wait_for(
        lambda: mock.state()["mode"] == "AUTO.LOITER",
        OFFBOARD_TIMEOUT_S + FAILSAFE_MARGIN_S + 1.0,
        0.05,
        "the OFFBOARD failsafe (AUTO.LOITER)",
    )
    failsafe_after_s = time.monotonic() - killed
    report_recovery("service killed -> vehicle failsafe hold", failsafe_after_s)
    assert failsafe_after_s <= OFFBOARD_TIMEOUT_S + FAILSAFE_MARGIN_S
    assert mock.stats()["failsafe_offboard"] >= 1
    held = ned_to_area(mock.state()["position_ned_m"])

    restarted = time.monotonic()
    api = harness.placing_service(*args)
    api.wait_ready()
    report_recovery("service restart -> ready (start to /readyz 200)", time.monotonic() - restarted)
    setpoint = api.setpoint()
    assert setpoint["source"] == "restored"
    assert target_xyz(setpoint) == pytest.approx(target)
    assert api.policy()["name"] == "min-distance"

    received = mock.stats()["setpoints_received"]
    quiet_for_heartbeats(mock)
    state = mock.state()
    assert state["mode"] == "AUTO.LOITER"
    assert math.dist(ned_to_area(state["position_ned_m"]), held) < 1.0
    assert mock.stats()["setpoints_received"] == received
    vehicle = api.vehicle()
    assert vehicle["link"] == "up" and vehicle["streaming"] is False

    # A fresh report: a decision by the restored policy, streamed, and the vehicle flies again.
    reported = time.monotonic()
    decision = api.report(USERS_NORTH).json()
    assert decision["source"] == "policy" and decision["policy"] == "min-distance"
    new_target = target_xyz(decision)
    wait_for(lambda: mock.state()["mode"] == "OFFBOARD", 10.0, 0.05, "OFFBOARD again")
    report_recovery("fresh report after restart -> OFFBOARD again", time.monotonic() - reported)
    wait_at(mock, new_target)


def test_restart_with_arm_and_takeoff_does_not_arm_until_a_fresh_report(
    harness: Harness, tmp_path: Path
) -> None:
    state_file = tmp_path / "state.json"
    state_file.write_text(
        json.dumps(
            {
                "format": "tupa-service-state/1",
                "policy": "min-distance",
                "decision": {
                    "target_m": [260.0, 260.0, 25.0],
                    "source": "policy",
                    "policy": "min-distance",
                    "decided_at": time.time() - 60,
                },
            }
        )
    )
    mock = harness.mock(*PX4_FAST, *NO_GCS_FAILSAFE, "--listen", "tcp:127.0.0.1:0")
    api = harness.placing_service(
        f"tcp:127.0.0.1:{mock.port}",
        "--state-file",
        str(state_file),
    )
    api.wait_ready()
    assert api.setpoint()["source"] == "restored"
    assert api.policy()["name"] == "min-distance"
    quiet_for_heartbeats(mock)
    state = mock.state()
    assert state["armed"] is False and state["landed"] is True
    assert mock.stats()["setpoints_received"] == 0

    decision = api.report(USERS_EAST).json()
    assert decision["source"] == "policy"
    wait_airborne(mock)  # the deferred arm-and-takeoff, now that a decision was made
    wait_at(mock, target_xyz(decision))


def test_unloadable_persisted_policy_keeps_the_configured_one(
    harness: Harness, tmp_path: Path
) -> None:
    state_file = tmp_path / "state.json"
    state_file.write_text(
        json.dumps(
            {
                "format": "tupa-service-state/1",
                "policy": str(tmp_path / "gone.zip"),
                "decision": None,
            }
        )
    )
    mock = harness.mock(*PX4_FAST, "--listen", "tcp:127.0.0.1:0")
    api = harness.service(
        "--mavlink",
        f"tcp:127.0.0.1:{mock.port}",
        "--policy",
        "load-weighted",
        "--state-file",
        str(state_file),
    )
    api.wait_ready()
    assert api.policy()["name"] == "load-weighted"
    assert api.setpoint()["source"] == "none"
    api.proc.wait_for_line(r"cannot restore the policy .*gone\.zip.*keeping the configured", 5.0)
