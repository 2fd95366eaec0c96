"""The world's flight inside random envelopes: violations on the flown paths (the target is 0),
the fleet's separation on its paths, and the cost of a decision step.

Random envelopes over the paper's 500 m x 500 m area, generated as ``benchmarks/envelope_paths.py``
does (``--exclusions`` rectangular volumes of 10-60 m sides, floors at 0 m, ceilings 30-150 m,
clearance 5 m, altitude band 25-100 m), ``--per-envelope`` decisions each. A decision is one
period (``--step-s``, the closed-loop world's 10 m/s and 3 m/s) toward a target drawn anywhere in
(or a little outside) the volume, kept for a geometric number of periods (``--keep-mean``; a
policy often asks for the same place again), flown by :mod:`sim.envelope.flight`:

* **single**: one vehicle, :func:`fly_route` (the route kept across periods, as the link keeps
  it);
* **fleet**: three vehicles, :func:`separated_legal_targets` then :func:`fly_fleet` with the
  10 m separation on the paths; and the same fleet with no separation rule (each vehicle flying
  its own legal route), to measure how often the paths alone come closer than the separation;
* **fleet with no envelope**, as the fleet environment flies it today (unchanged): its paths
  measured the same way.

Every flown path (each :class:`Track`'s pieces, sampled every 0.25 m) is held to the envelope
with the point test (:meth:`Envelope.violation`); the fleet's paths to the separation exactly
(:func:`closest_approach_m`). Also the overhead of the no-envelope path, in the same run:
:meth:`World.fly` with no envelope against the method as it was before envelopes (and
:func:`sim.flight.fly`, and :func:`fly_route` with no envelope), the same floats checked.
Writes JSON::

    .venv/bin/python benchmarks/envelope_flight.py --decisions 10000 \\
        --out benchmarks/results/envelope_flight.json
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import math
import platform
import sys
import time
from collections import Counter
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.config import AreaConfig  # noqa: E402
from sim.envelope.flight import (  # noqa: E402
    Track,
    closest_approach_m,
    fly_fleet,
    fly_route_track,
    legal_position,
    separated_legal_targets,
)
from sim.envelope.volume import Envelope  # noqa: E402
from sim.flight import Flight, fly, fly_many  # noqa: E402
from sim.geometry import clip_to_volume, enforce_separation, hold_separation  # noqa: E402
from sim.world import CLOSED_LOOP, World  # noqa: E402

STEP_M = 0.25
SEPARATION_M = 10.0
K = 3


def _random_envelope_function() -> Any:
    """``random_envelope`` of ``benchmarks/envelope_paths.py`` (one generator for both)."""
    spec = importlib.util.spec_from_file_location(
        "envelope_paths", ROOT / "benchmarks/envelope_paths.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.random_envelope


def track_violations(envelope: Envelope, track: Track) -> int:
    """Samples of ``track`` (every :data:`STEP_M`) outside the envelope."""
    bad = 0
    for a, b in itertools.pairwise(track.points_m):
        n = max(2, math.ceil(math.dist(a, b) / STEP_M) + 1)
        for point in np.linspace(a, b, n):
            bad += envelope.violation(point) is not None
    return bad


def path_conflicts(starts: np.ndarray, tracks: tuple[Track, ...], separation_m: float) -> int:
    """Pairs whose paths came closer than the separation (pairs that started closer excepted:
    closer than they started)."""
    bad = 0
    for i, j in itertools.combinations(range(len(tracks)), 2):
        floor = min(separation_m, float(np.linalg.norm(starts[i] - starts[j]))) - 1e-6
        bad += closest_approach_m(tracks[i], tracks[j]) < floor
    return bad


def _random_target(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform((-10, -10, 15), (510, 510, 110))


def _pct(values_s: list[float]) -> dict[str, float]:
    ms = np.array(values_s) * 1000
    return {
        "p50": round(float(np.percentile(ms, 50)), 3),
        "p99": round(float(np.percentile(ms, 99)), 3),
        "max": round(float(ms.max()), 3),
    }


def run_single(
    rng: np.random.Generator, area: AreaConfig, args: argparse.Namespace, make: Any
) -> dict[str, Any]:
    flight, step_s = CLOSED_LOOP.flight, args.step_s
    times_s: list[float] = []
    kinds: Counter[str] = Counter()
    violations = end_violations = 0
    envelope: Envelope | None = None
    for i in range(args.decisions):
        if i % args.per_envelope == 0:
            envelope = make(rng, area, args.exclusions)
            position = legal_position(
                envelope, rng.uniform((0, 0, 25), (500, 500, 100)), search=True
            )
            route = None
            target = _random_target(rng)
        assert envelope is not None
        if rng.random() < 1.0 / args.keep_mean:
            target = _random_target(rng)
        t0 = time.perf_counter()
        flown = fly_route_track(envelope, position, target, flight, step_s, route)
        times_s.append(time.perf_counter() - t0)
        kinds[flown.route.kind] += 1
        violations += track_violations(envelope, flown.track)
        end_violations += envelope.violation(flown.position_m) is not None
        position, route = flown.position_m, flown.route
    return {
        "decisions": args.decisions,
        "path_samples_violating": violations,
        "end_positions_violating": end_violations,
        "route_kinds": dict(kinds),
        "step_ms": _pct(times_s),
    }


def run_fleet(
    rng: np.random.Generator,
    area: AreaConfig,
    args: argparse.Namespace,
    make: Any,
    separation_m: float | None,
) -> dict[str, Any]:
    flight, step_s = CLOSED_LOOP.flight, args.step_s
    times_s: list[float] = []
    violations = conflicts = target_conflicts = held = steps_with_hold = 0
    stuck = 0  # vehicles held while not at their target, for at least 10 periods in a row
    envelope: Envelope | None = None
    for i in range(args.decisions):
        if i % args.per_envelope == 0:
            envelope = make(rng, area, args.exclusions)
            starts = rng.uniform((0, 0, 25), (500, 500, 100), (K, 3))
            positions = separated_legal_targets(envelope, starts, SEPARATION_M, area, True)
            routes: list[Any] = [None] * K
            wanted = np.stack([_random_target(rng) for _ in range(K)])
            held_for = np.zeros(K, dtype=int)
        assert envelope is not None
        for k in range(K):
            if rng.random() < 1.0 / args.keep_mean:
                wanted[k] = _random_target(rng)
        t0 = time.perf_counter()
        targets = separated_legal_targets(envelope, wanted, SEPARATION_M, area)
        result = fly_fleet(envelope, positions, targets, flight, step_s, separation_m, routes)
        times_s.append(time.perf_counter() - t0)
        if len(targets) > 1:
            gap = np.linalg.norm(targets[:, None] - targets[None], axis=-1) + np.eye(K) * 1e9
            target_conflicts += bool(gap.min() < SEPARATION_M - 1e-6)
        for track in result.tracks:
            violations += track_violations(envelope, track)
        conflicts += path_conflicts(positions, result.tracks, SEPARATION_M)
        held += sum(result.held)
        steps_with_hold += any(result.held)
        held_for = np.where(np.array(result.held), held_for + 1, 0)
        stuck += int(np.sum(held_for == 10))
        positions, routes = result.positions_m, list(result.routes)
    return {
        "decisions": args.decisions,
        "vehicles": K,
        "separation_m": SEPARATION_M,
        "separation_rule": separation_m is not None,
        "path_samples_violating": violations,
        "path_pairs_closer_than_separation": conflicts,
        "decisions_with_targets_closer_than_separation": target_conflicts,
        "vehicles_held": held,
        "decisions_with_a_hold": steps_with_hold,
        "vehicles_held_10_periods_in_a_row": stuck,
        "step_ms": _pct(times_s),
    }


def run_fleet_without_envelope(
    rng: np.random.Generator, area: AreaConfig, args: argparse.Namespace
) -> dict[str, Any]:
    """Today's fleet flight with no envelope (unchanged: :func:`sim.flight.fly_many` toward
    separated targets, then :func:`sim.geometry.hold_separation` on where the period ends),
    its paths measured as the envelope's are: each vehicle's dog-leg as :func:`fly` flies it,
    a held one still, a detour (a turned step) straight."""
    flight, step_s = CLOSED_LOOP.flight, args.step_s
    conflicts = 0
    for i in range(args.decisions):
        if i % args.per_envelope == 0:
            positions = enforce_separation(
                rng.uniform((0, 0, 25), (500, 500, 100), (K, 3)), SEPARATION_M, area
            )
            wanted = np.stack([_random_target(rng) for _ in range(K)])
        for k in range(K):
            if rng.random() < 1.0 / args.keep_mean:
                wanted[k] = _random_target(rng)
        targets = enforce_separation(clip_to_volume(wanted, area), SEPARATION_M, area)
        flown = fly_many(positions, targets, flight, step_s)
        ends = hold_separation(positions, flown, SEPARATION_M, area)
        tracks = []
        for k in range(K):
            if np.array_equal(ends[k], flown[k]):
                tracks.append(fly_route_track(None, positions[k], targets[k], flight, step_s).track)
            elif np.array_equal(ends[k], positions[k]):
                tracks.append(Track.still(tuple(positions[k]), step_s))
            else:
                tracks.append(Track((0.0, step_s), (tuple(positions[k]), tuple(ends[k]))))
        conflicts += path_conflicts(positions, tuple(tracks), SEPARATION_M)
        positions = ends
    return {
        "decisions": args.decisions,
        "vehicles": K,
        "separation_m": SEPARATION_M,
        "path_pairs_closer_than_separation": conflicts,
    }


@dataclass(frozen=True)
class _WorldBefore(World):
    """:class:`World` with :meth:`World.fly` as it was before envelopes (the baseline)."""

    def fly(self, position_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
        return fly(position_m, target_m, self.flight, self.step_s)


def overhead(rng: np.random.Generator, n: int) -> dict[str, Any]:
    """The no-envelope path: :func:`fly`, :meth:`World.fly` with no envelope, and
    :func:`fly_route` with none, each timed over the same ``n`` (start, target) pairs."""
    from sim.envelope.flight import fly_route

    world = CLOSED_LOOP
    flight: Flight = world.flight
    before = _WorldBefore(**{f.name: getattr(world, f.name) for f in fields(World)})
    starts = rng.uniform((0, 0, 25), (500, 500, 100), (n, 3))
    targets = rng.uniform((0, 0, 25), (500, 500, 100), (n, 3))
    same = all(
        np.array_equal(fly(p, t, flight, 1.0), world.fly(p, t))
        and np.array_equal(fly(p, t, flight, 1.0), before.fly(p, t))
        and np.array_equal(fly(p, t, flight, 1.0), fly_route(None, p, t, flight, 1.0)[0])
        for p, t in zip(starts[:1000], targets[:1000], strict=True)
    )
    timings: dict[str, float] = {}
    for name, call in (
        ("fly", lambda p, t: fly(p, t, flight, 1.0)),
        ("World.fly before", before.fly),
        ("World.fly", world.fly),
        ("fly_route(None)", lambda p, t: fly_route(None, p, t, flight, 1.0)),
    ):
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            for p, t in zip(starts, targets, strict=True):
                call(p, t)
            best = min(best, time.perf_counter() - t0)
        timings[name] = best / n * 1e6
    return {
        "calls": n,
        "same_floats": same,
        "us_per_call": {k: round(v, 3) for k, v in timings.items()},
        "World.fly_over_fly": round(timings["World.fly"] / timings["fly"], 3),
        "World.fly_over_before": round(timings["World.fly"] / timings["World.fly before"], 3),
        "fly_route_none_over_fly": round(timings["fly_route(None)"] / timings["fly"], 3),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--decisions", type=int, default=10_000)
    parser.add_argument("--exclusions", type=int, default=20)
    parser.add_argument("--per-envelope", type=int, default=100, help="decisions per envelope")
    parser.add_argument("--keep-mean", type=float, default=8.0, help="periods a target is kept")
    parser.add_argument("--step-s", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/envelope_flight.json"))
    args = parser.parse_args()
    if args.decisions < 1 or args.per_envelope < 1 or args.exclusions < 0 or args.keep_mean < 1:
        parser.error("--decisions, --per-envelope, --keep-mean: at least 1; --exclusions >= 0")
    make = _random_envelope_function()
    area = AreaConfig()
    started = time.monotonic()
    result: dict[str, Any] = {
        "command": f"benchmarks/envelope_flight.py --decisions {args.decisions} "
        f"--exclusions {args.exclusions} --per-envelope {args.per_envelope} "
        f"--keep-mean {args.keep_mean:g} --step-s {args.step_s:g} --seed {args.seed}",
        "machine": {"python": platform.python_version(), "cpus": _cpus()},
    }
    result["single"] = run_single(np.random.default_rng(args.seed), area, args, make)
    print("single:", json.dumps(result["single"]), flush=True)
    for name, rule in (("fleet", SEPARATION_M), ("fleet_without_path_rule", None)):
        result[name] = run_fleet(np.random.default_rng(args.seed + 1), area, args, make, rule)
        print(f"{name}:", json.dumps(result[name]), flush=True)
    result["fleet_no_envelope_today"] = run_fleet_without_envelope(
        np.random.default_rng(args.seed + 1), area, args
    )
    print("fleet_no_envelope_today:", json.dumps(result["fleet_no_envelope_today"]), flush=True)
    result["no_envelope_overhead"] = overhead(np.random.default_rng(args.seed + 2), 20_000)
    result["elapsed_s"] = round(time.monotonic() - started, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(args.out)
    print(json.dumps(result, indent=2))
    bad = (
        result["single"]["path_samples_violating"]
        + result["single"]["end_positions_violating"]
        + result["fleet"]["path_samples_violating"]
        + result["fleet"]["path_pairs_closer_than_separation"]
    )
    return 0 if bad == 0 and result["no_envelope_overhead"]["same_floats"] else 1


def _cpus() -> int:
    import os

    return os.cpu_count() or 0


if __name__ == "__main__":
    raise SystemExit(main())
