"""Fly ``tupa serve --arm-and-takeoff`` against a real autopilot's SITL (ArduCopter, PX4 SIH).

The SITL is not part of the project (GPL; build it from its own source): pass the command that
starts it fresh. SITLs bind every interface, so run this inside a private network namespace::

    unshare -n bash -c 'ip link set lo up; .venv/bin/python benchmarks/real_sitl.py \
        --autopilot ardupilot --autopilot-cmd "ARDUCOPTER_START_COMMAND" --out runs/sitl-ap1'
    # ArduCopter: build/sitl/bin/arducopter --model quad --speedup 1 -w \
    #             --defaults Tools/autotest/default_params/copter.parm   (in a fresh directory)
    # PX4 (v1.16, SIH): PX4_SIM_MODEL=sihsim_quadx PX4_SIMULATOR=sihsim \
    #             build/px4_sitl_default/bin/px4 -d -w RUN_DIR build/px4_sitl_default/etc

Records (seconds from the autopilot's start): link up, each take-off phase, airborne, targets
decided and reached while reports come in (:func:`reached_targets`: a target is reached when the
vehicle came within :data:`REACH_TOLERANCE_M` of it while it was the target, whether or not
another target followed), then a fault: ArduPilot, the SITL frozen (SIGSTOP)
for 6 s, link lost and back; PX4, the service killed, PX4's offboard-loss failsafe seen by a
second MAVLink client on UDP 14550 (where PX4 SITL's ground-station link sends). Writes
DIR/result.json and the logs; ``--json`` adds the run to a results file (a list of runs).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

TUPA = Path(sys.executable).with_name("tupa")
USERS = [
    {"id": "ue-1", "x_m": 120.0, "y_m": 80.0, "offered_bps": 30e6},
    {"id": "ue-2", "x_m": 60.0, "y_m": 140.0, "offered_bps": 5e6},
    {"id": "ue-3", "x_m": 160.0, "y_m": 40.0, "offered_bps": 5e6},
]
REACH_TOLERANCE_M = 3.0
POSITION_POLL_S = 0.25
"""How often the vehicle's position is sampled while it flies (reports go every second)."""

Point = tuple[float, float, float]


@dataclass(frozen=True)
class TargetOutcome:
    """One target as flown: when it was decided (s), how long it stayed the target, the closest
    the vehicle came to it meanwhile (m, None without a position sample) and, when that was
    within the tolerance, how long after its decision (s; None: not reached)."""

    t_s: float
    xyz_m: Point
    held_s: float
    closest_m: float | None
    reached_after_s: float | None

    @property
    def reached(self) -> bool:
        return self.reached_after_s is not None


