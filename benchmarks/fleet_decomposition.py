"""Where does the search oracle's margin over k-means come from: where each UAV hovers over its
group of users, or which users form the groups?

The k-means baselines (:mod:`policies.placements.fleet_baselines`) split the users into K groups,
then place one UAV per group with the one-line single-UAV placement. Here the split stays and the
placement per group becomes the single-UAV search oracle (:mod:`policies.placements.oracle`, the
best single-UAV position for that group's users on the network model):
``KMeansPlacement(per_cluster=oracle)``. If that flies no better than k-means, no policy that
only places a UAV over its k-means group (a single-UAV policy per cluster, learned or not) can
close the gap to the fleet oracle: the gap is in the partition.

Same validation cells and seeds as ``benchmarks/fleet_checkpoints.py`` (K = 2, 3, 4; 20, 50
and 100 users; uniform, hot spots, mixture; static and moving users, closed-loop world); every
placement is held for the episode with static users and re-placed every ``--moving-replan``
decisions with moving ones (the single-UAV search takes up to seconds). Prints and writes
``benchmarks/results/fleet_decomposition.json``: mean utility per world, fleet size and user
count, and how often the per-group optimum beats each k-means.

    python benchmarks/fleet_decomposition.py
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from fleet_checkpoints import (
    BASELINES,
    Candidate,
    built,
    int_list,
    mean_utility,
    validation_utilities,
)

from policies.placements.fleet_baselines import KMeansPlacement
from policies.registry import make_placement
from sim.fleet import MAX_UAVS

RESULTS = Path(__file__).resolve().parent / "results" / "fleet_decomposition.json"
PER_GROUP_ORACLE = "kmeans-load-weighted+oracle"


def per_group_oracle() -> Candidate:
    """Load-weighted k-means' groups, each placed by the single-UAV search oracle."""
    return lambda k, world, fleet: KMeansPlacement(
        k, world.area, True, fleet.separation_m, per_cluster=make_placement("oracle", world)
    )


def summarise(rows: dict[str, dict[str, list[dict[str, Any]]]]) -> dict[str, Any]:
    """Means per world (all, per K, per user count) and the per-group oracle's wins."""
    summary: dict[str, Any] = {}
    for world, per_name in rows.items():
        by = {
            "all": {name: mean_utility(r) for name, r in per_name.items()},
            **{
                f"{field}={value}": {
                    name: mean_utility([row for row in r if row[field] == value])
                    for name, r in per_name.items()
                }
                for field in ("uavs", "users")
                for value in sorted({row[field] for row in per_name[PER_GROUP_ORACLE]})
            },
        }
        ours = np.array([row["utility"] for row in per_name[PER_GROUP_ORACLE]])
        wins = {
            f"above_{name}": int(
                np.sum(ours > np.array([row["utility"] for row in per_name[name]]))
            )
            for name in BASELINES
        }
        summary[world] = {"mean_utility": by, "scenarios": len(ours), **wins}
    return summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--per-family", type=int, default=2)
    parser.add_argument("--uavs", type=int_list, default=(2, 3, 4), help="fleet sizes, e.g. 2,3")
    parser.add_argument("--users", type=int_list, default=(20, 50, 100), help="e.g. 20,50")
    parser.add_argument(
        "--moving-replan", type=int, default=10, help="decisions between placements"
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if max(args.uavs) > MAX_UAVS:
        parser.error(f"argument --uavs: a fleet has 1..{MAX_UAVS} UAVs, got {max(args.uavs)}")
    if args.per_family < 1 or args.moving_replan < 1:
        parser.error("arguments --per-family and --moving-replan: must be >= 1")
    candidates = {name: built(name) for name in BASELINES}
    candidates[PER_GROUP_ORACLE] = per_group_oracle()
    rows = validation_utilities(
        candidates, args.per_family, args.uavs, args.users, args.moving_replan
    )
    document = {
        "benchmark": "fleet_decomposition",
        "command": "python benchmarks/fleet_decomposition.py " + " ".join(sys.argv[1:]),
        "uavs": list(args.uavs),
        "users": list(args.users),
        "moving_replan_every": args.moving_replan,
        **summarise(rows),
    }
    print(json.dumps(document, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
