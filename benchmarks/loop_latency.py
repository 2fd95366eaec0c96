"""How the world's flight predicts the loop's: the latency that fits a ``tupa demo`` track best.

Reads a ``demo.json`` written by ``tupa demo`` (the served loop's track: the vehicle's true
position at each report and the target the service answered), flies the world's accelerating
flight (:mod:`sim.dynamics`, the ``closed-loop`` world's speed and acceleration limits) through
the same targets from the first position at rest, for each candidate latency, and reports the
position error at every report. Scenarios after the first only (the first one's first decision
waits for the policy's cold start). ``sim.world.LOOP_LATENCY_S`` is the latency chosen here.

    .venv/bin/tupa demo --environment site:munich --out runs/demo
    .venv/bin/python benchmarks/loop_latency.py runs/demo/demo.json

Writes ``benchmarks/results/loop_latency.json`` (``--out``). The latency that fits includes the
served policy's decision time: the tracking oracle's loop fits 0.05 s
(``benchmarks/results/demo_site_munich_oracle.json``), the planning oracle's about 0.15 s
(``benchmarks/results/demo_site_munich.json``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from sim.atomic import atomic_write_json
from sim.dynamics import fly_accelerating
from sim.world import CLOSED_LOOP

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "loop_latency.json"
CANDIDATES_S = (0.0, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5)


def track_errors_m(demo: dict, latency_s: float) -> np.ndarray:
    """The world's predicted position against the loop's, at every report but the first of
    every scenario after the first (metres)."""
    flight = CLOSED_LOOP.flight
    assert flight.accel_mps2 is not None
    assert flight.horizontal_mps is not None and flight.vertical_mps is not None
    errors = []
    for scenario in demo["scenarios"][1:]:
        track = scenario["track"]
        position = np.array([track[0]["position_m"]], dtype=float)
        velocity = np.zeros((1, 3))
        previous = position.copy()
        for now, then in itertools.pairwise(track):
            if now["target_m"] is None:
                break
            target = np.array([now["target_m"]], dtype=float)
            position, velocity = fly_accelerating(
                position, velocity, previous, target,
                duration_s=CLOSED_LOOP.step_s, latency_s=latency_s,
                max_h_mps=flight.horizontal_mps, max_v_mps=flight.vertical_mps,
                accel_h_mps2=flight.accel_mps2, accel_v_mps2=flight.accel_mps2,
            )  # fmt: skip
            previous = target
            errors.append(float(np.linalg.norm(position[0] - np.asarray(then["position_m"]))))
    return np.array(errors)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo_json", type=Path, help="a demo.json written by tupa demo")
    parser.add_argument("--out", type=Path, default=OUT, help=f"default {OUT.relative_to(ROOT)}")
    args = parser.parse_args(argv)
    try:
        demo = json.loads(args.demo_json.read_text())
    except (OSError, ValueError) as exc:
        print(f"demo_json: {args.demo_json}: cannot read it ({exc})", file=sys.stderr)
        return 2
    if len(demo.get("scenarios", [])) < 2:
        print(f"demo_json: {args.demo_json}: needs at least two scenarios", file=sys.stderr)
        return 2
    rows = []
    for latency_s in CANDIDATES_S:
        errors = track_errors_m(demo, latency_s)
        rows.append(
            {
                "latency_s": latency_s,
                "n_reports": len(errors),
                "error_mean_m": round(float(errors.mean()), 3),
                "error_p90_m": round(float(np.percentile(errors, 90)), 3),
                "error_max_m": round(float(errors.max()), 3),
            }
        )
        print(
            f"latency {latency_s:5.3f} s: position error mean {rows[-1]['error_mean_m']:.2f} m, "
            f"p90 {rows[-1]['error_p90_m']:.2f} m, max {rows[-1]['error_max_m']:.2f} m "
            f"({len(errors)} reports)"
        )
    best = min(rows, key=lambda r: r["error_mean_m"])
    print(f"best: {best['latency_s']} s (the world's: {CLOSED_LOOP.flight.latency_s} s)")
    atomic_write_json(
        args.out,
        {
            "benchmark": "loop_latency",
            "demo": str(args.demo_json),
            "served": demo.get("policy"),
            "environment": demo.get("config", {}).get("environment"),
            "world_latency_s": CLOSED_LOOP.flight.latency_s,
            "best_latency_s": best["latency_s"],
            "candidates": rows,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
