"""A fleet of mocks: several vehicles in one process, one port and one system id each.

Driven with raw pymavlink as a ground station drives several SITL instances; ``tupa sitl-mock
--vehicles N`` as a real process on free ports; and its argument errors.
"""

from __future__ import annotations

import argparse
import math
import re
import select
import signal
import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.cli import register
from sitl_mock.config import VehicleConfig
from sitl_mock.fleet import MockFleet, fleet_listens
from sitl_mock.geo import global_to_ned
from sitl_mock.server import MockAutopilot
from tests.sitl_mock.helpers import MavClient

REPO_ROOT = Path(__file__).resolve().parents[2]
GUIDED = 4


@pytest.fixture
def start_fleet() -> Iterator[Callable[..., MockFleet]]:
    """Factory: ``start_fleet(count, flavour, listen=..., **VehicleConfig fields)``; every fleet
    is stopped at teardown, also on failure."""
    fleets: list[MockFleet] = []

    def _start(
        count: int, flavour: str, listen: Any = "tcp:127.0.0.1:0", **config: Any
    ) -> MockFleet:
        config.setdefault("ready_delay_s", 0.3)
        fleet = MockFleet(count, listen, flavour, VehicleConfig(**config))
        fleets.append(fleet)
        return fleet.start()

    yield _start
    for fleet in fleets:
        fleet.stop()


@pytest.fixture
def clients() -> Iterator[Callable[..., MavClient]]:
    """Factory: ``clients(port, kind)``: a raw-pymavlink ground station, closed at teardown."""
    opened: list[MavClient] = []

    def _open(port: int, kind: str = "tcp") -> MavClient:
        client = MavClient(("127.0.0.1", port), kind=kind)
        opened.append(client)
        return client

    yield _open
    for client in opened:
        client.close()


def command(client: MavClient, system_id: int, command_id: int, *params: float) -> Any:
    """COMMAND_LONG to vehicle ``system_id`` (component 1); returns its COMMAND_ACK."""
    values = [*params, *([0.0] * (7 - len(params)))]
    client.mark()
    client.mav.command_long_send(system_id, 1, command_id, 0, *values)
    return client.wait("COMMAND_ACK", lambda m: m.command == command_id, timeout_s=3.0)


def take_off(client: MavClient, mock: MockAutopilot, flavour: str) -> None:
    """Arm and take off ``mock`` (over ``client``) the way its flavour wants it."""
    system_id = mock.protocol.system_id
    # Arming (and ArduPilot's GUIDED) only once the position estimate is ready.
    client.pump_for(lambda: mock.state().ready, 10.0, "the position estimate")
    if flavour == "ardupilot":
        ack = command(client, system_id, mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert command(client, system_id, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
        ack = command(client, system_id, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0)
    else:
        assert command(client, system_id, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
        nan = math.nan  # PX4: its default take-off altitude, here
        ack = command(client, system_id, mavlink.MAV_CMD_NAV_TAKEOFF, nan, 0, 0, nan, nan, nan, nan)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_each_vehicle_has_its_own_port_sysid_and_home_and_only_the_commanded_one_flies(
    flavour, start_fleet, clients
):
    fleet = start_fleet(3, flavour)
    assert fleet.system_ids == [1, 2, 3]
    assert len(set(fleet.ports)) == 3 and all(port > 0 for port in fleet.ports)
    links = [clients(port) for port in fleet.ports]
    autopilot = {"ardupilot": mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink.MAV_AUTOPILOT_PX4}
    for system_id, client in zip(fleet.system_ids, links, strict=True):
        heartbeat = client.wait("HEARTBEAT")
        assert heartbeat.get_header().srcSystem == system_id
        assert heartbeat.autopilot == autopilot[flavour]
    # Homes in a row, 15 m apart eastwards; the first is the flavour's SITL home.
    first = fleet[0].vehicle.home
    assert first == fleet[0].vehicle.flavour.default_home
    for i, mock in enumerate(fleet):
        home = mock.vehicle.home
        north_m, east_m, down_m = global_to_ned(first, home.lat_deg, home.lon_deg, home.alt_amsl_m)
        assert (north_m, east_m, down_m) == pytest.approx((0.0, 15.0 * i, 0.0), abs=1e-6)

    # A command for system 1 sent to the second vehicle's port is not for it.
    second = links[1]
    second.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    second.pump_for(lambda: fleet[1].stats["not_for_us"] >= 1, 3.0, "the command to be ignored")
    take_off(second, fleet[1], flavour)
    ack = command(
        second,
        2,
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        1e5,
    )
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    position = second.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 1500, timeout_s=15.0)
    assert position.get_header().srcSystem == 2
    # The others heard nothing of it: still on the ground, disarmed, as their heartbeats say.
    for index in (0, 2):
        heartbeat = links[index].wait("HEARTBEAT")
        assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        state = fleet[index].state()
        assert not state.armed and state.alt_m == 0.0
        assert fleet[index].stats["commands"] == 0
    assert fleet[1].state().armed


def test_a_udp_fleet_answers_each_sender_with_its_own_sysid(start_fleet, clients):
    fleet = start_fleet(2, "px4", listen="udp:127.0.0.1:0")
    assert fleet.addresses == [f"udp:127.0.0.1:{port}" for port in fleet.ports]
    for system_id, port in zip(fleet.system_ids, fleet.ports, strict=True):
        assert clients(port, kind="udp").wait("HEARTBEAT").get_header().srcSystem == system_id


def test_a_fleet_that_cannot_bind_stops_the_vehicles_it_started(start_fleet):
    busy = start_fleet(1, "ardupilot")
    fleet = MockFleet(2, ["tcp:127.0.0.1:0", f"tcp:127.0.0.1:{busy.ports[0]}"], "ardupilot")
    with pytest.raises(OSError, match=f"cannot open tcp:127.0.0.1:{busy.ports[0]}"):
        fleet.start()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", fleet.ports[0]), timeout=2.0).close()


def test_listen_specs_expand_to_consecutive_ports():
    assert fleet_listens("tcp:127.0.0.1:5760", 3) == [
        "tcp:127.0.0.1:5760",
        "tcp:127.0.0.1:5761",
        "tcp:127.0.0.1:5762",
    ]
    assert fleet_listens("udpout:127.0.0.1:14540", 2) == [
        "udpout:127.0.0.1:14540",
        "udpout:127.0.0.1:14541",
    ]
    assert fleet_listens("tcp:127.0.0.1:0", 2) == ["tcp:127.0.0.1:0"] * 2
    # tcp and udp ports do not collide.
    assert fleet_listens(["tcp:127.0.0.1:5760", "udp:127.0.0.1:5760"], 2)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"count": 0}, "count"),
        ({"count": 9}, "count"),
        ({"count": 3, "system_id_base": 254}, "system_id_base"),
        ({"count": 2, "listen": ["tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760"]}, "listen"),
        ({"count": 2, "listen": ["tcp:127.0.0.1:5760"]}, "listen"),
        ({"count": 2, "listen": "tcp:127.0.0.1:65535"}, "listen"),
        ({"count": 2, "spacing_m": 0.0}, "spacing_m"),
        ({"count": 2, "spacing_m": math.nan}, "spacing_m"),
    ],
)
def test_impossible_fleets_raise_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"^{field}: "):
        MockFleet(**kwargs)


