"""What does a real ArduCopter SITL do for 60 s after ``tupa serve`` dies mid-flight?

One run per call, with a fresh ArduCopter SITL (built from its own source outside this
repository: it is GPL) in DIR/sitl. SITLs bind every interface, so the run happens in a private
network namespace (only ``lo``): the script re-runs itself under ``unshare -n`` unless it is
already in one (``--no-unshare`` refuses instead)::

    .venv/bin/python benchmarks/real_sitl_service_death.py --scenario default \
        --arducopter /root/sitl/ardupilot/build/sitl/bin/arducopter \
        --defaults /root/sitl/ardupilot/Tools/autotest/default_params/copter.parm \
        --out runs/service-death/default-1 --json benchmarks/results/real_sitl_service_death.json

The flight is ``real_sitl_handback.py``'s (its helpers are imported): the SITL (``--model quad
--speedup 1 -w``), ``tupa serve --mavlink tcp:127.0.0.1:5760 --arm-and-takeoff --decision-mode
paced`` (token in ``TUPA_API_TOKEN``), a report of three users every 0.5 s, a ground station on
SERIAL1 (tcp:127.0.0.1:5762, system 255 component 190). Once the service has the vehicle
airborne, in GUIDED and streaming, and has flown it ``--fly-s`` (10 s), ``tupa serve`` gets
SIGKILL (the SITL and the ground station stay), and for ``--observe-s`` (60 s) from the kill the
ground station samples at 5 Hz the vehicle's mode and armed state (HEARTBEAT), its altitude
(GLOBAL_POSITION_INT ``relative_alt``) and its horizontal drift from where it was at the kill
(LOCAL_POSITION_NED), all asked for at 5 Hz on its link, and records every STATUSTEXT.

Scenarios:

* ``default``: copter.parm as is. ``GUID_TIMEOUT``, ``FS_GCS_ENABLE``, ``FS_GCS_TIMEOUT``,
  ``FS_OPTIONS``, ``FS_THR_ENABLE`` and ``MAV_GCS_SYSID`` are read (PARAM_REQUEST_READ) and
  recorded.
  The ground station sends its HEARTBEAT at 1 Hz as system 255, as in the handback script.
* ``gcs-failsafe``: ``FS_GCS_ENABLE`` 1 (RTL) and ``FS_GCS_TIMEOUT`` 5 are set before the
  take-off. ArduCopter's GCS failsafe counts only HEARTBEATs (and RC override / MANUAL_CONTROL)
  from system ``MAV_GCS_SYSID`` (255), and the ground station here is system 255 too, so in this
  scenario it sends **no HEARTBEAT at all** (for the whole run): it only sets and reads
  parameters, asks for message intervals before the take-off, and reads. The service (system 255
  by default) is then the only GCS the vehicle hears.
* ``rc-failsafe``: ``FS_THR_ENABLE`` 1 (the radio failsafe: RTL when the RC link is lost) set
  before the take-off, the ground station's HEARTBEAT as in ``default``. The SITL's simulated RC
  stays connected: what an RC failsafe does when only the service dies.

Seconds are from the SITL's start; the samples' ``t`` from the kill. Writes DIR/result.json,
DIR/autopilot.log, DIR/serve.log; with ``--json`` appends the run to a results file (a list of
runs, locked). SITL and service are stopped at the end of the run, also on failure.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_sitl_handback import USERS, GroundStation, append_run, only_loopback, stop

TUPA = Path(sys.executable).with_name("tupa")
READ_PARAMS = (
    "GUID_TIMEOUT",
    "FS_GCS_ENABLE",
    "FS_GCS_TIMEOUT",
    "FS_OPTIONS",
    "FS_THR_ENABLE",
    "MAV_GCS_SYSID",  # older builds: SYSID_MYGCS
)
GCS_FAILSAFE_PARAMS = {"FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 5.0}
RC_FAILSAFE_PARAMS = {"FS_THR_ENABLE": 1.0}  # radio (throttle) failsafe: RTL on RC loss
STREAMS_US = {0: 200_000, 32: 200_000, 33: 200_000}  # HEARTBEAT, LOCAL_POSITION_NED, GLOBAL_POS


class QuietableGroundStation(GroundStation):
    """The handback ground station; with ``quiet`` it never sends its own HEARTBEAT."""

    quiet = False

    def send(self, fn: str, *a: Any) -> None:
        if fn == "heartbeat_send" and self.quiet:
            return
        super().send(fn, *a)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--scenario", choices=("default", "gcs-failsafe", "rc-failsafe"), required=True
    )
    parser.add_argument("--arducopter", type=Path, required=True, help="the SITL binary")
    parser.add_argument("--defaults", type=Path, required=True, help="copter.parm")
    parser.add_argument("--json", type=Path, help="append this run's result to this JSON list")
    parser.add_argument("--fly-s", type=float, default=10.0, help="flown by the service first")
    parser.add_argument("--observe-s", type=float, default=60.0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-unshare", action="store_true", help="refuse outside a namespace")
    args = parser.parse_args()
    if (why := only_loopback()) is not None:
        if args.no_unshare or not shutil.which("unshare"):
            print(f"refusing: {why}", file=sys.stderr)
            return 2
        inner = " ".join(_quote(a) for a in [sys.executable, *sys.argv, "--no-unshare"])
        return subprocess.call(["unshare", "-n", "bash", "-c", f"ip link set lo up; {inner}"])
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

    result: dict[str, Any] = {"scenario": args.scenario, "completed": False}
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
    result["serve_command"] = " ".join(cmd[1:])
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
    gcs: QuietableGroundStation | None = None
    stop_reports = threading.Event()
    report_codes: dict[str, int] = {}
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
            """A report of three users every 0.5 s until the service is killed."""
            client = httpx.Client(base_url=base, headers=headers, timeout=2.0)
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

        QuietableGroundStation.quiet = args.scenario == "gcs-failsafe"
        deadline = time.monotonic() + 60
        while gcs is None and time.monotonic() < deadline:
            try:
                gcs = QuietableGroundStation("tcp:127.0.0.1:5762", t0)
            except OSError:
                time.sleep(0.5)
        if gcs is None:
            note("no ground-station connection to tcp:127.0.0.1:5762")
            return 1
        result["ground_station_heartbeats"] = not gcs.quiet
        deadline = time.monotonic() + 30
        while gcs.heartbeats == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        for msg_id, interval_us in STREAMS_US.items():
            gcs.send(
                "command_long_send",
                1,
                1,
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
        note(f"ground station up (own HEARTBEAT: {not gcs.quiet}), vehicle mode {gcs.mode()}")
        if args.scenario in ("gcs-failsafe", "rc-failsafe"):
            wanted = GCS_FAILSAFE_PARAMS if args.scenario == "gcs-failsafe" else RC_FAILSAFE_PARAMS
            result["params_set"] = {n: gcs.set_param(n, v) for n, v in wanted.items()}
            note(f"failsafe set: {result['params_set']}")
        result["params"] = {name: gcs.get_param(name) for name in READ_PARAMS}
        note(f"parameters: {result['params']}")

        # Take-off (the service's), then GUIDED and streaming.
        last_phase = None
        guided_streaming = None
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
            if v["takeoff"]["state"] == "airborne" and v["mode"] == "GUIDED" and v["streaming"]:
                guided_streaming = now()
                note(f"airborne, GUIDED and streaming, control {v['control']}")
                break
            if v["takeoff"]["state"].startswith("failed"):
                break
            time.sleep(0.2)
        result["guided_streaming_s"] = guided_streaming
        if guided_streaming is None:
            note("never airborne in GUIDED and streaming")
            return 1
        fly_until = time.monotonic() + args.fly_s
        targets: list[Any] = []
        while time.monotonic() < fly_until:
            with_target = api.get("/v1/setpoint").json().get("target")
            if with_target and (not targets or targets[-1][1] != with_target):
                targets.append((now(), with_target))
            time.sleep(0.25)
        result["targets"] = targets
        before = api.get("/v1/vehicle").json()
        result["before_kill"] = {
            k: before.get(k) for k in ("mode", "armed", "streaming", "control")
        }
        api.close()

        # The service dies.
        stop_reports.set()
        os.killpg(serve.pid, signal.SIGKILL)
        kill_t = now()
        serve.wait(5)
        result["kill_s"] = kill_t
        note(f"tupa serve killed (SIGKILL), exit {serve.returncode}")
        texts_mark = len(gcs.texts)
        lp0 = gcs.conn.messages.get("LOCAL_POSITION_NED")
        gp0 = gcs.conn.messages.get("GLOBAL_POSITION_INT")
        if lp0 is None or gp0 is None:
            note("no LOCAL_POSITION_NED / GLOBAL_POSITION_INT on the ground-station link")
            return 1
        x0, y0 = lp0.x, lp0.y
        alt0 = gp0.relative_alt / 1000.0
        result["at_kill"] = {"north_m": round(x0, 2), "east_m": round(y0, 2), "alt_m": alt0}
        samples: list[dict[str, Any]] = []
        next_t = time.monotonic()
        until = t0 + kill_t + args.observe_s
        while time.monotonic() < until:
            lp = gcs.conn.messages.get("LOCAL_POSITION_NED")
            gp = gcs.conn.messages.get("GLOBAL_POSITION_INT")
            last = gcs.modes[-1] if gcs.modes else {}
            samples.append(
                {
                    "t": round(now() - kill_t, 2),
                    "mode": last.get("mode"),
                    "armed": last.get("armed"),
                    "alt_m": round(gp.relative_alt / 1000.0, 2),
                    "drift_m": round(math.hypot(lp.x - x0, lp.y - y0), 2),
                    "north_m": round(lp.x, 2),
                    "east_m": round(lp.y, 2),
                    "boot_ms": gp.time_boot_ms,
                }
            )
            next_t += 0.2
            time.sleep(max(0.0, next_t - time.monotonic()))
        result["samples"] = samples
        result["status_texts_after_kill"] = [
            (round(t - kill_t, 2), text) for t, text in gcs.texts[texts_mark:]
        ]
        modes_after = [{**m, "t": round(m["t"] - kill_t, 2)} for m in gcs.modes if m["t"] >= kill_t]
        result["mode_changes_after_kill"] = modes_after
        alts = [s["alt_m"] for s in samples]
        result["summary"] = {
            "modes": _runs([s["mode"] for s in samples], [s["t"] for s in samples]),
            "armed_at_end": samples[-1]["armed"],
            "alt_at_kill_m": alt0,
            "alt_end_m": alts[-1],
            "alt_min_m": min(alts),
            "alt_max_m": max(alts),
            "alt_change_m": round(alts[-1] - alt0, 2),
            "drift_max_m": max(s["drift_m"] for s in samples),
            "drift_end_m": samples[-1]["drift_m"],
            "distance_from_home_at_kill_m": round(math.hypot(x0, y0), 2),
            "distance_from_home_end_m": round(
                math.hypot(samples[-1]["north_m"], samples[-1]["east_m"]), 2
            ),
            "samples": len(samples),
        }
        result["completed"] = True
        note(f"summary: {result['summary']}")
        return 0
    except Exception as exc:  # recorded, then the run is cleaned up
        note(f"error: {type(exc).__name__}: {exc}")
        result["error"] = f"{type(exc).__name__}: {exc}"
        return 1
    finally:
        stop_reports.set()
        result["reports_posted"] = report_codes
        if gcs is not None:
            result["vehicle_mode_timeline"] = gcs.modes
            result["status_texts"] = gcs.texts
            gcs.close()
        stop(serve, serve.pid)
        stop(ap, ap.pid)
        serve_log.close()
        ap_log.close()
        result["events"] = events
        (out / "result.json").write_text(json.dumps(result, indent=1))
        if args.json:
            append_run(args.json, {k: v for k, v in result.items() if k != "events"})


def _runs(values: list[Any], times: list[float]) -> list[tuple[float, Any]]:
    """(time it began, value) for each run of equal values."""
    runs: list[tuple[float, Any]] = []
    for t, v in zip(times, values, strict=True):
        if not runs or runs[-1][1] != v:
            runs.append((t, v))
    return runs


def _quote(arg: str) -> str:
    return "'" + arg.replace("'", "'\\''") + "'"


if __name__ == "__main__":
    sys.exit(main())
