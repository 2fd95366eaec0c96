"""A fleet of real ArduCopter SITLs flown by ``tupa serve --fleet-file`` (manual: needs a SITL
built outside the repository, as ``benchmarks/real_sitl.py`` does).

Starts ``--uavs`` ArduCopter SITL instances (``-I i``: TCP port 5760 + 10·i, ``--sysid i + 1``,
homes 15 m apart eastwards from ArduPilot's default SITL home), writes the matching fleet file
(each vehicle's own area origin: the area's centre over the first home), starts ``tupa serve
--fleet-file --arm-and-takeoff --decision-mode on-report``, posts a report of users in ``--uavs``
hot spots every second, and records from ``GET /v1/vehicles`` when each link comes up (with the
system id heard), when each vehicle is commanded and airborne, and when every vehicle stands
within 3 m of its own target. Writes ``OUT/result.json`` and the SITLs' and the service's logs.

SITLs listen on every interface: run it in a network namespace of its own::

    unshare -n bash -c 'ip link set lo up; .venv/bin/python benchmarks/real_sitl_fleet.py \\
        --arducopter /path/to/ardupilot/build/sitl/bin/arducopter \\
        --defaults /path/to/ardupilot/Tools/autotest/default_params/copter.parm --out /tmp/fleet'
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

EARTH_RADIUS_M = 6378137.0
HOME = (-35.363261, 149.165230, 584.0)  # ArduPilot's default SITL home (CMAC)
SPACING_M = 15.0
PORT = 18081


def _xyz(point: dict[str, float]) -> list[float]:
    return [point["x_m"], point["y_m"], point["z_m"]]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arducopter", required=True, help="the SITL binary")
    parser.add_argument("--defaults", required=True, help="copter.parm")
    parser.add_argument("--uavs", type=int, default=2, help="vehicles, 2..4 (default 2)")
    parser.add_argument("--timeout-s", type=float, default=240.0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if not 2 <= args.uavs <= 4:
        parser.error("--uavs: must be in 2..4")
    args.out.mkdir(parents=True, exist_ok=False)
    lat, lon, alt = HOME
    sitls = []
    for i in range(args.uavs):
        east = SPACING_M * i
        home_lon = lon + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
        workdir = args.out / f"sitl{i}"
        workdir.mkdir()
        sitls.append(
            subprocess.Popen(
                [args.arducopter, "--model", "quad", "--speedup", "1", "-w", "-I", str(i),
                 "--sysid", str(i + 1), "--home", f"{lat},{home_lon},{alt},0",
                 "--defaults", args.defaults],
                cwd=workdir, stdout=(workdir / "log.txt").open("w"), stderr=subprocess.STDOUT,
            )
        )  # fmt: skip
    fleet = {
        "separation_m": 10,
        "vehicles": [
            {"id": f"uav{i + 1}", "mavlink": f"tcp:127.0.0.1:{5760 + 10 * i}",
             "system_id": i + 1, "area_origin_north_m": -250.0,
             "area_origin_east_m": -250.0 - SPACING_M * i}
            for i in range(args.uavs)
        ],
    }  # fmt: skip
    (args.out / "fleet.json").write_text(json.dumps(fleet, indent=2))
    started = time.monotonic()
    serve = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--fleet-file", str(args.out / "fleet.json"),
         "--arm-and-takeoff", "--insecure", "--port", str(PORT), "--decision-mode", "on-report"],
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
    result: dict[str, Any] = {"uavs": args.uavs, "events": events, "in_place_s": None}

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
    (args.out / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["in_place_s"] is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
