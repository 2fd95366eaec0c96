"""A fleet of real autopilot SITLs (ArduCopter or PX4) flown by ``tupa serve --fleet-file``
(manual: needs SITLs built outside the repository, as ``benchmarks/real_sitl.py`` does).

Starts ``--uavs`` SITL instances, homes 15 m apart eastwards from the autopilot's default SITL
home, each with its own system id (i + 1):

- ArduCopter: ``-I i`` (TCP port 5760 + 10·i), ``--sysid i + 1``;
- PX4 (v1.16, SIH quadrotor, no Gazebo): ``px4 -i i`` (its rcS sets ``MAV_SYS_ID`` to i + 1;
  the offboard link sends to UDP 14540 + i), the home set through ``PX4_HOME_LAT/LON/ALT``.

It writes the matching fleet file (each vehicle's own area origin: the area's centre over the
first home), starts ``tupa serve --fleet-file --arm-and-takeoff --decision-mode on-report``,
posts a report of users in ``--uavs`` hot spots every second, and records from ``GET
/v1/vehicles`` when each link comes up (with the system id heard), when each vehicle is
commanded and airborne, and when every vehicle stands within 3 m of its own target. Writes
``OUT/result.json`` and the SITLs' and the service's logs.

SITLs listen on every interface: run it in a network namespace of its own::

    unshare -n bash -c 'ip link set lo up; .venv/bin/python benchmarks/real_sitl_fleet.py \\
        --arducopter /path/to/ardupilot/build/sitl/bin/arducopter \\
        --defaults /path/to/ardupilot/Tools/autotest/default_params/copter.parm --out /tmp/fleet'

    unshare -n bash -c 'ip link set lo up; .venv/bin/python benchmarks/real_sitl_fleet.py \\
        --px4 /path/to/PX4-Autopilot/build/px4_sitl_default --uavs 3 --out /tmp/fleet-px4'
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

EARTH_RADIUS_M = 6378137.0
HOME = {
    "ardupilot": (-35.363261, 149.165230, 584.0),  # ArduPilot's default SITL home (CMAC)
    "px4": (47.3977428, 8.5455952, 488.0),  # PX4's default SITL home (Zurich)
}
SPACING_M = 15.0
PORT = 18081


def _xyz(point: dict[str, float]) -> list[float]:
    return [point["x_m"], point["y_m"], point["z_m"]]


def _start_ardupilot(
    args: argparse.Namespace, i: int, home: tuple[float, float, float], workdir: Path
) -> subprocess.Popen:
    lat, lon, alt = home
    return subprocess.Popen(
        [args.arducopter, "--model", "quad", "--speedup", "1", "-w", "-I", str(i),
         "--sysid", str(i + 1), "--home", f"{lat},{lon},{alt},0", "--defaults", args.defaults],
        cwd=workdir, stdout=(workdir / "log.txt").open("w"), stderr=subprocess.STDOUT,
    )  # fmt: skip


def _start_px4(
    args: argparse.Namespace, i: int, home: tuple[float, float, float], workdir: Path
) -> subprocess.Popen:
    """PX4 SITL instance ``i`` with the SIH quadrotor (what ``make px4_sitl sihsim_quadx``
    runs), daemon mode, its parameters and logs in ``workdir``."""
    lat, lon, alt = home
    env = dict(os.environ, PX4_SIM_MODEL="sihsim_quadx", PX4_SIMULATOR="sihsim")
    env.update(PX4_HOME_LAT=str(lat), PX4_HOME_LON=str(lon), PX4_HOME_ALT=str(alt))
    build = args.px4.resolve()
    return subprocess.Popen(
        [str(build / "bin" / "px4"), "-i", str(i), "-d", "-w", str(workdir.resolve()),
         str(build / "etc")],
        cwd=workdir, env=env, stdout=(workdir / "log.txt").open("w"), stderr=subprocess.STDOUT,
    )  # fmt: skip


def _connection(autopilot: str, i: int) -> str:
    """Where vehicle ``i``'s MAVLink is: ArduPilot's TCP server, or the UDP port PX4's offboard
    link sends to."""
    if autopilot == "px4":
        return f"udpin:127.0.0.1:{14540 + i}"
    return f"tcp:127.0.0.1:{5760 + 10 * i}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arducopter", help="ArduCopter: the SITL binary")
    parser.add_argument("--defaults", help="ArduCopter: copter.parm")
    parser.add_argument("--px4", type=Path, help="PX4: the build folder (px4_sitl_default)")
    parser.add_argument("--uavs", type=int, default=2, help="vehicles, 2..4 (default 2)")
    parser.add_argument("--timeout-s", type=float, default=240.0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--backend", choices=("pymavlink", "mavsdk"), default="pymavlink")
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args()
    if not 2 <= args.uavs <= 4:
        parser.error("--uavs: must be in 2..4")
    if (args.px4 is None) == (args.arducopter is None):
        parser.error("give either --arducopter (with --defaults) or --px4")
    if args.arducopter is not None and args.defaults is None:
        parser.error("--defaults: needed with --arducopter")
    autopilot = "px4" if args.px4 is not None else "ardupilot"
    args.out.mkdir(parents=True, exist_ok=False)
    lat, lon, alt = HOME[autopilot]
    sitls = []
    for i in range(args.uavs):
        east = SPACING_M * i
        home_lon = lon + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
        workdir = args.out / f"sitl{i}"
        workdir.mkdir()
        start = _start_px4 if autopilot == "px4" else _start_ardupilot
        sitls.append(start(args, i, (lat, home_lon, alt), workdir))
    fleet = {
        "separation_m": 10,
        "vehicles": [
            {"id": f"uav{i + 1}", "mavlink": _connection(autopilot, i),
             "system_id": i + 1, "area_origin_north_m": -250.0,
             "area_origin_east_m": -250.0 - SPACING_M * i}
            for i in range(args.uavs)
        ],
    }  # fmt: skip
    (args.out / "fleet.json").write_text(json.dumps(fleet, indent=2))
    started = time.monotonic()
    serve = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--fleet-file", str(args.out / "fleet.json"),
         "--arm-and-takeoff", "--insecure", "--port", str(PORT), "--decision-mode", "on-report",
         "--mavlink-backend", args.backend],
        stdout=(args.out / "serve.log").open("w"), stderr=subprocess.STDOUT,
    )  # fmt: skip
    angles = [2 * math.pi * k / args.uavs + math.pi for k in range(args.uavs)]
    spots = [(250.0 + 200.0 * math.cos(a), 250.0 + 200.0 * math.sin(a)) for a in angles]
    users = [
        {"id": f"u{k}-{j}", "x_m": x + dx, "y_m": y + dy, "offered_bps": 4e6,
         "throughput_bps": 4e6, "delay_s": 0.01, "plr": 0.0}
        for k, (x, y) in enumerate(spots)
        for j, (dx, dy) in enumerate(((0, 0), (5, -5), (-5, 5)))
    ]  # fmt: skip
    events: list[tuple[float, str]] = []
    result: dict[str, Any] = {
        "autopilot": autopilot,
        "backend": args.backend,
        "uavs": args.uavs,
        "events": events,
        "in_place_s": None,
    }

    def say(text: str) -> None:
        events.append((round(time.monotonic() - started, 1), text))
        print(*events[-1], flush=True)

    try:
        client = httpx.Client(base_url=f"http://127.0.0.1:{PORT}", timeout=5.0)
        seen: set[tuple[str, str]] = set()
        deadline = time.monotonic() + args.timeout_s
        while time.monotonic() < deadline:
            time.sleep(1.0)
            try:
                client.post("/v1/reports", json={"timestamp": time.time(), "users": users})
                vehicles = {v["id"]: v for v in client.get("/v1/vehicles").json()["vehicles"]}
            except httpx.HTTPError:
                continue  # the service is still starting
            for vid, v in vehicles.items():
                state = v["vehicle"]
                for key, now in (
                    ("link up", state["link"] == "up"),
                    ("commanded", v["commanded"]),
                    ("airborne", state["takeoff"]["state"] == "airborne"),
                ):
                    if now and (vid, key) not in seen:
                        seen.add((vid, key))
                        say(f"{vid} {key}: system id {v['system_id']}, mode {state['mode']}")
            placed = [v for v in vehicles.values() if v["commanded"] and v["vehicle"]["position"]]
            if len(placed) == args.uavs and all(
                math.dist(_xyz(v["vehicle"]["position"]), _xyz(v["setpoint"]["target"])) < 3.0
                for v in placed
            ):
                here = [_xyz(v["vehicle"]["position"]) for v in placed]
                result["in_place_s"] = round(time.monotonic() - started, 1)
                result["positions_m"] = {v["id"]: _xyz(v["vehicle"]["position"]) for v in placed}
                result["targets_m"] = {v["id"]: _xyz(v["setpoint"]["target"]) for v in placed}
                result["modes"] = {v["id"]: v["vehicle"]["mode"] for v in placed}
                result["min_separation_m"] = min(
                    math.dist(a, b) for i, a in enumerate(here) for b in here[i + 1 :]
                )
                apart = result["min_separation_m"]
                say(f"every vehicle within 3 m of its target; closest two {apart:.1f} m apart")
                break
    finally:
        serve.send_signal(signal.SIGTERM)
        for process in (serve, *sitls):
            if process is not serve:
                process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
    for path in filter(None, (args.out / "result.json", args.json)):
        path.write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["in_place_s"] is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
