"""Do the battery reserve and the autopilot fence of ``tupa serve`` work on a real ArduCopter SITL?

One run per call, with a fresh ArduCopter SITL (built from its own source outside this
repository: it is GPL) in DIR/sitl and a fresh ``tupa serve --mavlink tcp:127.0.0.1:5760
--arm-and-takeoff --decision-mode paced``. SITLs bind every interface, so the run happens in a
private network namespace (only ``lo``): the script re-runs itself under ``unshare -n`` unless it
is already in one (``--no-unshare`` refuses instead)::

    .venv/bin/python benchmarks/real_sitl_safety.py --scenario reserve \
        --arducopter /root/sitl/ardupilot/build/sitl/bin/arducopter \
        --defaults /root/sitl/ardupilot/Tools/autotest/default_params/copter.parm \
        --out runs/safety/reserve-1 --json benchmarks/results/real_sitl_safety.json

What is recorded, on three connections to the SITL:

* the service's own link, through a transparent relay (the *tap*): the service connects to
  tcp:127.0.0.1:5760 as always, the SITL's SERIAL0 is moved to 5770 (``--base-port 5770``) and
  every byte is passed on unchanged both ways; what the service sends is parsed and timed
  (setpoints, COMMAND_LONG/INT such as DO_SET_MODE and NAV_RETURN_TO_LAUNCH, SET_MODE,
  PARAM_SET, the fence's MISSION_ITEM_INTs) and so are the vehicle's COMMAND_ACKs to it;
* a ground station on SERIAL1 (tcp:127.0.0.1:5772, system 255 component 190, its HEARTBEAT at
  1 Hz): the vehicle's modes (HEARTBEAT at 5 Hz), STATUSTEXTs, battery (SYS_STATUS and
  BATTERY_STATUS at 1 Hz), LOCAL_POSITION_NED at 5 Hz, parameters it sets before the take-off;
* for ``fence`` a second ground station on SERIAL2 (tcp:127.0.0.1:5773, system 254) that
  downloads the fence (MISSION_REQUEST_LIST, mission_type FENCE).

and the service's API: ``GET /v1/vehicle`` at 5 Hz (control, mode, fence, route, battery,
take-off), ``GET /metrics`` at 1 Hz; reports of the three users of ``real_sitl_handback.py``
every 0.5 s. Seconds are from the SITL's start.

The area frame: ``TUPA_AREA_ORIGIN_NORTH_M``/``_EAST_M`` -20 (``--area-origin-m``) in every
scenario, so home is at (20, 20) in the area frame and the users' hot spot, where the service
flies, ~115 m from home. (With home on the area's corner, ``--area-origin-m 0 0`` as
``real_sitl_handback.py`` has it, the vehicle drifts a few centimetres outside the default
envelope, the area box, climbs to 24.1-24.7 m, below its 25 m floor, and its route holds at home
for the whole flight: ``flew_away_from_home`` fails.)

Scenarios (the SITL's simulated quad draws ~28 A hovering, its pack voltage stays constant:
``SIM_BATT_CAP_AH`` is not used by the ``quad`` model, so the remaining charge is ArduPilot's
own coulomb count against ``BATT_CAPACITY``, the only way to drain it fast):

* ``reserve``: ``BATT_CAPACITY`` ``--capacity-mah`` (1500: about three minutes of flight),
  ArduCopter's failsafe lower than the service's reserve: ``BATT_LOW_MAH`` 15 % of it with
  ``BATT_FS_LOW_ACT`` 2 (RTL), ``BATT_CRT_MAH`` 5 % with ``BATT_FS_CRT_ACT`` 1 (LAND); the
  service at its default reserve (20 %). Pass: the vehicle flew away from home (> 50 m), the
  service lets go with "battery reserve reached", the vehicle is in RTL before any
  battery-failsafe STATUSTEXT, the service sends no setpoint, mode request or command after its
  return command, the vehicle never shows GUIDED again.
* ``failsafe-first``: ``BATT_LOW_MAH`` ``--fs-low-pct`` (default 60 %) of the capacity with
  ``BATT_FS_LOW_ACT`` 1 (LAND), above where the service would return (its ``return_at_pct``,
  ~51 % at the hot spot with this pack), so close that the charge passes the service's
  ``return_at_pct`` while the vehicle lands. Pass: the vehicle lands (LAND, then disarmed), the
  service lets go, never commands a return or a mode (tap), and its reserve never fires.
  ``failsafe-first-off``: the same with ``--battery-reserve-pct off``.
* ``fence``: ``--envelope`` (inclusion 10 m inside the 500 m area, one 40 m x 40 m exclusion 0-40 m,
  "mast", across the straight line from home to the users' hot spot, clearance 5 m) and
  ``--autopilot-fence``. Pass: ``fence`` is "uploaded" before the vehicle arms, the fence
  read back on SERIAL2 equals what the service sent (tap) and what ``service.fence.fence_plan``
  makes of the file around the SITL's origin, the fence parameters read back are the ones
  the service set, the route is "around", the 5 Hz track never enters the exclusion's
  footprint, and no STATUSTEXT says "fence" and "breach".

Writes DIR/result.json, DIR/autopilot.log, DIR/serve.log; with ``--json`` appends the run to a
results file (a list of runs, locked). SITL, service and relay are stopped at the end of the
run, also on failure; a run is bounded by ``--max-run-s``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import itertools
import json
import math
import os
import re
import secrets
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from shapely.geometry import Point, Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_sitl_handback import USERS, append_run, only_loopback, stop

from service.fence import fence_plan
from service.frames import FrameConfig, GeoPoint, ned_to_area
from service.mission_protocol import MavPort, MissionError, download_fence
from sim.config import AreaConfig
from sim.envelope.files import load_envelope

MAV = mavutil.mavlink
TUPA = Path(sys.executable).with_name("tupa")
SERVICE_PORT = 5760
"""Where ``tupa serve`` connects (the tap listens here)."""
SITL_BASE_PORT = 5770
"""The SITL's SERIAL0 with the tap; SERIAL1 (ground station) +2, SERIAL2 (read-back) +3."""
GCS_SYSTEM, GCS_COMPONENT = 255, 190
READBACK_SYSTEM = 254
SETPOINT_MESSAGES = ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT")
QUIET_COMMANDS = (MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAV_CMD_REQUEST_MESSAGE)
FAILSAFE_TEXT = re.compile(r"Battery \d is (low|critical)|Battery Failsafe", re.I)
SERVE_LOG_KEYS = re.compile(
    r"battery|reserve|return|fence|route|autopilot has|pilot has|control|GUIDED|take-off|"
    r"airborne|failsafe|link lost|link up|WARNING|ERROR",
    re.I,
)
SERVE_LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) (\w+) ([\w.]+): (.*)$")

