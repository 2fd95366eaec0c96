"""A shared-parameter fleet checkpoint against the k-means baselines and the search oracle.

Writes benchmarks/results/fleet_policy.json (and prints the same): on held-out scenarios of K
UAVs (``--uavs``), ``--users`` users, the uniform, hot-spot and mixture families
(``--per-family`` each, Λ = 40 Mbit/s per UAV, seed ``--seed``), one episode of the fleet
environment in the ``--world`` world (its decision period and episode length; ``--episode-steps``
shortens it) from the fleet's homes, for:

* the checkpoint (:class:`policies.fleet_training.FleetCheckpointPolicy`), deciding every step;
* ``kmeans-min-distance`` and ``kmeans-load-weighted`` and the search oracle
  (:class:`policies.fleet_oracle.FleetOracle` over the world's network and episode), each
  placed once on the first report the decision sees and held (``--replan-every`` re-places
  them; the closed-loop world's users do not move).

Per policy: mean utility, served-user fraction, Jain fairness, minimum user throughput (means
over the episode's steps, then over scenarios), per family, and the policy's ratio to the
oracle. The vehicles fly there at the world's speed, so every policy pays the same transit.
Run: ``.venv/bin/python benchmarks/fleet_policy.py --checkpoint DIR [--uavs 2]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from policies.fleet_baselines import KMeansPlacement
from policies.fleet_oracle import FleetOracle, FleetOracleConfig
from policies.fleet_training import FleetCheckpointPolicy, evaluate_fleet
from sim.fleet import FleetConfig
from sim.scenarios import generate_scenarios
from sim.world import get_world

RESULTS = Path(__file__).parent / "results" / "fleet_policy.json"
FAMILIES = ("uniform", "hotspots", "mixture")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--uavs", type=int, default=2)
    parser.add_argument("--users", type=int, default=20)
    parser.add_argument("--per-family", type=int, default=10)
    parser.add_argument("--world", default="closed-loop")
    parser.add_argument("--episode-steps", type=int, default=None)
    parser.add_argument("--replan-every", type=int, default=None)
    parser.add_argument("--seed", type=int, default=777)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    world = get_world(args.world)
    if args.episode_steps:
        world = replace(world, episode_steps=args.episode_steps)
    k = args.uavs
    fleet = FleetConfig(n_uavs=k)
    replan = args.replan_every or world.episode_steps
    policy = FleetCheckpointPolicy.load(args.checkpoint, world.area, fleet.separation_m)
    oracle = FleetOracle(
        fleet,
        world.area,
        world.network,
        world.utility,
        FleetOracleConfig(episode_steps=world.episode_steps, step_s=world.step_s, seed=args.seed),
    )
    candidates: dict[str, Any] = {
        "fleet-checkpoint": policy,
        "kmeans-min-distance": KMeansPlacement(k, world.area, False, fleet.separation_m),
        "kmeans-load-weighted": KMeansPlacement(k, world.area, True, fleet.separation_m),
        "fleet-oracle": oracle,
    }
    results: dict[str, Any] = {name: {} for name in candidates}
    seconds: dict[str, float] = dict.fromkeys(candidates, 0.0)
    for f, family in enumerate(FAMILIES):
        scenarios = generate_scenarios(
            args.per_family, args.users, args.seed + f, family=family, total_load_bps=40e6 * k
        )
        for name, candidate in candidates.items():
            started = time.perf_counter()
            summary = evaluate_fleet(candidate, scenarios, k, world, fleet, replan, args.seed)
            seconds[name] += time.perf_counter() - started
            results[name][family] = summary
    table: dict[str, Any] = {}
    for name, per_family in results.items():
        utilities = np.concatenate([s["utilities"] for s in per_family.values()])
        table[name] = {
            "mean_utility": float(utilities.mean()),
            **{
                key: float(np.mean([s[key] for s in per_family.values()]))
                for key in ("mean_served_fraction", "mean_jain_fairness", "mean_min_throughput_bps")
            },
            "per_family_mean_utility": {fam: s["mean_utility"] for fam, s in per_family.items()},
            "seconds": round(seconds[name], 1),
        }
    oracle_mean = table["fleet-oracle"]["mean_utility"]
    for row in table.values():
        row["ratio_to_oracle"] = row["mean_utility"] / oracle_mean
    meta = json.loads(Path(args.checkpoint, "model.json").read_text())
    report = {
        "benchmark": "fleet_policy",
        "checkpoint": {
            key: meta.get(key)
            for key in ("n_uavs_trained", "episodes", "timesteps", "seed", "wall_time_s", "command")
        },
        "uavs": k,
        "users": args.users,
        "families": list(FAMILIES),
        "scenarios_per_family": args.per_family,
        "world": world.name,
        "episode_steps": world.episode_steps,
        "placements_replan_every": replan,
        "seed": args.seed,
        "results": table,
        "python": platform.python_version(),
        "machine": {"cpu": platform.machine()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    for name, row in table.items():
        print(
            f"{name:22s} utility {row['mean_utility']:.3f} ({row['ratio_to_oracle']:.3f} of the "
            f"oracle)  served {row['mean_served_fraction']:.3f}  Jain "
            f"{row['mean_jain_fairness']:.3f}  min {row['mean_min_throughput_bps'] / 1e6:.2f} "
            f"Mbit/s  per family {row['per_family_mean_utility']}  [{row['seconds']} s]"
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
