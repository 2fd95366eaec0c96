"""Targets and paths inside random envelopes: violations (the target is 0) and planning cost.

Random envelopes over the paper's 500 m x 500 m area (``--exclusions`` rectangular volumes of
10-60 m sides, floors at 0 m, ceilings 30-150 m, clearance 5 m, altitude band 25-100 m) and random
decisions (a start and a target anywhere, made legal with :func:`legal_target`, then
:func:`plan_path`). Every leg of every path is sampled every 0.25 m, straight and along both
dog-legs an autopilot may fly instead, and each sample is held to the envelope with the point
test (:meth:`Envelope.violation`), a code path apart from the segment
test the planner uses. Reports violations, holds, the kinds of path, and the planning time per
decision (p50, p99, max) in JSON::

    .venv/bin/python benchmarks/envelope_paths.py --decisions 10000 \
        --out benchmarks/results/envelope_paths.json

``--site NAME`` plans inside a shipped district's envelope instead (its buildings as exclusions,
:mod:`sim.envelope.buildings`; every decision in the same envelope, so the graphs are built
once per height band and their cost shows in the max), starts and targets drawn at the lowest
``--site-height-m`` metres of the band, where the buildings are in the way::

    .venv/bin/python benchmarks/envelope_paths.py --site munich --decisions 400 \
        --out benchmarks/results/envelope_paths_munich.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import platform
import time
from collections import Counter
from pathlib import Path

import numpy as np
from shapely.geometry import box

from sim.config import AreaConfig
from sim.envelope import (
    Envelope,
    Exclusion,
    FlightPath,
    area_envelope,
    legal_target,
    plan_path,
)

STEP_M = 0.25


def random_envelope(rng: np.random.Generator, area: AreaConfig, n: int) -> Envelope:
    exclusions = []
    for i in range(n):
        x, y = rng.uniform(0, area.size_x_m - 60, 2)
        w, h = rng.uniform(10, 60, 2)
        exclusions.append(
            Exclusion(box(x, y, x + w, y + h), 0.0, float(rng.uniform(30, 150)), f"x{i}")
        )
    return Envelope.for_area(area, exclusions, clearance_m=5.0)


def path_violations(envelope: Envelope, start: tuple[float, ...], path: FlightPath) -> int:
    """Samples of the path outside the envelope: each leg flown straight, and both ways an
    autopilot that reaches height and position at separate speeds may fly it (height first,
    position first: every path it flies lies between those)."""
    bad = 0
    for a, b in itertools.pairwise([start, *path.waypoints]):
        up, across = (a[0], a[1], b[2]), (b[0], b[1], a[2])
        for p, q in ((a, b), (a, up), (up, b), (a, across), (across, b)):
            n = max(2, math.ceil(math.dist(p, q) / STEP_M) + 1)
            for point in np.linspace(p, q, n):
                bad += envelope.violation(point) is not None
    return bad


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--decisions", type=int, default=10_000)
    parser.add_argument("--exclusions", type=int, default=20)
    parser.add_argument("--per-envelope", type=int, default=100, help="decisions per envelope")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--site", help="a shipped site's name: plan in its buildings' envelope")
    parser.add_argument("--site-height-m", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/envelope_paths.json"))
    args = parser.parse_args()
    if args.decisions < 1 or args.per_envelope < 1 or args.exclusions < 0:
        parser.error("--decisions and --per-envelope: at least 1; --exclusions: at least 0")
    rng = np.random.default_rng(args.seed)
    area = AreaConfig(environment=f"site:{args.site}") if args.site else AreaConfig()
    low, high = (0.0, 120.0)
    if args.site:
        low, high = area.z_min_m, area.z_min_m + args.site_height_m
    times_s: list[float] = []
    kinds: Counter[str] = Counter()
    violations = target_violations = no_legal_target = 0
    started = time.monotonic()
    envelope = area_envelope(area) if args.site else random_envelope(rng, area, args.exclusions)
    for i in range(args.decisions):
        if i and i % args.per_envelope == 0 and not args.site:
            envelope = random_envelope(rng, area, args.exclusions)
        start = legal_target(envelope, rng.uniform((0, 0, low), (500, 500, high)))
        target = legal_target(envelope, rng.uniform((0, 0, low), (500, 500, high)))
        if start is None or target is None:
            no_legal_target += 1
            continue
        target_violations += envelope.violation(target) is not None
        t0 = time.perf_counter()
        path = plan_path(envelope, start, target)
        times_s.append(time.perf_counter() - t0)
        if isinstance(path, FlightPath):
            kinds[path.kind] += 1
            violations += path_violations(envelope, start, path)
        else:
            kinds["hold"] += 1
        if (i + 1) % 1000 == 0:
            done = time.monotonic() - started
            print(f"{i + 1}/{args.decisions} decisions, {violations} violations, "
                  f"ETA {done / (i + 1) * (args.decisions - i - 1):.0f} s", flush=True)  # fmt: skip
    ms = np.array(times_s) * 1000
    result = {
        "command": f"benchmarks/envelope_paths.py --decisions {args.decisions} "
        f"--exclusions {args.exclusions} --per-envelope {args.per_envelope} --seed {args.seed}"
        + (f" --site {args.site} --site-height-m {args.site_height_m:g}" if args.site else ""),
        "exclusions": len(envelope.exclusions),
        "machine": {"python": platform.python_version()},
        "decisions": args.decisions,
        "planned": len(times_s),
        "no_legal_target": no_legal_target,
        "target_violations": target_violations,
        "path_samples_violating": violations,
        "kinds": dict(kinds),
        "plan_ms": {
            "p50": round(float(np.percentile(ms, 50)), 3),
            "p90": round(float(np.percentile(ms, 90)), 3),
            "p99": round(float(np.percentile(ms, 99)), 3),
            "max": round(float(ms.max()), 3),
        },
        "elapsed_s": round(time.monotonic() - started, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(args.out)
    print(json.dumps(result, indent=2))
    return 0 if violations == 0 and target_violations == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
