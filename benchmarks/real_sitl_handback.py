"""Does ``tupa serve`` let go of a real ArduCopter SITL when a ground station or a failsafe
lands it?

One run per call, with a fresh ArduCopter SITL (built from its own source outside this
repository: it is GPL) in DIR/sitl. SITLs bind every interface, so this refuses to run unless
``lo`` is the only network interface (a private network namespace)::

    unshare -n bash -c 'ip link set lo up; .venv/bin/python benchmarks/real_sitl_handback.py \
        --scenario land --arducopter ARDUPILOT/build/sitl/bin/arducopter \
        --defaults ARDUPILOT/Tools/autotest/default_params/copter.parm \
        --out runs/handback-land-1 --json benchmarks/results/real_sitl_handback.json'

The run: the SITL (``--model quad --speedup 1 -w``) and ``tupa serve --mavlink
tcp:127.0.0.1:5760 --arm-and-takeoff --decision-mode paced`` (token in ``TUPA_API_TOKEN``, a free
port); a report of three users every 0.5 s throughout; a ground station on SERIAL1
(tcp:127.0.0.1:5762, system 255 component 190, its own HEARTBEAT at 1 Hz) that records the
vehicle's mode from every vehicle HEARTBEAT (asked for at 5 Hz on its link). Once the service has
the vehicle airborne, in GUIDED and streaming, and has flown it ``--fly-s``, the takeover:

* ``land``: the ground station commands LAND (``MAV_CMD_DO_SET_MODE``);
* ``battery``: ``BATT_FS_LOW_ACT`` 1 (LAND) and ``BATT_LOW_VOLT`` 11.0 are set before the
  take-off; mid-flight ``SIM_BATT_VOLTAGE`` 10.5, and ArduCopter's battery failsafe lands the
  vehicle ``BATT_LOW_TIMER`` (10 s) later.

Then for ``--observe-s`` (30 s) from the vehicle's first HEARTBEAT in the new mode, the vehicle's
mode (HEARTBEATs) and the service's ``control`` (``GET /v1/vehicle`` at 5 Hz) are recorded, and
``GET /metrics`` each second (setpoints sent; a mode-request count if it is ever exposed). Pass:
the vehicle entered LAND or RTL, the service says ``autopilot`` (or ``pilot``) within
``--let-go-within-s`` (5 s) of it, the vehicle never shows GUIDED again, and the mode-request
count (where visible) does not grow. Seconds are from the SITL's start. Writes DIR/result.json,
the logs, and with ``--json`` appends the run to a results file (a list of runs, locked).
SITL and service are stopped at the end of the run, also on failure.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import re
import secrets
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

TUPA = Path(sys.executable).with_name("tupa")
USERS = [
    {"id": "ue-1", "x_m": 120.0, "y_m": 80.0, "offered_bps": 30e6},
    {"id": "ue-2", "x_m": 60.0, "y_m": 140.0, "offered_bps": 5e6},
    {"id": "ue-3", "x_m": 160.0, "y_m": 40.0, "offered_bps": 5e6},
]
GCS_SYSTEM, GCS_COMPONENT = 255, 190
VEHICLE_SYSTEM, VEHICLE_COMPONENT = 1, 1
LAND_MODE = 9  # ArduCopter custom mode number (mavutil.mode_mapping_acm)
BATTERY_PARAMS = {"BATT_FS_LOW_ACT": 1.0, "BATT_LOW_VOLT": 11.0}
TAKEN_MODES = ("LAND", "RTL")
SERVE_LOG_KEYS = re.compile(
    r"has the vehicle|mode|GUIDED|failsafe|Battery|control|link lost|link up|take-off", re.I
)


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


class GroundStation:
    """A MAVLink ground station on SERIAL1: its HEARTBEAT at 1 Hz, the vehicle's HEARTBEATs,
    PARAM_VALUEs, COMMAND_ACKs, STATUSTEXTs and battery voltage recorded (times from ``t0``)."""

    def __init__(self, url: str, t0: float) -> None:
        self.t0 = t0
        self.conn = mavutil.mavlink_connection(
            url, source_system=GCS_SYSTEM, source_component=GCS_COMPONENT, retries=30
        )
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.modes: list[dict[str, Any]] = []  # each change of (mode, armed, system_status)
        self.heartbeats = 0
        self.first_hb_t: float | None = None
        self.last_hb_t: float | None = None
        self.params: dict[str, float] = {}
        self.acks: list[dict[str, Any]] = []
        self.texts: list[tuple[float, str]] = []
        self.voltages: list[tuple[float, float]] = []
        self.changed = threading.Condition()
        threading.Thread(target=self._run, daemon=True).start()

    def now(self) -> float:
        return round(time.monotonic() - self.t0, 2)

    def send(self, fn: str, *a: Any) -> None:
        with self.lock:
            getattr(self.conn.mav, fn)(*a)

    def _run(self) -> None:
        next_hb = 0.0
        last_state = None
        while not self.stop.is_set():
            if time.monotonic() >= next_hb:
                self.send(
                    "heartbeat_send",
                    mavutil.mavlink.MAV_TYPE_GCS,
                    mavutil.mavlink.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    mavutil.mavlink.MAV_STATE_ACTIVE,
                )
                next_hb = time.monotonic() + 1.0
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):
                time.sleep(0.1)
                continue
            if m is None:
                continue
            if m.get_srcSystem() != VEHICLE_SYSTEM or m.get_srcComponent() != VEHICLE_COMPONENT:
                continue
            kind = m.get_type()
            t = self.now()
            if kind == "HEARTBEAT":
                self.heartbeats += 1
                self.first_hb_t = self.first_hb_t if self.first_hb_t is not None else t
                self.last_hb_t = t
                state = (
                    mavutil.mode_string_v10(m),
                    bool(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED),
                    m.system_status,
                )
                if state != last_state:
                    last_state = state
                    with self.changed:
                        self.modes.append(
                            {"t": t, "mode": state[0], "armed": state[1], "system_status": state[2]}
                        )
                        self.changed.notify_all()
            elif kind == "PARAM_VALUE":
                with self.changed:
                    self.params[m.param_id] = m.param_value
                    self.changed.notify_all()
            elif kind == "COMMAND_ACK":
                self.acks.append({"t": t, "command": m.command, "result": m.result})
            elif kind == "STATUSTEXT":
                self.texts.append((t, m.text))
            elif (
                kind == "SYS_STATUS"
                and m.voltage_battery not in (0, 65535)
                and (not self.voltages or t - self.voltages[-1][0] >= 1.0)
            ):
                self.voltages.append((t, round(m.voltage_battery / 1000.0, 2)))

    def mode(self) -> str | None:
        return self.modes[-1]["mode"] if self.modes else None

    def ask_intervals(self) -> None:
        """HEARTBEAT at 5 Hz and SYS_STATUS at 1 Hz on this link."""
        for msg_id, interval_us in ((0, 200_000), (1, 1_000_000)):
            self.send(
                "command_long_send",
                VEHICLE_SYSTEM,
                VEHICLE_COMPONENT,
                mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                msg_id,
                interval_us,
                0,
                0,
                0,
                0,
                0,
            )

    def set_param(self, name: str, value: float, tries: int = 5) -> float | None:
        """PARAM_SET until the vehicle's PARAM_VALUE echoes ``value``; the value it has then."""
        for _ in range(tries):
            with self.changed:
                self.params.pop(name, None)
            self.send(
                "param_set_send",
                VEHICLE_SYSTEM,
                VEHICLE_COMPONENT,
                name.encode(),
                value,
                mavutil.mavlink.MAV_PARAM_TYPE_REAL32,
            )
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
            self.send(
                "param_request_read_send", VEHICLE_SYSTEM, VEHICLE_COMPONENT, name.encode(), -1
            )
            deadline = time.monotonic() + 2.0
            with self.changed:
                while name not in self.params and time.monotonic() < deadline:
                    self.changed.wait(0.2)
                if name in self.params:
                    return self.params[name]
        return None

    def command_mode(self, custom_mode: int) -> None:
        self.send(
            "command_long_send",
            VEHICLE_SYSTEM,
            VEHICLE_COMPONENT,
            mavutil.mavlink.MAV_CMD_DO_SET_MODE,
            0,
            mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            custom_mode,
            0,
            0,
            0,
            0,
            0,
        )

    def close(self) -> None:
        self.stop.set()
        with contextlib.suppress(OSError):
            self.conn.close()


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenario", choices=("land", "battery"), required=True)
    parser.add_argument("--arducopter", type=Path, required=True, help="the SITL binary")
    parser.add_argument("--defaults", type=Path, required=True, help="copter.parm")
    parser.add_argument("--json", type=Path, help="append this run's result to this JSON list")
    parser.add_argument("--fly-s", type=float, default=10.0, help="flown by the service first")
    parser.add_argument("--observe-s", type=float, default=30.0)
    parser.add_argument("--let-go-within-s", type=float, default=5.0)
    parser.add_argument("--sim-batt-voltage", type=float, default=10.5)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if (why := only_loopback()) is not None:
        print(f"refusing: {why}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # the finally below still runs
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=False)
    run_dir = out / "sitl"
    run_dir.mkdir()
    events: list[tuple[float, str]] = []
    t0 = time.monotonic()

    def now() -> float:
        return round(time.monotonic() - t0, 2)

    def note(text: str) -> None:
        events.append((now(), text))
        print(f"{now():7.2f} {text}", flush=True)

    result: dict[str, Any] = {"scenario": args.scenario, "passed": False}
    ap_log = open(out / "autopilot.log", "w")  # noqa: SIM115 (open for the whole run)
    ap_cmd = [
        str(args.arducopter.resolve()),
        "--model",
        "quad",
        "--speedup",
        "1",
        "-w",
        "--defaults",
        str(args.defaults.resolve()),
    ]
    ap = subprocess.Popen(ap_cmd, cwd=run_dir, stdout=ap_log, stderr=ap_log, start_new_session=True)
    note("arducopter started: " + " ".join(ap_cmd))
    token = secrets.token_urlsafe(24)
    cmd = [
        str(TUPA),
        "serve",
        "--mavlink",
        "tcp:127.0.0.1:5760",
        "--arm-and-takeoff",
        "--decision-mode",
        "paced",
        "--port",
        "0",
    ]
    serve_log_path = out / "serve.log"
    serve_log = open(serve_log_path, "w")  # noqa: SIM115
    serve = subprocess.Popen(
        cmd,
        stdout=serve_log,
        stderr=serve_log,
        env={**os.environ, "TUPA_API_TOKEN": token},
        start_new_session=True,
    )
    note("tupa serve started: " + " ".join(cmd[1:]))
    gcs: GroundStation | None = None
    stop_reports = threading.Event()
    report_codes: dict[str, int] = {}
    api: httpx.Client | None = None
    try:
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
        api = httpx.Client(base_url=base, headers=headers, timeout=5.0)
        note(f"tupa serve listening on {base}")

        def post_reports() -> None:
            """A report of three users every 0.5 s, from start to end."""
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

        # The ground station on SERIAL1 (the SITL listens there once it runs).
        deadline = time.monotonic() + 60
        while gcs is None and time.monotonic() < deadline:
            try:
                gcs = GroundStation("tcp:127.0.0.1:5762", t0)
            except OSError:
                time.sleep(0.5)
        if gcs is None:
            note("no ground-station connection to tcp:127.0.0.1:5762")
            return 1
        deadline = time.monotonic() + 30
        while gcs.heartbeats == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        gcs.ask_intervals()
        note(f"ground station up, vehicle mode {gcs.mode()}")
        if args.scenario == "battery":
            result["battery_params"] = {
                name: gcs.set_param(name, value) for name, value in BATTERY_PARAMS.items()
            }
            result["battery_params"]["BATT_LOW_TIMER"] = gcs.get_param("BATT_LOW_TIMER")
            result["battery_params"]["BATT_MONITOR"] = gcs.get_param("BATT_MONITOR")
            note(f"battery failsafe set: {result['battery_params']}")

        # Take-off (the service's), then GUIDED and streaming.
        last_phase = None
        airborne = guided_streaming = None
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            try:
                v = api.get("/v1/vehicle").json()
            except (httpx.HTTPError, ValueError):
                time.sleep(0.3)
                continue
            phase = (v["takeoff"]["state"], v["takeoff"]["phase"], v["takeoff"]["attempts"])
            if phase != last_phase:
                note(f"take-off {phase} last refusal: {v['takeoff']['last_refusal']}")
                last_phase = phase
            if airborne is None and v["takeoff"]["state"] == "airborne":
                airborne = now()
                note(f"airborne, mode {v['mode']}")
            if airborne is not None and v["mode"] == "GUIDED" and v["streaming"]:
                guided_streaming = now()
                note(f"GUIDED and streaming, control {v['control']}")
                break
            if v["takeoff"]["state"].startswith("failed"):
                break
            time.sleep(0.2)
        result["airborne_s"] = airborne
        result["guided_streaming_s"] = guided_streaming
        if guided_streaming is None:
            note("never airborne in GUIDED and streaming")
            return 1
        # Fly: the paced loop decides every period (the same target set again and again).
        targets: list[dict[str, Any]] = []
        decisions_before = 0
        last_decided = None
        fly_until = time.monotonic() + args.fly_s
        while time.monotonic() < fly_until:
            sp = api.get("/v1/setpoint").json()
            if sp.get("decided_at") != last_decided:
                last_decided = sp.get("decided_at")
                decisions_before += 1
            if sp.get("target") and (not targets or targets[-1]["target"] != sp["target"]):
                targets.append({"t": now(), "target": sp["target"], "source": sp.get("source")})
                note(f"target {sp['target']}")
            time.sleep(0.25)
        result["targets"] = targets
        result["decisions_seen_while_flying"] = decisions_before
        before = api.get("/v1/vehicle").json()
        result["before_takeover"] = {
            k: before.get(k) for k in ("mode", "armed", "streaming", "position", "control")
        }
        if (holder := before["control"]["holder"]) != "service":
            note(f"the service does not hold the vehicle before the takeover: {holder}")
            return 1

        # The takeover.
        mark = len(gcs.modes)
        if args.scenario == "land":
            result["takeover_command_s"] = now()
            note("ground station: DO_SET_MODE LAND")
            for _ in range(3):
                gcs.command_mode(LAND_MODE)
                until = time.monotonic() + 2.0
                while time.monotonic() < until and gcs.mode() != "LAND":
                    time.sleep(0.05)
                if gcs.mode() == "LAND":
                    break
            wait_s = 10.0
        else:
            result["takeover_command_s"] = now()
            got = gcs.set_param("SIM_BATT_VOLTAGE", args.sim_batt_voltage)
            note(f"ground station: SIM_BATT_VOLTAGE {got}")
            wait_s = (result["battery_params"].get("BATT_LOW_TIMER") or 10.0) + 20.0
        taken = None
        until = time.monotonic() + wait_s
        while time.monotonic() < until and taken is None:
            taken = next((m for m in gcs.modes[mark:] if m["mode"] != "GUIDED"), None)
            time.sleep(0.05)
        result["command_acks"] = gcs.acks
        if taken is None:
            note(f"the vehicle never left GUIDED within {wait_s} s of the takeover")
            return 1
        result["takeover_s"] = taken["t"]
        result["takeover_mode"] = taken["mode"]
        note(f"vehicle HEARTBEAT: {taken['mode']} (takeover)")

        # Observe.
        control_timeline: list[dict[str, Any]] = []
        service_modes: list[tuple[float, str | None]] = []
        metrics: list[dict[str, Any]] = []
        let_go = None
        last_control = None
        next_metrics = 0.0
        decisions_after = 0
        until = t0 + taken["t"] + args.observe_s
        while time.monotonic() < until:
            try:
                v = api.get("/v1/vehicle").json()
            except (httpx.HTTPError, ValueError) as exc:
                note(f"GET /v1/vehicle failed: {exc}")
                time.sleep(0.2)
                continue
            c = v["control"]
            if (c["holder"], c["reason"]) != last_control:
                last_control = (c["holder"], c["reason"])
                control_timeline.append({"t": now(), "holder": c["holder"], "reason": c["reason"]})
                note(f"service control: {c['holder']} ({c['reason']})")
            if let_go is None and c["holder"] != "service":
                let_go = now()
            if not service_modes or service_modes[-1][1] != v["mode"]:
                service_modes.append((now(), v["mode"]))
            if "counters" in v and "mode_requests" in (v["counters"] or {}):
                result.setdefault("mode_requests_via", "GET /v1/vehicle counters")
            if time.monotonic() >= next_metrics:
                metrics.append(sample_metrics(api, v, now()))
                next_metrics = time.monotonic() + 1.0
                decided = api.get("/v1/setpoint").json().get("decided_at")
                if decided != last_decided:
                    last_decided = decided
                    decisions_after += 1
            time.sleep(0.2)
        end = api.get("/v1/vehicle").json()
        result["after"] = {k: end.get(k) for k in ("mode", "armed", "streaming", "control")}
        result["service_let_go_s"] = let_go
        result["let_go_after_takeover_s"] = (
            None if let_go is None else round(let_go - taken["t"], 2)
        )
        result["holder"] = control_timeline[-1]["holder"] if control_timeline else None
        result["reason"] = control_timeline[-1]["reason"] if control_timeline else None
        result["control_timeline"] = control_timeline
        result["service_mode_timeline"] = service_modes
        result["metrics"] = metrics
        result["decisions_seen_after_takeover"] = decisions_after
        after = [m for m in gcs.modes if m["t"] >= taken["t"]]
        reentries = [m for m in after if m["mode"] == "GUIDED"]
        result["guided_reentries"] = len(reentries)
        result["first_guided_reentry_s"] = reentries[0]["t"] if reentries else None
        requests = [m["mode_requests"] for m in metrics if m.get("mode_requests") is not None]
        result["mode_requests_visible"] = bool(requests)
        result["mode_requests_growth"] = requests[-1] - requests[0] if requests else None
        sent = [m["setpoints_sent"] for m in metrics if m.get("setpoints_sent") is not None]
        after_let_go = [
            m["setpoints_sent"]
            for m in metrics
            if let_go is not None and m["t"] >= let_go + 1.0 and m.get("setpoints_sent") is not None
        ]
        result["setpoints_sent_after_let_go"] = (
            after_let_go[-1] - after_let_go[0] if after_let_go else None
        )
        result["setpoints_sent_total"] = sent[-1] if sent else None
        result["observed_s"] = round(now() - taken["t"], 2)
        checks = {
            "taken_by_land_or_rtl": taken["mode"] in TAKEN_MODES,
            "let_go_in_time": result["let_go_after_takeover_s"] is not None
            and result["let_go_after_takeover_s"] <= args.let_go_within_s,
            "holder_autopilot_or_pilot": result["holder"] in ("autopilot", "pilot"),
            "never_guided_again": not reentries,
            "no_mode_requests": not requests or requests[-1] == requests[0],
        }
        result["checks"] = checks
        result["passed"] = all(checks.values())
        note(f"{'PASS' if result['passed'] else 'FAIL'}: {checks}")
        return 0 if result["passed"] else 1
    except Exception as exc:  # recorded, then the run is cleaned up
        note(f"error: {type(exc).__name__}: {exc}")
        result["error"] = f"{type(exc).__name__}: {exc}"
        return 1
    finally:
        stop_reports.set()
        result["reports_posted"] = report_codes
        if gcs is not None:
            result["vehicle_mode_timeline"] = gcs.modes
            result["vehicle_heartbeats"] = gcs.heartbeats
            if gcs.first_hb_t is not None and gcs.last_hb_t and gcs.last_hb_t > gcs.first_hb_t:
                span = gcs.last_hb_t - gcs.first_hb_t
                result["vehicle_heartbeat_hz"] = round((gcs.heartbeats - 1) / span, 2)
            result["status_texts"] = gcs.texts
            result["battery_voltage"] = gcs.voltages[-40:]
            gcs.close()
        stop(serve, serve.pid)
        stop(ap, ap.pid)
        serve_log.close()
        ap_log.close()
        result["serve_log"] = [
            line
            for line in serve_log_path.read_text(errors="replace").splitlines()
            if SERVE_LOG_KEYS.search(line) and "HTTP/1.1" not in line
        ][-60:]
        result["events"] = events
        (out / "result.json").write_text(json.dumps(result, indent=1))
        if args.json:
            append_run(args.json, {k: v for k, v in result.items() if k != "events"})


