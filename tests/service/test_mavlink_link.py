"""What only the pymavlink backend of the vehicle link (service.mavlink_link) does, against the
sitl_mock autopilot on loopback: MAVLink 2 signing, the REQUEST_DATA_STREAM fallback, addressing
the vehicle by its own ids, taking in only the vehicle's messages, the warning for an unsigned link
others can reach, and what it sends on the wire. The contract both backends keep is in
``test_link_contract.py``; hostile peers on a live link are in ``tests/security``.

Every mock and link a test starts is stopped at teardown (also on failure); every wait is on a
condition with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import logging
import math
import time

import pytest

from service import mavlink_link
from service.mavlink_link import POSITION_ONLY_TYPE_MASK, MavlinkLink, unsigned_exposure
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
        (1, dialect.MAV_TYPE_GIMBAL, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA),  # a gimbal, likewise
        (1, dialect.MAV_TYPE_ADSB, dialect.MAV_AUTOPILOT_PX4),  # an ADS-B receiver
    ):
        encoder = dialect.MAVLink(None, srcSystem=source, srcComponent=190)
        message = encoder.heartbeat_encode(kind, autopilot, 0, 0, dialect.MAV_STATE_ACTIVE)
        message.pack(encoder)  # sets the header the link reads
        link._handle(message)
    state = link.state()
    assert state.link == "connecting" and state.flavour is None and state.mode is None
    assert link._target_sys == 1  # still addressing the default, not a ground station
    assert state.system_id is None and state.component_id is None  # nothing locked


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


def _packet(dialect, system_id, component_id, build):
    """A decoded message from ``system_id``/``component_id``, as the link's poll hands it over."""
    encoder = dialect.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    data = build(encoder).pack(encoder)
    return dialect.MAVLink(None).parse_char(data)


def test_only_the_locked_vehicle_changes_the_state():
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:1", area=AREA, frames=FRAMES))  # not started
    armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED

    def heartbeat(system_id, component_id, base_mode, custom_mode):
        return _packet(
            dialect,
            system_id,
            component_id,
            lambda e: e.heartbeat_encode(
                dialect.MAV_TYPE_QUADROTOR,
                dialect.MAV_AUTOPILOT_PX4,
                base_mode,
                custom_mode,
                dialect.MAV_STATE_STANDBY,
            ),
        )

    def position(system_id, component_id, north_m):
        return _packet(
            dialect,
            system_id,
            component_id,
            lambda e: e.local_position_ned_encode(0, north_m, 0.0, 0.0, 0, 0, 0),
        )

    # Before any vehicle HEARTBEAT nothing is the vehicle's, not even a position.
    link._handle(position(1, 1, 5.0))
    assert link.state().position_m is None
    link._handle(heartbeat(1, 1, 0, 4 << 16 | 3 << 24))  # the vehicle: disarmed, AUTO.LOITER
    link._handle(position(1, 1, 5.0))
    locked = link.state()
    assert (locked.system_id, locked.component_id) == (1, 1) and locked.link == "up"
    for lie in (
        heartbeat(42, 1, armed, 5 << 16),  # another vehicle, armed in ACRO
        heartbeat(1, 7, armed, 5 << 16),  # another component of its system
        position(99, 1, -3000.0),
        position(1, 7, -3000.0),
        _packet(dialect, 99, 1, lambda e: e.statustext_encode(2, b"hostile")),
    ):
        link._handle(lie)
    state = link.state()
    assert (state.mode, state.armed, state.position_m) == (locked.mode, False, locked.position_m)
    assert (state.system_id, state.component_id) == (1, 1)
    assert (link._target_sys, link._target_comp) == (1, 1)
    assert state.status_texts == ()
    assert link.counters["foreign_messages"] == 5


@pytest.mark.parametrize(
    ("url", "exposed"),
    [
        ("tcp:127.0.0.1:5760", None),
        ("udpin:127.0.0.1:14540", None),
        ("udpout:localhost:14550", None),
        ("tcp:[::1]:5760", None),
        ("tcpout://127.0.0.2:5760", None),
        ("udpin:0.0.0.0:14540", "listens on every network interface"),
        ("udpin://0.0.0.0:14540", "listens on every network interface"),
        ("udpin:192.168.1.5:14540", "listens on 192.168.1.5"),
        ("tcp:10.0.0.2:5760", "talks to 10.0.0.2"),
        ("udpout:vehicle.lan:14550", "talks to vehicle.lan"),
        ("/dev/ttyUSB0,57600", "is a serial link"),
        ("serial:///dev/ttyACM0:921600", "is a serial link"),
        ("COM3", "is a serial link"),
    ],
)
def test_who_else_can_reach_a_link(url, exposed):
    phrase = unsigned_exposure(url)
    assert phrase == exposed if exposed is None else phrase.startswith(exposed)


def test_an_unsigned_link_others_can_reach_is_warned_about_at_start(monkeypatch, caplog):
    caplog.set_level(logging.WARNING, logger="service.mavlink_link")
    assert not mavlink_link.warn_if_unsigned("udpin:0.0.0.0:14540", True, "pymavlink")
    assert not mavlink_link.warn_if_unsigned("tcp:127.0.0.1:5760", False, "pymavlink")
    assert caplog.records == []
    assert mavlink_link.warn_if_unsigned("udpin:0.0.0.0:14540", False, "mavsdk")
    (record,) = caplog.records
    assert "UNSIGNED" in record.getMessage() and "cannot sign" in record.getMessage()
    caplog.clear()
    # start() asks (a loopback URL made to look exposed: nothing leaves this machine).
    monkeypatch.setattr(mavlink_link, "unsigned_exposure", lambda url: "talks to 192.0.2.1")
    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:1", area=AREA, frames=FRAMES, reconnect_min_s=1))
    try:
        link.start()
    finally:
        link.close()
    assert any("TUPA_MAVLINK_SIGNING_KEY" in r.getMessage() for r in caplog.records)
