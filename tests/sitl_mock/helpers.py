"""Helpers for the sitl_mock tests: a raw-pymavlink ground station and a simulated-time stepper.

``wait_for`` (the bounded polling helper) lives in ``tests/helpers.py`` and is re-exported here
for the tests that import it from this module."""

from __future__ import annotations

import contextlib
import math
import select
import signal
import socket
import subprocess
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.vehicle import Vehicle
from tests.helpers import wait_for

__all__ = ["MavClient", "distance_m", "run_vehicle", "signing_timestamp_now", "wait_for"]


def run_vehicle(
    vehicle: Vehicle,
    until: Callable[[Vehicle], bool],
    max_s: float,
    dt_s: float = 0.02,
    each_step: Callable[[Vehicle], None] | None = None,
) -> float:
    """Step ``vehicle`` until ``until(vehicle)``; returns the simulated seconds it took."""
    start = vehicle.time_s
    while not until(vehicle):
        if vehicle.time_s - start > max_s:
            raise AssertionError(
                f"not reached within {max_s} simulated seconds: {vehicle.snapshot()}"
            )
        if each_step is not None:
            each_step(vehicle)
        vehicle.step(dt_s)
    return vehicle.time_s - start


def signing_timestamp_now() -> int:
    """MAVLink 2 signing timestamp: 10 µs units since 2015-01-01."""
    return int((time.time() - 1420070400) * 100_000)


class MavClient:
    """A minimal ground station on raw pymavlink (TCP or UDP), to drive the mock in tests.

    It sends its own HEARTBEAT (type GCS) every second while it waits, records everything it
    receives, and runs registered periodic tasks (e.g. a setpoint stream) while it waits.
    """

    def __init__(
        self,
        address: tuple[str, int],
        kind: str = "tcp",
        system_id: int = 255,
        component_id: int = 190,
        signing_key: bytes | None = None,
        send_heartbeats: bool = True,
        sock: socket.socket | None = None,
    ) -> None:
        self.kind = kind
        self.address = address
        if sock is not None:
            self.sock = sock
        elif kind == "tcp":
            self.sock = socket.create_connection(address, timeout=5.0)
        else:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.mav = mavlink.MAVLink(self, system_id, component_id)
        self.mav.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            self.mav.signing.timestamp = signing_timestamp_now()
        self.send_heartbeats = send_heartbeats
        self.received: list[Any] = []
        self.statustexts: list[str] = []
        self._tasks: list[list[Any]] = []
        self._next_heartbeat = 0.0
        self._cursor = 0

    # pymavlink's MAVLink.send() calls this with packed bytes.
    def write(self, data: bytes) -> None:
        if self.kind == "tcp":
            self.sock.setblocking(True)
            try:
                self.sock.sendall(data)
            finally:
                self.sock.setblocking(False)
        else:
            self.sock.sendto(data, self.address)

    def send_raw(self, data: bytes) -> None:
        self.write(data)

    def every(self, interval_s: float, task: Callable[[], None]) -> None:
        """Run ``task`` every ``interval_s`` while pumping."""
        self._tasks.append([interval_s, 0.0, task])

    def clear_tasks(self) -> None:
        self._tasks.clear()

    def heartbeat(self) -> None:
        self.mav.heartbeat_send(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
        )

    def pump(self, timeout_s: float = 0.02) -> None:
        """Send what is due, then read and parse whatever arrives within ``timeout_s``."""
        now = time.monotonic()
        if self.send_heartbeats and now >= self._next_heartbeat:
            self.heartbeat()
            self._next_heartbeat = now + 1.0
        for task in self._tasks:
            if now >= task[1]:
                task[2]()
                task[1] = now + task[0]
        readable, _, _ = select.select([self.sock], [], [], timeout_s)
        if not readable:
            return
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionError:
                return
            if not data:
                return
            for message in self.mav.parse_buffer(data) or []:
                self.received.append(message)
                if message.get_type() == "STATUSTEXT":
                    self.statustexts.append(message.text)

    def mark(self) -> None:
        """Forget what arrived so far: the next :meth:`wait` looks only at newer messages."""
        self._cursor = len(self.received)

    def wait(
        self,
        message_type: str | tuple[str, ...],
        predicate: Callable[[Any], bool] = lambda _m: True,
        timeout_s: float = 5.0,
    ) -> Any:
        """The next message of ``message_type`` satisfying ``predicate``.

        Messages are consumed in order: the search starts after the message the previous
        :meth:`wait` returned (or after :meth:`mark` / the last :meth:`command`).
        """
        types = (message_type,) if isinstance(message_type, str) else message_type
        deadline = time.monotonic() + timeout_s
        while True:
            for index in range(self._cursor, len(self.received)):
                message = self.received[index]
                if message.get_type() in types and predicate(message):
                    self._cursor = index + 1
                    return message
            if time.monotonic() > deadline:
                raise AssertionError(f"no {types} within {timeout_s} s")
            self.pump()

    def pump_for(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Keep pumping (heartbeats, tasks) until ``condition()`` holds."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
            self.pump()

    def command(self, command: int, *params: float, timeout_s: float = 3.0) -> Any:
        """COMMAND_LONG to the vehicle (sysid 1, compid 1); returns its COMMAND_ACK."""
        values = [*params, *([0.0] * (7 - len(params)))]
        self.mark()
        self.mav.command_long_send(1, 1, command, 0, *values)
        return self.wait("COMMAND_ACK", lambda m: m.command == command, timeout_s)

    def set_message_interval(self, name: str, rate_hz: float) -> Any:
        message_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, 1e6 / rate_hz)

    def latest(self, message_type: str) -> Any | None:
        for message in reversed(self.received):
            if message.get_type() == message_type:
                return message
        return None

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


def distance_m(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    return math.dist(a, b)


def read_line(process: subprocess.Popen, timeout_s: float) -> str:
    """One line of the process's stdout, waiting at most ``timeout_s``."""
    assert process.stdout is not None
    ready, _, _ = select.select([process.stdout], [], [], timeout_s)
    if not ready:
        raise AssertionError(f"no output within {timeout_s} s")
    return process.stdout.readline()


def stop_process(process: subprocess.Popen) -> int:
    """SIGTERM, then SIGKILL after 10 s; the exit status."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)
    return process.returncode
