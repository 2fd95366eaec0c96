"""The planning oracle (``planning-oracle``, :mod:`policies.placements.planning`): how close it is
to an exhaustive search, how it does in the closed loop against the tracking oracle and the
baselines, and what a decision costs.

Writes ``benchmarks/results/planning_oracle.json`` and ``planning_oracle.md``:

``exhaustive`` (a): small cases — 3 users, the vehicle at a random point of the volume, a short
    episode (``--exhaustive-steps`` steps left, 30) in the ``closed-loop`` world's flight — where
    every sequence of H targets from a 3 × 3 × 3 lattice over the volume, the tracking oracle's
    answer and staying put (29 targets; 841 trajectories for H = 2, 24,389 for H = 3) is scored
    on the planner's own objective (:meth:`~policies.placements.planning.PlanningPolicy.score`),
    against the planner's plan with the same H. The gap is (best − planner) / best, per case, where
    the best is above 0.01 per step (below, nothing is served wherever the vehicle goes); the
    tracking oracle's trajectory is measured the same way.
``closed_loop`` (b): ``tupa eval``'s protocol
    (:func:`policies.evaluation.evaluation.evaluate_policy`) for planning-oracle, oracle (the
    tracking oracle), min-distance, load-weighted and min-distance-env, in the worlds
    ``closed-loop`` and ``closed-loop-moving``, environments ``open``, ``urban`` and
    ``site:munich``, on generated held-out scenarios (3 and 10 users, ``--scenarios`` per set,
    seeds used nowhere else), the stochastic world as evaluated.
    Ratios are of means measured in the same run.
``latency`` (c): wall time of each planning-oracle decision in (b) (and of the tracking
    oracle's, for comparison; after two untimed decisions that compile the model's kernels),
    p50 and p99 per users count (two workers, one per core of this shared 2-core machine, so
    other work competes with them), plus 20 users in ``closed-loop-moving``
    (the first ``--latency-steps`` decisions of ``--latency-scenarios`` full episodes per
    environment: the costliest, with the most steps left to plan for), timed in the main
    process alone after the workers are done.

    .venv/bin/python benchmarks/planning_oracle.py            # about 10 to 15 minutes
    .venv/bin/python benchmarks/planning_oracle.py --quick    # a smoke run, a couple of minutes

Progress goes to standard error.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "benchmarks" / "results"
TEST_SEED = 4_040_000  # held-out sets: TEST_SEED + a hash of (environment, users)
CASE_SEED = 4_041_000  # the exhaustive cases
WORLDS = ("closed-loop", "closed-loop-moving")
ENVIRONMENTS = ("open", "urban", "site:munich")
POLICIES = ("planning-oracle", "oracle", "min-distance", "load-weighted", "min-distance-env")
TIMED = ("planning-oracle", "oracle")


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------
# (a) the exhaustive search


def _exhaustive_case(job: tuple[str, int, int, int]) -> dict[str, Any]:
    """One small case: the planner against every H-sequence of the lattice's targets."""
    from dataclasses import replace

    from policies.interface import ReportedUsers
    from policies.placements.planning import PlanningConfig, PlanningPolicy
    from sim.config import AreaConfig
    from sim.scenarios import generate_scenarios
    from sim.world import CLOSED_LOOP

    environment, horizon, steps, index = job
    area = AreaConfig(environment=environment)
    world = replace(CLOSED_LOOP, area=area, episode_steps=steps)
    seed = CASE_SEED + zlib.crc32(f"{environment}/{horizon}/{index}".encode()) % 100_000
    scenario = generate_scenarios(1, 3, seed=seed, area=area)[0]
    rng = np.random.default_rng(seed)
    vehicle = np.array([*rng.uniform(0, area.size_x_m, 2), rng.uniform(area.z_min_m, area.z_max_m)])
    policy = PlanningPolicy(world, PlanningConfig(horizon_steps=horizon))
    policy.begin_episode(scenario, world)
    users = ReportedUsers(scenario.users_xy_m, scenario.load_bps)
    started = time.perf_counter()
    plan = policy.plan(users, vehicle, remaining_steps=steps)
    plan_s = time.perf_counter() - started
    xs = [area.size_x_m / 6, area.size_x_m / 2, 5 * area.size_x_m / 6]
    ys = [area.size_y_m / 6, area.size_y_m / 2, 5 * area.size_y_m / 6]
    zs = np.linspace(area.z_min_m, area.z_max_m, 3)
    lattice = np.array(list(itertools.product(xs, ys, zs)))
    targets = np.concatenate([lattice, plan.tracking_trajectory_m[:1], vehicle[None]])
    sequences = np.array(list(itertools.product(targets, repeat=horizon)))
    started = time.perf_counter()
    values = np.concatenate(
        [policy.score(chunk, users, vehicle, steps) for chunk in np.array_split(sequences, 8)]
    )
    exhaustive_s = time.perf_counter() - started
    return {
        "environment": environment,
        "horizon_steps": horizon,
        "steps": steps,
        "case": index,
        "trajectories": len(sequences),
        "planner_per_step": plan.value / steps,
        "tracking_per_step": plan.tracking_value / steps,
        "exhaustive_per_step": float(values.max()) / steps,
        "planner_trajectories_scored": plan.trajectories_scored,
        "planner_s": plan_s,
        "exhaustive_s": exhaustive_s,
    }


