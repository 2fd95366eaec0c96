"""Does a real ArduCopter SITL take the envelope as its fence, give it back identical, and act on
a breach the way the mock says it does?

One run per call, with a fresh ArduCopter SITL (built from its own source outside this
repository: it is GPL) in DIR/sitl. SITLs bind every interface, so the run happens in a private
network namespace (only ``lo``): the script re-runs itself under ``unshare -n`` unless it is
already in one (``--no-unshare`` refuses instead)::

    .venv/bin/python benchmarks/real_sitl_fence.py \
        --arducopter /root/sitl/ardupilot/build/sitl/bin/arducopter \
        --defaults /root/sitl/ardupilot/Tools/autotest/default_params/copter.parm \
        --out runs/fence-1 --json benchmarks/results/real_sitl_fence.json

The run, on one pymavlink connection to SERIAL0 (tcp:127.0.0.1:5760, system 255 component 190,
its HEARTBEAT at 1 Hz; every HEARTBEAT mode and STATUSTEXT of the vehicle recorded):

1. the SITL (``--model quad --speedup 1 -w``); wait for its home (HOME_POSITION);
2. refusals: a MISSION_COUNT of 1000 fence items and a polygon of 2 vertices (what the autopilot
   answers and says);
3. the envelope (an inclusion pentagon around home, one exclusion 80 m east of home, a 60 m
   ceiling) becomes :func:`service.fence.fence_plan`'s plan; :func:`service.mission_protocol.
   apply_fence_plan` uploads it, reads it back and compares, sets the parameters and reads them
   back;
4. GUIDED, arm, take off to 20 m; then three pushes towards the outside:
   a. a position setpoint 200 m outside the inclusion (SET_POSITION_TARGET_LOCAL_NED, 2 Hz,
      8 s): taken or not (the vehicle moves or not);
   b. a velocity setpoint of 5 m/s east, towards the exclusion, with ``AVOID_ENABLE`` as it is
      (default 3: AC_Avoid stops at the fence), 20 s: the closest approach, any breach;
   c. the same with ``AVOID_ENABLE`` 0: the breach, its STATUSTEXT and the mode it goes to,
      observed ``--observe-s`` (25 s).

Writes DIR/result.json and the logs; with ``--json``, that file too (one run). SITL stopped at
the end of the run, also on failure.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import math
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from shapely.geometry import Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service.fence import (
    PARAM_INT,
    FenceItem,
    FenceParam,
    fence_plan,
    items_to_area,
    plan_summary,
)
from service.frames import FrameConfig, GeoPoint, area_to_ned, ned_to_area
from service.mission_protocol import (
    MavPort,
    MissionError,
    apply_fence_plan,
    download_fence,
    set_params,
    upload_fence,
)
from sim.envelope import Envelope, Exclusion

MAV = mavutil.mavlink
GCS_SYSTEM, GCS_COMPONENT = 255, 190
FRAME = FrameConfig(area_origin_north_m=-100.0, area_origin_east_m=-100.0)
"""Home sits at (100, 100) m in the area frame."""
INCLUSION = [(0.0, 0.0), (300.0, 0.0), (300.0, 250.0), (150.0, 320.0), (0.0, 250.0)]
EXCLUSION = [(180.0, 60.0), (240.0, 60.0), (240.0, 140.0), (180.0, 140.0)]
TAKEOFF_ALT_M = 20.0
VELOCITY_ONLY_MASK = 0b0000_1100_0111  # use vx, vy, vz; ignore position, accel, yaw, yaw rate
POSITION_ONLY_MASK = 0b0000_1111_1111_1000


def only_loopback() -> str | None:
    """Why this is not a private network namespace with ``lo`` up, or None when it is."""
    names = [name for _, name in socket.if_nameindex()]
    if names != ["lo"]:
        return f"network interfaces {names}: run inside `unshare -n` (only lo)"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        flags = struct.unpack("16sH", fcntl.ioctl(s, 0x8913, struct.pack("16sH", b"lo", 0)))[1]
    if not flags & 1:  # IFF_UP
        return "lo is down: `ip link set lo up` first"
    return None


class Vehicle:
    """The one connection: records the vehicle's modes, STATUSTEXTs and positions as every
    message passes (also while :mod:`service.mission_protocol` reads it), sends our HEARTBEAT
    at 1 Hz."""

    def __init__(self, url: str, t0: float) -> None:
        self.t0 = t0
        self.conn = mavutil.mavlink_connection(
            url, source_system=GCS_SYSTEM, source_component=GCS_COMPONENT, retries=60
        )
        self.modes: list[dict[str, Any]] = []
        self.texts: list[tuple[float, int, str]] = []
        self.ned: tuple[float, float, float] | None = None
        self.target: tuple[float, float, float] | None = None
        self.home: GeoPoint | None = None
        self.armed = False
        self.params: dict[str, float] = {}
        self._next_hb = 0.0

    def now(self) -> float:
        return round(time.monotonic() - self.t0, 2)

    def idle(self) -> None:
        if time.monotonic() >= self._next_hb:
            self.conn.mav.heartbeat_send(
                MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, MAV.MAV_STATE_ACTIVE
            )
            self._next_hb = time.monotonic() + 1.0

    def receive(self, timeout_s: float) -> Any | None:
        self.idle()
        m = self.conn.recv_match(blocking=True, timeout=timeout_s)
        if m is None or (m.get_srcSystem(), m.get_srcComponent()) != (1, 1):
            return m
        kind = m.get_type()
        if kind == "HEARTBEAT":
            mode = mavutil.mode_string_v10(m)
            self.armed = bool(m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
            if not self.modes or (self.modes[-1]["mode"], self.modes[-1]["armed"]) != (
                mode,
                self.armed,
            ):
                self.modes.append({"t": self.now(), "mode": mode, "armed": self.armed})
        elif kind == "STATUSTEXT":
            self.texts.append((self.now(), m.severity, m.text))
            print(f"{self.now():7.2f} STATUSTEXT {m.text}", flush=True)
        elif kind == "LOCAL_POSITION_NED":
            self.ned = (m.x, m.y, m.z)
        elif kind == "POSITION_TARGET_LOCAL_NED":
            self.target = (m.x, m.y, m.z)
        elif kind == "HOME_POSITION":
            self.home = GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1000.0)
        elif kind == "PARAM_VALUE":
            self.params[m.param_id] = m.param_value
        return m

    def pump(self, seconds: float) -> None:
        until = time.monotonic() + seconds
        while (left := until - time.monotonic()) > 0:
            self.receive(min(left, 0.1))

    def wait(self, what: str, condition: Any, timeout_s: float) -> bool:
        until = time.monotonic() + timeout_s
        while time.monotonic() < until:
            if condition():
                return True
            self.receive(0.1)
        print(f"{self.now():7.2f} timed out waiting for {what}", flush=True)
        return False

    def mode(self) -> str | None:
        return self.modes[-1]["mode"] if self.modes else None

    def command(self, command: int, *params: float) -> int | None:
        values = [*params, *([0.0] * (7 - len(params)))]
        self.conn.mav.command_long_send(1, 1, command, 0, *values)
        until = time.monotonic() + 3.0
        while time.monotonic() < until:
            m = self.receive(0.1)
            if m is not None and m.get_type() == "COMMAND_ACK" and m.command == command:
                return m.result
        return None

    def port(self) -> MavPort:
        return MavPort(
            send=self.conn.mav.send,
            receive=self.receive,
            own_system=GCS_SYSTEM,
        )

    def setpoint(self, ned: tuple[float, float, float] | None, vel: tuple[float, ...] = ()) -> None:
        if ned is not None:
            self.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, MAV.MAV_FRAME_LOCAL_NED, POSITION_ONLY_MASK, *ned, 0, 0, 0, 0, 0, 0, 0, 0
            )
        else:
            self.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, MAV.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, *vel, 0, 0, 0, 0, 0
            )


def envelope() -> Envelope:
    return Envelope(
        Polygon(INCLUSION),
        10.0,
        60.0,
        (Exclusion(Polygon(EXCLUSION), 0.0, 40.0, "tower"),),
        clearance_m=5.0,
    )


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--arducopter", type=Path, required=True, help="the SITL binary")
    parser.add_argument("--defaults", type=Path, required=True, help="copter.parm")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--json", type=Path, help="write the result here too")
    parser.add_argument("--observe-s", type=float, default=25.0)
    parser.add_argument("--no-unshare", action="store_true", help="refuse outside a namespace")
    args = parser.parse_args()
    if (why := only_loopback()) is not None:
        if args.no_unshare or not shutil.which("unshare"):
            print(f"refusing: {why}", file=sys.stderr)
            return 2
        inner = " ".join(_quote(a) for a in [sys.executable, *sys.argv, "--no-unshare"])
        return subprocess.call(["unshare", "-n", "bash", "-c", f"ip link set lo up; {inner}"])
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=False)
    (out / "sitl").mkdir()
    t0 = time.monotonic()
    result: dict[str, Any] = {"autopilot": "ArduCopter SITL", "passed": False}
    log_file = open(out / "autopilot.log", "w")  # noqa: SIM115 (open for the whole run)
    cmd = [
        str(args.arducopter.resolve()),
        "--model",
        "quad",
        "--speedup",
        "1",
        "-w",
        "--defaults",
        str(args.defaults.resolve()),
    ]
    ap = subprocess.Popen(
        cmd, cwd=out / "sitl", stdout=log_file, stderr=log_file, start_new_session=True
    )
    vehicle: Vehicle | None = None
    try:
        result["version"] = _version(args.arducopter)
        vehicle = Vehicle("tcp:127.0.0.1:5760", t0)
        result.update(run(vehicle, args))
    except Exception as exc:  # recorded, then the run is cleaned up
        result["error"] = f"{type(exc).__name__}: {exc}"
        print(f"error: {result['error']}", flush=True)
    finally:
        if vehicle is not None:
            result["vehicle_mode_timeline"] = vehicle.modes
            result["status_texts"] = vehicle.texts
            with contextlib.suppress(OSError):
                vehicle.conn.close()
        _stop(ap)
        log_file.close()
        result["run_s"] = round(time.monotonic() - t0, 1)
        text = json.dumps(result, indent=1)
        (out / "result.json").write_text(text)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(text + "\n")
    print("PASS" if result.get("passed") else "FAIL", flush=True)
    return 0 if result.get("passed") else 1


def run(v: Vehicle, args: argparse.Namespace) -> dict[str, Any]:
    r: dict[str, Any] = {}
    v.wait("the first HEARTBEAT", lambda: v.modes, 60)
    v.conn.mav.request_data_stream_send(1, 1, MAV.MAV_DATA_STREAM_ALL, 4, 1)
    v.command(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED, 2e5)
    # Home: once the EKF uses GPS (~40 s).
    ok = v.wait("EKF using GPS", lambda: any("using GPS" in t for _, _, t in v.texts), 120)
    for _ in range(10):
        if v.home is not None:
            break
        v.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_HOME_POSITION)
        v.pump(1.0)
    r["home_s"] = v.now()
    if not ok or v.home is None:
        r["failed_at"] = "home"
        return r
    home = v.home
    r["home"] = [home.lat_deg, home.lon_deg, home.alt_amsl_m]
    port = v.port()

    # Refusals.
    r["refusals"] = {}
    for name, count_items in (("too_many", 1000), ("vertex_count_2", 2)):
        plan = fence_plan(envelope(), home, FRAME)
        items = list(plan.items[:5])
        if name == "vertex_count_2":
            items = [FenceItem(i.command, 2, i.lat_e7, i.lon_e7) for i in items[:2]]
        else:
            items = items * (count_items // len(items))
        mark = len(v.texts)
        try:
            upload_fence(port, items)
            r["refusals"][name] = {"refused": False}
        except MissionError as exc:
            r["refusals"][name] = {
                "refused": True,
                "error": str(exc),
                "result": exc.result,
                "statustexts": [t for _, _, t in v.texts[mark:]],
            }
        print(f"{v.now():7.2f} refusal {name}: {r['refusals'][name]}", flush=True)

    # The plan: upload, read back, parameters.
    plan = fence_plan(envelope(), home, FRAME, "ardupilot", "rtl")
    r["plan"] = plan_summary(plan)
    try:
        report = apply_fence_plan(port, plan)
    except MissionError as exc:
        r["failed_at"] = f"apply_fence_plan: {exc}"
        return r
    r["fence_report"] = {
        "items_sent": report.items_sent,
        "items_read_back": report.items_read_back,
        "params": report.params,
        "upload_s": report.upload_s,
        "download_s": report.download_s,
        "params_s": report.params_s,
        "resends": report.resends,
        "statustexts": list(report.statustexts),
    }
    got = download_fence(port)
    r["read_back_identical"] = [(i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in got] == [
        (i.command, i.vertex_count, i.lat_e7, i.lon_e7) for i in plan.items
    ]
    r["read_back_frames"] = sorted({i.frame for i in got})
    polygons = items_to_area(got, home, FRAME)
    r["read_back_max_error_m"] = round(
        max(
            math.dist(a, b)
            for (_, ring), original in zip(polygons, (INCLUSION, EXCLUSION), strict=True)
            for a, b in zip(ring, original, strict=True)
        ),
        4,
    )
    print(f"{v.now():7.2f} fence applied: {r['fence_report']}", flush=True)

    # Take off.
    v.command(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
    armed = False
    for _ in range(20):
        if v.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV.MAV_RESULT_ACCEPTED:
            armed = True
            break
        v.pump(1.0)
    if not armed:
        r["failed_at"] = "arming"
        return r
    r["takeoff_ack"] = v.command(MAV.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, TAKEOFF_ALT_M)
    if not v.wait("take-off", lambda: v.ned is not None and -v.ned[2] > TAKEOFF_ALT_M - 1, 40):
        r["failed_at"] = "take-off"
        return r
    start = v.ned
    assert start is not None
    r["airborne_at_ned"] = [round(c, 2) for c in start]

    # a. A position setpoint outside the inclusion.
    outside_area = (100.0, 520.0, 20.0)  # 200 m north of the pentagon's top
    outside_ned = area_to_ned(*outside_area, FRAME)
    r["probe_position_outside"] = probe(
        v, lambda: v.setpoint(outside_ned), 8.0, start, f"position target {outside_area}"
    )
    v.setpoint(start)
    v.pump(4.0)

    # b. Velocity towards the exclusion, AVOID_ENABLE as it is.
    r["avoid_enable_default"] = _param(v, "AVOID_ENABLE")
    r["probe_velocity_avoid_on"] = probe(
        v, lambda: v.setpoint(None, (0.0, 5.0, 0.0)), 20.0, start, "5 m/s east, avoidance on"
    )
    if v.mode() == "GUIDED":
        v.setpoint(start)
        v.pump(12.0)

    # c. The same without avoidance.
    set_params(port, [FenceParam("AVOID_ENABLE", 0, PARAM_INT)], bytewise=False)
    r["probe_velocity_avoid_off"] = probe(
        v, lambda: v.setpoint(None, (0.0, 5.0, 0.0)), args.observe_s, start, "5 m/s east"
    )
    c = r["probe_velocity_avoid_off"]
    r["breach_mode"] = c["modes_after"][0] if c["modes_after"] else None
    r["passed"] = bool(
        r["read_back_identical"]
        and not r["probe_position_outside"]["moved_towards"]
        and any("fence breached" in t for t in c["statustexts"])
        and r["breach_mode"] == "RTL"
    )
    return r


def probe(v: Vehicle, push: Any, seconds: float, start: Any, what: str) -> dict[str, Any]:
    """Push at 2 Hz for ``seconds`` while the vehicle stays in GUIDED (and a little after):
    where it got to, the STATUSTEXTs and modes meanwhile."""
    print(f"{v.now():7.2f} probe: {what}", flush=True)
    texts, modes = len(v.texts), len(v.modes)
    t_start = v.now()
    until = time.monotonic() + seconds
    track = []
    while time.monotonic() < until:
        if v.mode() == "GUIDED":
            push()
        v.pump(0.5)
        if v.ned is not None:
            track.append((v.now(), *(round(c, 2) for c in v.ned)))
    end = v.ned or start
    area = ned_to_area(*end, FRAME)
    moved = math.dist(end[:2], start[:2])
    return {
        "what": what,
        "t": t_start,
        "moved_m": round(moved, 2),
        "moved_towards": moved > 5.0,
        "end_area_m": [round(c, 2) for c in area],
        "target_ned": v.target,
        "statustexts": [t for _, _, t in v.texts[texts:]],
        "modes_after": [m["mode"] for m in v.modes[modes:]],
        "track": track[:: max(1, len(track) // 20)],
    }


def _param(v: Vehicle, name: str) -> float | None:
    v.params.pop(name, None)
    v.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
    v.wait(name, lambda: name in v.params, 5)
    return v.params.get(name)


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


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)


def _quote(arg: str) -> str:
    return "'" + arg.replace("'", "'\\''") + "'"


if __name__ == "__main__":
    sys.exit(main())