AREA_ORIGIN_M = (-20.0, -20.0)
"""The default ``TUPA_AREA_ORIGIN_NORTH_M``/``_EAST_M``: the area's south-west corner 20 m south
and 20 m west of home, so home is at (20, 20) in the area frame (inside the fence's inclusion;
with home on the corner, 0 0, the vehicle holds at home: see ``--area-origin-m``)."""
INCLUSION = [[10.0, 10.0], [490.0, 10.0], [490.0, 490.0], [10.0, 490.0]]
EXCLUSION = [[45.0, 35.0], [85.0, 35.0], [85.0, 75.0], [45.0, 75.0]]
MAX_SPEED_MPS = 5.0
"""The envelope's speed limit in ``fence``: half ArduCopter's default WPNAV_SPEED (10 m/s)."""
SPEED_TOLERANCE_MPS = 0.75
"""How far above the limit the measured horizontal speed (1 s differences of the 5 Hz track)
may go: the position controller's overshoot and the EKF's noise."""
ENVELOPE = {
    "format": "tupa-envelope/1",
    "inclusion": INCLUSION,
    "clearance_m": 5.0,
    "max_speed_mps": MAX_SPEED_MPS,
    "exclusions": [{"name": "mast", "polygon": EXCLUSION, "floor_m": 0.0, "ceiling_m": 40.0}],
}


def rel(t0: float) -> float:
    return round(time.monotonic() - t0, 2)


def cmd_name(command: int) -> str:
    entry = MAV.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


class Tap:
    """A transparent TCP relay between ``tupa serve`` (it connects to ``listen_port``) and the
    SITL's SERIAL0 (``upstream_port``): every byte passes unchanged; both directions are parsed
    to time what the service sends and what the vehicle acknowledges to it."""

    def __init__(self, listen_port: int, upstream_port: int, t0: float) -> None:
        self.t0 = t0
        self.upstream_port = upstream_port
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", listen_port))
        self.server.listen(1)
        self.server.settimeout(0.5)
        self.halt = threading.Event()
        self.lock = threading.Lock()
        self.connections: list[float] = []
        self.sent_types: dict[str, int] = {}
        self.setpoint_times: list[float] = []
        self.commands: list[dict[str, Any]] = []  # COMMAND_LONG/INT (not intervals) and SET_MODE
        self.acks: list[dict[str, Any]] = []
        self.params_set: list[dict[str, Any]] = []
        self.fence_items: dict[int, tuple[int, int, int, int, int]] = {}
        self.mission_counts: list[dict[str, Any]] = []
        self.mission_acks: list[dict[str, Any]] = []
        self.parse_errors = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.halt.set()
        self.thread.join(5)
        with contextlib.suppress(OSError):
            self.server.close()

    def _run(self) -> None:
        while not self.halt.is_set():
            try:
                client, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            upstream = None
            deadline = time.monotonic() + 60
            while upstream is None and not self.halt.is_set() and time.monotonic() < deadline:
                try:
                    upstream = socket.create_connection(("127.0.0.1", self.upstream_port), 2)
                except OSError:
                    time.sleep(0.2)
            if upstream is None:
                client.close()
                continue
            self.connections.append(rel(self.t0))
            try:
                self._pump(client, upstream)
            finally:
                for s in (client, upstream):
                    with contextlib.suppress(OSError):
                        s.close()

    def _pump(self, client: socket.socket, upstream: socket.socket) -> None:
        from_service = MAV.MAVLink(None)
        from_vehicle = MAV.MAVLink(None)
        for parser in (from_service, from_vehicle):
            parser.robust_parsing = True
        while not self.halt.is_set():
            ready, _, _ = select.select([client, upstream], [], [], 0.5)
            for s in ready:
                try:
                    data = s.recv(65536)
                except OSError:
                    data = b""
                if not data:
                    return
                other = upstream if s is client else client
                try:
                    other.sendall(data)
                except OSError:
                    return
                self._parse(from_service if s is client else from_vehicle, data, s is client)

    def _parse(self, parser: Any, data: bytes, by_service: bool) -> None:
        try:
            messages = parser.parse_buffer(data) or []
        except Exception:  # a parse error must never stop the relay
            self.parse_errors += 1
            return
        t = rel(self.t0)
        with self.lock:
            for m in messages:
                kind = m.get_type()
                if kind == "BAD_DATA":
                    continue
                if by_service:
                    self._from_service(t, kind, m)
                elif kind == "COMMAND_ACK":
                    self.acks.append(
                        {"t": t, "command": cmd_name(m.command), "result": int(m.result)}
                    )
                elif kind == "MISSION_ACK":
                    self.mission_acks.append(
                        {"t": t, "type": int(m.type), "mission_type": int(m.mission_type)}
                    )

    def _from_service(self, t: float, kind: str, m: Any) -> None:
        self.sent_types[kind] = self.sent_types.get(kind, 0) + 1
        if kind in SETPOINT_MESSAGES:
            self.setpoint_times.append(t)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if m.command not in QUIET_COMMANDS:
                self.commands.append(
                    {
                        "t": t,
                        "kind": kind,
                        "command": cmd_name(m.command),
                        "params": [round(float(m.param1), 3), round(float(m.param2), 3)],
                    }
                )
        elif kind == "SET_MODE":
            self.commands.append(
                {"t": t, "kind": kind, "command": "SET_MODE", "params": [m.custom_mode]}
            )
        elif kind == "PARAM_SET":
            name = m.param_id if isinstance(m.param_id, str) else m.param_id.decode()
            self.params_set.append(
                {"t": t, "name": name, "value": float(m.param_value), "type": m.param_type}
            )
        elif kind == "MISSION_COUNT":
            self.mission_counts.append(
                {"t": t, "count": int(m.count), "mission_type": int(m.mission_type)}
            )
        elif kind == "MISSION_ITEM_INT" and m.mission_type == MAV.MAV_MISSION_TYPE_FENCE:
            self.fence_items[int(m.seq)] = (
                int(m.command),
                round(m.param1),
                int(m.x),
                int(m.y),
                int(m.frame),
            )

    def setpoints_after(self, t: float) -> int:
        with self.lock:
            return sum(1 for s in self.setpoint_times if s > t)

    def summary(self) -> dict[str, Any]:
        with self.lock:
            times = list(self.setpoint_times)
            return {
                "connections": self.connections,
                "sent_types": dict(sorted(self.sent_types.items())),
                "setpoints": len(times),
                "first_setpoint_s": times[0] if times else None,
                "last_setpoint_s": times[-1] if times else None,
                "commands": list(self.commands),
                "acks": list(self.acks),
                "params_set": list(self.params_set),
                "mission_counts": list(self.mission_counts),
                "mission_acks": list(self.mission_acks),
                "parse_errors": self.parse_errors,
            }


