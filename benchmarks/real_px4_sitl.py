"""``tupa serve``'s safety layers and hand-over rules on a real PX4 SITL (SIH quadrotor).

One scenario per call, with a fresh PX4 (``px4_sitl_default``, airframe 10040 ``sihsim_quadx``,
headless, built from its own source outside this repository: it is BSD but large, and CI cannot
build it) whose working directory -- parameters, dataman (mission, fence), ULog -- is new for
every run (DIR/px4). PX4 binds UDP on 0.0.0.0, so the run happens in a private network
namespace (only ``lo``): the script replaces itself with ``unshare -n`` running the same command
line unless it is in such a namespace already (``--no-unshare`` refuses instead)::

    .venv/bin/python benchmarks/real_px4_sitl.py --scenario fence --out runs/px4/fence-1
    .venv/bin/python benchmarks/real_px4_sitl.py --scenario fence --mavlink-backend mavsdk \\
        --out runs/px4/fence-mavsdk-1
    .venv/bin/python benchmarks/real_px4_sitl.py --scenario breach --out runs/px4/breach-1
    .venv/bin/python benchmarks/real_px4_sitl.py --scenario reserve --out runs/px4/reserve-1
    .venv/bin/python benchmarks/real_px4_sitl.py --scenario death --obl-rc-act default ...
    .venv/bin/python benchmarks/real_px4_sitl.py --scenario handback --takeover hold ...

(``--px4-build`` defaults to /root/sitl/px4/build/px4_sitl_default; every run is appended to
``--json``, default benchmarks/results/real_px4_sitl.json, and written to DIR/result.json beside
DIR/px4.log and DIR/serve.log.)

PX4's links (instance 0): the API/offboard link sends from UDP 14580 to 127.0.0.1:14540, where
``tupa serve --mavlink udpin:0.0.0.0:14540`` listens; the GCS link sends from 18570 to
127.0.0.1:14550. Three observers, none of them the service's word:

* a **ground station** on the GCS link (``udpin:0.0.0.0:14550``, system 250 component 190, its
  HEARTBEAT at 1 Hz, MAV_TYPE_GCS): the vehicle's modes (HEARTBEAT, asked for at 5 Hz; names as
  QGroundControl shows them, :func:`service.modes.mode_name`), STATUSTEXTs, LOCAL_POSITION_NED
  and GLOBAL_POSITION_INT at 5 Hz, SYS_STATUS (battery) at 2 Hz, EXTENDED_SYS_STATE (landed
  state), HOME_POSITION and GPS_GLOBAL_ORIGIN. It sets the scenario's parameters before the
  service starts (:func:`service.mission_protocol.set_params`, PX4's integers bit for bit), and
  for ``fence`` downloads the fence (:func:`service.mission_protocol.download_fence`) and reads
  GF_ACTION / GF_MAX_VER_DIST back (``read_params``) on its own connection.
* a **tap** on the service's link: a packet socket (AF_PACKET) on ``lo`` that sees every UDP
  datagram to or from port 14540 without touching it; what the service sends (setpoints,
  COMMAND_LONG/INT, SET_MODE, PARAM_SET, fence items) is parsed and timed, and so are PX4's
  COMMAND_ACKs to it. The service keeps its ordinary command line: ``--mavlink
  udpin:0.0.0.0:14540``, on either backend (MAVSDK runs over the link's own socket there).
* the service's **API**: ``GET /v1/vehicle`` at 5 Hz, ``GET /metrics`` at 1 Hz; a report of the
  three users of ``real_sitl_handback.py`` every 0.5 s.

PX4 SITL's simulated battery empties in 60 s of armed time (``SIM_BAT_DRAIN`` 60, floored at
``SIM_BAT_MIN_PCT`` 50 %): the service's reserve would send the vehicle home seconds after its
take-off. ``fence``, ``death`` and ``handback`` therefore set ``SIM_BAT_DRAIN``
``--sim-bat-drain-s`` (1800: a 30-minute pack) on the GCS link before the service starts.

The area frame: ``TUPA_AREA_ORIGIN_NORTH_M``/``_EAST_M`` -20 (``--area-origin-m``), so home is
at (20, 20) and the users' hot spot ~115 m away, beyond the exclusion of ``fence``. Seconds are
from PX4's start.

Scenarios:

* ``fence``: ``tupa serve --mavlink udpin:0.0.0.0:14540 --arm-and-takeoff --decision-mode paced
  --envelope FILE --autopilot-fence [--mavlink-backend B]``; the envelope: inclusion 10 m inside
  the area, exclusion "mast" (45-85, 35-75) 0-40 m across the straight line from home to the hot
  spot, clearance 5 m, the area's band (25-100 m). Pass: ``fence`` "uploaded" before PX4 armed
  (API and HEARTBEAT; and on the wire: PX4's MISSION_ACK of the fence and the service's GF_*
  PARAM_SETs before its first arm command); the fence downloaded on the GCS link equals what
  the service sent (tap) and, within :data:`PLAN_TOLERANCE_E7` (5 degE7),
  ``service.fence.fence_plan(envelope, origin, frame, "px4", "rtl")`` around PX4's local origin
  (GPS_GLOBAL_ORIGIN; also recorded: the plan around the origin the service could compute, the
  last HOME_POSITION PX4 sent it before the upload minus its local x/y/z, and the fence's mean
  offset from each plan in metres); GF_ACTION and GF_MAX_VER_DIST read back are the plan's; the
  route is "around"; the 5 Hz track never enters the exclusion's footprint and stays in the
  inclusion; no geofence STATUSTEXT; the vehicle reached the target.
* ``breach``: no service. On one pymavlink connection to the API link (the *hook*, system 245):
  the same envelope as ``fence`` becomes ``fence_plan(..., "px4", "rtl")`` around PX4's origin,
  put on with :func:`service.mission_protocol.apply_fence_plan`; arm, take off to 25 m, OFFBOARD
  (position setpoints at 20 Hz), then setpoints to a point outside the inclusion
  (``--breach-point``, default (-60, 20, 25): 80 m west of home, 70 m outside). Pass: PX4 leaves
  OFFBOARD for AUTO.RTL (GF_ACTION 3, Return) with a geofence STATUSTEXT; where it was then, how
  far outside, and what it did until it landed are recorded.
* ``reserve``: the SIH battery drains (``SIM_BAT_DRAIN`` ``--drain-s``, 300 s from full to empty
  while armed; ``SIM_BAT_MIN_PCT`` 2), PX4's own low-battery failsafe below the service's
  reserve (``BAT_LOW_THR`` 0.10, ``BAT_CRIT_THR`` 0.07, ``BAT_EMERGEN_THR`` 0.05,
  ``COM_LOW_BAT_ACT`` 3: warn, Return at critical, Land at emergency), set on the GCS link
  before the service starts; ``tupa serve --mavlink udpin:0.0.0.0:14540 --arm-and-takeoff
  --decision-mode paced`` with its default reserve (20 %). Pass: the vehicle flew away (> 50 m),
  the service let go with "battery reserve reached", commanded MAV_CMD_NAV_RETURN_TO_LAUNCH
  (accepted), PX4 went to AUTO.RTL before any battery-failsafe STATUSTEXT, the tap saw no
  setpoint, mode request or command from the service after its return command, the metrics'
  setpoint and mode-request counters stood still, PX4 never showed OFFBOARD armed again, and it
  landed and disarmed.
* ``death``: the service flies the vehicle in OFFBOARD to the hot spot; ``--fly-s`` (10 s)
  after it is airborne and streaming, ``tupa serve`` gets SIGKILL (PX4 and the ground station
  stay); for ``--observe-s`` (60 s) the ground station samples mode, armed, altitude above home,
  drift from the kill point and PX4's landed state at 5 Hz and records every STATUSTEXT.
  ``--obl-rc-act default`` leaves PX4's defaults (COM_OF_LOSS_T 1, COM_OBL_RC_ACT 0, no RC);
  a number sets COM_OBL_RC_ACT before the flight (3 Return, 4 Land, 5 Hold, ...). Pass: recorded
  (the scenario measures; it passes when the kill happened in OFFBOARD and 60 s were observed).
* ``handback``: the service flies as in ``death``; ``--fly-s`` after airborne the ground station
  switches PX4 to ``--takeover`` (``hold``: AUTO.LOITER, ``land``: AUTO.LAND, ``posctl``: POSCTL)
  with MAV_CMD_DO_SET_MODE, and for ``--observe-s`` (30 s) the service's ``control``, the tap and
  PX4's modes are recorded. Pass: PX4 took the mode, the service let go within 5 s naming
  ``pilot`` or ``autopilot``, and sent no setpoint, mode request or command after it let go
  (tap; the metrics), and PX4 never showed OFFBOARD armed again. The speed limit too: the
  ground station reads ``MPC_XY_VEL_MAX`` (and ``MPC_XY_CRUISE``, ``MPC_VEL_MANUAL``, which PX4
  lowers to it) before the service starts, just before the takeover
  and after ``--observe-s``; pass when it was the envelope's (``--max-speed-mps``, default the
  area envelope's 10 m/s; the vehicle's own if lower) while the service flew, all three PX4's
  own again after, and the 5 Hz track never went faster than the envelope's limit
  (+ :data:`SPEED_TOLERANCE_MPS`) while the service flew.

Every process (PX4, ``tupa serve``) is started in its own session, killed by the kernel if this
driver dies, and stopped at the end of the run, also on failure; a run is bounded by
``--max-run-s``. The ULog is deleted unless ``--keep-ulog``.
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
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from shapely.geometry import Point, Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_sitl_handback import USERS
from sitl_harness import (
    ApiPoller,
    ReportPoster,
    append_run,
    ensure_private_namespace,
    parse_serve_log,
    start_child,
    start_serve,
    stop,
    wait_for_port,
)

from service.fence import FenceParam, fence_plan, plan_summary
from service.frames import (
    EARTH_RADIUS_M,
    FrameConfig,
    GeoPoint,
    area_to_ned,
    ned_to_area,
    ned_to_global,
)
from service.mission_protocol import (
    MavPort,
    MissionError,
    apply_fence_plan,
    download_fence,
    read_params,
    set_params,
)
from service.modes import mode_name, set_mode_numbers
from sim.config import AreaConfig
from sim.envelope import Envelope
from sim.envelope.files import envelope_from_document

MAV = mavutil.mavlink
REPO = Path(__file__).resolve().parents[1]
PX4_BUILD = Path("/root/sitl/px4/build/px4_sitl_default")
PX4_ENV = {
    "PX4_SYS_AUTOSTART": "10040",
    "PX4_SIMULATOR": "sihsim",
    "PX4_SIM_MODEL": "sihsim_quadx",
    "HEADLESS": "1",
}
SERVICE_PORT = 14540
"""Where PX4's API link sends and ``tupa serve`` (or the breach hook) listens."""
PX4_API_PORT = 14580
GCS_PORT = 14550
"""Where PX4's GCS link sends (from 18570) and the ground station listens."""
STATION_SYSTEM, STATION_COMPONENT = 250, 190
HOOK_SYSTEM = 245
AREA_ORIGIN_M = (-20.0, -20.0)
INCLUSION = [[10.0, 10.0], [490.0, 10.0], [490.0, 490.0], [10.0, 490.0]]
EXCLUSION = [[45.0, 35.0], [85.0, 35.0], [85.0, 75.0], [45.0, 75.0]]
ENVELOPE = {
    "format": "tupa-envelope/1",
    "inclusion": INCLUSION,
    "clearance_m": 5.0,
    "exclusions": [{"name": "mast", "polygon": EXCLUSION, "floor_m": 0.0, "ceiling_m": 40.0}],
}
SETPOINT_MESSAGES = ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT")
INFO_COMMANDS = {
    MAV.MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV.MAV_CMD_GET_MESSAGE_INTERVAL,
    MAV.MAV_CMD_REQUEST_MESSAGE,
    MAV.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    MAV.MAV_CMD_REQUEST_PROTOCOL_VERSION,
    MAV.MAV_CMD_REQUEST_CAMERA_INFORMATION,
    MAV.MAV_CMD_REQUEST_FLIGHT_INFORMATION,
    MAV.MAV_CMD_REQUEST_STORAGE_INFORMATION,
}
"""Commands that ask for information and command nothing (left out of "commands after")."""
BATTERY_FAILSAFE_WORDS = ("low battery", "critical battery", "emergency battery", "battery")
FENCE_WORDS = ("fence", "geofence")
POSITION_ONLY_MASK = 0b0000_1101_1111_1000  # position + yaw (PX4 wants a yaw or ignores it)
TAKEOVER_MODES = {"hold": "AUTO.LOITER", "land": "AUTO.LAND", "posctl": "POSCTL"}
SERVE_TAIL = 150
SPEED_PARAM = "MPC_XY_VEL_MAX"
SPEED_PARAMS = (SPEED_PARAM, "MPC_XY_CRUISE", "MPC_VEL_MANUAL")
"""The limit and the speeds PX4 lowers to it (cruise, the pilot's), read before, during, after."""
ENVELOPE_DEFAULT_SPEED_MPS = Envelope.for_area(AreaConfig()).max_speed_mps
"""``handback`` flies the area's envelope: this is its speed limit."""
SPEED_TOLERANCE_MPS = 0.5
"""How far above the limit a 5 Hz track's speed may read (its position noise and overshoot)."""
SO_ATTACH_FILTER = 26
PLAN_TOLERANCE_E7 = 5
"""How far (degE7, ~5.6 cm) a vertex read back may lie from ``fence_plan`` around PX4's origin
as the ground station reads it: the origin itself comes rounded to 1 degE7 (GPS_GLOBAL_ORIGIN) or
through float arithmetic (HOME_POSITION minus its local x/y/z), as the service computes it."""
LET_GO_LOG = re.compile(r"^the (autopilot|pilot|operator) has the vehicle")


