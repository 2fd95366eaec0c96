"""Does a slow route plan stall a vehicle link's setpoint stream?

A new envelope whose first plan in a height band builds the corners' graph of many corners (the
most a document may have, :data:`sim.envelope.files.MAX_EXCLUSION_CORNERS`, as star-shaped
no-fly zones whose corners cannot be simplified away) is given to a pymavlink link flying a
PX4-flavoured ``tupa sitl-mock`` in its own process (so the mock does not share this process's
interpreter lock) at 10 m/s. Measured per run: how long the plan took (the link's route says
``planning the route`` meanwhile, or, planned inline, the time the I/O loop spent in it), the
longest gap between two setpoints the link sent, and whether PX4's offboard failsafe fired (it
does after 1 s without a setpoint). Two runs in the same invocation: the link as shipped (plans
on a thread of its own) and with plans made inline in the I/O loop (as before).

    .venv/bin/python benchmarks/link_plan_stall.py  -> benchmarks/results/link_plan_stall.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import platform
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.faults is not an installed package

RESULTS = Path(__file__).parent / "results" / "link_plan_stall.json"
TARGET_M = (470.0, 250.0, 50.0)


def star(cx: float, cy: float, radius_m: float, corners: int) -> list[list[float]]:
    """A star of ``corners`` corners (every other one 30 % further in)."""
    points = []
    for k in range(corners):
        r = radius_m if k % 2 == 0 else 0.7 * radius_m
        angle = 2 * math.pi * k / corners
        points.append([cx + r * math.cos(angle), cy + r * math.sin(angle)])
    return points


def hostile_document(total_corners: int) -> dict[str, Any]:
    """Eight stars of ``total_corners / 8`` corners, 80 m apart, between the vehicle's home
    (the area's south-west corner) and its target (:data:`TARGET_M`)."""
    per = total_corners // 8
    exclusions = [
        {"polygon": star(120 + 80 * i, 150 + 100 * j, 35.0, per), "floor_m": 0, "ceiling_m": 200}
        for i in range(4)
        for j in range(2)
    ]
    return {"format": "tupa-envelope/1", "exclusions": exclusions}


def one_run(inline: bool, total_corners: int) -> dict[str, Any]:
    import service.vehicle_link
    from service import links
    from service.routing import PLANNING, InlinePlanner
    from service.vehicle_link import LinkConfig
    from sim.config import AreaConfig
    from sim.envelope.files import envelope_from_document
    from tests.faults.mock_process import start_mock_process

    area = AreaConfig()
    if inline:
        service.vehicle_link.background_planner = lambda name: InlinePlanner()  # type: ignore[assignment]
    mock = start_mock_process(["--flavour", "px4", "--listen", "tcp:127.0.0.1:0"])
    link = None
    try:
        link = links.open_link("pymavlink", LinkConfig(f"tcp:127.0.0.1:{mock.port}", area=area))
        link.start()
        link.arm_and_takeoff().result(timeout=60.0)
        link.set_target(TARGET_M)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and math.hypot(*link.state().position_m[:2]) < 60.0:
            time.sleep(0.05)  # on its way, at speed
        envelope = envelope_from_document(hostile_document(total_corners), area)
        sent_times: list[float] = []
        planning = []
        stop = threading.Event()

        def sample() -> None:
            last = None
            while not stop.is_set():
                state = link.state()
                now = time.monotonic()
                count = state.counters["setpoints_sent"]
                if count != last:
                    sent_times.append(now)
                    last = count
                route = state.route
                planning.append((now, route is not None and route.hold_reason == PLANNING))
                time.sleep(0.005)

        sampler = threading.Thread(target=sample, daemon=True)
        failsafes_before = mock.stats()["failsafe_offboard"]
        sampler.start()
        time.sleep(0.5)
        asked = time.monotonic()
        link.set_envelope(envelope)
        planned_at = None
        deadline = asked + 120.0
        while time.monotonic() < deadline:
            route = link.state().route
            if route is not None and route.hold_reason != PLANNING and route.kind != "direct":
                planned_at = time.monotonic()
                break
            time.sleep(0.01)
        time.sleep(1.5)
        stop.set()
        sampler.join(5.0)
        window = [t for t in sent_times if t >= asked - 0.5]
        gaps = [b - a for a, b in itertools.pairwise(window)]
        return {
            "planner": "inline (in the I/O loop)" if inline else "thread of its own (shipped)",
            "plan_s": None if planned_at is None else round(planned_at - asked, 3),
            "route_kind": link.state().route.kind if link.state().route else None,
            "max_setpoint_gap_s": round(max(gaps), 3) if gaps else None,
            "setpoints_sent_in_window": len(window),
            "offboard_failsafes": mock.stats()["failsafe_offboard"] - failsafes_before,
            "mode_after": link.state().mode,
        }
    finally:
        if link is not None:
            link.close()
        mock.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--corners", type=int, default=1000, help="exclusion corners in all")
    parser.add_argument("--json", type=Path, default=RESULTS)
    args = parser.parse_args()
    import multiprocessing

    runs = []
    for inline in (False, True):
        # A fresh process per run: the inline run patches the link's planner.
        with multiprocessing.get_context("spawn").Pool(1) as pool:
            run = pool.apply(one_run, (inline, args.corners))
        print(json.dumps(run))
        runs.append(run)
    result = {
        "benchmark": "link_plan_stall",
        "command": "python benchmarks/link_plan_stall.py",
        "machine": platform.node(),
        "corners": args.corners,
        "runs": runs,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