class Station:
    """A ground station on one SITL serial port: its HEARTBEAT at 1 Hz; the vehicle's modes,
    STATUSTEXTs, battery, local position, home, origin, parameters and COMMAND_ACKs recorded."""

    def __init__(self, url: str, t0: float) -> None:
        self.t0 = t0
        self.conn = mavutil.mavlink_connection(
            url, source_system=GCS_SYSTEM, source_component=GCS_COMPONENT, retries=30
        )
        self.lock = threading.Lock()
        self.changed = threading.Condition()
        self.halt = threading.Event()
        self.modes: list[dict[str, Any]] = []
        self.heartbeats = 0
        self.texts: list[dict[str, Any]] = []
        self.battery: list[dict[str, Any]] = []
        self.consumed_mah: float | None = None
        self.track: list[tuple[float, float, float, float]] = []
        self.home: GeoPoint | None = None
        self.origin: GeoPoint | None = None
        self.params: dict[str, float] = {}
        self.acks: list[dict[str, Any]] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def send(self, fn: str, *a: Any) -> None:
        with self.lock:
            getattr(self.conn.mav, fn)(*a)

    def _run(self) -> None:
        next_hb = 0.0
        last_state = None
        while not self.halt.is_set():
            if time.monotonic() >= next_hb:
                self.send(
                    "heartbeat_send",
                    MAV.MAV_TYPE_GCS,
                    MAV.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    MAV.MAV_STATE_ACTIVE,
                )
                next_hb = time.monotonic() + 1.0
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):
                time.sleep(0.1)
                continue
            if m is None or (m.get_srcSystem(), m.get_srcComponent()) != (1, 1):
                continue
            kind = m.get_type()
            t = rel(self.t0)
            if kind == "HEARTBEAT":
                self.heartbeats += 1
                state = (
                    mavutil.mode_string_v10(m),
                    bool(m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED),
                    int(m.system_status),
                )
                if state != last_state:
                    last_state = state
                    with self.changed:
                        self.modes.append(
                            {"t": t, "mode": state[0], "armed": state[1], "system_status": state[2]}
                        )
                        self.changed.notify_all()
            elif kind == "STATUSTEXT":
                self.texts.append({"t": t, "severity": int(m.severity), "text": m.text})
                print(f"{t:7.2f} STATUSTEXT {m.text}", flush=True)
            elif kind == "SYS_STATUS":
                self.battery.append(
                    {
                        "t": t,
                        "remaining_pct": int(m.battery_remaining),
                        "voltage_v": round(m.voltage_battery / 1000.0, 2),
                        "current_a": round(m.current_battery / 100.0, 1),
                        "consumed_mah": self.consumed_mah,
                    }
                )
            elif kind == "BATTERY_STATUS" and m.id == 0:
                self.consumed_mah = float(m.current_consumed)
            elif kind == "LOCAL_POSITION_NED":
                self.track.append((t, round(m.x, 2), round(m.y, 2), round(m.z, 2)))
            elif kind == "HOME_POSITION":
                self.home = GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
            elif kind == "GPS_GLOBAL_ORIGIN":
                self.origin = GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
            elif kind == "PARAM_VALUE":
                with self.changed:
                    self.params[m.param_id] = m.param_value
                    self.changed.notify_all()
            elif kind == "COMMAND_ACK":
                self.acks.append({"t": t, "command": cmd_name(m.command), "result": m.result})

    def command(self, command: int, *params: float) -> None:
        values = [*params, *([0.0] * (7 - len(params)))]
        self.send("command_long_send", 1, 1, command, 0, *values)

    def ask_intervals(self) -> None:
        for msg_id, interval_us in (
            (MAV.MAVLINK_MSG_ID_HEARTBEAT, 200_000),
            (MAV.MAVLINK_MSG_ID_SYS_STATUS, 1_000_000),
            (MAV.MAVLINK_MSG_ID_BATTERY_STATUS, 1_000_000),
            (MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 200_000),
        ):
            self.command(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)

    def ask_home(self) -> None:
        self.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_HOME_POSITION)
        self.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def set_param(self, name: str, value: float, tries: int = 5) -> float | None:
        """PARAM_SET until the vehicle's PARAM_VALUE echoes ``value``; the value it has then."""
        for _ in range(tries):
            with self.changed:
                self.params.pop(name, None)
            self.send("param_set_send", 1, 1, name.encode(), value, MAV.MAV_PARAM_TYPE_REAL32)
            deadline = time.monotonic() + 2.0
            with self.changed:
                while name not in self.params and time.monotonic() < deadline:
                    self.changed.wait(0.2)
                got = self.params.get(name)
            if got is not None and abs(got - value) < 1e-3:
                return got
        return self.params.get(name)

    def get_param(self, name: str) -> float | None:
        for _ in range(3):
            with self.changed:
                self.params.pop(name, None)
            self.send("param_request_read_send", 1, 1, name.encode(), -1)
            deadline = time.monotonic() + 2.0
            with self.changed:
                while name not in self.params and time.monotonic() < deadline:
                    self.changed.wait(0.2)
                if name in self.params:
                    return self.params[name]
        return None

    def mode(self) -> str | None:
        return self.modes[-1]["mode"] if self.modes else None

    def armed(self) -> bool:
        return bool(self.modes and self.modes[-1]["armed"])

    def battery_at(self, t: float) -> dict[str, Any] | None:
        """The last SYS_STATUS reading at or before ``t``."""
        before = [b for b in self.battery if b["t"] <= t]
        return before[-1] if before else None

    def close(self) -> None:
        self.halt.set()
        self.thread.join(3)
        with contextlib.suppress(OSError):
            self.conn.close()


