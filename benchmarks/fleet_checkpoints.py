"""Fleet checkpoints against the k-means baselines and ``kmeans-scored`` on validation scenarios
(no oracle: quick).

Picks between trained fleet checkpoints before the held-out benchmark
(``benchmarks/fleet_policy.py``, whose scenario seeds these never share): K = 2 and 3 UAVs and
20 and 50 users by default (``--uavs``, ``--users``), the uniform, hot-spot and mixture
families (``--per-family`` each, seeds from 4242), static (``closed-loop``) and moving
(``closed-loop-moving``) users; one episode each, from the fleet's homes, every checkpoint
deciding every step, the k-means placements held (static users) or re-placed every decision
(moving users), ``kmeans-scored`` (the bar a learned fleet policy has to pass) re-placed every
decision, as served.
Prints and writes ``benchmarks/results/fleet_checkpoints.json``: mean utility per world and
policy, each checkpoint's training command and time, and for DDPG the mean of each agent's raw
action over a few hot-spot episodes (a saturated actor shows as ±1 with no spread).

    python benchmarks/fleet_checkpoints.py runs/fleet-residual-k3 runs/fleet-ddqn-k3
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from policies.evaluation.fleet_evaluation import build_fleet_candidate, evaluate_fleet
from policies.learned.checkpoints import read_metadata
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.placements.fleet_scored import KMEANS_SCORED
from sim.fleet import MAX_UAVS, FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.scenarios import generate_scenarios
from sim.world import World, get_world

RESULTS = Path(__file__).resolve().parent / "results" / "fleet_checkpoints.json"
BASELINES = ("kmeans-load-weighted", "kmeans-min-distance")
REFERENCES = (*BASELINES, "kmeans-scored")
"""What every checkpoint is flown beside."""
FAMILIES = ("uniform", "hotspots", "mixture")


Candidate = Callable[[int, World, FleetConfig], Any]
"""What to fly for a fleet size, world and fleet: a checkpoint or a placement, as
:func:`policies.evaluation.fleet_evaluation.evaluate_fleet` takes it."""


def built(name: str) -> Candidate:
    """The candidate :func:`policies.evaluation.fleet_evaluation.build_fleet_candidate` makes of
    ``name``."""
    return lambda k, world, fleet: build_fleet_candidate(name, k, world, fleet)[1]


def validation_utilities(
    candidates: dict[str, Candidate],
    per_family: int,
    fleet_sizes: tuple[int, ...],
    user_counts: tuple[int, ...],
    moving_replan_every: int = 1,
) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Every candidate flown on the validation cells: per world and candidate, one row
    ``{"uavs", "users", "family", "utility"}`` per scenario, the cells in the same order.
    Placements are held with static users and re-placed every ``moving_replan_every``
    decisions with moving ones, but ``kmeans-scored`` every decision (as served: it scores from
    where the fleet is); checkpoints decide every step."""
    rows: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for world_name in ("closed-loop", "closed-loop-moving"):
        world = get_world(world_name)
        every = moving_replan_every if world.mobility.model != "static" else world.episode_steps
        for k in fleet_sizes:
            fleet = FleetConfig(n_uavs=k)
            for users in user_counts:
                for f, family in enumerate(FAMILIES):
                    seed = 4242 + 100 * k + users + f
                    scenarios = generate_scenarios(
                        per_family, users, seed, family=family, total_load_bps=40e6 * k
                    )
                    for name, candidate in candidates.items():
                        flown = candidate(k, world, fleet)
                        often = 1 if name == KMEANS_SCORED else every
                        summary = evaluate_fleet(flown, scenarios, k, world, fleet, often, 0,
                                                 name=name, progress=False)  # fmt: skip
                        cell = {"uavs": k, "users": users, "family": family}
                        rows.setdefault(world_name, {}).setdefault(name, []).extend(
                            {**cell, "utility": u} for u in summary["utilities"]
                        )
    return rows


def validate(
    names: list[str], per_family: int, fleet_sizes: tuple[int, ...], user_counts: tuple[int, ...]
) -> dict[str, dict[str, float]]:
    """Mean utility per world and policy (checkpoint paths or fleet policy names) over the
    validation cells."""
    rows = validation_utilities(
        {name: built(name) for name in names}, per_family, fleet_sizes, user_counts
    )
    return {
        world: {name: mean_utility(r) for name, r in per_name.items()}
        for world, per_name in rows.items()
    }


def mean_utility(rows: list[dict[str, Any]]) -> float:
    return round(float(np.mean([row["utility"] for row in rows])), 4)


def raw_actions(path: str, episodes: int = 4, steps: int = 30) -> dict[str, Any]:
    """The mean and spread of a checkpoint's raw actions on hot-spot episodes (K = 3)."""
    policy = FleetCheckpointPolicy.load(path)
    world = get_world("closed-loop")
    actions = []
    scenarios = generate_scenarios(episodes, 30, 99, family="hotspots", total_load_bps=120e6)
    for i, scenario in enumerate(scenarios):
        env = FleetParallelEnv(3, "continuous", scenarios=[scenario], world=world)
        observations, _ = env.reset(seed=i, options={"scenario": scenario})
        for _ in range(steps):
            joint = np.stack([observations[a] for a in env.possible_agents])
            action, _ = policy.model.predict(joint.astype(np.float32), deterministic=True)
            actions.append(np.asarray(action, dtype=float).reshape(3, -1))
            targets = policy.targets(joint, env.reports, env.uav_xyz_m, env.reported_association)
            observations, *_ = env.step_to(targets)
    stacked = np.concatenate(actions)
    return {"mean": stacked.mean(0).round(3).tolist(), "std": stacked.std(0).round(3).tolist()}


def int_list(text: str) -> tuple[int, ...]:
    """``"2,3"`` -> (2, 3): positive integers separated by commas."""
    try:
        values = tuple(int(part) for part in text.split(","))
    except ValueError:
        message = f"expected integers separated by commas, got {text!r}"
        raise argparse.ArgumentTypeError(message) from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "checkpoints", nargs="+", help="fleet checkpoints (a run directory or its model.zip)"
    )
    parser.add_argument("--per-family", type=int, default=2)
    parser.add_argument("--uavs", type=int_list, default=(2, 3), help="fleet sizes, e.g. 2,3")
    parser.add_argument("--users", type=int_list, default=(20, 50), help="user counts, e.g. 20,50")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if max(args.uavs) > MAX_UAVS:
        parser.error(f"argument --uavs: a fleet has 1..{MAX_UAVS} UAVs, got {max(args.uavs)}")
    results = validate([*args.checkpoints, *REFERENCES], args.per_family, args.uavs, args.users)
    checkpoints = {}
    for path in args.checkpoints:
        meta = read_metadata(Path(path))
        checkpoints[path] = {
            **{
                key: meta.get(key)
                for key in (
                    "algorithm",
                    "action",
                    "residual_radius_m",
                    "episodes",
                    "wall_time_s",
                    "command",
                )
            },
            # DDPG's continuous actions (DDQN's are move numbers: nothing to saturate)
            "raw_actions": raw_actions(path) if meta.get("algorithm") == "ddpg" else None,
        }
    document = {
        "benchmark": "fleet_checkpoints",
        "command": "python benchmarks/fleet_checkpoints.py " + " ".join(sys.argv[1:]),
        "uavs": list(args.uavs),
        "users": list(args.users),
        "scenarios_per_world": len(args.uavs) * len(args.users) * len(FAMILIES) * args.per_family,
        "mean_utility": results,
        "checkpoints": checkpoints,
    }
    print(json.dumps(document, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