def reached_targets(
    targets: Sequence[tuple[float, Point]],
    track: Sequence[tuple[float, Point]],
    end_s: float,
    tolerance_m: float = REACH_TOLERANCE_M,
) -> list[TargetOutcome]:
    """Each target ``(decided at s, xyz m)``, in order, against the vehicle's ``track`` of
    ``(t s, xyz m)`` samples: it is the target from its decision until the next one's (or
    ``end_s``, both ends included), and reached when a sample of that time lies within
    ``tolerance_m`` of it (3-D distance), whether or not another target follows."""
    outcomes = []
    for i, (t_s, xyz) in enumerate(targets):
        until_s = targets[i + 1][0] if i + 1 < len(targets) else end_s
        near = [(t, math.dist(p, xyz)) for t, p in track if t_s <= t <= until_s]
        reached = next((t - t_s for t, d in near if d <= tolerance_m), None)
        outcomes.append(
            TargetOutcome(
                t_s=t_s,
                xyz_m=tuple(xyz),
                held_s=round(until_s - t_s, 2),
                closest_m=round(min(d for _, d in near), 2) if near else None,
                reached_after_s=None if reached is None else round(reached, 2),
            )
        )
    return outcomes


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--autopilot", choices=("ardupilot", "px4"), required=True)
    parser.add_argument(
        "--autopilot-cmd", required=True, help="shell command that starts the SITL fresh"
    )
    parser.add_argument("--json", type=Path, help="append this run's result to this JSON list")
    parser.add_argument("--backend", choices=("pymavlink", "mavsdk"), default="pymavlink")
    parser.add_argument("--policy", default=None)
    parser.add_argument("--fly-s", type=float, default=60.0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=False)
    events: list[tuple[float, str]] = []
    t0 = time.monotonic()

    def note(text: str) -> None:
        t = time.monotonic() - t0
        events.append((round(t, 2), text))
        print(f"{t:7.2f} {text}", flush=True)

    ap_log = open(out / "autopilot.log", "w")  # noqa: SIM115 (open for the whole run)
    ap = subprocess.Popen(
        ["bash", "-c", args.autopilot_cmd],
        stdout=ap_log,
        stderr=ap_log,
        start_new_session=True,
    )
    url = "tcp:127.0.0.1:5760" if args.autopilot == "ardupilot" else "udpin:127.0.0.1:14540"
    note(f"{args.autopilot} started")
    port = 18080
    cmd = [
        str(TUPA),
        "serve",
        "--mavlink",
        url,
        "--arm-and-takeoff",
        "--insecure",
        "--port",
        str(port),
        "--decision-mode",
        "on-report",
        "--mavlink-backend",
        args.backend,
    ]
    if args.policy:
        cmd += ["--policy", args.policy]
    serve_log = open(out / "serve.log", "w")  # noqa: SIM115
    serve = subprocess.Popen(cmd, stdout=serve_log, stderr=serve_log)
    note("tupa serve started: " + " ".join(cmd[1:]))
    api = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5.0)
    result: dict = {"autopilot": args.autopilot, "backend": args.backend}
    observer_modes: list[tuple[float, str, bool]] = []
    stop_observer = threading.Event()

    def observe() -> None:
        """PX4: a ground station on 14550 (where PX4 SITL's GCS link sends)."""
        conn = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=250)
        last = None
        while not stop_observer.is_set():
            m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if m is None or m.autopilot != 12:
                continue
            state = (mode_name_px4(m.custom_mode), bool(m.base_mode & 128))
            if state != last:
                observer_modes.append((round(time.monotonic() - t0, 2), *state))
                last = state

    if args.autopilot == "px4":
        threading.Thread(target=observe, daemon=True).start()

    try:
        last_phase = None
        link_up = airborne = None
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            try:
                v = api.get("/v1/vehicle").json()
            except (httpx.HTTPError, ValueError):
                time.sleep(0.3)
                continue
            if link_up is None and v["link"] == "up":
                link_up = time.monotonic() - t0
                note("link up, mode " + str(v["mode"]))
            phase = (v["takeoff"]["state"], v["takeoff"]["phase"], v["takeoff"]["attempts"])
            if phase != last_phase:
                note(f"take-off {phase} last refusal: {v['takeoff']['last_refusal']}")
                last_phase = phase
            if v["takeoff"]["state"] == "airborne":
                airborne = time.monotonic() - t0
                note(f"airborne, mode {v['mode']}, z {v['position'] and v['position']['z_m']}")
                break
            if v["takeoff"]["state"].startswith("failed"):
                break
            time.sleep(0.2)
        result["link_up_s"] = link_up
        result["airborne_s"] = airborne
        result["status_texts"] = api.get("/v1/vehicle").json()["status_texts"]
        if airborne is None:
            note("never airborne")
            return 1
        # Fly: a report every second; the vehicle's position sampled in between.
        targets: list[tuple[float, Point]] = []
        track: list[tuple[float, Point]] = []
        current = None
        fly_until = time.monotonic() + args.fly_s
        next_report = time.monotonic()
        while time.monotonic() < fly_until:
            if time.monotonic() >= next_report:
                next_report += 1.0
                users = [
                    {**u, "throughput_bps": u["offered_bps"] * 0.8, "delay_s": 0.05, "plr": 0.01}
                    for u in USERS
                ]
                r = api.post("/v1/reports", json={"timestamp": time.time(), "users": users})
                target = r.json().get("target") if r.status_code == 200 else None
                if target and target != current:
                    current = target
                    xyz = (target["x_m"], target["y_m"], target["z_m"])
                    targets.append((round(time.monotonic() - t0, 2), xyz))
                    note(f"target {target}")
            p = api.get("/v1/vehicle").json()["position"]
            if p:
                track.append((time.monotonic() - t0, (p["x_m"], p["y_m"], p["z_m"])))
            time.sleep(POSITION_POLL_S)
        outcomes = reached_targets(targets, track, end_s=time.monotonic() - t0)
        result["reach_tolerance_m"] = REACH_TOLERANCE_M
        result["targets"] = [{**asdict(o), "reached": o.reached} for o in outcomes]
        result["targets_reached"] = sum(o.reached for o in outcomes)
        result["targets_decided"] = len(outcomes)
        note(
            f"{result['targets_reached']} of {len(outcomes)} targets reached "
            f"(within {REACH_TOLERANCE_M} m while each was the target)"
        )
        # The fault.
        if args.autopilot == "ardupilot":
            note("SITL frozen (SIGSTOP) for 6 s")
            os.killpg(ap.pid, signal.SIGSTOP)
            frozen = time.monotonic()
            lost = back = None
            while time.monotonic() - frozen < 6.0:
                if lost is None and api.get("/v1/vehicle").json()["link"] == "link_lost":
                    lost = time.monotonic() - frozen
                    note("service: link_lost")
                time.sleep(0.1)
            os.killpg(ap.pid, signal.SIGCONT)
            resumed = time.monotonic()
            note("SITL resumed")
            while time.monotonic() - resumed < 30.0:
                v = api.get("/v1/vehicle").json()
                if v["link"] == "up" and v["streaming"]:
                    back = time.monotonic() - resumed
                    note(f"service: link up and streaming again, mode {v['mode']}")
                    break
                time.sleep(0.1)
            result["link_lost_after_freeze_s"] = lost
            result["streaming_again_after_resume_s"] = back
            v = api.get("/v1/vehicle").json()
            result["after_fault"] = {k: v[k] for k in ("mode", "armed", "link", "position")}
        else:
            note("service killed (SIGKILL)")
            killed_at = time.monotonic() - t0
            serve.kill()
            time.sleep(8.0)
            result["service_killed_at_s"] = round(killed_at, 2)
            result["px4_modes_seen"] = observer_modes
        return 0
    finally:
        result["events"] = events
        (out / "result.json").write_text(json.dumps(result, indent=1))
        if args.json:
            runs = json.loads(args.json.read_text()) if args.json.exists() else []
            runs.append({k: v for k, v in result.items() if k != "events"})
            args.json.write_text(json.dumps(runs, indent=1))
        stop_observer.set()
        if serve.poll() is None:
            serve.terminate()
            try:
                serve.wait(10)
            except subprocess.TimeoutExpired:
                serve.kill()
        os.killpg(ap.pid, signal.SIGCONT)
        os.killpg(ap.pid, signal.SIGTERM)
        try:
            ap.wait(15)
        except subprocess.TimeoutExpired:
            ap.kill()


def mode_name_px4(custom_mode: int) -> str:
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    names = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STAB"}
    subs = {2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND"}
    name = names.get(main, str(main))
    return f"{name}.{subs.get(sub, sub)}" if main == 4 else name


if __name__ == "__main__":
    sys.exit(main())
