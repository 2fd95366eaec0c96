"""Hand-back, repeated: does the paced placement loop ever ask for the guided mode after a pilot
or a failsafe took the vehicle? (``service/control.py`` has the rule.)

For each autopilot flavour (ArduPilot, PX4) and link backend (pymavlink, MAVSDK), ``--runs``
flights of the in-process mock autopilot, each flown by a paced :class:`PlacementService`
(min-distance, one report kept fresh, so the same target is set every ``--period-s``), through
four takeovers in turn: a pilot's RC mode switch, a ground station's RTL, a ground station's
LAND, the battery failsafe. After each, the loop runs ``--quiet-periods`` periods and the mock
counts every command for the guided mode it receives (the finding this guards against: the
service switched the vehicle back within 0.4-1.1 s). Between takeovers the pilot leaves any
return or landing mode and an operator hands the vehicle back.

    .venv/bin/python benchmarks/handback.py --runs 20 --out benchmarks/results/handback.json

Writes the JSON after every flight (a run cut short keeps what it measured).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from service import links
from service.decisions import Report
from service.frames import FrameConfig
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot

KINDS = ("pilot", "rtl", "land", "battery")
FAST = {"accel_h_mps2": 5.0, "accel_v_mps2": 5.0, "max_speed_up_mps": 5.0, "ready_delay_s": 0.3}


def wait(condition: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.02)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")


def report() -> Report:
    xy = np.array([[120.0, 80.0], [60.0, 140.0], [160.0, 40.0]])
    columns = {
        "x_m": xy[:, 0],
        "y_m": xy[:, 1],
        "offered_bps": np.array([30e6, 5e6, 5e6]),
        "throughput_bps": np.array([20e6, 5e6, 5e6]),
        "delay_s": np.full(3, 0.01),
        "plr": np.zeros(3),
    }
    return Report.from_columns(1.0, ("a", "b", "c"), columns)


def passes(service: PlacementService) -> int:
    counters = service.snapshot_counters()
    return counters.get("decisions", 0) + counters.get("decisions_waiting_link", 0)


def fly(flavour: str, backend: str, period_s: float, quiet: int) -> dict[str, Any]:
    """One flight through the four takeovers: per kind, the guided-mode commands the vehicle got
    after it (0 is the target), who had the vehicle, and how long the service took to let go."""
    guided = "GUIDED" if flavour == "ardupilot" else "OFFBOARD"
    pilot_mode = "LOITER" if flavour == "ardupilot" else "POSCTL"
    rtl, land = ("RTL", "LAND") if flavour == "ardupilot" else ("AUTO.RTL", "AUTO.LAND")
    mock = MockAutopilot(
        "tcp:127.0.0.1:0", flavour, VehicleConfig(gcs_failsafe_action="none", **FAST)
    ).start()
    config = LinkConfig(f"tcp:127.0.0.1:{mock.port}", frames=FrameConfig(), mode_retry_s=0.2)
    link = links.open_link(backend, config)
    settings = ServiceSettings(
        mavlink=config.url, api_token="t", policy="min-distance", step_s=period_s,
        report_max_age_s=3600.0,
    )  # fmt: skip
    service = PlacementService(settings, link, load_policy("min-distance")).start()
    result: dict[str, Any] = {}
    try:
        link.arm_and_takeoff(z_m=25.0).result(timeout=60.0)
        service.submit_report(report())
        wait(lambda: mock.state().mode == guided, 15.0, guided)
        actions = {
            "pilot": lambda v: v.rc_mode_switch(pilot_mode),
            "rtl": lambda v: v.set_mode_by_name(rtl),
            "land": lambda v: v.land(),
            "battery": lambda v: v.set_battery_remaining(5.0),
        }
        for kind in KINDS:
            before = mock.stats.get(f"mode_commands_{guided}", 0)
            acted = time.monotonic()
            mock.with_vehicle(actions[kind])
            state = wait(lambda: (s := link.state()).control != "service" and s, 10.0, "let go")
            let_go_s = time.monotonic() - acted
            start = passes(service)
            wait(
                lambda start=start: passes(service) >= start + quiet,
                quiet * period_s + 20.0,
                "periods",
            )
            result[kind] = {
                "guided_commands_after": mock.stats.get(f"mode_commands_{guided}", 0) - before,
                "mode_after": mock.state().mode,
                "holder": state.control,
                "reason": state.control_reason,
                "let_go_s": round(let_go_s, 3),
            }
            if kind == "battery":
                break
            if mock.state().mode in (rtl, land):  # the pilot leaves it, then the operator
                mock.with_vehicle(lambda v: v.rc_mode_switch(pilot_mode))
                wait(lambda: link.state().mode == pilot_mode, 10.0, pilot_mode)
            link.hand_back()
            wait(lambda: mock.state().mode == guided, 15.0, f"{guided} again")
            wait(lambda: link.state().mode == guided, 10.0, f"{guided} heard")
    finally:
        service.stop()
        mock.stop()
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--period-s", type=float, default=0.2)
    parser.add_argument("--quiet-periods", type=int, default=8)
    parser.add_argument("--flavours", default="ardupilot,px4")
    parser.add_argument("--backends", default="pymavlink,mavsdk")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/handback.json"))
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs: must be at least 1")
    logging.basicConfig(level=logging.ERROR)
    document: dict[str, Any] = {
        "command": "benchmarks/handback.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
        "combos": {},
    }
    started = time.monotonic()
    total = args.runs * len(args.flavours.split(",")) * len(args.backends.split(","))
    done = 0
    for flavour in args.flavours.split(","):
        for backend in args.backends.split(","):
            flights: list[dict[str, Any]] = []
            errors: list[str] = []
            for _ in range(args.runs):
                try:
                    flights.append(fly(flavour, backend, args.period_s, args.quiet_periods))
                except Exception as exc:  # a flight that could not be flown is reported
                    errors.append(f"{type(exc).__name__}: {exc}")
                done += 1
                summary: dict[str, Any] = {}
                for kind in KINDS:
                    seen = [f[kind] for f in flights if kind in f]
                    summary[kind] = {
                        "runs": len(seen),
                        "guided_commands_after_total": sum(
                            s["guided_commands_after"] for s in seen
                        ),
                        "holders": dict(Counter(s["holder"] for s in seen)),
                        "let_go_s_max": max((s["let_go_s"] for s in seen), default=None),
                    }
                document["combos"][f"{flavour}/{backend}"] = {"summary": summary, "errors": errors}
                document["elapsed_s"] = round(time.monotonic() - started, 1)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                tmp = args.out.with_suffix(".tmp")
                tmp.write_text(json.dumps(document, indent=2) + "\n")
                tmp.replace(args.out)
                eta_s = (time.monotonic() - started) / done * (total - done)
                print(f"{flavour}/{backend}: {len(flights)} flights, {len(errors)} errors "
                      f"({done}/{total}, ETA {eta_s:.0f} s)", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
