"""Hostile MAVLink peers on loopback against the vehicle link and the sitl_mock vehicle.

The vehicle is a PX4-flavoured mock sending from an ephemeral port to the link's ``udpin`` port,
as PX4 SITL does. The hostile peers are other sockets on the same machine:

* one that sends straight to the link's port: HEARTBEATs from system 42, positions from system
  99, and copies of the vehicle's own ids (the link hears only the vehicle's address);
* a router in front of the link that forwards the vehicle and lets other systems' messages
  through from the same address, as a MAVLink router serving several systems does (the link
  takes only the locked system and component);
* a process spraying datagrams from 2,000 source ports.

What is asserted is what the service would report and where it streams: position, mode, armed,
system and component ids never show a foreign message; setpoints keep reaching the real vehicle
(the mock counts them, and those addressed to another system) and nobody else. All but the
silent vehicle run on both backends (the MAVSDK one's ``udpin`` is a ``raw://`` connection over
the link's own socket); the MAVSDK backend's version of that one, over TCP, is in
``tests/service/test_mavsdk_link.py``. Every mock, link, socket and process a test starts is
stopped at teardown (also on failure); every wait is on a condition with a timeout; rates are
measured over fixed windows.
"""

from __future__ import annotations

import contextlib
import math
import select
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from service import links
from service.links import LINK_BACKENDS
from service.mavlink_link import VehicleUdp
from service.modes import mode_name
from service.vehicle_link import LinkConfig, VehicleLinkBase
from tests.helpers import free_udp_port, wait_for
from tests.service.conftest import AREA, FRAMES, HOME_AREA_M

HOSTILE_MODE = 5 << 16
"""PX4's ACRO: a mode the mock never enters by itself."""
HOSTILE_TEXT = "hostile statustext"
SPRAY_PORTS = 2_000
RATE_WINDOW_S = 3.0


def packet(system_id: int, component_id: int, build: Callable[[Any], Any]) -> bytes:
    """One MAVLink 2 packet from ``system_id``/``component_id``: ``build(encoder)`` makes it."""
    encoder = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    return build(encoder).pack(encoder)


def vehicle_heartbeat(system_id: int, component_id: int = 1) -> bytes:
    """A PX4 quadrotor's HEARTBEAT, armed, in ACRO."""
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    return packet(
        system_id,
        component_id,
        lambda e: e.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR,
            mavlink.MAV_AUTOPILOT_PX4,
            armed,
            HOSTILE_MODE,
            mavlink.MAV_STATE_ACTIVE,
        ),
    )


def hostile_telemetry(system_id: int, component_id: int = 1) -> list[bytes]:
    """Everything the link reads from a vehicle, far from the real one: at NED (5000, -3000,
    -900), 900 m up, in the air, an ACK for every command it might wait on, a STATUSTEXT."""
    return [
        packet(
            system_id,
            component_id,
            lambda e: e.local_position_ned_encode(0, 5000.0, -3000.0, -900.0, 0, 0, 0),
        ),
        packet(
            system_id,
            component_id,
            lambda e: e.global_position_int_encode(0, 0, 0, 1_000_000, 900_000, 0, 0, 0, 9000),
        ),
        packet(
            system_id,
            component_id,
            lambda e: e.extended_sys_state_encode(0, mavlink.MAV_LANDED_STATE_IN_AIR),
        ),
        packet(
            system_id,
            component_id,
            lambda e: e.ekf_status_report_encode(0xFFFF, 0, 0, 0, 0, 0),
        ),
        *(
            packet(
                system_id,
                component_id,
                lambda e, c=command: e.command_ack_encode(c, mavlink.MAV_RESULT_ACCEPTED),
            )
            for command in (
                mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                mavlink.MAV_CMD_DO_SET_MODE,
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            )
        ),
        packet(
            system_id,
            component_id,
            lambda e: e.statustext_encode(mavlink.MAV_SEVERITY_CRITICAL, HOSTILE_TEXT.encode()),
        ),
    ]