def _gap(best: float, value: float) -> float | None:
    return (best - value) / best if best > 0.01 else None


def summarise_exhaustive(cases: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for horizon in sorted({c["horizon_steps"] for c in cases}):
        rows = [c for c in cases if c["horizon_steps"] == horizon]
        planner = [_gap(c["exhaustive_per_step"], c["planner_per_step"]) for c in rows]
        tracking = [_gap(c["exhaustive_per_step"], c["tracking_per_step"]) for c in rows]
        p = np.array([g for g in planner if g is not None])
        t = np.array([g for g in tracking if g is not None])
        absolute = np.array([c["exhaustive_per_step"] - c["planner_per_step"] for c in rows])
        out[f"H={horizon}"] = {
            "cases": len(rows),
            "cases_with_gap": len(p),
            "planner_gap_mean": float(p.mean()),
            "planner_gap_max": float(p.max()),
            "planner_within_2pct": float(np.mean(p <= 0.02)),
            "planner_at_or_above_exhaustive": float(np.mean(p <= 1e-9)),
            "planner_abs_gap_max_per_step": float(absolute.max()),
            "tracking_gap_mean": float(t.mean()),
            "tracking_gap_max": float(t.max()),
            "planner_ms_median": float(np.median([c["planner_s"] for c in rows]) * 1e3),
            "exhaustive_ms_median": float(np.median([c["exhaustive_s"] for c in rows]) * 1e3),
            "trajectories_exhaustive": rows[0]["trajectories"],
            "trajectories_planner_median": float(
                np.median([c["planner_trajectories_scored"] for c in rows])
            ),
        }
    return out


# ----------------------------------------------------------------------------------------------
# (b) the closed loop and (c) latency


class _Timed:
    """A policy whose decisions are timed (wall clock, seconds)."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.name, self.spec, self.kind = policy.name, policy.spec, policy.kind
        self.times_s: list[float] = []

    def begin_episode(self, users: Any, world: Any) -> Any:
        return self.policy.begin_episode(users, world)

    def decide(self, reports: Any, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        started = time.perf_counter()
        target = self.policy.decide(reports, vehicle_xyz_m)
        self.times_s.append(time.perf_counter() - started)
        return target

    def describe(self) -> dict[str, Any]:
        return self.policy.describe()


def _world(world_name: str, environment: str, steps: int | None = None) -> Any:
    from dataclasses import replace

    from sim.config import AreaConfig
    from sim.world import get_world

    world = replace(get_world(world_name), area=AreaConfig(environment=environment))
    return world if steps is None else replace(world, episode_steps=steps)


def _scenarios(environment: str, users: int, n: int, seed_base: int) -> list[Any]:
    from sim.config import AreaConfig
    from sim.scenarios import generate_scenarios

    seed = seed_base + zlib.crc32(f"{environment}/{users}".encode()) % 100_000
    return generate_scenarios(n, users, seed=seed, area=AreaConfig(environment=environment))


def _warm_up(policy: Any, scenario: Any, world: Any) -> None:
    """Two untimed decisions, so that compiling the model's kernels (numba, on first use in a
    process) is not counted as a decision's time."""
    from dataclasses import replace

    from policies.evaluation.evaluation import run_episode

    run_episode(policy, scenario, replace(world, episode_steps=2), seed=0)


