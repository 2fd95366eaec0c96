"""What only the pymavlink backend of the vehicle link (service.mavlink_link) does, against the
sitl_mock autopilot on loopback: MAVLink 2 signing, the REQUEST_DATA_STREAM fallback, addressing
the vehicle by its own ids, and what it sends on the wire. The contract both backends keep is in
``test_link_contract.py``.

Every mock and link a test starts is stopped at teardown (also on failure); every wait is on a
condition with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import math
import time

import pytest

from service.mavlink_link import POSITION_ONLY_TYPE_MASK, MavlinkLink
from service.vehicle_link import LinkConfig, signing_key_from_passphrase
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA, FAST_VEHICLE, FRAMES, HOME_AREA_M


def test_setpoints_carry_the_position_only_type_mask_built_from_pymavlinks_flags():
    assert POSITION_ONLY_TYPE_MASK == 3576  # x, y, z used; velocity, acceleration, yaw ignored


def test_signing_with_the_right_key_works_and_a_wrong_key_moves_nothing(start_mock, open_link):
    key = signing_key_from_passphrase("tupa")
    good = start_mock("px4", signing_key=key)
    link = open_link(tcp_url(good), signing_key=key)
    wait_for(lambda: link.state().position_m is not None, 5.0, message="signed telemetry")
    assert good.stats["signing_rejected"] == 0

    bad = start_mock("px4", signing_key=key)
    intruder = open_link(tcp_url(bad), signing_key=signing_key_from_passphrase("wrong"))
    future = intruder.arm_and_takeoff(timeout_s=1.5)
    intruder.set_target((30.0, 30.0, 10.0))
    # The link drops the vehicle's (differently signed) messages, so it never sees the vehicle
    # and sends it nothing but its own HEARTBEAT.
    wait_for(lambda: intruder.counters["bad_data"] >= 5, 5.0, message="rejected telemetry")
    assert isinstance(future.exception(timeout=5.0), TimeoutError)
    assert intruder.state().link == "connecting"
    assert intruder.counters["setpoints_sent"] == 0
    state = bad.state()
    assert not state.armed and state.landed
    assert bad.stats["setpoints_received"] == 0
    assert bad.stats["commands"] == 0


@pytest.mark.parametrize("refuses_intervals", [False, True])
def test_ardupilot_without_set_message_interval_gets_request_data_stream(
    start_mock, open_link, monkeypatch, refuses_intervals
):
    """An ArduPilot that answers SET_MESSAGE_INTERVAL with UNSUPPORTED (older firmware, or a
    router that filters it) still streams positions after the link's REQUEST_DATA_STREAM
    fallback; one that honours it never gets the fallback.

    sitl_mock has no option for such a vehicle, so the test refuses the command on this mock
    instance only (its protocol's handler for SET_MESSAGE_INTERVAL).
    """
    from sitl_mock.flavours import MavResult

    mock = start_mock("ardupilot")
    if refuses_intervals:
        monkeypatch.setattr(
            mock.protocol,
            "_set_message_interval",
            lambda _link, _message_id, _interval_us: (MavResult.UNSUPPORTED, "old firmware"),
        )
    link = open_link(tcp_url(mock))
    wait_for(lambda: link.state().link == "up", 5.0, message="link up")
    up = time.monotonic()
    state = wait_for(
        lambda: (s := link.state()).position_m is not None and s, 8.0, message="positions"
    )
    assert math.dist(state.position_m, HOME_AREA_M) < 0.1
    assert state.relative_alt_m == pytest.approx(0.0, abs=0.01)
    assert link._fallback_streams_sent is refuses_intervals
    if refuses_intervals:
        assert mock.stats["commands_unsupported"] >= 3
        # The fallback goes out once SET_MESSAGE_INTERVAL has had 1.5 s to work.
        assert time.monotonic() - up >= 1.4
    else:
        assert mock.stats["commands_unsupported"] == 0


def test_heartbeats_of_other_ground_stations_and_companions_are_not_the_vehicle():
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:1", area=AREA, frames=FRAMES))  # not started
    for source, kind, autopilot in (
        (255, dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID),  # a ground station
        (1, dialect.MAV_TYPE_ONBOARD_CONTROLLER, dialect.MAV_AUTOPILOT_INVALID),  # a companion
        (7, dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA),  # a GCS claiming APM
    ):
        encoder = dialect.MAVLink(None, srcSystem=source, srcComponent=190)
        message = encoder.heartbeat_encode(kind, autopilot, 0, 0, dialect.MAV_STATE_ACTIVE)
        message.pack(encoder)  # sets the header the link reads
        link._handle(message)
    state = link.state()
    assert state.link == "connecting" and state.flavour is None and state.mode is None
    assert link._target_sys == 1  # still addressing the default, not a ground station


@pytest.mark.slow
@pytest.mark.parametrize(("system_id", "component_id"), [(42, 1), (42, 7)])
def test_a_vehicle_with_other_ids_is_addressed_by_them(open_link, system_id, component_id):
    mock = MockAutopilot(
        "tcp:127.0.0.1:0",
        "ardupilot",
        VehicleConfig(ready_delay_s=0.3, **FAST_VEHICLE),
        system_id=system_id,
        component_id=component_id,
    ).start()
    try:
        link = open_link(tcp_url(mock))
        link.arm_and_takeoff().result(timeout=30.0)
        link.set_target((14.0, 24.0, 8.0))
        wait_for(lambda: mock.stats["setpoints_accepted"] > 5, 10.0, message="setpoints taken")
        assert mock.stats["not_for_us"] == 0
        assert (link._target_sys, link._target_comp) == (system_id, component_id)
    finally:
        mock.stop()
