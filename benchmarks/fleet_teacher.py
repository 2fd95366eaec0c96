"""The imitation teacher (``policies/training/fleet_imitation.py``): is the cheap search good
enough, and how far are its placements from the k-means prior the residual actor corrects?

1. **The teachers against the full search, flown.** K = 2, 3, 4 with 20, 50 and 100 users in
   hot spots (``--per-case`` scenarios each, total load 40 Mbit/s per UAV), closed-loop world:
   one fleet episode per scenario (``policies.evaluation.fleet_evaluation.evaluate_fleet``, the
   oracle searching from where the fleet is) with the full search (``fleet-oracle``), each teacher's
   (:data:`policies.training.fleet_imitation.TEACHERS`: ``teacher-search``, ``teacher-local``) and
   load-weighted k-means; mean utility and seconds per scenario.
2. **Distance to the prior.** On ``--prior-scenarios`` training scenarios (K = 3, 20–100 users,
   the three families), the horizontal distance from each UAV's k-means place to the
   ``search`` teacher's target matched to it (least total distance, as the labels are made).

Prints and writes ``benchmarks/results/fleet_teacher.json``.

    python benchmarks/fleet_teacher.py
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from policies.evaluation.fleet_evaluation import build_fleet_candidate, evaluate_fleet
from policies.interface import ReportedUsers
from policies.learned.fleet_residual import KMeansPrior
from policies.training.fleet_imitation import TEACHERS, teacher_oracle
from policies.training.fleet_training import FleetTrainConfig
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets
from sim.scenarios import generate_scenarios
from sim.world import get_world

RESULTS = Path(__file__).resolve().parent / "results" / "fleet_teacher.json"
CASES = ((2, 20), (3, 50), (4, 100))


def search_cases(per_case: int) -> list[dict[str, Any]]:
    """Mean flown utility and seconds per scenario of the three placements, per case."""
    world = get_world("closed-loop")
    rows = []
    for n_uavs, n_users in CASES:
        fleet = FleetConfig(n_uavs=n_uavs)
        scenarios = generate_scenarios(
            per_case, n_users, 99 + n_uavs, family="hotspots", total_load_bps=40e6 * n_uavs
        )
        candidates = {
            "kmeans-load-weighted": build_fleet_candidate("kmeans-load-weighted", n_uavs, world)[1],
            "fleet-oracle": build_fleet_candidate("fleet-oracle", n_uavs, world)[1],
            **{
                f"teacher-{name}": teacher_oracle(n_uavs, world, world.episode_steps, name)
                for name in TEACHERS
            },
        }
        row: dict[str, Any] = {"n_uavs": n_uavs, "n_users": n_users, "scenarios": per_case}
        for name, candidate in candidates.items():
            started = time.perf_counter()
            result = evaluate_fleet(
                candidate, scenarios, n_uavs, world, fleet, world.episode_steps, 0,
                name=name, progress=False,
            )  # fmt: skip
            row[name] = {
                "mean_utility": round(result["mean_utility"], 4),
                "s_per_scenario": round((time.perf_counter() - started) / per_case, 2),
            }
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def prior_distances(n_scenarios: int) -> dict[str, float]:
    """How far (m) the teacher's matched targets lie from the UAVs' k-means places."""
    config = FleetTrainConfig(n_uavs=3, episodes=1, out_dir=Path("unused"), users=(20, 100))
    world = config.train_world()
    env = FleetParallelEnv(
        n_uavs=3, action_kind="continuous", scenarios=config.sampler(world.area), world=world
    )
    oracle = teacher_oracle(3, world, world.episode_steps)
    prior = KMeansPrior(world.area, env.fleet.separation_m)
    distances = []
    for index in range(n_scenarios):
        env.reset(seed=900 + index)
        here = env.uav_xyz_m
        users = ReportedUsers.of(env.reports)
        held = oracle.place_from(users, here, env.reported_association, world.flight)
        places = assign_targets(here, prior.place(env.reports, 3))
        matched = assign_targets(places, held)
        distances.append(np.linalg.norm(matched[:, :2] - places[:, :2], axis=1))
    d = np.concatenate(distances)
    return {
        "uavs": int(d.size),
        "median_m": round(float(np.median(d)), 1),
        "p90_m": round(float(np.percentile(d, 90)), 1),
        "share_within_5_m": round(float(np.mean(d < 5.0)), 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-case", type=int, default=6)
    parser.add_argument("--prior-scenarios", type=int, default=25)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.per_case < 1 or args.prior_scenarios < 1:
        parser.error("--per-case and --prior-scenarios: must be at least 1")
    document = {
        "benchmark": "fleet_teacher",
        "command": " ".join(
            ["python benchmarks/fleet_teacher.py", *(sys.argv[1:] if argv is None else argv)]
        ),
        "teachers": TEACHERS,
        "search": search_cases(args.per_case),
        "prior_distance": prior_distances(args.prior_scenarios),
    }
    text = json.dumps(document, indent=2)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(text + "\n")
    tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