def _closed_loop_job(job: tuple[str, str, int, int, str]) -> dict[str, Any]:
    """One policy on one held-out set in one world and environment (a worker process)."""
    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import resolve_policy

    world_name, environment, users, n, spec = job
    world = _world(world_name, environment)
    scenarios = _scenarios(environment, users, n, TEST_SEED)
    inner = resolve_policy(spec, world)
    if spec in TIMED:
        _warm_up(inner, scenarios[0], world)
    policy = _Timed(inner)
    started = time.perf_counter()
    result = evaluate_policy(policy, scenarios, world, progress=False)
    return {
        "world": world_name,
        "environment": environment,
        "users": users,
        "policy": spec,
        "utilities": [row["utility"] for row in result["scenarios"]],
        "decision_ms": [1e3 * t for t in policy.times_s] if spec in TIMED else [],
        "wall_s": time.perf_counter() - started,
    }


def _latency_job(job: tuple[str, int, int, int, str]) -> dict[str, Any]:
    """Decision times of one policy, 20 users, the first decisions of full episodes of
    closed-loop-moving (the costliest: the most steps left to plan for)."""
    from policies.registry import resolve_policy
    from sim.envs import FapContinuousEnv

    environment, users, n, steps, spec = job
    world = _world("closed-loop-moving", environment)
    scenarios = _scenarios(environment, users, n, TEST_SEED + 7)
    inner = resolve_policy(spec, world)
    _warm_up(inner, scenarios[0], world)
    policy = _Timed(inner)
    env = FapContinuousEnv(scenarios, world=world)
    for i, scenario in enumerate(scenarios):
        policy.begin_episode(scenario, world)
        _, info = env.reset(seed=i, options={"scenario": scenario})
        for _ in range(steps):
            _, _, _, _, info = env.step_to(policy.decide(info["reports"], info["uav_xyz_m"]))
    return {
        "environment": environment,
        "users": users,
        "policy": spec,
        "decision_ms": [1e3 * t for t in policy.times_s],
    }


def _percentiles(values: list[float]) -> dict[str, float]:
    a = np.array(values)
    return {
        "n": len(a),
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }


def _ratio(a: float, b: float) -> float | None:
    return float(a / b) if b > 0 else None