def check_the_vehicle_is_reported(link: VehicleLinkBase) -> None:
    """The link's state is the mock's (on the ground, disarmed, at home, system 1 component 1),
    never a foreign system's."""
    state = link.state()
    assert state.system_id == 1 and state.component_id == 1
    assert not state.armed
    assert state.mode != mode_name("px4", HOSTILE_MODE)
    assert state.position_m is not None and math.dist(state.position_m, HOME_AREA_M) < 1.0
    assert state.relative_alt_m is not None and abs(state.relative_alt_m) < 1.0
    assert not any(HOSTILE_TEXT in text for text in state.status_texts)


def setpoint_rate_hz(mock: Any, window_s: float = RATE_WINDOW_S) -> float:
    """Setpoints addressed to the mock per second, over a measurement window of ``window_s``."""
    before, started = mock.stats["setpoints_received"], time.monotonic()
    time.sleep(window_s)  # a measurement window, not a wait for a condition
    return (mock.stats["setpoints_received"] - before) / (time.monotonic() - started)


class HostileSocket:
    """A UDP socket on loopback that sends to the link's port and counts what it gets back."""

    def __init__(self, link_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.link = ("127.0.0.1", link_port)
        self.sent = 0
        self.received = 0

    def send(self, *packets: bytes) -> None:
        for data in packets:
            self.sock.sendto(data, self.link)
            self.sent += 1

    def drain(self) -> int:
        """Datagrams received so far (what the link sent to this socket)."""
        while True:
            try:
                self.sock.recv(65536)
            except OSError:
                return self.received
            self.received += 1

    def close(self) -> None:
        self.sock.close()


class Router:
    """A MAVLink router on loopback: the vehicle's datagrams go to the link and the link's back
    to the vehicle, from one socket; :meth:`inject` sends other systems' packets to the link
    through it, so that they come from the vehicle's address."""

    def __init__(self, link_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.link = ("127.0.0.1", link_port)
        self.vehicle: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="router", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not select.select([self.sock], [], [], 0.05)[0]:
                continue
            while True:
                try:
                    data, address = self.sock.recvfrom(65536)
                except OSError:
                    break
                with contextlib.suppress(OSError):
                    if address == self.link:
                        if self.vehicle is not None:
                            self.sock.sendto(data, self.vehicle)
                    else:
                        self.vehicle = address
                        self.sock.sendto(data, self.link)

    def inject(self, *packets: bytes) -> None:
        for data in packets:
            self.sock.sendto(data, self.link)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.sock.close()


@pytest.fixture
def closing() -> Iterator[Callable[[Any], Any]]:
    """``closing(thing)``: ``thing.close()`` at teardown, in reverse order; returns ``thing``."""
    things: list[Any] = []

    def _closing(thing: Any) -> Any:
        things.append(thing)
        return thing

    yield _closing
    for thing in reversed(things):
        thing.close()


@pytest.fixture(params=LINK_BACKENDS)
def backend(request: pytest.FixtureRequest) -> str:
    return request.param


def peer_of(link: Any) -> tuple[str, int] | None:
    """The one address the link's ``udpin`` transport talks to, on either backend."""
    if hasattr(link, "_session"):
        return link._session.udp.peer
    return link._conn.peer


def open_link(
    closing: Callable[[Any], Any], port: int, backend: str = "pymavlink", **options: Any
) -> Any:
    """A started link on ``backend`` listening on loopback ``port``, closed at teardown."""
    config = LinkConfig(f"udpin:127.0.0.1:{port}", area=AREA, frames=FRAMES, **options)
    link = closing(links.open_link(backend, config))
    link.start()
    return link


def streaming_link(start_mock: Callable[..., Any], closing: Callable[[Any], Any], **options: Any):
    """A PX4 mock sending to a link's ``udpin`` port (directly, or through a :class:`Router`
    with ``router=True``), the link up with a position and streaming a target; returns
    ``(link, mock, port, router)``."""
    use_router = options.pop("router", False)
    port = free_udp_port()
    router = closing(Router(port)) if use_router else None
    link = open_link(closing, port, **options)
    mock = start_mock("px4", listen=f"udpout:127.0.0.1:{router.port if router else port}")
    wait_for(lambda: (s := link.state()).link == "up" and s.position_m is not None, 20.0)
    link.set_target((30.0, 30.0, 10.0))
    wait_for(lambda: mock.stats["setpoints_received"] >= 5, 10.0, message="setpoints")
    return link, mock, port, router


def test_a_hostile_socket_gets_nothing_and_changes_nothing(start_mock, closing, backend):
    link, mock, port, _ = streaming_link(start_mock, closing, backend=backend)
    hostile = closing(HostileSocket(port))
    check_the_vehicle_is_reported(link)
    received_before = mock.stats["setpoints_received"]
    started = time.monotonic()
    while time.monotonic() - started < 2.0:  # 20 rounds of lies, each checked right after
        hostile.send(vehicle_heartbeat(42), *hostile_telemetry(99))
        # Copies of the vehicle's own ids, from another address.
        hostile.send(vehicle_heartbeat(1), *hostile_telemetry(1))
        wait_for(lambda: link.counters["foreign_datagrams"] >= hostile.sent, 5.0)
        check_the_vehicle_is_reported(link)
    assert link.counters["foreign_datagrams"] == hostile.sent
    assert link.counters["foreign_messages"] == 0  # dropped by address, never parsed
    # Setpoints went on to the real vehicle, at 10 Hz, and to nobody else.
    assert mock.stats["setpoints_received"] - received_before >= 12
    assert mock.stats["not_for_us"] == 0
    assert hostile.drain() == 0
    assert peer_of(link) == ("127.0.0.1", mock.port)


def test_other_systems_behind_the_vehicles_address_change_nothing(start_mock, closing, backend):
    link, mock, _, router = streaming_link(start_mock, closing, router=True, backend=backend)
    check_the_vehicle_is_reported(link)
    received_before = mock.stats["setpoints_received"]
    lies = [
        vehicle_heartbeat(42),  # another vehicle
        vehicle_heartbeat(1, 7),  # another component of the vehicle's system claiming to fly
        *hostile_telemetry(99),
        *hostile_telemetry(1, 7),
    ]
    started = time.monotonic()
    while time.monotonic() - started < 2.0:  # lies for 2 s, each round checked right after
        foreign_before = link.counters["foreign_messages"]
        router.inject(*lies)
        wait_for(lambda f=foreign_before: link.counters["foreign_messages"] >= f + len(lies), 5.0)
        check_the_vehicle_is_reported(link)
    assert link.counters["foreign_datagrams"] == 0  # all came from the vehicle's address
    if backend == "pymavlink":
        assert (link._target_sys, link._target_comp) == (1, 1)
    assert mock.stats["setpoints_received"] - received_before >= 12
    assert mock.stats["not_for_us"] == 0


def test_another_system_does_not_take_over_while_the_vehicle_is_silent(start_mock, closing):
    link, first, port, _ = streaming_link(
        start_mock, closing, heartbeat_timeout_s=1.0, reconnect_min_s=0.1, reconnect_max_s=0.2
    )
    hostile = closing(HostileSocket(port))
    first.stop()  # the vehicle falls silent; system 42 keeps calling
    reconnects = link.counters["reconnects"]

    def lie_until(condition: Callable[[], bool]) -> None:
        def step() -> bool:
            hostile.send(vehicle_heartbeat(42), *hostile_telemetry(42))
            return condition()

        wait_for(step, 10.0, interval_s=0.05)

    # The link is lost, its transport made anew (no peer): system 42 is parsed and refused.
    lie_until(lambda: link.counters["reconnects"] >= reconnects + 2)
    foreign = link.counters["foreign_messages"]
    lie_until(lambda: link.counters["foreign_messages"] >= foreign + 20)
    state = link.state()
    assert state.link == "link_lost" and state.system_id == 1 and not state.streaming
    assert state.mode != mode_name("px4", HOSTILE_MODE) and not state.armed
    assert hostile.drain() == 0  # nothing is sent before the vehicle's address is known

    # The vehicle comes back from another source port: found again, streamed to again.
    second = start_mock("px4", listen=f"udpout:127.0.0.1:{port}")
    assert second.port != first.port
    lie_until(lambda: second.stats["setpoints_received"] >= 5)
    check_the_vehicle_is_reported(link)
    assert peer_of(link) == ("127.0.0.1", second.port)
    assert second.stats["not_for_us"] == 0
    assert hostile.drain() == 0


SPRAY = r"""
import select, socket, sys, time
port, count, payload = int(sys.argv[1]), int(sys.argv[2]), bytes.fromhex(sys.argv[3])
socks = []
for _ in range(count):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    socks.append(s)
ports = len({s.getsockname()[1] for s in socks})
sent = rounds = 0
deadline = time.monotonic() + 60.0
while time.monotonic() < deadline:
    started = time.monotonic()
    for i, s in enumerate(socks):
        try:
            s.sendto(payload, ("127.0.0.1", port))
            sent += 1
        except OSError:
            pass
        if i % 200 == 199:
            time.sleep(0.002)
    rounds += 1
    if rounds == 1:
        print(f"ready {ports}", flush=True)
    if select.select([sys.stdin], [], [], max(0.0, 0.5 - (time.monotonic() - started)))[0]:
        break
received = 0
for s in socks:
    while True:
        try:
            s.recv(65536)
        except OSError:
            break
        received += 1
print(f"done {sent} {received}", flush=True)
"""
"""A spray: one datagram from each of ``count`` source ports every 0.5 s, until stdin says stop
(at most 60 s); prints ``ready PORTS`` after the first round and ``done SENT RECEIVED``."""


def read_line(process: subprocess.Popen, timeout_s: float) -> list[str]:
    """The next line ``process`` prints, split; AssertionError if none within ``timeout_s``."""
    assert process.stdout is not None
    if not select.select([process.stdout], [], [], timeout_s)[0]:
        raise AssertionError(f"no line from the spray within {timeout_s} s")
    return process.stdout.readline().split()


# A throughput bound under a spray from a helper process: beside the other timing tests only.
@pytest.mark.process
@pytest.mark.xdist_group("timing")
def test_a_spray_from_thousands_of_ports_neither_slows_the_stream_nor_grows_memory(
    start_mock, closing, backend
):
    link, mock, port, _ = streaming_link(start_mock, closing, backend=backend)
    baseline_hz = setpoint_rate_hz(mock)
    spray = subprocess.Popen(
        [sys.executable, "-c", SPRAY, str(port), str(SPRAY_PORTS), vehicle_heartbeat(42).hex()],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert spray.stdin is not None
        assert read_line(spray, 30.0) == ["ready", str(SPRAY_PORTS)]
        wait_for(lambda: link.counters["foreign_datagrams"] >= SPRAY_PORTS, 10.0)
        spray_hz = setpoint_rate_hz(mock)
        spray.stdin.write("stop\n")
        spray.stdin.flush()
        _, sent, received = read_line(spray, 10.0)
        assert spray.wait(10.0) == 0
    finally:
        if spray.poll() is None:
            spray.kill()
            spray.wait(10.0)
    print(
        f"SPRAY {backend}: setpoint rate {baseline_hz:.2f} Hz without, {spray_hz:.2f} Hz during "
        "a spray "
        f"from {SPRAY_PORTS} ports ({sent} datagrams sent, "
        f"{link.counters['foreign_datagrams']} dropped by the link)"
    )
    assert spray_hz >= 0.8 * baseline_hz
    assert int(received) == 0  # the link never sent a datagram to a sprayer
    check_the_vehicle_is_reported(link)
    # Nothing is kept per sender.
    if backend == "mavsdk":
        assert link._session.udp._heartbeat_sources == {}  # forgotten once the peer is chosen
        return
    conn = link._conn
    assert isinstance(conn, VehicleUdp)
    # pymavlink's list of receivers is empty; its per-system state has only the vehicle's (and
    # its own default's).
    assert conn.clients == set() and conn.clients_last_alive == {}
    assert set(conn.sysid_state) <= {0, 1}
    assert set(conn.last_seq) <= {(1, 1)}


def test_no_other_local_socket_can_bind_the_links_port():
    port = free_udp_port()
    transport = VehicleUdp(f"127.0.0.1:{port}", 255, 191)
    try:
        thief = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        thief.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        with thief, pytest.raises(OSError):
            thief.bind(("127.0.0.1", port))  # pymavlink's own mavudp would allow it
    finally:
        transport.close()
