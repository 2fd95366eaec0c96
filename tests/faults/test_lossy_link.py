"""A lossy, delaying MAVLink path: the vehicle still gets where the service sends it.

``tupa serve --mavlink udpout:...`` talks to a PX4-flavoured mock (``--listen udp:...``) through
:class:`~tests.faults.udp_proxy.UdpProxy`, which drops 10 % or 30 % of the datagrams in each
direction and delays the rest by 0-30 ms (so some also arrive out of order). Arming, takeoff,
OFFBOARD and two placements must still succeed (commands are retried until acknowledged; a report
that arrives while the service has declared the link lost, after 3 s without a HEARTBEAT, which
happens now and then at these rates on a loaded machine, is decided once the link is back), and
the setpoint rate measured at the mock during the second flight must stay above PX4's 2 Hz
offboard minimum at 10 % loss (about 9 Hz expected of the 10 Hz stream).

While the link is declared lost nothing streams, so PX4's offboard-loss failsafe may hold the
vehicle (AUTO.LOITER); the service then leaves it to an operator (``service.control``). The test
plays that operator: it hands the vehicle back (``PUT /v1/vehicle/control``) and posts the
report again, and counts how often it had to.
"""

from __future__ import annotations

import time
from typing import Any

import pytest

from tests.faults.harness import (
    PX4_FAST,
    USERS_EAST,
    USERS_NORTH,
    Api,
    Harness,
    MockProcess,
    report_recovery,
    target_xyz,
    wait_airborne,
    wait_at,
)
from tests.helpers import wait_for

pytestmark = pytest.mark.slow

JITTER_S = 0.03
PX4_MIN_RATE_HZ = 2.0


def fly_to(
    api: Api, mock: MockProcess, users: list[dict[str, Any]], timeout_s: float = 40.0
) -> tuple[tuple[float, float, float], int]:
    """Place for ``users`` and wait until the vehicle is there; when a link flap left the vehicle
    to PX4's offboard-loss hold (before or after the report), hand it back and place again, as
    an operator would. Returns the target and the number of hand-backs."""
    deadline = time.monotonic() + timeout_s
    target, handbacks, place = None, 0, True
    while True:
        try:
            if place:
                placed = target_xyz(api.place(users, timeout_s=_left(deadline, 3.0)))
                if target is not None:  # placed again after a hand-back: the same target
                    assert placed == pytest.approx(target)
                target, place = placed, False
            wait_at(mock, target, timeout_s=_left(deadline, 2.0))
            return target, handbacks
        except AssertionError:
            if time.monotonic() >= deadline:
                raise
        if _hand_back_if_left(api):
            handbacks += 1
            place = True


def _left(deadline: float, most_s: float) -> float:
    return min(most_s, max(0.1, deadline - time.monotonic()))


def _hand_back_if_left(api: Api) -> bool:
    """Hand the vehicle back when a link flap left it to the autopilot (and only then); True
    when it was handed back."""
    control = api.vehicle()["control"]
    if control["holder"] == "service" or api.vehicle()["link"] != "up":
        return False
    assert control["holder"] == "autopilot", control
    # The flap itself, or PX4's offboard failsafe after it (the stream stops while the link is
    # lost; when the HEARTBEAT that brings it back still shows OFFBOARD, the failsafe's mode
    # change is seen after the loss, named by the failsafe's own text).
    reason = control["reason"]
    assert "while the link was lost" in reason or "no offboard signal" in reason, control
    return api.client.put("/v1/vehicle/control", json={"holder": "service"}).is_success


@pytest.mark.parametrize("loss", [0.1, 0.3])
def test_vehicle_reaches_its_targets_through_a_lossy_jittery_link(
    harness: Harness, loss: float
) -> None:
    # PX4's own data-link loss timeout (COM_DL_LOSS_T, 10 s by default) rather than the mock's
    # 5 s: at 30 % loss five 1 Hz HEARTBEATs in a row are lost now and then, and the vehicle's
    # return that follows (the service's to leave alone) is another test's subject
    # (tests/service/test_handback.py), not this one's.
    mock = harness.mock(*PX4_FAST, "--gcs-failsafe-s", "10", "--listen", "udp:127.0.0.1:0")
    proxy = harness.proxy(mock.port, loss, JITTER_S, seed=int(loss * 100))
    api = harness.placing_service(
        f"udpout:127.0.0.1:{proxy.port}",
    )
    api.wait_ready(45.0)
    wait_airborne(mock, timeout_s=60.0)

    first, handbacks = fly_to(api, mock, USERS_EAST)
    wait_for(lambda: mock.state()["mode"] == "OFFBOARD", 5.0, 0.1, "OFFBOARD at the first target")

    before = mock.stats()["setpoints_received"]
    started = time.monotonic()
    second, more = fly_to(api, mock, USERS_NORTH)
    assert second != first
    handbacks += more
    elapsed_s = time.monotonic() - started
    rate_hz = (mock.stats()["setpoints_received"] - before) / elapsed_s
    report_recovery(
        f"lossy link {loss:.0%}: flight to the second target",
        elapsed_s,
        f"(setpoint rate at the mock {rate_hz:.1f} Hz; hand-backs after a link flap "
        f"{handbacks}; proxy {dict(proxy.counters)})",
    )
    assert proxy.counters["dropped_up"] > 0 and proxy.counters["dropped_down"] > 0
    if loss <= 0.1:
        assert rate_hz > PX4_MIN_RATE_HZ

    def offboard_again() -> dict[str, Any] | None:
        """In OFFBOARD at the target; a flap after the arrival left it to PX4's hold: the
        operator hands it back and the service places it again."""
        if (s := mock.state())["mode"] == "OFFBOARD":
            return s
        if _hand_back_if_left(api):
            fly_to(api, mock, USERS_NORTH)
        return None

    state = wait_for(offboard_again, 30.0, 0.1, "OFFBOARD")
    assert state["armed"]
    assert mock.stats()["setpoints_rejected_invalid"] == 0