def fastest_horizontal_mps(
    track: list[tuple[float, float, float, float]], from_s: float, to_s: float
) -> float | None:
    """The fastest horizontal speed between successive (t, north, east, down) samples of
    ``track`` within [from_s, to_s] (None with fewer than two)."""
    samples = [p for p in track if from_s <= p[0] <= to_s]
    speeds = [
        math.hypot(b[1] - a[1], b[2] - a[2]) / (b[0] - a[0])
        for a, b in itertools.pairwise(samples)
        if b[0] - a[0] >= 0.1
    ]
    return round(max(speeds), 2) if speeds else None


def rel(t0: float) -> float:
    return round(time.monotonic() - t0, 2)


def cmd_name(command: int) -> str:
    entry = MAV.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


def _num(value: float, digits: int = 3) -> float | None:
    """A JSON-able number: rounded, None for NaN or infinity (MAVSDK sends NaN params)."""
    value = float(value)
    return round(value, digits) if math.isfinite(value) else None


def _text(value: Any) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)


# ---------------------------------------------------------------------- PX4


def start_px4(build: Path, work: Path, log: Any) -> subprocess.Popen:
    """PX4 SITL (SIH quad X, headless) with ``work`` as its fresh working directory."""
    work.mkdir(parents=True)
    cmd = [
        str(build / "bin" / "px4"),
        "-d",
        "-i",
        "0",
        "-w",
        str(work),
        "-s",
        "etc/init.d-posix/rcS",
        str(build / "etc"),
    ]
    return start_child(cmd, log, cwd=work, env={**os.environ, **PX4_ENV})


