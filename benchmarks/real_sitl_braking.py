"""Does a real ArduCopter SITL, flown by the vehicle link, keep out of a block when it is turned
at full speed onto a route that passes the block's corner?

The link (pymavlink backend, the service's own, in this process) flies a fresh ArduCopter SITL
(built outside this repository: it is GPL) in the default 500 m area, home at area (20, 20),
inside an envelope with one block, 100 m x 115 m, from the ground to the ceiling, 5 m clearance.
The vehicle takes off to 30 m, is sent east along the block's south side and, once past x 130 m
at speed, north to (140, 300): the straight leg passes the block's west side, but the vehicle's
momentum carries it on east while it turns. Two runs, each with a fresh SITL:

* ``braking``: the link as shipped (the vehicle's velocity from LOCAL_POSITION_NED; stops
  reckoned at 2.5 m/s², :func:`sim.envelope.route.plan_route_moving`);
* ``blind``: ``brake_mps2`` 1e9, the stop reckoned at once, as the link planned before it read
  the velocity.

Recorded at 10 Hz from the link's position: the deepest point inside the block (raw, without the
clearance) and inside its clearance, the route kinds, and whether the vehicle got there. Pass:
``braking`` never enters the block and arrives. SITLs bind every interface, so the run happens in a
private network namespace (only ``lo``)::

    .venv/bin/python benchmarks/real_sitl_braking.py \
        --arducopter /root/sitl/ardupilot/build/sitl/bin/arducopter \
        --defaults /root/sitl/ardupilot/Tools/autotest/default_params/copter.parm \
        --out runs/braking --json benchmarks/results/real_sitl_braking.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from shapely.geometry import Point, box
from sitl_harness import ensure_private_namespace, start_child, stop

from service import links
from service.frames import FrameConfig
from service.vehicle_link import LinkConfig
from sim.config import AreaConfig
from sim.envelope import Envelope, Exclusion

AREA = AreaConfig()
FRAMES = FrameConfig(area_origin_north_m=-20.0, area_origin_east_m=-20.0)
BLOCK = Exclusion(box(150.0, 35.0, 250.0, 150.0), 0.0, 150.0, "block")
CLEARANCE_M = 5.0
ALTITUDE_M = 30.0
EAST_TARGET = (480.0, 20.0, ALTITUDE_M)
TURN_AT_X_M = 130.0
NORTH_TARGET = (140.0, 300.0, ALTITUDE_M)


def fly(args: argparse.Namespace, name: str, brake_mps2: float) -> dict[str, Any]:
    """One run with a fresh SITL; what it recorded."""
    out = args.out / name
    (out / "sitl").mkdir(parents=True)
    log = open(out / "autopilot.log", "w")  # noqa: SIM115 (open for the run)
    command = [
        str(args.arducopter.resolve()), "--model", "quad", "--speedup", "1", "-w",
        "--defaults", str(args.defaults.resolve()),
    ]  # fmt: skip
    sitl = start_child(command, log, cwd=out / "sitl")
    envelope = Envelope.for_area(AREA, [BLOCK], clearance_m=CLEARANCE_M)
    config = LinkConfig(
        "tcp:127.0.0.1:5760", area=AREA, frames=FRAMES, envelope=envelope, brake_mps2=brake_mps2
    )
    link = links.open_link("pymavlink", config).start()
    run: dict[str, Any] = {"run": name, "brake_mps2": brake_mps2, "arrived": False}
    try:
        link.arm_and_takeoff(ALTITUDE_M, timeout_s=120.0).result(timeout=180.0)
        link.set_target(EAST_TARGET)
        deadline = time.monotonic() + 60.0
        speed = 0.0
        previous: tuple[float, float, float] | None = None
        while time.monotonic() < deadline:
            position = link.state().position_m
            if position is not None and previous is not None:
                speed = math.hypot(position[0] - previous[0], position[1] - previous[1]) / 0.1
            previous = position
            if position is not None and position[0] >= TURN_AT_X_M:
                break
            time.sleep(0.1)
        run["turned_at_m"] = previous
        run["speed_at_turn_mps"] = round(speed, 2)
        run["leg_clear"] = envelope.segment_violation(previous, NORTH_TARGET) is None
        link.set_target(NORTH_TARGET)
        deepest_m = deepest_clearance_m = 0.0
        kinds: list[str] = []
        track = []
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline:
            state = link.state()
            position = state.position_m
            if state.route is not None and (not kinds or kinds[-1] != state.route.kind):
                kinds.append(state.route.kind)
            if position is not None:
                track.append([round(v, 2) for v in position])
                here = Point(position[0], position[1])
                if BLOCK.footprint.contains(here):
                    deepest_m = max(deepest_m, BLOCK.footprint.exterior.distance(here))
                grown = BLOCK.footprint.buffer(CLEARANCE_M, join_style="mitre")
                if grown.contains(here):
                    deepest_clearance_m = max(deepest_clearance_m, grown.exterior.distance(here))
                if math.dist(position, NORTH_TARGET) <= 2.0:
                    run["arrived"] = True
                    break
            time.sleep(0.1)
        run.update(
            deepest_in_block_m=round(deepest_m, 2),
            deepest_in_clearance_m=round(deepest_clearance_m, 2),
            route_kinds=kinds,
            track_10hz=track,
        )
    finally:
        link.close()
        stop(sitl)
        log.close()
    print(
        f"{name}: turned at {run.get('turned_at_m')} at {run.get('speed_at_turn_mps')} m/s, "
        f"routes {run.get('route_kinds')}, deepest in the block {run.get('deepest_in_block_m')} m "
        f"(in its clearance {run.get('deepest_in_clearance_m')} m), arrived {run['arrived']}",
        flush=True,
    )
    return run


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arducopter", type=Path, required=True, help="the SITL binary")
    parser.add_argument("--defaults", type=Path, required=True, help="copter.parm")
    parser.add_argument("--out", type=Path, required=True, help="a new directory")
    parser.add_argument("--json", type=Path, help="write the result here")
    parser.add_argument("--no-unshare", action="store_true", help="refuse outside a namespace")
    args = parser.parse_args()
    if (why := ensure_private_namespace(args.no_unshare)) is not None:
        print(f"refusing: {why}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=False)
    result: dict[str, Any] = {
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "autopilot": "ArduCopter SITL",
        "block": list(BLOCK.footprint.bounds),
        "clearance_m": CLEARANCE_M,
        "runs": [fly(args, "braking", 2.5), fly(args, "blind", 1e9)],
    }
    braking = result["runs"][0]
    result["passed"] = braking["arrived"] and braking["deepest_in_block_m"] == 0.0
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    print("passed" if result["passed"] else "FAILED")
    return 0 if result["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