class Api:
    """``GET /v1/vehicle`` at 5 Hz and ``GET /metrics`` at 1 Hz, in a thread: the latest answer,
    each change of what matters, and the metrics' counters."""

    def __init__(self, base: str, headers: dict[str, str], t0: float) -> None:
        self.t0 = t0
        self.client = httpx.Client(base_url=base, headers=headers, timeout=5.0)
        self.halt = threading.Event()
        self.latest: dict[str, Any] | None = None
        self.latest_t = 0.0
        self.timeline: list[dict[str, Any]] = []
        self.battery: list[dict[str, Any]] = []
        self.routes: list[dict[str, Any]] = []
        self.metrics: list[dict[str, Any]] = []
        self.errors = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        last_key = last_route = None
        next_metrics = next_battery = 0.0
        while not self.halt.is_set():
            t = rel(self.t0)
            try:
                v = self.client.get("/v1/vehicle").json()
            except (httpx.HTTPError, ValueError):
                self.errors += 1
                self.halt.wait(0.2)
                continue
            self.latest, self.latest_t = v, t
            route = v.get("route") or {}
            key = (
                v["control"]["holder"],
                v["control"]["reason"],
                v.get("mode"),
                v.get("armed"),
                v.get("streaming"),
                v.get("fence"),
                v["takeoff"]["state"],
                route.get("kind"),
            )
            if key != last_key:
                last_key = key
                entry = {
                    "t": t,
                    "holder": key[0],
                    "reason": key[1],
                    "mode": key[2],
                    "armed": key[3],
                    "streaming": key[4],
                    "fence": key[5],
                    "takeoff": key[6],
                    "route_kind": key[7],
                    "battery": v.get("battery"),
                }
                self.timeline.append(entry)
                print(
                    f"{t:7.2f} service: {key[0]} ({key[1]}) mode {key[2]} armed {key[3]} "
                    f"streaming {key[4]} fence {key[5]!r} take-off {key[6]} route {key[7]}",
                    flush=True,
                )
            route_key = (
                route.get("kind"),
                route.get("hold_reason"),
                len(route.get("waypoints") or []),
            )
            if route and route_key != last_route:
                last_route = route_key
                self.routes.append({"t": t, **route})
            if t >= next_battery and v.get("battery"):
                self.battery.append({"t": t, "control": key[0], **v["battery"]})
                next_battery = t + 2.0
            if t >= next_metrics:
                self.metrics.append(self._metrics(t))
                next_metrics = t + 1.0
            self.halt.wait(0.2)
        self.client.close()

    def _metrics(self, t: float) -> dict[str, Any]:
        sample: dict[str, Any] = {"t": t}
        try:
            text = self.client.get("/metrics").text
        except httpx.HTTPError:
            return sample
        wanted = {
            "tupa_setpoints_sent_total": "setpoints_sent",
            "tupa_vehicle_mode_requests_total": "mode_requests",
            "tupa_vehicle_battery_returns_total": "battery_returns",
            "tupa_vehicle_battery_remaining_percent": "battery_pct",
            "tupa_vehicle_control_released_total": "control_released",
        }
        for line in text.splitlines():
            if line.startswith("#") or " " not in line:
                continue
            name, _, value = line.rpartition(" ")
            base = name.split("{", 1)[0]
            if base in wanted:
                with contextlib.suppress(ValueError):
                    sample[wanted[base]] = sample.get(wanted[base], 0.0) + float(value)
        return sample

    def close(self) -> None:
        self.halt.set()
        self.thread.join(5)