def px4_version(build: Path) -> str | None:
    try:
        return subprocess.run(
            ["git", "-C", str(build.parents[1]), "log", "-1", "--format=%h %cd", "--date=short"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


# ---------------------------------------------------------------------- the ground station


class Station:
    """A ground station on PX4's GCS link: records what the vehicle says (see the module
    docstring); its connection can be lent to :mod:`service.mission_protocol`
    (:meth:`borrow`), the recording going on through ``on_other`` meanwhile."""

    def __init__(self, t0: float, url: str = f"udpin:0.0.0.0:{GCS_PORT}") -> None:
        self.t0 = t0
        self.conn = mavutil.mavlink_connection(
            url, source_system=STATION_SYSTEM, source_component=STATION_COMPONENT
        )
        self.io = threading.RLock()
        self.wanted = threading.Event()  # a borrower waits: the reader steps aside
        self.changed = threading.Condition()
        self.halt = threading.Event()
        self.modes: list[dict[str, Any]] = []
        self.heartbeats = 0
        self.last_hb: tuple[float, str, bool] | None = None
        self.texts: list[dict[str, Any]] = []
        self.battery: list[dict[str, Any]] = []
        self.track: list[tuple[float, float, float, float]] = []
        self.alts: list[tuple[float, float]] = []
        self.landed: list[dict[str, Any]] = []
        self.home: GeoPoint | None = None
        self.home_local: tuple[float, float, float] | None = None
        self.origin: GeoPoint | None = None
        self.homes: list[list[float]] = []  # each new HOME_POSITION: t, degE7, mm, local x/y/z
        self.origins: list[list[float]] = []  # each new GPS_GLOBAL_ORIGIN: t, degE7, mm
        self.params: dict[str, tuple[float, int]] = {}
        self.acks: list[dict[str, Any]] = []
        self._next_hb = 0.0
        self.thread = threading.Thread(target=self._run, name="station", daemon=True)
        self.thread.start()

    def idle(self) -> None:
        if time.monotonic() >= self._next_hb:
            self.conn.mav.heartbeat_send(
                MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, MAV.MAV_STATE_ACTIVE
            )
            self._next_hb = time.monotonic() + 1.0

    def _run(self) -> None:
        while not self.halt.is_set():
            if self.wanted.is_set():
                time.sleep(0.005)
                continue
            with self.io:
                try:
                    self.idle()
                    m = self.conn.recv_match(blocking=True, timeout=0.05)
                except (OSError, ValueError):
                    m = None
            if m is not None:
                self.handle(m)

    def handle(self, m: Any) -> None:
        if (m.get_srcSystem(), m.get_srcComponent()) != (1, 1):
            return
        kind = m.get_type()
        t = rel(self.t0)
        if kind == "HEARTBEAT":
            self.heartbeats += 1
            mode = mode_name("px4", m.custom_mode)
            armed = bool(m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
            state = (mode, armed, int(m.system_status))
            self.last_hb = (t, mode, armed)
            if (
                not self.modes
                or (
                    self.modes[-1]["mode"],
                    self.modes[-1]["armed"],
                    self.modes[-1]["system_status"],
                )
                != state
            ):
                with self.changed:
                    self.modes.append(
                        {"t": t, "mode": mode, "armed": armed, "system_status": state[2]}
                    )
                    self.changed.notify_all()
                print(f"{t:7.2f} PX4 mode {mode} armed {armed} status {state[2]}", flush=True)
        elif kind == "STATUSTEXT":
            self.texts.append({"t": t, "severity": int(m.severity), "text": _text(m.text)})
            print(f"{t:7.2f} STATUSTEXT {int(m.severity)} {_text(m.text)}", flush=True)
        elif kind == "LOCAL_POSITION_NED":
            self.track.append((t, round(m.x, 2), round(m.y, 2), round(m.z, 2)))
        elif kind == "GLOBAL_POSITION_INT":
            self.alts.append((t, round(m.relative_alt / 1000.0, 2)))
        elif kind == "SYS_STATUS":
            self.battery.append(
                {
                    "t": t,
                    "remaining_pct": int(m.battery_remaining),
                    "voltage_v": round(m.voltage_battery / 1000.0, 3),
                }
            )
        elif kind == "EXTENDED_SYS_STATE":
            if not self.landed or self.landed[-1]["state"] != m.landed_state:
                self.landed.append({"t": t, "state": int(m.landed_state)})
        elif kind == "HOME_POSITION":
            self.home = GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
            self.home_local = (float(m.x), float(m.y), float(m.z))
            seen = [m.latitude, m.longitude, m.altitude, *(round(v, 3) for v in self.home_local)]
            if not self.homes or self.homes[-1][1:] != seen:
                self.homes.append([t, *seen])
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
            seen = [m.latitude, m.longitude, m.altitude]
            if not self.origins or self.origins[-1][1:] != seen:
                self.origins.append([t, *seen])
        elif kind == "PARAM_VALUE":
            with self.changed:
                self.params[_text(m.param_id)] = (float(m.param_value), int(m.param_type))
                self.changed.notify_all()
        elif kind == "COMMAND_ACK":
            self.acks.append({"t": t, "command": cmd_name(m.command), "result": int(m.result)})

    @contextlib.contextmanager
    def borrow(self) -> Iterator[MavPort]:
        """The connection as a :class:`MavPort` (the reader thread waits meanwhile)."""
        with self._exclusive():
            yield MavPort.for_connection(self.conn, on_other=self.handle, on_idle=self.idle)

    @contextlib.contextmanager
    def _exclusive(self) -> Iterator[None]:
        self.wanted.set()
        try:
            with self.io:
                self.wanted.clear()
                yield
        finally:
            self.wanted.clear()

    def command(self, command: int, *params: float) -> None:
        values = [*params, *([0.0] * (7 - len(params)))]
        with self._exclusive():
            self.conn.mav.command_long_send(1, 1, command, 0, *values)

    def ask_intervals(self) -> None:
        for msg_id, hz in (
            (MAV.MAVLINK_MSG_ID_HEARTBEAT, 5),
            (MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 5),
            (MAV.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5),
            (MAV.MAVLINK_MSG_ID_SYS_STATUS, 2),
            (MAV.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2),
            (MAV.MAVLINK_MSG_ID_HOME_POSITION, 1),
            (MAV.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 1),
        ):
            self.command(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def ask_home(self) -> None:
        self.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_HOME_POSITION)
        self.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def param_type(self, name: str) -> int | None:
        """The MAV_PARAM_TYPE PX4 gives ``name`` (PARAM_REQUEST_READ), None without an answer."""
        for _ in range(3):
            with self.changed:
                self.params.pop(name, None)
            with self._exclusive():
                self.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
            deadline = time.monotonic() + 2.0
            with self.changed:
                while name not in self.params and time.monotonic() < deadline:
                    self.changed.wait(0.2)
                if name in self.params:
                    return self.params[name][1]
        return None

    def set_params(self, wanted: dict[str, float]) -> dict[str, float]:
        """Set each parameter with its own type (PX4's integers bit for bit) and read all back."""
        params = []
        for name, value in wanted.items():
            kind = self.param_type(name)
            if kind is None:
                raise MissionError(f"{name}: PX4 does not answer for it")
            params.append(FenceParam(name, value, kind))
        with self.borrow() as port:
            set_params(port, params, bytewise=True)
            return read_params(port, list(wanted), bytewise=True)

    def read_params(self, names: list[str]) -> dict[str, float | None]:
        out: dict[str, float | None] = {}
        for name in names:
            try:
                with self.borrow() as port:
                    out.update(read_params(port, [name], bytewise=True))
            except MissionError:
                out[name] = None
        return out

    def mode(self) -> str | None:
        return self.last_hb[1] if self.last_hb else None

    def armed(self) -> bool:
        return bool(self.last_hb and self.last_hb[2])

    def position(self) -> tuple[float, float, float, float] | None:
        return self.track[-1] if self.track else None

    def rel_alt(self) -> float | None:
        return self.alts[-1][1] if self.alts else None

    def battery_at(self, t: float) -> dict[str, Any] | None:
        before = [b for b in self.battery if b["t"] <= t]
        return before[-1] if before else None

    def origin_from_home(self) -> GeoPoint | None:
        """PX4's local origin as the service computes it: home minus home's local x/y/z."""
        if self.home is None or self.home_local is None:
            return None
        return ned_to_global(self.home, *(-v for v in self.home_local))

    def wait_heartbeat(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.heartbeats == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        return self.heartbeats > 0

    def close(self) -> None:
        self.halt.set()
        self.thread.join(3)
        with contextlib.suppress(OSError):
            self.conn.close()


# ---------------------------------------------------------------------- the tap


def _bpf_udp_port(port: int) -> bytes:
    """A classic BPF program: IPv4 UDP datagrams from or to ``port``, received side only
    (``lo`` shows each datagram twice: outgoing and incoming), whole packet kept."""
    code = [
        (0x28, 0, 0, 0x0000000C),  # ldh [12]            ethertype
        (0x15, 0, 12, 0x00000800),  # jeq IPv4
        (0x30, 0, 0, 0xFFFFF004),  # ldb pkttype
        (0x15, 10, 0, 0x00000004),  # jeq PACKET_OUTGOING -> drop
        (0x30, 0, 0, 0x00000017),  # ldb [23]            protocol
        (0x15, 0, 8, 0x00000011),  # jeq UDP
        (0x28, 0, 0, 0x00000014),  # ldh [20]            fragment offset
        (0x45, 6, 0, 0x00001FFF),  # jset -> drop
        (0xB1, 0, 0, 0x0000000E),  # ldxb 4*([14]&0xf)
        (0x48, 0, 0, 0x0000000E),  # ldh [x+14]          source port
        (0x15, 2, 0, port),  # jeq port -> accept
        (0x48, 0, 0, 0x00000010),  # ldh [x+16]          destination port
        (0x15, 0, 1, port),  # jeq port -> accept
        (0x06, 0, 0, 0x00040000),  # ret 262144 (accept)
        (0x06, 0, 0, 0x00000000),  # ret 0 (drop)
    ]
    return b"".join(struct.pack("HBBI", *c) for c in code)


def _frames(data: bytes) -> Iterator[tuple[int, int, int, bytes]]:
    """(msgid, system, component, frame) of each MAVLink frame in a datagram (v1 and v2)."""
    i = 0
    while i < len(data):
        magic = data[i]
        if magic == 0xFD and i + 10 <= len(data):
            length, incompat = data[i + 1], data[i + 2]
            size = 10 + length + 2 + (13 if incompat & 1 else 0)
            msgid = data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16
            yield msgid, data[i + 5], data[i + 6], data[i : i + size]
            i += size
        elif magic == 0xFE and i + 6 <= len(data):
            length = data[i + 1]
            size = 6 + length + 2
            yield data[i + 5], data[i + 3], data[i + 4], data[i : i + size]
            i += size
        else:
            return


class Tap:
    """Every UDP datagram to or from port 14540 on ``lo``, seen by a packet socket (nothing is
    relayed or changed): what the service (port 14540 -> PX4's 14580) sends, parsed and timed;
    PX4's COMMAND_ACKs and MISSION_ACKs to it."""

    ACK_IDS = (
        MAV.MAVLINK_MSG_ID_COMMAND_ACK,
        MAV.MAVLINK_MSG_ID_MISSION_ACK,
        MAV.MAVLINK_MSG_ID_HOME_POSITION,
    )

    def __init__(self, t0: float, port: int = SERVICE_PORT) -> None:
        self.t0 = t0
        self.port = port
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0003))
        program = _bpf_udp_port(port)
        self._filter, address = ctypes_buffer(program)  # kept alive with the socket
        fprog = struct.pack("HL", len(program) // 8, address)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
        self.sock.bind(("lo", 0))
        self.halt = threading.Event()
        self.lock = threading.Lock()
        self.from_service = MAV.MAVLink(None)
        self.from_service.robust_parsing = True
        self.from_vehicle = MAV.MAVLink(None)
        self.from_vehicle.robust_parsing = True
        self.datagrams = {"from_service": 0, "to_service": 0}
        self.sent_types: dict[str, int] = {}
        self.sent: list[tuple[float, str]] = []  # every message the service sent, timed
        self.setpoint_times: list[float] = []
        self.commands: list[dict[str, Any]] = []
        self.info_commands: dict[str, int] = {}
        self.acks: list[dict[str, Any]] = []
        self.params_set: list[dict[str, Any]] = []
        self.fence_items: dict[int, tuple[int, int, int, int, int]] = {}
        self.mission: list[dict[str, Any]] = []
        self.homes: list[list[float]] = []  # each new HOME_POSITION PX4 sent the service
        self.parse_errors = 0
        self.packets = 0
        """Datagrams seen so far: each record's ``i`` orders it on the wire (``t`` is rounded)."""
        self.thread = threading.Thread(target=self._run, name="tap", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.halt.is_set():
            ready, _, _ = select.select([self.sock], [], [], 0.3)
            if not ready:
                continue
            try:
                packet = self.sock.recv(65536)
            except OSError:
                return
            t = rel(self.t0)
            self.packets += 1
            try:
                self._packet(t, packet)
            except Exception:  # a parse error must never stop the tap
                self.parse_errors += 1

    def _packet(self, t: float, packet: bytes) -> None:
        ip = packet[14:]
        header = (ip[0] & 0x0F) * 4
        src_port, dst_port = struct.unpack("!HH", ip[header : header + 4])
        payload = ip[header + 8 :]
        if src_port == self.port:
            self.datagrams["from_service"] += 1
            messages = self.from_service.parse_buffer(payload) or []
            with self.lock:
                for m in messages:
                    if m.get_type() != "BAD_DATA":
                        self._from_service(t, m)
        elif dst_port == self.port:
            self.datagrams["to_service"] += 1
            for msgid, sysid, compid, frame in _frames(payload):
                if msgid not in self.ACK_IDS or (sysid, compid) != (1, 1):
                    continue
                for m in self.from_vehicle.parse_buffer(frame) or []:
                    with self.lock:
                        if m.get_type() == "COMMAND_ACK":
                            self.acks.append(
                                {
                                    "t": t,
                                    "i": self.packets,
                                    "command": cmd_name(m.command),
                                    "result": int(m.result),
                                }
                            )
                        elif m.get_type() == "HOME_POSITION":
                            seen = [
                                m.latitude,
                                m.longitude,
                                m.altitude,
                                *(round(float(v), 3) for v in (m.x, m.y, m.z)),
                            ]
                            if not self.homes or self.homes[-1][1:] != seen:
                                self.homes.append([t, *seen])
                        elif m.get_type() == "MISSION_ACK":
                            self.mission.append(
                                {
                                    "t": t,
                                    "i": self.packets,
                                    "kind": "MISSION_ACK from PX4",
                                    "type": int(m.type),
                                    "mission_type": int(m.mission_type),
                                }
                            )

    def _from_service(self, t: float, m: Any) -> None:
        kind = m.get_type()
        self.sent_types[kind] = self.sent_types.get(kind, 0) + 1
        self.sent.append((t, kind))
        if kind in SETPOINT_MESSAGES:
            self.setpoint_times.append(t)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            name = cmd_name(m.command)
            if m.command in INFO_COMMANDS:
                self.info_commands[name] = self.info_commands.get(name, 0) + 1
            else:
                self.commands.append(
                    {
                        "t": t,
                        "i": self.packets,
                        "kind": kind,
                        "command": name,
                        "params": [_num(p) for p in (m.param1, m.param2, m.param3)],
                    }
                )
        elif kind == "SET_MODE":
            self.commands.append(
                {"t": t, "kind": kind, "command": "SET_MODE", "params": [int(m.custom_mode)]}
            )
        elif kind == "PARAM_SET":
            self.params_set.append(
                {
                    "t": t,
                    "i": self.packets,
                    "name": _text(m.param_id),
                    "value": float(m.param_value),
                }
            )
        elif kind in ("MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_REQUEST_LIST"):
            self.mission.append(
                {"t": t, "kind": kind, "mission_type": int(getattr(m, "mission_type", 0))}
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

    def types_after(self, t: float) -> dict[str, int]:
        """What the service sent after ``t``, by message type."""
        with self.lock:
            out: dict[str, int] = {}
            for at, kind in self.sent:
                if at > t:
                    out[kind] = out.get(kind, 0) + 1
            return out

    def commands_after(self, t: float, but: str | None = None) -> list[dict[str, Any]]:
        with self.lock:
            return [c for c in self.commands if c["t"] > t and c["command"] != but]

    def summary(self) -> dict[str, Any]:
        with self.lock:
            times = list(self.setpoint_times)
            return {
                "datagrams": dict(self.datagrams),
                "sent_types": dict(sorted(self.sent_types.items())),
                "setpoints": len(times),
                "first_setpoint_s": times[0] if times else None,
                "last_setpoint_s": times[-1] if times else None,
                "commands": list(self.commands),
                "info_commands": dict(self.info_commands),
                "acks": list(self.acks),
                "params_set": list(self.params_set),
                "mission": list(self.mission),
                "fence_items": len(self.fence_items),
                "home_positions_to_service": self.homes[:50],
                "parse_errors": self.parse_errors,
            }

    def close(self) -> None:
        self.halt.set()
        self.thread.join(3)
        with contextlib.suppress(OSError):
            self.sock.close()


def ctypes_buffer(program: bytes) -> tuple[Any, int]:
    """The program in a C buffer, and its address (for ``struct sock_fprog``)."""
    import ctypes

    buf = ctypes.create_string_buffer(program)
    return buf, ctypes.addressof(buf)


# ---------------------------------------------------------------------- the breach hook


class Hook:
    """A companion of our own on the API link (system 245), for ``breach``: HEARTBEAT at 1 Hz,
    position setpoints at 20 Hz once :attr:`setpoint` is set; every vehicle message is also
    handed to the ground station's recorder."""

    def __init__(self, t0: float, station: Station) -> None:
        self.t0 = t0
        self.station = station
        self.conn = mavutil.mavlink_connection(
            f"udpin:0.0.0.0:{SERVICE_PORT}", source_system=HOOK_SYSTEM, source_component=191
        )
        self.setpoint: tuple[float, float, float] | None = None
        self.setpoints_sent = 0
        self.mode: str | None = None
        self.armed = False
        self.acks: dict[int, int] = {}
        self._next_hb = 0.0
        self._next_sp = 0.0

    def idle(self) -> None:
        now = time.monotonic()
        if now >= self._next_hb:
            self.conn.mav.heartbeat_send(
                MAV.MAV_TYPE_ONBOARD_CONTROLLER, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            self._next_hb = now + 1.0
        if self.setpoint is not None and now >= self._next_sp:
            n, e, d = self.setpoint
            self.conn.mav.set_position_target_local_ned_send(
                int((now - self.t0) * 1000) & 0xFFFFFFFF,
                1,
                1,
                MAV.MAV_FRAME_LOCAL_NED,
                POSITION_ONLY_MASK,
                n,
                e,
                d,
                0,
                0,
                0,
                0,
                0,
                0,
                0.0,
                0,
            )
            self.setpoints_sent += 1
            self._next_sp = now + 0.05

    def handle(self, m: Any) -> None:
        if (m.get_srcSystem(), m.get_srcComponent()) != (1, 1):
            return
        kind = m.get_type()
        if kind == "HEARTBEAT":
            self.mode = mode_name("px4", m.custom_mode)
            self.armed = bool(m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
        elif kind == "COMMAND_ACK":
            self.acks[int(m.command)] = int(m.result)

    def pump(self, seconds: float, until: Any = None) -> bool:
        """Read and send for ``seconds``, or until ``until()``; whether it came true."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.idle()
            m = self.conn.recv_match(blocking=True, timeout=0.02)
            while m is not None:
                self.handle(m)
                m = self.conn.recv_match(blocking=False)
            if until is not None and until():
                return True
        return until is not None and bool(until())

    def command(self, command: int, params: list[float], timeout_s: float = 3.0) -> int | None:
        """COMMAND_LONG, sent again each second until PX4's COMMAND_ACK; its result."""
        self.acks.pop(command, None)
        values = [*params, *([0.0] * (7 - len(params)))]
        for _ in range(max(1, int(timeout_s))):
            self.conn.mav.command_long_send(1, 1, command, 0, *values)
            if self.pump(1.0, lambda: command in self.acks):
                return self.acks[command]
        return None

    def port(self) -> MavPort:
        return MavPort.for_connection(self.conn, on_other=self.handle, on_idle=self.idle)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()


# ---------------------------------------------------------------------- the run


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scenario", choices=("fence", "breach", "reserve", "death", "handback"), required=True
    )
    parser.add_argument("--out", type=Path, required=True, help="a new directory for this run")
    parser.add_argument(
        "--json",
        type=Path,
        default=REPO / "benchmarks" / "results" / "real_px4_sitl.json",
        help="append the run to this JSON list (default benchmarks/results/real_px4_sitl.json)",
    )
    parser.add_argument("--px4-build", type=Path, default=PX4_BUILD)
    parser.add_argument("--mavlink-backend", choices=("pymavlink", "mavsdk"), default="pymavlink")
    parser.add_argument(
        "--area-origin-m", type=float, nargs=2, default=AREA_ORIGIN_M, metavar=("NORTH", "EAST")
    )
    parser.add_argument("--fly-s", type=float, default=10.0, help="death/handback: flown first")
    parser.add_argument("--observe-s", type=float, help="death 60, handback 30, breach 120")
    parser.add_argument("--fence-fly-s", type=float, default=120.0)
    parser.add_argument("--drain-s", type=float, default=300.0, help="reserve: SIM_BAT_DRAIN")
    parser.add_argument("--max-flight-s", type=float, default=420.0, help="reserve")
    parser.add_argument(
        "--sim-bat-drain-s",
        type=float,
        default=1800.0,
        help="fence, death, handback: SIM_BAT_DRAIN (PX4's default 60 s would trip the "
        "service's reserve seconds after the take-off)",
    )
    parser.add_argument(
        "--obl-rc-act",
        default="default",
        help="death: COM_OBL_RC_ACT to set (default: PX4's own, not set)",
    )
    parser.add_argument("--takeover", choices=sorted(TAKEOVER_MODES), default="hold")
    parser.add_argument(
        "--max-speed-mps",
        type=float,
        help="handback: the envelope's speed limit (default: the area's envelope, 10 m/s)",
    )
    parser.add_argument(
        "--breach-point",
        type=float,
        nargs=3,
        default=(-60.0, 20.0, 25.0),
        metavar=("X", "Y", "Z"),
        help="breach: the setpoint outside the inclusion, area frame (default -60 20 25)",
    )
    parser.add_argument("--max-run-s", type=float, default=900.0)
    parser.add_argument("--keep-ulog", action="store_true")
    parser.add_argument("--no-unshare", action="store_true", help="refuse outside a namespace")
    args = parser.parse_args()
    if args.observe_s is None:
        args.observe_s = {"death": 60.0, "handback": 30.0, "breach": 120.0}.get(args.scenario, 0)
    if (why := ensure_private_namespace(args.no_unshare)) is not None:
        print(f"refusing: {why}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # the finally below still runs

    def overrun(*_: Any) -> None:
        raise TimeoutError(f"the run took longer than --max-run-s {args.max_run_s:g}")

    signal.signal(signal.SIGALRM, overrun)
    signal.alarm(int(args.max_run_s))
    out: Path = args.out.resolve()
    out.mkdir(parents=True, exist_ok=False)
    frame = FrameConfig(
        area_origin_north_m=args.area_origin_m[0], area_origin_east_m=args.area_origin_m[1]
    )
    t0 = time.monotonic()
    t0_wall = time.time()
    result: dict[str, Any] = {
        "scenario": args.scenario,
        "autopilot": "PX4 SITL (SIH quad X, sihsim_quadx, headless)",
        "px4_version": px4_version(args.px4_build),
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "command": " ".join(
            ["benchmarks/real_px4_sitl.py", *[a for a in sys.argv[1:] if a != "--no-unshare"]]
        ),
        "area_origin_ned_m": [frame.area_origin_north_m, frame.area_origin_east_m],
        "passed": False,
    }
    if args.scenario in ("fence", "reserve", "death", "handback"):
        result["mavlink_backend"] = args.mavlink_backend
    events: list[tuple[float, str]] = []

    def note(text: str) -> None:
        events.append((rel(t0), text))
        print(f"{rel(t0):7.2f} {text}", flush=True)

    px4_log = open(out / "px4.log", "w")  # noqa: SIM115 (open for the whole run)
    serve_log_path = out / "serve.log"
    run = Run(args, result, note, t0, frame, out)
    try:
        run.px4 = start_px4(args.px4_build, out / "px4", px4_log)
        note(f"PX4 started (pid {run.px4.pid}), working directory {out / 'px4'}")
        run.station = Station(t0)
        if not run.station.wait_heartbeat(30):
            note("no HEARTBEAT from PX4 on the GCS link")
            return 1
        run.station.ask_intervals()
        note(f"ground station up: PX4 in {run.station.mode()}")
        if args.scenario == "breach":
            run.breach()
        else:
            run.with_service(serve_log_path)
        return 0 if result["passed"] else 1
    except Exception as exc:  # recorded, then the run is cleaned up
        note(f"error: {type(exc).__name__}: {exc}")
        result["error"] = f"{type(exc).__name__}: {exc}"
        return 1
    finally:
        signal.alarm(0)
        run.close()
        px4_log.close()
        if serve_log_path.exists():
            result["serve_log"] = parse_serve_log(serve_log_path, t0_wall)[-SERVE_TAIL:]
        if not args.keep_ulog:
            for ulog in (out / "px4").glob("log/**/*.ulg"):
                ulog.unlink()
        result["run_s"] = rel(t0)
        result["events"] = events
        print("PASS" if result["passed"] else "FAIL", flush=True)
        (out / "result.json").write_text(json.dumps(result, indent=1))
        if args.json:
            append_run(args.json, {k: v for k, v in result.items() if k != "events"})


class Run:
    """One scenario's processes, observers and steps."""

    def __init__(
        self,
        args: argparse.Namespace,
        result: dict[str, Any],
        note: Any,
        t0: float,
        frame: FrameConfig,
        out: Path,
    ) -> None:
        self.args, self.result, self.note, self.t0, self.frame, self.out = (
            args,
            result,
            note,
            t0,
            frame,
            out,
        )
        self.px4: subprocess.Popen | None = None
        self.serve: subprocess.Popen | None = None
        self.station: Station | None = None
        self.tap: Tap | None = None
        self.api: ApiPoller | None = None
        self.reports: ReportPoster | None = None
        self.hook: Hook | None = None
        self.envelope = envelope_from_document(ENVELOPE, AreaConfig())

    # ------------------------------------------------------------------ cleanup

    def close(self) -> None:
        r = self.result
        if self.reports is not None:
            self.reports.close()
            r["reports_posted"] = self.reports.codes
        if self.api is not None:
            self.api.close()
            r["service_timeline"] = self.api.timeline
            r["service_battery"] = self.api.battery
            r["service_routes"] = self.api.routes[:40]
            r["metrics"] = self.api.metrics[-400:]
            r["api_errors"] = self.api.errors
        if self.serve is not None:
            r["serve_exit"] = stop(self.serve)
        if self.hook is not None:
            self.hook.close()
        if self.tap is not None:
            self.tap.close()
            r["tap"] = self.tap.summary()
        if self.station is not None:
            st = self.station
            st.close()
            r["vehicle_mode_timeline"] = st.modes
            r["vehicle_heartbeats"] = st.heartbeats
            r["status_texts"] = st.texts
            r["vehicle_battery"] = st.battery[::4]
            r["landed_states"] = st.landed
            r["ground_station_acks"] = st.acks
            r["track_1hz"] = one_hz(st.track)
            r["home_positions"] = st.homes[:50]
            r["global_origins"] = st.origins[:50]
        if self.px4 is not None:
            r["px4_exit"] = stop(self.px4, grace_s=10.0)

    # ------------------------------------------------------------------ common steps

    def set_px4_params(self, wanted: dict[str, float]) -> None:
        assert self.station is not None
        got = self.station.set_params(wanted)
        self.result["params_set"] = got
        self.result["params_set_s"] = rel(self.t0)
        self.note(f"PX4 parameters set and read back: {got}")
        bad = {n: v for n, v in wanted.items() if abs(got.get(n, math.nan) - v) > 1e-3}
        if bad:
            raise RuntimeError(f"PX4 did not take {bad}")

    def start_service(self, serve_log_path: Path) -> None:
        args = self.args
        serve_args = [
            "--mavlink",
            f"udpin:0.0.0.0:{SERVICE_PORT}",
            "--arm-and-takeoff",
            "--decision-mode",
            "paced",
            "--mavlink-backend",
            args.mavlink_backend,
        ]
        if args.scenario == "fence":
            envelope_path = self.out / "envelope.json"
            envelope_path.write_text(json.dumps(ENVELOPE, indent=1))
            serve_args += ["--envelope", str(envelope_path), "--autopilot-fence"]
            self.result["envelope"] = ENVELOPE
        elif args.scenario == "handback" and args.max_speed_mps is not None:
            envelope_path = self.out / "envelope.json"
            document = {"format": "tupa-envelope/1", "max_speed_mps": args.max_speed_mps}
            envelope_path.write_text(json.dumps(document, indent=1))
            serve_args += ["--envelope", str(envelope_path)]
            self.result["envelope"] = document
        env = {
            "TUPA_AREA_ORIGIN_NORTH_M": str(self.frame.area_origin_north_m),
            "TUPA_AREA_ORIGIN_EAST_M": str(self.frame.area_origin_east_m),
        }
        self.tap = Tap(self.t0)
        self.serve, _token, headers, shown = start_serve(serve_args, serve_log_path, env)
        self.result["serve_command"] = (
            f"TUPA_AREA_ORIGIN_NORTH_M={env['TUPA_AREA_ORIGIN_NORTH_M']} "
            f"TUPA_AREA_ORIGIN_EAST_M={env['TUPA_AREA_ORIGIN_EAST_M']} TUPA_API_TOKEN=... " + shown
        )
        self.note("started: " + self.result["serve_command"])
        port = wait_for_port(self.serve, serve_log_path)
        if port is None:
            raise RuntimeError("tupa serve never listened")
        base = f"http://127.0.0.1:{port}"
        self.api = ApiPoller(base, headers, self.t0)
        self.reports = ReportPoster(base, headers, USERS, 0.5)
        self.note(f"tupa serve listening on {base}")

    def wait_airborne(self, timeout_s: float = 240.0) -> float:
        """Until the service has the vehicle airborne, in OFFBOARD and streaming; for ``fence``
        the fence is read back on the GCS link as soon as the service says it is uploaded."""
        assert self.api is not None and self.station is not None
        readback_done = False
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            v, _ = self.api.snapshot()
            if (
                self.args.scenario == "fence"
                and not readback_done
                and v is not None
                and v.get("fence") == "uploaded"
            ):
                readback_done = True
                self.result["fence_readback"] = self.fence_readback()
            if v is not None and v["takeoff"]["state"].startswith("failed"):
                raise RuntimeError(f"take-off failed: {v['takeoff']}")
            if (
                v is not None
                and v["takeoff"]["state"] == "airborne"
                and v["mode"] == "OFFBOARD"
                and v["streaming"]
            ):
                t = rel(self.t0)
                self.result["airborne_streaming_s"] = t
                self.result["armed_s"] = next(
                    (m["t"] for m in self.station.modes if m["armed"]), None
                )
                self.note(f"airborne, OFFBOARD and streaming; battery {v.get('battery')}")
                if self.args.scenario == "fence" and not readback_done:
                    self.result["fence_readback"] = self.fence_readback()
                return t
            if self.serve is not None and self.serve.poll() is not None:
                raise RuntimeError(f"tupa serve ended ({self.serve.returncode})")
            time.sleep(0.2)
        raise RuntimeError("never airborne in OFFBOARD and streaming")

    def origin(self) -> GeoPoint | None:
        """PX4's local origin (GPS_GLOBAL_ORIGIN), asked for until it comes."""
        assert self.station is not None
        for _ in range(10):
            if self.station.origin is not None and self.station.home is not None:
                break
            self.station.ask_home()
            time.sleep(1.0)
        return self.station.origin

    # ------------------------------------------------------------------ scenarios

    def with_service(self, serve_log_path: Path) -> None:
        args, st = self.args, self.station
        assert st is not None
        self.result["px4_defaults"] = st.read_params(
            [
                "COM_OF_LOSS_T",
                "COM_OBL_RC_ACT",
                "COM_RC_IN_MODE",
                "COM_RCL_EXCEPT",
                "NAV_RCL_ACT",
                "NAV_DLL_ACT",
                "GF_ACTION",
                "GF_MAX_VER_DIST",
                "GF_PREDICT",
                "RTL_RETURN_ALT",
                "RTL_DESCEND_ALT",
                "MPC_XY_CRUISE",
                "MPC_XY_VEL_MAX",
                "SIM_BAT_DRAIN",
                "SIM_BAT_MIN_PCT",
                "BAT_LOW_THR",
                "BAT_CRIT_THR",
                "BAT_EMERGEN_THR",
                "COM_LOW_BAT_ACT",
            ]
        )
        if args.scenario == "reserve":
            self.set_px4_params(
                {
                    "SIM_BAT_DRAIN": args.drain_s,
                    "SIM_BAT_MIN_PCT": 2.0,
                    "BAT_LOW_THR": 0.10,
                    "BAT_CRIT_THR": 0.07,
                    "BAT_EMERGEN_THR": 0.05,
                    "COM_LOW_BAT_ACT": 3,
                }
            )
        else:
            # PX4 SITL's own battery empties in 60 s (floored at 50 %): the service's reserve
            # would send the vehicle home seconds after the take-off. A 30-minute pack instead.
            wanted = {"SIM_BAT_DRAIN": args.sim_bat_drain_s}
            if args.scenario == "death" and args.obl_rc_act != "default":
                wanted["COM_OBL_RC_ACT"] = float(args.obl_rc_act)
            self.set_px4_params(wanted)
        if args.scenario == "handback":
            self.result["speed_params_before"] = self.station.read_params(list(SPEED_PARAMS))
        self.start_service(serve_log_path)
        airborne = self.wait_airborne()
        if args.scenario == "fence":
            self.fly_fence(airborne)
        elif args.scenario == "reserve":
            self.fly_reserve(airborne)
        elif args.scenario == "death":
            self.fly_death()
        else:
            self.fly_handback()

    # ---------------------------------------------------------------- fence

    def fence_readback(self) -> dict[str, Any]:
        """Download the fence on the GCS link and compare it with what the service sent (tap)
        and with :func:`fence_plan` around PX4's origin; read GF_ACTION and GF_MAX_VER_DIST."""
        assert self.station is not None and self.tap is not None
        r: dict[str, Any] = {"t": rel(self.t0)}
        origin = self.origin()
        from_home = self.station.origin_from_home()
        for name, point in (
            ("origin", origin),
            ("home", self.station.home),
            ("origin_from_home", from_home),
        ):
            r[name] = None if point is None else [point.lat_deg, point.lon_deg, point.alt_amsl_m]
        r["home_local_ned"] = self.station.home_local
        try:
            with self.station.borrow() as port:
                got = download_fence(port)
                r["downloaded_s"] = rel(self.t0)
                params = read_params(port, ["GF_ACTION", "GF_MAX_VER_DIST"], bytewise=True)
        except MissionError as exc:
            r["error"] = str(exc)
            self.note(f"fence read-back failed: {exc}")
            return r
        downloaded = [(i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in got]
        r["downloaded"] = downloaded
        r["frames_downloaded"] = sorted({i.frame for i in got})
        with self.tap.lock:
            sent = [self.tap.fence_items[s][:4] for s in sorted(self.tap.fence_items)]
        r["items_downloaded"] = len(downloaded)
        r["items_sent_by_service"] = len(sent)
        r["downloaded_equals_sent"] = downloaded == sent
        # The origin the service could compute (HOME_POSITION minus its local x/y/z) from the last
        # HOME_POSITION PX4 sent it before the fence upload began (the tap).
        with self.tap.lock:
            began = next(
                (m["t"] for m in self.tap.mission if m["kind"] == "MISSION_COUNT"), math.inf
            )
            homes = [h for h in self.tap.homes if h[0] <= began]
        service_origin = None
        if homes:
            _, lat, lon, alt, x, y, z = homes[-1]
            service_origin = ned_to_global(GeoPoint(lat / 1e7, lon / 1e7, alt / 1000.0), -x, -y, -z)
            r["service_home_before_upload"] = homes[-1]
            r["origin_from_service_home"] = [
                service_origin.lat_deg,
                service_origin.lon_deg,
                service_origin.alt_amsl_m,
            ]
        for label, point in (
            ("plan", origin),
            ("plan_from_home", from_home),
            ("plan_from_service_home", service_origin),
        ):
            if point is None:
                continue
            plan = fence_plan(self.envelope, point, self.frame, "px4", "rtl")
            expected = [(i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in plan.items]
            err = (
                max(
                    max(abs(a[2] - b[2]), abs(a[3] - b[3]))
                    for a, b in zip(downloaded, expected, strict=True)
                )
                if len(expected) == len(downloaded) and expected
                else None
            )
            r[f"max_error_vs_{label}_e7"] = err
            r[f"downloaded_equals_{label}"] = (
                err is not None
                and err <= PLAN_TOLERANCE_E7
                and [d[:2] for d in downloaded] == [e[:2] for e in expected]
            )
            if err is not None:
                # The fence's mean offset from the plan, metres north and east.
                dn = sum(a[2] - b[2] for a, b in zip(downloaded, expected, strict=True))
                de = sum(a[3] - b[3] for a, b in zip(downloaded, expected, strict=True))
                n = len(expected)
                r[f"offset_from_{label}_m"] = [
                    round(math.radians(dn / n / 1e7) * EARTH_RADIUS_M, 3),
                    round(
                        math.radians(de / n / 1e7)
                        * EARTH_RADIUS_M
                        * math.cos(math.radians(point.lat_deg)),
                        3,
                    ),
                ]
            if label == "plan":
                r["plan"] = plan_summary(plan)
                r["params"] = {
                    p.name: {"planned": p.value, "read_back": params.get(p.name)}
                    for p in plan.params
                }
                r["params_equal"] = all(
                    v["read_back"] is not None and abs(v["read_back"] - v["planned"]) <= 0.01
                    for v in r["params"].values()
                )
        with self.tap.lock:
            r["params_set_by_service"] = [
                p for p in self.tap.params_set if p["name"].startswith("GF_")
            ]
        self.note(
            f"fence read back: {len(downloaded)} items, equal to the service's upload "
            f"{r['downloaded_equals_sent']}, to the plan {r.get('downloaded_equals_plan')} "
            f"(max error {r.get('max_error_vs_plan_e7')} degE7), params {r.get('params')}"
        )
        return r

    def fly_fence(self, airborne: float) -> None:
        assert self.api is not None and self.station is not None and self.tap is not None
        at_target_since = None
        until = time.monotonic() + self.args.fence_fly_s
        while time.monotonic() < until:
            v, _ = self.api.snapshot()
            v = v or {}
            route = v.get("route") or {}
            wps = route.get("waypoints") or []
            pos = v.get("position")
            if wps and pos and len(wps) == 1:
                d = math.dist((pos["x_m"], pos["y_m"]), (wps[-1]["x_m"], wps[-1]["y_m"]))
                if d < 3.0:
                    at_target_since = at_target_since or time.monotonic()
                    if time.monotonic() - at_target_since > 10.0:
                        self.note(f"at the target {wps[-1]} for 10 s")
                        break
                else:
                    at_target_since = None
            if v.get("control", {}).get("holder") not in (None, "service"):
                self.note(f"the service let go during the fence flight: {v['control']}")
                break
            time.sleep(0.2)
        end, _ = self.api.snapshot()
        end = end or {}
        self.result["fence_flight_end"] = {
            k: end.get(k) for k in ("position", "mode", "control", "route", "fence")
        }
        uploaded = next((e["t"] for e in self.api.timeline if e["fence"] == "uploaded"), None)
        fences: list[tuple[float, str]] = []
        for e in self.api.timeline:
            if not fences or fences[-1][1] != e["fence"]:
                fences.append((e["t"], e["fence"]))
        armed_at = self.result.get("armed_s")
        route_kinds = sorted({r["kind"] for r in self.api.routes})
        around = next((r for r in self.api.routes if r["kind"] == "around"), None)
        footprint = Polygon(EXCLUSION)
        inclusion = Polygon(INCLUSION)
        track = [
            (t, *ned_to_area(n, e, d, self.frame))
            for t, n, e, d in list(self.station.track)
            if t >= (armed_at or airborne)
        ]
        inside = [p for p in track if footprint.contains(Point(p[1], p[2]))]
        dists = [footprint.distance(Point(p[1], p[2])) for p in track]
        outside_inclusion = [p for p in track if not inclusion.contains(Point(p[1], p[2]))]
        closest = min(range(len(dists)), key=dists.__getitem__) if dists else None
        fence_texts = [
            x for x in self.station.texts if any(w in x["text"].lower() for w in FENCE_WORDS)
        ]
        speeds = horizontal_speeds(track)
        dt = [b[0] - a[0] for a, b in itertools.pairwise(track)]
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
            "min_distance_to_exclusion_m": round(dists[closest], 2)
            if closest is not None
            else None,
            "closest_point": [round(c, 2) for c in track[closest]] if closest is not None else None,
            "track_points_outside_inclusion": len(outside_inclusion),
            "max_height_m": round(max(p[3] for p in track), 2) if track else None,
            "max_horizontal_speed_mps": round(max(speeds), 2) if speeds else None,
            "fence_statustexts": fence_texts,
            "reached_target_s": None if at_target_since is None else rel(self.t0),
        }
        # On the wire (the tap): PX4 accepted the fence and the service set GF_* before it
        # sent its first arm command.
        summary = self.tap.summary()
        acked = [
            m
            for m in summary["mission"]
            if m["kind"] == "MISSION_ACK from PX4" and m["type"] == 0 and m["mission_type"] == 1
        ]
        gf_set = [p for p in summary["params_set"] if p["name"].startswith("GF_")]
        arm_cmds = [
            c
            for c in summary["commands"]
            if c["command"] == "MAV_CMD_COMPONENT_ARM_DISARM" and c["params"][0] == 1.0
        ]
        r["wire"] = {
            "fence_accepted": acked[0] if acked else None,
            "gf_params_set": gf_set,
            "first_arm_command": arm_cmds[0] if arm_cmds else None,
        }
        # Ordered by the datagram index (the times are rounded to 10 ms).
        on_before_arm = (
            bool(acked and gf_set and arm_cmds)
            and acked[0]["i"] < arm_cmds[0]["i"]
            and max(p["i"] for p in gf_set) < arm_cmds[0]["i"]
        )
        self.result["fence"] = r
        readback = self.result.get("fence_readback") or {}
        checks = {
            "fence_uploaded_before_arming": r["uploaded_before_armed"],
            "fence_on_before_arm_command_on_the_wire": on_before_arm,
            "readback_equals_service_upload": bool(readback.get("downloaded_equals_sent"))
            and readback.get("items_downloaded", 0) > 0,
            "readback_equals_plan": bool(readback.get("downloaded_equals_plan")),
            "fence_params_read_back": bool(readback.get("params_equal")),
            "route_around": "around" in route_kinds,
            "track_never_in_exclusion": bool(track) and not inside,
            "track_inside_inclusion": bool(track) and not outside_inclusion,
            "no_fence_breach_text": not fence_texts,
            "reached_target": at_target_since is not None,
        }
        self.finish(checks)

    # ---------------------------------------------------------------- breach

    def breach(self) -> None:
        args, st, note = self.args, self.station, self.note
        assert st is not None
        self.result["px4_defaults"] = st.read_params(
            ["GF_ACTION", "GF_MAX_VER_DIST", "GF_PREDICT", "GF_SOURCE", "RTL_RETURN_ALT"]
        )
        self.tap = Tap(self.t0)
        self.hook = hook = Hook(self.t0, st)
        if not hook.pump(30, lambda: hook.mode is not None):
            raise RuntimeError("no HEARTBEAT on the API link")
        origin = self.origin()
        if origin is None or st.home is None:
            raise RuntimeError("no GPS_GLOBAL_ORIGIN / HOME_POSITION")
        plan = fence_plan(self.envelope, origin, self.frame, "px4", "rtl")
        self.result["plan"] = plan_summary(plan)
        self.result["origin"] = [origin.lat_deg, origin.lon_deg, origin.alt_amsl_m]
        try:
            report = apply_fence_plan(hook.port(), plan)
        except MissionError as exc:
            raise RuntimeError(f"apply_fence_plan: {exc}") from exc
        self.result["fence_report"] = {
            "items_sent": report.items_sent,
            "items_read_back": report.items_read_back,
            "params": report.params,
            "upload_s": report.upload_s,
            "download_s": report.download_s,
            "params_s": report.params_s,
            "resends": report.resends,
            "statustexts": list(report.statustexts),
        }
        note(f"fence on PX4 (apply_fence_plan): {self.result['fence_report']}")
        # Arm (PX4 refuses for its first seconds: health checks, EKF height settling).
        hook.pump(max(0.0, 15.0 - rel(self.t0)))
        armed = None
        for _ in range(20):
            armed = hook.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, [1.0])
            if armed == MAV.MAV_RESULT_ACCEPTED:
                break
            hook.pump(2.0)
        if armed != MAV.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"arming refused ({armed})")
        self.result["armed_s"] = rel(self.t0)
        home_amsl = st.home.alt_amsl_m
        took = hook.command(
            MAV.MAV_CMD_NAV_TAKEOFF, [0.0, 0.0, 0.0, math.nan, math.nan, math.nan, home_amsl + 25]
        )
        note(f"armed; take-off to {home_amsl + 25:.1f} m AMSL: {took}")
        if not hook.pump(60, lambda: (st.rel_alt() or 0) > 23.0 and hook.mode == "AUTO.LOITER"):
            raise RuntimeError(f"take-off did not end at 25 m (mode {hook.mode})")
        pos = st.position()
        assert pos is not None
        hook.setpoint = (pos[1], pos[2], pos[3])
        hook.pump(1.5)
        ok = hook.command(MAV.MAV_CMD_DO_SET_MODE, [1.0, *set_mode_numbers("px4", "OFFBOARD")])
        if not hook.pump(5, lambda: hook.mode == "OFFBOARD"):
            raise RuntimeError(f"OFFBOARD refused ({ok})")
        self.result["offboard_s"] = rel(self.t0)
        hook.pump(3.0)
        x, y, z = args.breach_point
        target = area_to_ned(x, y, z, self.frame)
        hook.setpoint = target
        pushed = rel(self.t0)
        self.result["breach_push"] = {"t": pushed, "area": [x, y, z], "ned": list(target)}
        note(f"pushing towards ({x:g}, {y:g}, {z:g}) in the area frame, NED {target}")
        left = hook.pump(60, lambda: hook.mode != "OFFBOARD")
        left_t = rel(self.t0)
        mode_after = hook.mode
        hook.setpoint = None
        note(f"PX4 left OFFBOARD: {left}, for {mode_after}")
        # Observe until disarmed or observe_s.
        hook.pump(args.observe_s, lambda: not hook.armed)
        hook.pump(2.0)
        inclusion = Polygon(INCLUSION)
        track = [(t, *ned_to_area(n, e, d, self.frame)) for t, n, e, d in st.track]

        def where(t: float) -> dict[str, Any] | None:
            before = [p for p in track if p[0] <= t]
            if not before:
                return None
            p = before[-1]
            signed = inclusion.exterior.distance(Point(p[1], p[2])) * (
                1 if not inclusion.contains(Point(p[1], p[2])) else -1
            )
            return {
                "t": p[0],
                "area": [round(c, 2) for c in p[1:]],
                "outside_by_m": round(signed, 2),
            }

        change = next((m for m in st.modes if m["t"] >= pushed and m["mode"] != "OFFBOARD"), None)
        fence_texts = [x for x in st.texts if any(w in x["text"].lower() for w in FENCE_WORDS)]
        after = [p for p in track if p[0] >= pushed]
        farthest = max(
            after,
            key=lambda p: (
                inclusion.exterior.distance(Point(p[1], p[2]))
                * (1 if not inclusion.contains(Point(p[1], p[2])) else -1)
            ),
            default=None,
        )
        rtl = next((m for m in st.modes if m["t"] >= pushed and m["mode"] == "AUTO.RTL"), None)
        disarmed = next((m["t"] for m in st.modes if m["t"] >= pushed and not m["armed"]), None)
        speeds_at = {}
        for label, at in (
            ("first_fence_text", fence_texts[0]["t"] if fence_texts else None),
            ("mode_change", change["t"] if change else None),
        ):
            near = [p for p in track if at is not None and at - 1.0 <= p[0] <= at + 0.2]
            sp = horizontal_speeds(near)
            speeds_at[label] = round(max(sp), 2) if sp else None
        r = {
            "pushed_s": pushed,
            "horizontal_speed_mps_before": speeds_at,
            "left_offboard_s": change["t"] if change else None,
            "mode_after": change["mode"] if change else mode_after,
            "rtl_s": rtl["t"] if rtl else None,
            "where_at_mode_change": where(change["t"]) if change else None,
            "where_at_first_fence_text": where(fence_texts[0]["t"]) if fence_texts else None,
            "farthest_outside": where(farthest[0]) if farthest else None,
            "fence_texts": fence_texts,
            "modes_after_push": [m for m in st.modes if m["t"] >= pushed],
            "disarmed_s": disarmed,
            "max_height_after_push_m": round(max((p[3] for p in after), default=0.0), 2),
            "setpoints_sent_by_hook": hook.setpoints_sent,
            "left_loop_s": left_t,
        }
        self.result["breach"] = r
        checks = {
            "fence_applied_and_read_back": report.items_read_back == report.items_sent > 0,
            "offboard_before_push": self.result.get("offboard_s") is not None,
            "left_offboard_for_rtl": r["mode_after"] == "AUTO.RTL",
            "fence_statustext": bool(fence_texts),
            "crossed_or_reached_the_edge": (r["farthest_outside"] or {}).get("outside_by_m", -99)
            > -5.0,
            "landed_disarmed": disarmed is not None,
        }
        self.finish(checks)

    # ---------------------------------------------------------------- reserve

    def fly_reserve(self, airborne: float) -> None:
        assert self.api is not None and self.station is not None and self.tap is not None
        st, api, tap, note = self.station, self.api, self.tap, self.note
        last_held = let_go = None
        deadline = time.monotonic() + self.args.max_flight_s
        while time.monotonic() < deadline:
            v, t = api.snapshot()
            if v is not None and v["control"]["holder"] == "service":
                last_held = {"t": t, **v}
            elif v is not None:
                let_go = {
                    "t": t,
                    "holder": v["control"]["holder"],
                    "reason": v["control"]["reason"],
                }
                note(f"service let go: {let_go}")
                break
            time.sleep(0.1)
        if let_go is None:
            note(f"the service still holds the vehicle after {self.args.max_flight_s:g} s")
            self.finish({"service_let_go": False})
            return
        self.result["service_let_go"] = let_go
        if last_held is not None:
            self.result["last_while_held"] = {
                k: last_held.get(k) for k in ("t", "battery", "position", "mode")
            }
        disarmed = self.wait_disarmed(airborne, 240.0)
        time.sleep(3.0)
        r = self.after_let_go(airborne, let_go)
        fs_texts = [
            x
            for x in st.texts
            if x["t"] >= airborne and any(w in x["text"].lower() for w in BATTERY_FAILSAFE_WORDS)
        ]
        t_fs = fs_texts[0]["t"] if fs_texts else None
        summary = tap.summary()
        rtl_cmds = [
            c for c in summary["commands"] if c["command"] == "MAV_CMD_NAV_RETURN_TO_LAUNCH"
        ]
        rtl_acks = [a for a in summary["acks"] if a["command"] == "MAV_CMD_NAV_RETURN_TO_LAUNCH"]
        t_rtl_cmd = rtl_cmds[0]["t"] if rtl_cmds else None
        t_rtl_mode = next(
            (m["t"] for m in st.modes if m["t"] >= airborne and m["mode"] == "AUTO.RTL"), None
        )
        cut = t_rtl_cmd if t_rtl_cmd is not None else r["t_let_go"]
        later = tap.commands_after(cut, but="MAV_CMD_NAV_RETURN_TO_LAUNCH")
        flown = [
            p for p in st.track if airborne <= p[0] <= (r["t_first_mode_after_offboard"] or 1e9)
        ]
        farthest = round(max((math.hypot(p[1], p[2]) for p in flown), default=0.0), 1)
        service_log = parse_serve_log(self.out / "serve.log", time.time() - rel(self.t0))
        reserve_lines = [e for e in service_log if "battery reserve reached" in e["text"]]
        r.update(
            {
                "farthest_from_home_m": farthest,
                "service_reserve_log": reserve_lines,
                "t_reserve_logged": reserve_lines[0]["t"] if reserve_lines else None,
                "t_rtl_command": t_rtl_cmd,
                "rtl_commands": rtl_cmds,
                "rtl_acks": rtl_acks,
                "t_rtl_mode": t_rtl_mode,
                "rtl_command_to_rtl_mode_s": (
                    round(t_rtl_mode - t_rtl_cmd, 2) if t_rtl_mode and t_rtl_cmd else None
                ),
                "t_first_battery_failsafe_text": t_fs,
                "battery_failsafe_texts": fs_texts,
                "setpoints_after_rtl_command": tap.setpoints_after(cut),
                "sent_after_rtl_command": tap.types_after(cut),
                "last_setpoint_s": summary["last_setpoint_s"],
                "commands_after_rtl_command": later,
                "vehicle_battery_at_rtl_command": st.battery_at(t_rtl_cmd or cut),
                "vehicle_battery_lowest_after_return": min(
                    (
                        b
                        for b in st.battery
                        if b["t"] >= cut and (not disarmed or b["t"] < disarmed)
                    ),
                    key=lambda b: b["remaining_pct"],
                    default=None,
                ),
                "service_battery_before_let_go": (self.result.get("last_while_held") or {}).get(
                    "battery"
                ),
                "disarmed_s": disarmed,
                "return_took_s": round(disarmed - cut, 2) if disarmed else None,
                "return_estimated_s": _estimate_s(self.result.get("last_while_held")),
            }
        )
        self.result["reserve"] = r
        checks = {
            "flew_away_from_home": farthest > 50.0,
            "let_go_reserve_reason": let_go["holder"] == "autopilot"
            and "battery reserve reached" in let_go["reason"],
            "rtl_commanded_and_accepted": bool(rtl_cmds)
            and any(a["result"] == MAV.MAV_RESULT_ACCEPTED for a in rtl_acks),
            "vehicle_in_rtl": t_rtl_mode is not None
            and r["first_mode_after_offboard"] == "AUTO.RTL",
            "rtl_before_any_battery_failsafe_text": t_rtl_mode is not None
            and (t_fs is None or t_fs > t_rtl_mode),
            "nothing_sent_after_rtl_command": not later and r["setpoints_after_rtl_command"] == 0,
            "setpoints_metric_flat": r["setpoints_metric_growth_after_let_go"] in (None, 0, 0.0),
            "mode_requests_metric_flat": r["mode_requests_metric_flat"],
            "never_offboard_armed_again": not r["offboard_armed_again"],
            "landed_disarmed": disarmed is not None,
        }
        self.finish(checks)

    def wait_disarmed(self, since: float, timeout_s: float) -> float | None:
        assert self.station is not None
        until = time.monotonic() + timeout_s
        while time.monotonic() < until:
            off = next((m for m in self.station.modes if m["t"] >= since and not m["armed"]), None)
            if off is not None:
                return off["t"]
            time.sleep(0.5)
        return None

    def after_let_go(self, airborne: float, let_go: dict[str, Any]) -> dict[str, Any]:
        """What the service did after it let go: the log line, the metrics, PX4's modes."""
        assert self.api is not None and self.station is not None
        st = self.station
        after = [m for m in st.modes if m["t"] >= airborne]
        first_off = next((m for m in after if m["mode"] != "OFFBOARD"), None)
        handover_t = first_off["t"] if first_off else let_go["t"]
        service_log = parse_serve_log(self.out / "serve.log", time.time() - rel(self.t0))
        logged = next(
            (e for e in service_log if e["t"] >= airborne and LET_GO_LOG.match(e["text"])),
            None,
        )
        t_let_go = logged["t"] if logged else let_go["t"]
        metrics = [m for m in self.api.metrics if "setpoints_sent" in m]
        after_metrics = [m for m in metrics if m["t"] >= let_go["t"] + 1.0]
        growth = (
            after_metrics[-1]["setpoints_sent"] - after_metrics[0]["setpoints_sent"]
            if after_metrics
            else None
        )
        requests = [m["mode_requests"] for m in after_metrics if "mode_requests" in m]
        offboard_again = [
            m for m in st.modes if m["t"] > handover_t and m["mode"] == "OFFBOARD" and m["armed"]
        ]
        return {
            "t_first_mode_after_offboard": first_off["t"] if first_off else None,
            "first_mode_after_offboard": first_off["mode"] if first_off else None,
            "t_let_go": t_let_go,
            "let_go_log": logged,
            "t_let_go_seen_by_api": let_go["t"],
            "let_go_after_mode_change_s": (
                round(let_go["t"] - first_off["t"], 2) if first_off else None
            ),
            "setpoints_metric_growth_after_let_go": growth,
            "mode_requests_metric": [requests[0], requests[-1]] if requests else None,
            "mode_requests_metric_flat": not requests or requests[-1] == requests[0],
            "offboard_armed_again": offboard_again,
            "modes_after": [m for m in st.modes if m["t"] >= handover_t],
        }

    # ---------------------------------------------------------------- death

    def fly_death(self) -> None:
        assert self.serve is not None and self.station is not None and self.api is not None
        st, note = self.station, self.note
        time.sleep(self.args.fly_s)
        v, _ = self.api.snapshot()
        pos = st.position()
        mode_at_kill = st.mode()
        kill_t = rel(self.t0)
        os.killpg(self.serve.pid, signal.SIGKILL)
        self.serve.wait(10)
        note(f"tupa serve killed (SIGKILL) in {mode_at_kill}, at NED {pos}, alt {st.rel_alt()}")
        self.api.close()
        if self.reports is not None:
            self.reports.close()
        samples = []
        start = time.monotonic()
        next_sample = start
        while time.monotonic() - start < self.args.observe_s:
            now = time.monotonic()
            if now >= next_sample:
                p = st.position()
                samples.append(
                    {
                        "t": round(now - start, 2),
                        "mode": st.mode(),
                        "armed": st.armed(),
                        "alt_m": st.rel_alt(),
                        "drift_m": (
                            round(math.hypot(p[1] - pos[1], p[2] - pos[2]), 2)
                            if p is not None and pos is not None
                            else None
                        ),
                        "landed_state": st.landed[-1]["state"] if st.landed else None,
                    }
                )
                next_sample += 0.2
            time.sleep(0.02)
        modes = [m for m in st.modes if m["t"] >= kill_t]
        texts = [x for x in st.texts if x["t"] >= kill_t]
        alts = [s["alt_m"] for s in samples if s["alt_m"] is not None]
        # MAV_LANDED_STATE_ON_GROUND (1) after the kill, and the mean descent rate on the way.
        on_ground = next((s["t"] for s in samples if s["landed_state"] == 1), None)
        disarmed = next((s["t"] for s in samples if not s["armed"]), None)
        first_change = next((m for m in modes if m["mode"] != mode_at_kill), None)
        descent = None
        if first_change is not None:
            from_t = first_change["t"] - kill_t + 3.0
            top = next((s for s in samples if s["t"] >= from_t and s["alt_m"] is not None), None)
            low = next(
                (s for s in samples if top and s["t"] > top["t"] and (s["alt_m"] or 0) < 2.0),
                None,
            )
            if top and low and low["t"] > top["t"]:
                descent = round((top["alt_m"] - low["alt_m"]) / (low["t"] - top["t"]), 2)
        r = {
            "kill_s": kill_t,
            "mode_at_kill": mode_at_kill,
            "position_at_kill_ned": pos,
            "alt_at_kill_m": alts[0] if alts else None,
            "service_view_at_kill": {k: (v or {}).get(k) for k in ("position", "mode", "route")},
            "modes_after_kill": [{**m, "after_kill_s": round(m["t"] - kill_t, 2)} for m in modes],
            "texts_after_kill": [{**x, "after_kill_s": round(x["t"] - kill_t, 2)} for x in texts],
            "first_mode_after_kill_s": (
                round(first_change["t"] - kill_t, 2) if first_change is not None else None
            ),
            "first_mode_after_kill": first_change["mode"] if first_change is not None else None,
            "on_ground_after_kill_s": on_ground,
            "disarmed_after_kill_s": disarmed,
            "mean_descent_mps": descent,
            "alt_min_m": min(alts) if alts else None,
            "alt_end_m": alts[-1] if alts else None,
            "drift_max_m": max((s["drift_m"] or 0 for s in samples), default=None),
            "drift_end_m": samples[-1]["drift_m"] if samples else None,
            "armed_end": samples[-1]["armed"] if samples else None,
            "alt_every_5s": [
                {k: s[k] for k in ("t", "mode", "armed", "alt_m", "drift_m", "landed_state")}
                for s in samples[::25]
            ],
            "samples": samples,
        }
        if self.args.obl_rc_act != "default":
            r["com_obl_rc_act"] = float(self.args.obl_rc_act)
        self.result["death"] = r
        seen = [(m["after_kill_s"], m["mode"]) for m in r["modes_after_kill"]]
        note(
            f"after the kill: modes {seen}, alt {r['alt_at_kill_m']} -> {r['alt_end_m']} m, "
            f"drift max {r['drift_max_m']} m"
        )
        self.finish(
            {
                "killed_in_offboard": mode_at_kill == "OFFBOARD",
                "observed_60s": len(samples) >= int(self.args.observe_s * 5 * 0.9),
            }
        )

    # ---------------------------------------------------------------- handback

    def fly_handback(self) -> None:
        assert self.station is not None and self.api is not None and self.tap is not None
        st, api, tap, note = self.station, self.api, self.tap, self.note
        airborne = self.result["airborne_streaming_s"]
        time.sleep(self.args.fly_s)
        speed_flying = st.read_params(list(SPEED_PARAMS))
        flown_to = rel(self.t0)
        wanted = TAKEOVER_MODES[self.args.takeover]
        main_mode, sub_mode = set_mode_numbers("px4", wanted)
        commanded = rel(self.t0)
        for _ in range(5):
            st.command(
                MAV.MAV_CMD_DO_SET_MODE,
                MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                main_mode,
                sub_mode,
            )
            time.sleep(1.0)
            if st.mode() == wanted:
                break
        note(f"ground station asked for {wanted}: PX4 in {st.mode()}")
        self.result["takeover"] = {"mode": wanted, "commanded_s": commanded}
        let_go = None
        until = time.monotonic() + 10.0
        while time.monotonic() < until and let_go is None:
            v, t = api.snapshot()
            if v is not None and v["control"]["holder"] != "service":
                let_go = {
                    "t": t,
                    "holder": v["control"]["holder"],
                    "reason": v["control"]["reason"],
                }
            time.sleep(0.05)
        note(f"service: {let_go}")
        time.sleep(self.args.observe_s)
        if let_go is None:
            self.finish({"service_let_go": False})
            return
        r = self.after_let_go(airborne, let_go)
        cut = r["t_let_go"]
        r.update(
            {
                "setpoints_after_let_go": tap.setpoints_after(cut),
                "sent_after_let_go": tap.types_after(cut),
                "commands_after_let_go": tap.commands_after(cut),
                "setpoints_between_mode_change_and_let_go": (
                    tap.setpoints_after(r["t_first_mode_after_offboard"]) - tap.setpoints_after(cut)
                    if r["t_first_mode_after_offboard"] is not None
                    else None
                ),
                "last_setpoint_s": tap.summary()["last_setpoint_s"],
                "let_go_holder": let_go["holder"],
                "let_go_reason": let_go["reason"],
            }
        )
        speed_after = st.read_params(list(SPEED_PARAMS))
        before = self.result["speed_params_before"]
        own_mps = before[SPEED_PARAM]
        fastest_mps = fastest_horizontal_mps(st.track, airborne, flown_to)
        limit_mps = self.args.max_speed_mps or ENVELOPE_DEFAULT_SPEED_MPS
        r.update(
            {
                "speed_params_while_flying": speed_flying,
                "speed_params_after_observing": speed_after,
                "envelope_max_speed_mps": limit_mps,
                "fastest_horizontal_mps_while_flying": fastest_mps,
            }
        )
        note(
            f"speeds: {before} before, {speed_flying} flying, {speed_after} after; "
            f"fastest {fastest_mps} m/s"
        )
        self.result["handback"] = r
        took = r["first_mode_after_offboard"] == wanted
        checks = {
            "px4_took_the_mode": took,
            "service_let_go_within_5s": r["let_go_after_mode_change_s"] is not None
            and r["let_go_after_mode_change_s"] <= 5.0,
            "holder_pilot_or_autopilot": let_go["holder"] in ("pilot", "autopilot"),
            "no_setpoint_after_let_go": r["setpoints_after_let_go"] == 0,
            "no_command_after_let_go": not r["commands_after_let_go"],
            "setpoints_metric_flat": r["setpoints_metric_growth_after_let_go"] in (None, 0, 0.0),
            "mode_requests_metric_flat": r["mode_requests_metric_flat"],
            "never_offboard_armed_again": not r["offboard_armed_again"],
            "envelope_speed_on_px4_while_flying": own_mps is not None
            and speed_flying[SPEED_PARAM] == min(limit_mps, own_mps),
            "flew_within_the_envelope_speed": fastest_mps is not None
            and fastest_mps <= limit_mps + SPEED_TOLERANCE_MPS,
            "own_speeds_back_after_let_go": own_mps is not None and speed_after == before,
        }
        self.finish(checks)

    # ---------------------------------------------------------------- verdict

    def finish(self, checks: dict[str, bool]) -> None:
        self.result["checks"] = checks
        self.result["passed"] = all(checks.values())
        print(f"{'PASS' if self.result['passed'] else 'FAIL'}: {checks}", flush=True)


def _estimate_s(held: dict[str, Any] | None, reserve_pct: float = 20.0) -> float | None:
    """How long the service reckoned the return would take when it let go: (its
    ``return_at_pct`` - the reserve) / its measured drain."""
    battery = (held or {}).get("battery") or {}
    at, drain = battery.get("return_at_pct"), battery.get("drain_pct_per_min")
    if at is None or not drain:
        return None
    return round((at - reserve_pct) / (drain / 60.0), 1)


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


if __name__ == "__main__":
    sys.exit(main())