def _fmt(value: float | None, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def summarise_closed_loop(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    sets = []
    keys = sorted({(r["world"], r["environment"], r["users"]) for r in rows}, key=str)
    for world_name, environment, users in keys:
        mine = {
            r["policy"]: np.array(r["utilities"])
            for r in rows
            if (r["world"], r["environment"], r["users"]) == (world_name, environment, users)
        }
        planner, tracking = mine["planning-oracle"], mine["oracle"]
        sets.append(
            {
                "world": world_name,
                "environment": environment,
                "users": users,
                "scenarios": len(planner),
                "mean_utility": {name: float(u.mean()) for name, u in mine.items()},
                "planner_over_oracle": _ratio(planner.mean(), tracking.mean()),
                "planner_over_min_distance": _ratio(planner.mean(), mine["min-distance"].mean()),
                "scenarios_planner_below_oracle_by_0.005": int(np.sum(planner < tracking - 0.005)),
                "scenarios_planner_above_oracle_by_0.005": int(np.sum(planner > tracking + 0.005)),
            }
        )
    return sets


# ----------------------------------------------------------------------------------------------
# Markdown


def markdown(document: dict[str, Any]) -> str:
    lines = [
        "# The planning oracle",
        "",
        f"`{document['command']}` ({document['machine']}; {document['wall_s']:.0f} s).",
        "",
        "## (a) Against an exhaustive search (small cases, the planner's own objective)",
        "",
        "| H | cases | exhaustive trajectories | planner's (median) | planner gap mean | max "
        "| within 2 % | ≥ exhaustive | tracking gap mean | max | planner ms | exhaustive ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for horizon, s in document["exhaustive"]["summary"].items():
        lines.append(
            f"| {horizon[2:]} | {s['cases']} ({s['cases_with_gap']} served) "
            f"| {s['trajectories_exhaustive']} | {s['trajectories_planner_median']:.0f} "
            f"| {100 * s['planner_gap_mean']:.2f} % | {100 * s['planner_gap_max']:.2f} % "
            f"| {100 * s['planner_within_2pct']:.0f} % "
            f"| {100 * s['planner_at_or_above_exhaustive']:.0f} % "
            f"| {100 * s['tracking_gap_mean']:.2f} % | {100 * s['tracking_gap_max']:.2f} % "
            f"| {s['planner_ms_median']:.0f} | {s['exhaustive_ms_median']:.0f} |"
        )
    lines += [
        "",
        "A negative gap: the planner's trajectory beats every lattice sequence (its targets are "
        "not on the lattice).",
        "",
        "## (b) Closed loop: mean utility per step (stochastic worlds, held-out scenarios)",
        "",
        "| world | environment | users | n | " + " | ".join(POLICIES) + " | planner / oracle "
        "| planner / min-distance | planner below / above oracle (> 0.005) |",
        "| --- | --- | --- | --- | " + " | ".join("---" for _ in POLICIES) + " | --- | --- | --- |",
    ]
    for s in document["closed_loop"]["sets"]:
        means = " | ".join(f"{s['mean_utility'][p]:.4f}" for p in POLICIES)
        lines.append(
            f"| {s['world']} | {s['environment']} | {s['users']} | {s['scenarios']} | {means} "
            f"| {_fmt(s['planner_over_oracle'], 4)} | {_fmt(s['planner_over_min_distance'], 3)} "
            f"| {s['scenarios_planner_below_oracle_by_0.005']} / "
            f"{s['scenarios_planner_above_oracle_by_0.005']} |"
        )
    overall = document["closed_loop"]["overall"]
    lines += [
        "",
        f"Over all sets: planning-oracle {overall['planning-oracle']:.4f}, oracle "
        f"{overall['oracle']:.4f} (ratio {_fmt(overall['planner_over_oracle'], 4)}).",
        "",
        "## (c) Decision latency (ms, wall clock; (b): two workers on a shared 2-core machine; "
        "20 users: one process alone)",
        "",
        "| policy | where | users | decisions | p50 | p99 | max |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in document["latency"]:
        lines.append(
            f"| {row['policy']} | {row['where']} | {row['users']} | {row['n']} "
            f"| {row['p50_ms']:.1f} | {row['p99_ms']:.1f} | {row['max_ms']:.1f} |"
        )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------


def environment_means(document: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Each environment's mean utility per step per policy over all its closed-loop sets (both
    worlds, every user count, every scenario alike): what the served-defaults table ranks."""
    out: dict[str, dict[str, list[float]]] = {}
    for row in document["closed_loop"]["rows"]:
        out.setdefault(row["environment"], {}).setdefault(row["policy"], []).extend(
            row["utilities"]
        )
    return {env: {p: float(np.mean(u)) for p, u in by.items()} for env, by in out.items()}


def write_defaults(document: dict[str, Any], source: Path) -> None:
    """The served-defaults table (:mod:`policies.defaults`) from a results document."""
    from policies.defaults import write_table

    means = environment_means(document)
    path = write_table(means, f"{document['command']} -> {source.relative_to(ROOT)}")
    for environment, by in sorted(means.items()):
        best = max(by, key=by.get)
        _say(f"{environment}: best {best} {by[best]:.4f}")
    _say(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--write-defaults",
        action="store_true",
        help="also write policies/served_defaults.json (the served default per environment)",
    )
    parser.add_argument(
        "--defaults-from",
        type=Path,
        help="write policies/served_defaults.json from this results file, and run nothing",
    )
    parser.add_argument(
        "--quick", action="store_true", help="a smoke run: 3 users only, 1 scenario a set (minutes)"
    )
    parser.add_argument("--scenarios", type=int, default=5, help="per closed-loop set (5)")
    parser.add_argument("--cases", type=int, default=12, help="exhaustive cases per env, H=2")
    parser.add_argument("--cases-h3", type=int, default=4, help="exhaustive cases per env, H=3")
    parser.add_argument("--exhaustive-steps", type=int, default=30)
    parser.add_argument("--latency-scenarios", type=int, default=2)
    parser.add_argument("--latency-steps", type=int, default=30)
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS / "planning_oracle.json")
    args = parser.parse_args(argv)
    if args.defaults_from is not None:
        try:
            document = json.loads(args.defaults_from.read_text())
        except (OSError, ValueError) as exc:
            parser.error(f"--defaults-from: {args.defaults_from}: cannot read it ({exc})")
        write_defaults(document, args.defaults_from.resolve())
        return
    if args.quick:
        args.scenarios, args.cases, args.cases_h3 = 1, 2, 1
        args.latency_scenarios, args.latency_steps = 1, 5
    users_counts = (3,) if args.quick else (3, 10)
    command = "python benchmarks/planning_oracle.py" + (
        " " + " ".join(sys.argv[1:]) if argv is None and len(sys.argv) > 1 else ""
    )
    started = time.perf_counter()

    jobs_a = [
        (environment, horizon, args.exhaustive_steps, index)
        for environment in ENVIRONMENTS
        for horizon, n in ((2, args.cases), (3, args.cases_h3))
        for index in range(n)
    ]
    jobs_b = [
        (world_name, environment, users, args.scenarios, spec)
        for world_name in WORLDS
        for environment in ENVIRONMENTS
        for users in users_counts
        for spec in POLICIES
    ]
    # The slowest first, so the two workers finish together.
    jobs_b.sort(key=lambda j: (j[4] not in TIMED, -j[2], j[0] != "closed-loop-moving"))
    jobs_c = [
        (environment, 20, args.latency_scenarios, args.latency_steps, spec)
        for environment in ENVIRONMENTS
        for spec in TIMED
    ]
    with ProcessPoolExecutor(args.workers) as pool:
        futures_b = [pool.submit(_closed_loop_job, job) for job in jobs_b]
        futures_a = [pool.submit(_exhaustive_case, job) for job in jobs_a]
        total = len(futures_a) + len(futures_b) + len(jobs_c)
        done = 0
        rows_b = []
        for future, job in zip(futures_b, jobs_b, strict=True):
            rows_b.append(future.result())
            done += 1
            _say(f"[{done}/{total}] {time.perf_counter() - started:6.0f} s  closed loop {job}")
        cases = []
        for future, job in zip(futures_a, jobs_a, strict=True):
            cases.append(future.result())
            done += 1
            _say(f"[{done}/{total}] {time.perf_counter() - started:6.0f} s  exhaustive {job}")
    # (c) at 20 users: one process, after the workers are done, so they do not share its core.
    rows_c = []
    for job in jobs_c:
        rows_c.append(_latency_job(job))
        done += 1
        _say(f"[{done}/{total}] {time.perf_counter() - started:6.0f} s  latency {job}")

    sets = summarise_closed_loop(rows_b)
    all_means = {
        name: float(np.mean([u for r in rows_b if r["policy"] == name for u in r["utilities"]]))
        for name in POLICIES
    }
    latency = []
    for spec in TIMED:
        for users in users_counts:
            times = [t for r in rows_b if r["policy"] == spec and r["users"] == users
                     for t in r["decision_ms"]]  # fmt: skip
            latency.append({"policy": spec, "where": "(b), all sets", "users": users,
                            **_percentiles(times)})  # fmt: skip
        for environment in ENVIRONMENTS:
            times = [t for r in rows_c if r["policy"] == spec and r["environment"] == environment
                     for t in r["decision_ms"]]  # fmt: skip
            latency.append({"policy": spec, "where": f"closed-loop-moving, {environment}",
                            "users": 20, **_percentiles(times)})  # fmt: skip
    document = {
        "command": command,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores (shared), {args.workers} workers",
        "wall_s": time.perf_counter() - started,
        "config": {
            "scenarios_per_set": args.scenarios,
            "exhaustive_cases_per_environment": {"H=2": args.cases, "H=3": args.cases_h3},
            "exhaustive_steps": args.exhaustive_steps,
            "latency_scenarios": args.latency_scenarios,
            "latency_steps": args.latency_steps,
            "test_seed": TEST_SEED,
            "case_seed": CASE_SEED,
        },
        "exhaustive": {"summary": summarise_exhaustive(cases), "cases": cases},
        "closed_loop": {
            "sets": sets,
            "overall": {
                **all_means,
                "planner_over_oracle": _ratio(all_means["planning-oracle"], all_means["oracle"]),
            },
            "rows": rows_b,
        },
        "latency": latency,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from sim.atomic import atomic_write_json, atomic_write_text

    atomic_write_json(args.out, document)
    atomic_write_text(args.out.with_suffix(".md"), markdown(document))
    _say(f"wrote {args.out} and {args.out.with_suffix('.md')} ({document['wall_s']:.0f} s)")
    if args.write_defaults:
        write_defaults(document, args.out.resolve())
    print(markdown(document))


if __name__ == "__main__":
    main()
