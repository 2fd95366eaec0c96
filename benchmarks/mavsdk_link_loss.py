"""Repeated link losses on the MAVSDK backend: does tearing sessions down ever crash the process?

One cycle, against an in-process PX4-flavoured ``sitl_mock`` on a loopback TCP port: the
:class:`~service.mavsdk_link.MavsdkLink` comes up and streams a target (so ``Offboard.start``
requests are in flight), the vehicle disappears (the mock stops), the link declares it lost and
drops its MAVSDK session, the vehicle comes back on the same port, and the stream resumes. A
session torn down while MAVSDK still had a command in flight used to end in a SIGSEGV inside the
plugins' ``destroy`` (see the ``service.mavsdk_session`` docstring).

The cycles run in a child process, so a native crash is counted, not fatal; ``--busy N`` adds N
busy-looping processes for the run (the crash needed a loaded machine to show).

    .venv/bin/python benchmarks/mavsdk_link_loss.py --cycles 40 --busy 2
        -> benchmarks/results/mavsdk_link_loss.json
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing
import os
import platform
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.helpers is not an installed package

RESULTS = Path(__file__).parent / "results" / "mavsdk_link_loss.json"
CYCLE_LIMIT_S = 60.0
"""The child is killed (SIGKILL, reported as such) after this long per asked cycle."""


def one_cycle() -> float:
    """One link loss and recovery; returns the seconds from the vehicle's return to streaming."""
    from service.mavsdk_link import MavsdkLink
    from service.vehicle_link import LinkConfig
    from sitl_mock.server import MockAutopilot
    from sitl_mock.vehicle import VehicleConfig
    from tests.helpers import wait_for

    mock = MockAutopilot("tcp:127.0.0.1:0", "px4", VehicleConfig(ready_delay_s=0.3)).start()
    port = mock.port
    link = MavsdkLink(
        LinkConfig(f"tcp:127.0.0.1:{port}", reconnect_min_s=0.1, reconnect_max_s=0.5)
    ).start()
    again = None
    try:
        wait_for(lambda: link.state().link == "up", 10.0, message="link up")
        link.set_target((20.0, 20.0, 10.0))
        wait_for(lambda: mock.stats["setpoints_received"] >= 5, 5.0, message="setpoints")
        mock.stop()
        wait_for(lambda: link.state().link == "link_lost", 6.0, message="link lost")
        failures = link.counters["connect_failures"]
        wait_for(lambda: link.counters["connect_failures"] > failures, 8.0, message="retries")
        again = MockAutopilot(
            f"tcp:127.0.0.1:{port}", "px4", VehicleConfig(ready_delay_s=0.3)
        ).start()
        back = time.monotonic()
        wait_for(lambda: again.stats["setpoints_received"] >= 5, 15.0, message="streaming again")
        return time.monotonic() - back
    finally:
        link.close()
        mock.stop()
        if again is not None:
            again.stop()


def child(cycles: int) -> int:
    """Run the cycles, one line per finished cycle on stdout (the parent counts them)."""
    for index in range(cycles):
        started = time.monotonic()
        seconds = one_cycle()
        took_s = time.monotonic() - started
        print(f"cycle {index} took {took_s:.3f} recovered {seconds:.3f}", flush=True)
    return 0


def _busy() -> None:
    while True:
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=40, help="link losses (default 40)")
    parser.add_argument("--busy", type=int, default=2, help="busy-looping processes (default 2)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.cycles < 1 or args.busy < 0:
        parser.error("--cycles must be >= 1 and --busy >= 0")
    if args.child:
        return child(args.cycles)

    busy = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(args.busy)]
    for process in busy:
        process.start()
    started = time.monotonic()
    recovered: list[float] = []
    cycle_s: list[float] = []
    try:
        run = subprocess.Popen(
            [sys.executable, __file__, "--child", "--cycles", str(args.cycles)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,  # one pipe, read as it comes: a full pipe would block it
            text=True,
        )
        assert run.stdout is not None
        # Each cycle's waits are bounded, but a hang inside MAVSDK would not be: a watchdog.
        watchdog = threading.Timer(CYCLE_LIMIT_S * args.cycles, run.kill)
        watchdog.start()
        other: collections.deque[str] = collections.deque(maxlen=40)  # its log, for a crash
        for line in run.stdout:
            if not line.startswith("cycle "):
                other.append(line)
            elif " recovered " in line:
                words = line.split()
                cycle_s.append(float(words[3]))
                recovered.append(float(words[5]))
                print(f"\rcycle {len(recovered)}/{args.cycles}", end="", file=sys.stderr)
        print(file=sys.stderr)
        run.wait()
        watchdog.cancel()
    finally:
        for process in busy:
            process.terminate()
    crashed = run.returncode < 0
    result: dict[str, Any] = {
        "cycles_asked": args.cycles,
        "cycles_completed": len(recovered),
        "exit": (signal.Signals(-run.returncode).name if crashed else run.returncode),
        "native_crash": crashed and run.returncode == -signal.SIGSEGV,
        "recovery_s_median": statistics.median(recovered) if recovered else None,
        "recovery_s_max": max(recovered) if recovered else None,
        "cycle_s_median": statistics.median(cycle_s) if cycle_s else None,
        "cycle_s_max": max(cycle_s) if cycle_s else None,
        "busy_processes": args.busy,
        "wall_s": round(time.monotonic() - started, 1),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
    }
    if run.returncode != 0:
        result["output_tail"] = "".join(other)[-4000:]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "output_tail"}, indent=2))
    return 0 if run.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
