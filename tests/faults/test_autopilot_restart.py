"""The autopilot dies mid-flight and comes back on the same port.

``tupa serve`` (pymavlink link, TCP) flies a PX4-flavoured mock in OFFBOARD; the mock process is
SIGKILLed while the vehicle streams towards its target. The service must report ``link_lost``
within its 3 s heartbeat timeout (plus the polling margin), stop streaming, keep reconnecting,
and, once a new mock listens on the same port, see the link up again within 5 s of the mock's
return. The new mock starts on the ground, disarmed and out of OFFBOARD: the vehicle changed
mode while the link was lost, so it is the autopilot's (``service.control``): nothing streams
and no mode is asked for until an operator hands it back (``PUT /v1/vehicle/control``); then
the next decision streams at once. Measured at the new mock (its counters). Flying again would
need a new takeoff, which the service does not do by itself.
"""

from __future__ import annotations

import time

import pytest

from tests.faults.harness import (
    PX4_FAST,
    USERS_EAST,
    Harness,
    report_recovery,
    target_xyz,
    wait_airborne,
)
from tests.helpers import wait_for

pytestmark = pytest.mark.slow

HEARTBEAT_TIMEOUT_S = 3.0
POLL_MARGIN_S = 1.0
RESUME_WITHIN_S = 5.0


def test_autopilot_killed_mid_flight_then_restarted(harness: Harness) -> None:
    mock = harness.mock(*PX4_FAST, "--listen", "tcp:127.0.0.1:0")
    port = mock.port
    api = harness.placing_service(
        f"tcp:127.0.0.1:{port}",
    )
    api.wait_ready()
    wait_airborne(mock)
    decision = api.report(USERS_EAST).json()
    assert decision["source"] == "policy"
    target = target_xyz(decision)
    wait_for(lambda: mock.state()["mode"] == "OFFBOARD", 15.0, 0.1, "OFFBOARD")
    received = mock.stats()["setpoints_received"]
    wait_for(lambda: mock.stats()["setpoints_received"] >= received + 5, 3.0, 0.05, "setpoints")

    mock.kill()  # mid-flight: the vehicle is on its way to the target
    killed = time.monotonic()
    vehicle = wait_for(
        lambda: (v := api.vehicle())["link"] == "link_lost" and v,
        HEARTBEAT_TIMEOUT_S + POLL_MARGIN_S + 1.0,
        0.05,
        "link_lost",
    )
    lost_after_s = time.monotonic() - killed
    report_recovery("autopilot killed -> link_lost", lost_after_s)
    assert lost_after_s <= HEARTBEAT_TIMEOUT_S + POLL_MARGIN_S
    assert vehicle["streaming"] is False
    readyz = api.readyz()
    assert readyz.status_code == 503 and "link_lost" in " ".join(readyz.json()["reasons"])

    # Nothing streams into the void: the service's own counter stands still for a second
    # of the service's time (its heartbeat age grows past +1 s).
    sent = api.metric("tupa_setpoints_sent_total")
    age = api.vehicle()["heartbeat_age_s"]
    wait_for(lambda: api.vehicle()["heartbeat_age_s"] > age + 1.0, 5.0, 0.1, "a second")
    assert api.metric("tupa_setpoints_sent_total") == sent
    assert api.setpoint()["target"] is not None

    again = harness.mock(*PX4_FAST, "--listen", f"tcp:127.0.0.1:{port}")
    back = time.monotonic()
    # It came back rebooted, on the ground and out of OFFBOARD: the autopilot's, not ours.
    vehicle = wait_for(
        lambda: (v := api.vehicle())["link"] == "up" and v["control"]["holder"] != "service" and v,
        RESUME_WITHIN_S + 2.0,
        0.05,
        "link up, and the service letting go",
    )
    report_recovery("autopilot back -> link up, left to an operator", time.monotonic() - back)
    assert vehicle["control"]["holder"] == "autopilot"
    assert "while the link was lost" in vehicle["control"]["reason"]
    assert vehicle["streaming"] is False
    # The service still hears the autopilot: a HEARTBEAT arrives after `since` (its age is then
    # shorter than the time since `since`, read before the request). Comparing the age with an
    # earlier reading instead raced: read just after the HEARTBEAT that brought the link up, that
    # age is a few ms, and a poll every 50 ms rarely lands that close after the next one.
    since = time.monotonic()

    def heard_since() -> bool:
        asked = time.monotonic()
        return api.vehicle()["heartbeat_age_s"] < asked - since

    wait_for(heard_since, 3.0, 0.05, "a HEARTBEAT")
    assert again.stats()["setpoints_received"] == 0
    assert again.stats().get("mode_commands_OFFBOARD", 0) == 0

    # An operator hands it back; the next decision streams again, steadily (>= 5 Hz).
    handed = time.monotonic()
    answer = api.client.put("/v1/vehicle/control", json={"holder": "service"})
    assert answer.status_code == 200, answer.text
    assert api.report(USERS_EAST).json()["source"] == "policy"
    wait_for(
        lambda: again.stats()["setpoints_received"] >= 1,
        RESUME_WITHIN_S,
        0.05,
        "setpoints at the restarted mock",
    )
    report_recovery("hand-back -> setpoints at the vehicle", time.monotonic() - handed)
    assert target_xyz(api.setpoint()) == pytest.approx(target)
    count = again.stats()["setpoints_received"]
    started = time.monotonic()
    wait_for(lambda: again.stats()["setpoints_received"] >= count + 10, 2.0, 0.05, "10 more")
    assert 10 / (time.monotonic() - started) >= 5.0
    assert api.metric("tupa_link_reconnects_total") >= 1
    assert again.state()["armed"] is False  # the service did not re-arm it by itself