def sample_metrics(api: httpx.Client, vehicle: dict[str, Any], t: float) -> dict[str, Any]:
    """Setpoints sent and, if exposed anywhere, the link's guided-mode request count."""
    sample: dict[str, Any] = {"t": t, "setpoints_sent": None, "mode_requests": None}
    counters = vehicle.get("counters") or {}
    if "mode_requests" in counters:
        sample["mode_requests"] = counters["mode_requests"]
    try:
        text = api.get("/metrics").text
    except httpx.HTTPError:
        text = ""
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        name, _, value = line.rpartition(" ")
        if name == "tupa_setpoints_sent_total" or name.startswith("tupa_setpoints_sent{"):
            sample["setpoints_sent"] = float(value)
        elif "mode_request" in name and sample["mode_requests"] is None:
            sample["mode_requests"] = float(value)
    return sample


def stop(proc: subprocess.Popen, group: int | None) -> None:
    """SIGCONT + SIGTERM to the process (its group where it leads one), SIGKILL after 15 s."""
    if proc.poll() is not None:
        return
    try:
        if group is not None:
            os.killpg(group, signal.SIGCONT)
            os.killpg(group, signal.SIGTERM)
        else:
            proc.terminate()
    except ProcessLookupError:
        return
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        if group is not None:
            os.killpg(group, signal.SIGKILL)
        else:
            proc.kill()
        proc.wait(5)


def append_run(path: Path, run: dict[str, Any]) -> None:
    """Append to the JSON list at ``path`` under an exclusive lock (runs may end together)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.seek(0)
        text = f.read()
        runs = json.loads(text) if text.strip() else []
        runs.append(run)
        f.seek(0)
        f.truncate()
        f.write(json.dumps(runs, indent=1))


if __name__ == "__main__":
    sys.exit(main())