def parse_serve_log(path: Path, t0_wall: float) -> list[dict[str, Any]]:
    """The service's log lines that matter, with their time from the SITL's start."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        if "HTTP/1.1" in line:
            continue
        found = SERVE_LOG_TIME.match(line)
        if found is None:
            continue
        stamp, level, logger, text = found.groups()
        if "vehicle says" in text or not SERVE_LOG_KEYS.search(text):
            continue
        wall = datetime.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()
        out.append({"t": round(wall - t0_wall, 2), "level": level, "logger": logger, "text": text})
    return out


def battery_params(args: argparse.Namespace) -> dict[str, float]:
    """What the ground station sets before the take-off (battery scenarios)."""
    cap = float(args.capacity_mah)
    if args.scenario == "reserve":
        low_pct, low_act = args.fs_low_pct if args.fs_low_pct is not None else 15.0, 2.0
    else:
        low_pct, low_act = args.fs_low_pct if args.fs_low_pct is not None else 60.0, 1.0
    return {
        "BATT_CAPACITY": cap,
        "BATT_CRT_MAH": round(cap * args.fs_crt_pct / 100.0),
        "BATT_FS_CRT_ACT": 1.0,
        "BATT_LOW_MAH": round(cap * low_pct / 100.0),
        "BATT_FS_LOW_ACT": low_act,
    }


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--scenario",
        choices=("reserve", "failsafe-first", "failsafe-first-off", "fence"),
        required=True,
    )
    parser.add_argument("--arducopter", type=Path, required=True, help="the SITL binary")
    parser.add_argument("--defaults", type=Path, required=True, help="copter.parm")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--json", type=Path, help="append this run's result to this JSON list")
    parser.add_argument("--capacity-mah", type=float, default=1500.0)
    parser.add_argument(
        "--fs-low-pct",
        type=float,
        help="BATT_LOW_MAH as %% of the capacity (reserve: 15, RTL; failsafe-first: 60, LAND)",
    )
    parser.add_argument("--fs-crt-pct", type=float, default=5.0, help="BATT_CRT_MAH, LAND")
    parser.add_argument("--max-flight-s", type=float, default=300.0)
    parser.add_argument("--observe-s", type=float, default=150.0, help="after the hand-over")
    parser.add_argument("--fence-fly-s", type=float, default=150.0)
    parser.add_argument("--max-run-s", type=float, default=900.0)
    parser.add_argument(
        "--area-origin-m",
        type=float,
        nargs=2,
        default=AREA_ORIGIN_M,
        metavar=("NORTH", "EAST"),
        help="TUPA_AREA_ORIGIN_NORTH_M/_EAST_M (default -20 -20: home at (20, 20))",
    )
    parser.add_argument(
        "--mavlink-backend",
        choices=("pymavlink", "mavsdk"),
        default="pymavlink",
        help="tupa serve's --mavlink-backend (default pymavlink)",
    )
    parser.add_argument("--no-unshare", action="store_true", help="refuse outside a namespace")
    args = parser.parse_args()
    frame = FrameConfig(
        area_origin_north_m=args.area_origin_m[0], area_origin_east_m=args.area_origin_m[1]
    )
    if (why := only_loopback()) is not None:
        if args.no_unshare or not shutil.which("unshare"):
            print(f"refusing: {why}", file=sys.stderr)
            return 2
        inner = " ".join(_quote(a) for a in [sys.executable, *sys.argv, "--no-unshare"])
        return subprocess.call(["unshare", "-n", "bash", "-c", f"ip link set lo up; {inner}"])
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # the finally below still runs

    def overrun(*_: Any) -> None:
        raise TimeoutError(f"the run took longer than --max-run-s {args.max_run_s:g}")

    signal.signal(signal.SIGALRM, overrun)
    signal.alarm(int(args.max_run_s))
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=False)
    (out / "sitl").mkdir()
    t0 = time.monotonic()
    t0_wall = time.time()
    result: dict[str, Any] = {
        "scenario": args.scenario,
        "autopilot": "ArduCopter SITL",
        "version": _version(args.arducopter),
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "passed": False,
    }
    events: list[tuple[float, str]] = []

    def note(text: str) -> None:
        events.append((rel(t0), text))
        print(f"{rel(t0):7.2f} {text}", flush=True)

    ap_log = open(out / "autopilot.log", "w")  # noqa: SIM115 (open for the whole run)
    serve_log_path = out / "serve.log"
    serve_log = open(serve_log_path, "w")  # noqa: SIM115
    ap = serve = None
    tap: Tap | None = None
    gcs: Station | None = None
    api: Api | None = None
    stop_reports = threading.Event()
    report_codes: dict[str, int] = {}
    try:
        tap = Tap(SERVICE_PORT, SITL_BASE_PORT, t0)
        ap_cmd = [
            str(args.arducopter.resolve()),
            "--model",
            "quad",
            "--speedup",
            "1",
            "-w",
            "--base-port",
            str(SITL_BASE_PORT),
            "--defaults",
            str(args.defaults.resolve()),
        ]
        ap = subprocess.Popen(
            ap_cmd, cwd=out / "sitl", stdout=ap_log, stderr=ap_log, start_new_session=True
        )
        note("arducopter started: " + " ".join(ap_cmd))
        token = secrets.token_urlsafe(24)
        env = {**os.environ, "TUPA_API_TOKEN": token}
        serve_cmd = [
            str(TUPA),
            "serve",
            "--mavlink",
            f"tcp:127.0.0.1:{SERVICE_PORT}",
            "--arm-and-takeoff",
            "--decision-mode",
            "paced",
            "--port",
            "0",
            "--mavlink-backend",
            args.mavlink_backend,
        ]
        result["mavlink_backend"] = args.mavlink_backend
        if args.scenario == "failsafe-first-off":
            serve_cmd += ["--battery-reserve-pct", "off"]
        if args.scenario == "fence":
            envelope_path = out / "envelope.json"
            envelope_path.write_text(json.dumps(ENVELOPE, indent=1))
            serve_cmd += ["--envelope", str(envelope_path), "--autopilot-fence"]
            result["envelope"] = ENVELOPE
        env["TUPA_AREA_ORIGIN_NORTH_M"] = str(frame.area_origin_north_m)
        env["TUPA_AREA_ORIGIN_EAST_M"] = str(frame.area_origin_east_m)
        result["area_origin_ned_m"] = [frame.area_origin_north_m, frame.area_origin_east_m]
        serve = subprocess.Popen(
            serve_cmd, stdout=serve_log, stderr=serve_log, env=env, start_new_session=True
        )
        result["serve_command"] = " ".join(serve_cmd[1:])
        note("tupa serve started: " + result["serve_command"])
        port = None
        deadline = time.monotonic() + 60
        while port is None and time.monotonic() < deadline:
            found = re.search(r"listening on http://127\.0\.0\.1:(\d+)", serve_log_path.read_text())
            if found:
                port = int(found.group(1))
            elif serve.poll() is not None:
                break
            else:
                time.sleep(0.2)
        if port is None:
            note("tupa serve never listened")
            return 1
        base = f"http://127.0.0.1:{port}"
        headers = {"Authorization": f"Bearer {token}"}
        api = Api(base, headers, t0)
        note(f"tupa serve listening on {base}")

        def post_reports() -> None:
            client = httpx.Client(base_url=base, headers=headers, timeout=5.0)
            while not stop_reports.is_set():
                users = [
                    {**u, "throughput_bps": u["offered_bps"] * 0.8, "delay_s": 0.05, "plr": 0.01}
                    for u in USERS
                ]
                try:
                    r = client.post("/v1/reports", json={"timestamp": time.time(), "users": users})
                    code = str(r.status_code)
                except httpx.HTTPError as exc:
                    code = type(exc).__name__
                report_codes[code] = report_codes.get(code, 0) + 1
                stop_reports.wait(0.5)
            client.close()

        threading.Thread(target=post_reports, daemon=True).start()

        deadline = time.monotonic() + 90
        while gcs is None and time.monotonic() < deadline:
            try:
                gcs = Station(f"tcp:127.0.0.1:{SITL_BASE_PORT + 2}", t0)
            except OSError:
                time.sleep(0.5)
        if gcs is None:
            note("no ground-station connection to SERIAL1")
            return 1
        deadline = time.monotonic() + 30
        while gcs.heartbeats == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        gcs.ask_intervals()
        note(f"ground station up, vehicle mode {gcs.mode()}")

        if args.scenario != "fence":
            wanted = battery_params(args)
            got = {name: gcs.set_param(name, value) for name, value in wanted.items()}
            for name in ("BATT_MONITOR", "BATT_LOW_VOLT", "BATT_LOW_TIMER", "FS_OPTIONS"):
                got[name] = gcs.get_param(name)
            result["battery_params"] = got
            result["battery_params_set_s"] = rel(t0)
            note(f"battery parameters: {got}")
            if any(got.get(n) is None or abs(got[n] - v) > 1e-3 for n, v in wanted.items()):
                note("the SITL did not take the battery parameters")
                return 1
            if gcs.armed():
                note("the vehicle armed before the battery parameters were set")
                return 1

        # Take-off (the service's): airborne, GUIDED and streaming.
        readback_done = False
        airborne = None
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            v = api.latest
            if (
                args.scenario == "fence"
                and not readback_done
                and v is not None
                and v.get("fence") == "uploaded"
            ):
                readback_done = True
                result["fence_readback"] = fence_readback(
                    gcs, tap, out / "envelope.json", frame, t0, note
                )
            if v is not None and v["takeoff"]["state"].startswith("failed"):
                note(f"take-off failed: {v['takeoff']}")
                break
            if (
                v is not None
                and v["takeoff"]["state"] == "airborne"
                and v["mode"] == "GUIDED"
                and v["streaming"]
            ):
                airborne = rel(t0)
                note(f"airborne, GUIDED and streaming; battery {v.get('battery')}")
                break
            time.sleep(0.2)
        result["airborne_streaming_s"] = airborne
        if airborne is None:
            note("never airborne in GUIDED and streaming")
            return 1
        armed_at = next((m["t"] for m in gcs.modes if m["armed"]), None)
        result["armed_s"] = armed_at

        if args.scenario == "fence":
            if not readback_done:
                result["fence_readback"] = fence_readback(
                    gcs, tap, out / "envelope.json", frame, t0, note
                )
            fly_fence(args, api, gcs, tap, frame, result, note)
        else:
            fly_battery(args, api, gcs, tap, result, t0, note)
        return 0 if result["passed"] else 1
    except Exception as exc:  # recorded, then the run is cleaned up
        note(f"error: {type(exc).__name__}: {exc}")
        result["error"] = f"{type(exc).__name__}: {exc}"
        return 1
    finally:
        signal.alarm(0)
        stop_reports.set()
        result["reports_posted"] = report_codes
        if api is not None:
            api.close()
            result["service_timeline"] = api.timeline
            result["service_battery"] = api.battery
            result["service_routes"] = api.routes[:40]
            result["metrics"] = api.metrics[-400:]
        if gcs is not None:
            gcs.close()
            result["vehicle_mode_timeline"] = gcs.modes
            result["vehicle_heartbeats"] = gcs.heartbeats
            result["status_texts"] = gcs.texts
            result["vehicle_battery"] = gcs.battery[::5]
            result["ground_station_acks"] = gcs.acks
        if serve is not None:
            stop(serve, serve.pid)
        if ap is not None:
            stop(ap, ap.pid)
        if tap is not None:
            tap.close()
            result["tap"] = tap.summary()
        serve_log.close()
        ap_log.close()
        result["serve_log"] = parse_serve_log(serve_log_path, t0_wall)[-120:]
        result["run_s"] = rel(t0)
        result["events"] = events
        print("PASS" if result["passed"] else "FAIL", flush=True)
        (out / "result.json").write_text(json.dumps(result, indent=1))
        if args.json:
            append_run(args.json, {k: v for k, v in result.items() if k != "events"})


def fly_battery(
    args: argparse.Namespace,
    api: Api,
    gcs: Station,
    tap: Tap,
    result: dict[str, Any],
    t0: float,
    note: Any,
) -> None:
    """Fly until the service lets go (its reserve, or ArduCopter's failsafe), then observe the
    vehicle until it has landed and disarmed."""
    airborne = result["airborne_streaming_s"]
    last_held: dict[str, Any] | None = None
    let_go = None
    deadline = time.monotonic() + args.max_flight_s
    while time.monotonic() < deadline:
        v = api.latest
        if v is not None and v["control"]["holder"] == "service":
            last_held = {"t": api.latest_t, **v}
        elif v is not None:
            let_go = {"t": api.latest_t, "holder": v["control"]["holder"]}
            let_go["reason"] = v["control"]["reason"]
            note(f"service let go: {let_go}")
            break
        time.sleep(0.1)
    if let_go is None:
        note(f"the service still holds the vehicle after {args.max_flight_s:g} s of flight")
        return
    result["service_let_go"] = let_go
    if last_held is not None:
        result["last_while_held"] = {
            "t": last_held["t"],
            "battery": last_held.get("battery"),
            "position": last_held.get("position"),
            "mode": last_held.get("mode"),
        }
    # Observe until landed and disarmed.
    until = time.monotonic() + args.observe_s
    disarmed_at = None
    while time.monotonic() < until:
        after = [m for m in gcs.modes if m["t"] >= airborne]
        off = next((m for m in after if not m["armed"]), None)
        if off is not None:
            disarmed_at = off["t"]
            break
        time.sleep(0.5)
    time.sleep(3.0)  # a few more samples after the disarm
    result["disarmed_s"] = disarmed_at
    evaluate_battery(args, api, gcs, tap, result, t0)


def evaluate_battery(
    args: argparse.Namespace,
    api: Api,
    gcs: Station,
    tap: Tap,
    result: dict[str, Any],
    t0: float,
) -> None:
    airborne = result["airborne_streaming_s"]
    let_go = result["service_let_go"]
    serve_log = parse_serve_log(Path(args.out) / "serve.log", time.time() - rel(t0))
    reserve_lines = [e for e in serve_log if "battery reserve reached" in e["text"]]
    result["service_reserve_log"] = reserve_lines
    t_reserve = reserve_lines[0]["t"] if reserve_lines else None
    fs_texts = [x for x in gcs.texts if FAILSAFE_TEXT.search(x["text"])]
    t_fs = fs_texts[0]["t"] if fs_texts else None
    after = [m for m in gcs.modes if m["t"] >= airborne]
    first_not_guided = next((m for m in after if m["mode"] != "GUIDED"), None)
    t_rtl_mode = next((m["t"] for m in after if m["mode"] == "RTL"), None)
    t_land_mode = next((m["t"] for m in after if m["mode"] == "LAND"), None)
    summary = tap.summary()
    rtl_commands = [
        c for c in summary["commands"] if c["command"] == "MAV_CMD_NAV_RETURN_TO_LAUNCH"
    ]
    rtl_acks = [a for a in summary["acks"] if a["command"] == "MAV_CMD_NAV_RETURN_TO_LAUNCH"]
    handover_t = first_not_guided["t"] if first_not_guided else let_go["t"]
    t_rtl_cmd = rtl_commands[0]["t"] if rtl_commands else None
    # The service's let-go as it logged it ("the autopilot has the vehicle: ...").
    let_go_logged = next(
        (
            e
            for e in serve_log
            if e["t"] >= airborne and re.match(r"the (autopilot|pilot|operator) has", e["text"])
        ),
        None,
    )
    t_let_go = let_go_logged["t"] if let_go_logged is not None else let_go["t"]
    # Commands and setpoints after the service let go (its RTL command excepted): from the RTL
    # command where it sent one, else from its logged let-go.
    cut = t_rtl_cmd if t_rtl_cmd is not None else t_let_go
    later_commands = [
        c
        for c in summary["commands"]
        if c["t"] > cut and c["command"] != "MAV_CMD_NAV_RETURN_TO_LAUNCH"
    ]
    metrics = [m for m in api.metrics if "setpoints_sent" in m]
    after_metrics = [m for m in metrics if m["t"] >= let_go["t"] + 1.0]
    setpoints_metric_growth = (
        after_metrics[-1]["setpoints_sent"] - after_metrics[0]["setpoints_sent"]
        if after_metrics
        else None
    )
    mode_requests = [m.get("mode_requests") for m in after_metrics if "mode_requests" in m]
    guided_again = [m for m in gcs.modes if m["t"] > handover_t and m["mode"] == "GUIDED"]
    battery_mins = [b for b in api.battery if b.get("drain_pct_per_min") is not None]
    flown = [p for p in gcs.track if airborne <= p[0] <= handover_t]
    farthest_m = round(max((math.hypot(p[1], p[2]) for p in flown), default=0.0), 1)
    holds = [x for x in api.routes if x["kind"] == "hold" and x["t"] <= handover_t]
    r = {
        "route_kinds_before_handover": sorted(
            {x["kind"] for x in api.routes if x["t"] <= handover_t}
        ),
        "route_hold_reasons": sorted({x["hold_reason"] for x in holds if x["hold_reason"]}),
        "farthest_from_home_m": farthest_m,
        "position_at_handover": next(([round(c, 2) for c in p] for p in reversed(flown)), None),
        "t_reserve_logged": t_reserve,
        "t_service_let_go_logged": t_let_go,
        "service_let_go_log": let_go_logged,
        "t_service_let_go_seen": let_go["t"],
        "setpoints_between_mode_change_and_let_go": (
            tap.setpoints_after(handover_t) - tap.setpoints_after(t_let_go)
            if first_not_guided is not None
            else None
        ),
        "let_go_holder": let_go["holder"],
        "let_go_reason": let_go["reason"],
        "t_rtl_command": t_rtl_cmd,
        "rtl_commands": len(rtl_commands),
        "rtl_acks": rtl_acks,
        "t_first_mode_after_guided": handover_t,
        "first_mode_after_guided": first_not_guided["mode"] if first_not_guided else None,
        "t_rtl_mode": t_rtl_mode,
        "t_land_mode": t_land_mode,
        "t_first_failsafe_text": t_fs,
        "failsafe_texts": fs_texts,
        "reserve_to_rtl_mode_s": (
            round(t_rtl_mode - t_reserve, 2) if t_rtl_mode is not None and t_reserve else None
        ),
        "rtl_command_to_rtl_mode_s": (
            round(t_rtl_mode - t_rtl_cmd, 2) if t_rtl_mode is not None and t_rtl_cmd else None
        ),
        "vehicle_battery_at_handover": gcs.battery_at(handover_t),
        "vehicle_battery_at_disarm": (
            gcs.battery_at(result["disarmed_s"]) if result.get("disarmed_s") else None
        ),
        "service_battery_before_let_go": (result.get("last_while_held") or {}).get("battery"),
        "service_drain_pct_per_min_seen": (
            [battery_mins[0]["drain_pct_per_min"], battery_mins[-1]["drain_pct_per_min"]]
            if battery_mins
            else None
        ),
        "setpoints_after_rtl_command_or_handover": tap.setpoints_after(cut),
        "last_setpoint_s": summary["last_setpoint_s"],
        "commands_after_rtl_command_or_handover": later_commands,
        "setpoints_metric_growth_after_let_go": setpoints_metric_growth,
        "mode_requests_metric": [mode_requests[0], mode_requests[-1]] if mode_requests else None,
        "guided_again": guided_again,
        "modes_after_handover": [m for m in gcs.modes if m["t"] >= handover_t],
        "disarmed_s": result.get("disarmed_s"),
    }
    result["battery"] = r
    no_commands_after = not later_commands and r["setpoints_after_rtl_command_or_handover"] == 0
    mode_requests_flat = not mode_requests or mode_requests[-1] == mode_requests[0]
    if args.scenario == "reserve":
        checks = {
            "flew_away_from_home": farthest_m > 50.0,
            "let_go_reserve_reason": let_go["holder"] == "autopilot"
            and "battery reserve reached" in let_go["reason"],
            "rtl_commanded_and_accepted": bool(rtl_commands)
            and any(a["result"] == MAV.MAV_RESULT_ACCEPTED for a in rtl_acks),
            "vehicle_in_rtl": t_rtl_mode is not None and r["first_mode_after_guided"] == "RTL",
            "rtl_before_any_battery_failsafe_text": t_rtl_mode is not None
            and (t_fs is None or t_fs > t_rtl_mode),
            "nothing_streamed_or_requested_after": no_commands_after,
            "setpoints_metric_flat": setpoints_metric_growth in (None, 0, 0.0),
            "mode_requests_flat": mode_requests_flat,
            "never_guided_again": not guided_again,
        }
    else:
        checks = {
            "flew_away_from_home": farthest_m > 50.0,
            "autopilot_failsafe_landed": r["first_mode_after_guided"] == "LAND"
            and t_fs is not None,
            "service_let_go_to_autopilot": let_go["holder"] == "autopilot",
            "no_rtl_command_ever": not rtl_commands,
            "no_reserve_fired": not reserve_lines,
            "never_rtl": all(m["mode"] != "RTL" for m in gcs.modes),
            "nothing_streamed_or_requested_after": no_commands_after,
            "setpoints_metric_flat": setpoints_metric_growth in (None, 0, 0.0),
            "mode_requests_flat": mode_requests_flat,
            "never_guided_again": not guided_again,
            "landed_disarmed": result.get("disarmed_s") is not None,
        }
    result["checks"] = checks
    result["passed"] = all(checks.values())
    print(f"{'PASS' if result['passed'] else 'FAIL'}: {checks}", flush=True)


def fence_readback(
    gcs: Station, tap: Tap, envelope_path: Path, frame: FrameConfig, t0: float, note: Any
) -> dict[str, Any]:
    """Download the fence on SERIAL2 and compare it with what the service sent (tap) and with
    what :func:`service.fence.fence_plan` makes of the envelope file around the SITL's origin;
    read the fence parameters back on SERIAL1."""
    r: dict[str, Any] = {"t": rel(t0)}
    for _ in range(10):
        if gcs.origin is not None and gcs.home is not None:
            break
        gcs.ask_home()
        time.sleep(1.0)
    for name, point in (("origin", gcs.origin), ("home", gcs.home)):
        r[name] = None if point is None else [point.lat_deg, point.lon_deg, point.alt_amsl_m]
    conn = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{SITL_BASE_PORT + 3}",
        source_system=READBACK_SYSTEM,
        source_component=GCS_COMPONENT,
        retries=10,
    )
    try:
        got = download_fence(MavPort.for_connection(conn))
        r["downloaded_s"] = rel(t0)
    except MissionError as exc:
        r["error"] = str(exc)
        note(f"fence download failed: {exc}")
        return r
    finally:
        with contextlib.suppress(OSError):
            conn.close()
    downloaded = [(i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in got]
    with tap.lock:
        sent = [tap.fence_items[s][:4] for s in sorted(tap.fence_items)]
    r["items_downloaded"] = len(downloaded)
    r["items_sent_by_service"] = len(sent)
    r["downloaded_equals_sent"] = downloaded == sent
    r["frames_downloaded"] = sorted({i.frame for i in got})
    if gcs.origin is not None:
        envelope = load_envelope(envelope_path, AreaConfig())
        plan = fence_plan(envelope, gcs.origin, frame, "ardupilot", "rtl")
        expected = [(i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in plan.items]
        r["items_expected"] = len(expected)
        r["max_error_vs_plan_e7"] = (
            max(
                max(abs(a[2] - b[2]), abs(a[3] - b[3]))
                for a, b in zip(downloaded, expected, strict=True)
            )
            if len(expected) == len(downloaded)
            else None
        )
        r["downloaded_equals_plan"] = r["max_error_vs_plan_e7"] is not None and (
            r["max_error_vs_plan_e7"] <= 1
            and [d[:2] for d in downloaded] == [e[:2] for e in expected]
        )
        params = {}
        for p in plan.params:
            params[p.name] = {"planned": p.value, "read_back": gcs.get_param(p.name)}
        r["params"] = params
        r["params_equal"] = all(
            v["read_back"] is not None and abs(v["read_back"] - v["planned"]) <= 0.01
            for v in params.values()
        )
    with tap.lock:
        r["params_set_by_service"] = [
            p for p in tap.params_set if p["name"].startswith(("FENCE", "AVOID"))
        ]
    note(
        f"fence read back: {len(downloaded)} items, equal to the service's upload "
        f"{r['downloaded_equals_sent']}, to the plan {r.get('downloaded_equals_plan')}, "
        f"params {r.get('params_equal')}"
    )
    return r


def fly_fence(
    args: argparse.Namespace,
    api: Api,
    gcs: Station,
    tap: Tap,
    frame: FrameConfig,
    result: dict[str, Any],
    note: Any,
) -> None:
    """Fly until the vehicle has been at its target for 10 s (or ``--fence-fly-s``), then
    check the fence's timeline, the route and the track."""
    airborne = result["airborne_streaming_s"]
    at_target_since = None
    until = time.monotonic() + args.fence_fly_s
    while time.monotonic() < until:
        v = api.latest or {}
        route = v.get("route") or {}
        wps = route.get("waypoints") or []
        pos = v.get("position")
        if wps and pos and len(wps) == 1:
            d = math.dist((pos["x_m"], pos["y_m"]), (wps[-1]["x_m"], wps[-1]["y_m"]))
            if d < 3.0:
                at_target_since = at_target_since or time.monotonic()
                if time.monotonic() - at_target_since > 10.0:
                    note(f"at the target {wps[-1]} for 10 s")
                    break
            else:
                at_target_since = None
        if v.get("control", {}).get("holder") not in (None, "service"):
            note(f"the service let go during the fence flight: {v['control']}")
            break
        time.sleep(0.2)
    end = api.latest or {}
    result["fence_flight_end"] = {
        k: end.get(k) for k in ("position", "mode", "control", "route", "fence")
    }
    # Fence timeline: uploaded before the vehicle armed?
    uploaded = next((e["t"] for e in api.timeline if e["fence"] == "uploaded"), None)
    fences = []
    for e in api.timeline:
        if not fences or fences[-1][1] != e["fence"]:
            fences.append((e["t"], e["fence"]))
    armed_at = result.get("armed_s")
    route_kinds = sorted({r["kind"] for r in api.routes})
    around = next((r for r in api.routes if r["kind"] == "around"), None)
    # The track, in the area frame.
    footprint = Polygon(EXCLUSION)
    inclusion = Polygon(INCLUSION)
    track = [
        (t, *ned_to_area(n, e, d, frame))
        for t, n, e, d in list(gcs.track)
        if t >= (armed_at or airborne)
    ]
    inside = [p for p in track if footprint.contains(Point(p[1], p[2]))]
    dists = [footprint.distance(Point(p[1], p[2])) for p in track]
    outside_inclusion = [p for p in track if not inclusion.contains(Point(p[1], p[2]))]
    closest = min(range(len(dists)), key=dists.__getitem__) if dists else None
    fence_texts = [
        x for x in gcs.texts if "fence" in x["text"].lower() or "breach" in x["text"].lower()
    ]
    dt = [b[0] - a[0] for a, b in itertools.pairwise(track)]
    speed_sent = [
        c
        for c in tap.commands
        if c["command"] == "MAV_CMD_DO_CHANGE_SPEED" and c["params"][1] == MAX_SPEED_MPS
    ]
    limited_from = speed_sent[0]["t"] + 2.0 if speed_sent else math.inf
    speeds = horizontal_speeds([p for p in track if p[0] >= limited_from])
    r = {
        "fence_timeline": fences,
        "fence_uploaded_s": uploaded,
        "armed_s": armed_at,
        "uploaded_before_armed": uploaded is not None
        and armed_at is not None
        and uploaded < armed_at,
        "route_kinds": route_kinds,
        "first_around_route": around,
        "track_points": len(track),
        "track_rate_hz": round(len(dt) / sum(dt), 2) if dt and sum(dt) > 0 else None,
        "track_points_in_exclusion": len(inside),
        "min_distance_to_exclusion_m": round(dists[closest], 2) if closest is not None else None,
        "closest_point": ([round(c, 2) for c in track[closest]] if closest is not None else None),
        "track_points_outside_inclusion": len(outside_inclusion),
        "max_height_m": round(max(p[3] for p in track), 2) if track else None,
        "fence_statustexts": fence_texts,
        "speed_limit_sent_s": speed_sent[0]["t"] if speed_sent else None,
        "max_horizontal_speed_mps": round(max(speeds), 2) if speeds else None,
        "max_horizontal_speed_before_limit_mps": (
            round(max(sp), 2)
            if (sp := horizontal_speeds([p for p in track if p[0] < limited_from]))
            else None
        ),
        "track_1hz": one_hz(track),
    }
    result["fence"] = r
    readback = result.get("fence_readback") or {}
    checks = {
        "fence_uploaded_before_arming": r["uploaded_before_armed"],
        "readback_equals_service_upload": bool(readback.get("downloaded_equals_sent"))
        and readback.get("items_downloaded", 0) > 0,
        "readback_equals_plan": bool(readback.get("downloaded_equals_plan")),
        "fence_params_read_back": bool(readback.get("params_equal")),
        "route_around": "around" in route_kinds,
        "track_never_in_exclusion": bool(track) and not inside,
        "track_inside_inclusion": bool(track) and not outside_inclusion,
        "no_fence_breach_text": not any("breach" in x["text"].lower() for x in fence_texts),
        "reached_target": at_target_since is not None,
        "speed_limit_sent": bool(speed_sent),
        "flew_within_the_speed_limit": bool(speeds)
        and max(speeds) <= MAX_SPEED_MPS + SPEED_TOLERANCE_MPS,
    }
    result["checks"] = checks
    result["passed"] = all(checks.values())
    print(f"{'PASS' if result['passed'] else 'FAIL'}: {checks}", flush=True)


def horizontal_speeds(track: list[tuple[float, ...]]) -> list[float]:
    """Horizontal speeds (m/s) over 1 s windows of ``(t, x, y, z)`` points."""
    speeds = []
    j = 0
    for p in track:
        while j < len(track) and track[j][0] < p[0] + 1.0:
            j += 1
        if j >= len(track):
            break
        q = track[j]
        speeds.append(math.hypot(q[1] - p[1], q[2] - p[2]) / (q[0] - p[0]))
    return speeds


def one_hz(track: list[tuple[float, ...]]) -> list[list[float]]:
    """A point a second of the track, rounded."""
    out: list[list[float]] = []
    for p in track:
        if not out or p[0] >= out[-1][0] + 1.0:
            out.append([round(c, 1) for c in p])
    return out


def _version(binary: Path) -> str | None:
    head = binary.resolve().parents[3]
    try:
        return subprocess.run(
            ["git", "-C", str(head), "log", "-1", "--format=%h %cd", "--date=short"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def _quote(arg: str) -> str:
    return "'" + arg.replace("'", "'\\''") + "'"


if __name__ == "__main__":
    sys.exit(main())