# ---------------------------------------------------------------------- the command line


def run_in_process(*args: str) -> int:
    parser = argparse.ArgumentParser(prog="tupa")
    register(parser.add_subparsers(dest="command"))
    namespace = parser.parse_args(["sitl-mock", *args])
    return namespace.handler(namespace)


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (("--vehicles", "0"), "--vehicles"),
        (("--vehicles", "9"), "--vehicles"),
        (("--vehicles", "3", "--sysid-base", "254"), "--sysid-base"),
        (("--vehicles", "2", "--system-id", "256"), "--system-id"),
        (("--listen", "tcp:127.0.0.1:5760", "--listen", "tcp:127.0.0.1:5760"), "--listen"),
        (("--vehicles", "3", "--listen", "tcp:127.0.0.1:0", "--listen", "udp:127.0.0.1:0"),
         "--listen"),
        (("--vehicles", "2", "--listen", "tcp:127.0.0.1:65535"), "--listen"),
        (("--vehicles", "2", "--listen", "tcp:127.0.0.1:0", "--listen", "serial:x"), "--listen"),
        (("--vehicles", "2", "--spacing-m", "-15"), "--spacing-m"),
        (("--vehicles", "2", "--spacing-m", "inf"), "--spacing-m"),
    ],
)  # fmt: skip
def test_bad_fleet_arguments_print_one_line_and_return_2(args, option, capsys):
    assert run_in_process(*args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option in err[0], err


def test_tupa_sitl_mock_vehicles_prints_one_line_per_vehicle_and_stops_on_sigterm(spawn, clients):
    process = spawn(
        "--vehicles", "3", "--listen", "tcp:127.0.0.1:0", "--flavour", "ardupilot",
        "--sysid-base", "10", "--ready-delay-s", "0.2", "--log-level", "WARNING",
    )  # fmt: skip
    assert process.stdout is not None
    ready, _, _ = select.select([process.stdout], [], [], 20.0)
    assert ready, "no output within 20 s"
    # The three lines come in one write.
    lines = [process.stdout.readline() for _ in range(3)]
    pattern = r"^sitl-mock ardupilot sysid (\d+) listening on tcp:127\.0\.0\.1:(\d+)$"
    matches = [re.match(pattern, line.rstrip("\n")) for line in lines]
    assert all(matches), lines
    vehicles = [(int(m.group(1)), int(m.group(2))) for m in matches if m]
    assert [system_id for system_id, _ in vehicles] == [10, 11, 12]
    for system_id, port in vehicles:
        assert clients(port).wait("HEARTBEAT").get_header().srcSystem == system_id
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=10) == 0
