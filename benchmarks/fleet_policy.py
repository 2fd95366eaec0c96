"""A shared-parameter fleet checkpoint against the k-means baselines and the search oracle.

Writes benchmarks/results/fleet_policy.json (and prints the same): on held-out cells of K UAVs
(``--uavs 2,3,4``) × users (``--users 20,50,100``) × worlds (``--world
closed-loop,closed-loop-moving``: static and moving users), each with the uniform, hot-spot and
mixture families (``--per-family`` each, Λ = 40 Mbit/s per UAV, seeds from ``--seed`` and the
cell, never the training's), one episode of the fleet environment in that world (its decision
period and episode length; ``--episode-steps`` shortens it) from the fleet's homes, for:

* the checkpoint (:class:`policies.learned.fleet_checkpoint.FleetCheckpointPolicy`), deciding every
  step (``--checkpoint``; without it the placements alone);
* ``kmeans-min-distance``, ``kmeans-load-weighted``, ``kmeans-scored``
  (:class:`policies.placements.fleet_scored.ScoredKMeansPlacement`) and the search oracle
  (:class:`policies.placements.fleet_oracle.FleetOracle` over the world's network and episode), each
  placed once on the first report the decision sees and held when users stand still; when they
  move, k-means re-places every decision and the oracle every ``--oracle-replan``.
  ``kmeans-scored`` re-places every decision in both worlds, as the service flies it: it scores
  from where the fleet is, so its pick can change on the way (flown so, it is also what a
  residual checkpoint on the ``kmeans-scored`` prior flies with its actor's output at zero).

The evaluation is ``tupa eval --uavs K``'s
(:func:`policies.evaluation.fleet_evaluation.evaluate_fleet`, the policies built by
:func:`policies.evaluation.fleet_evaluation.build_fleet_candidate`). Per policy: mean utility,
served-user fraction, Jain fairness, minimum user throughput (means over the episode's steps, then
over scenarios), handovers per episode, per family, the policy's ratio to the oracle, and every
scenario's row (``rows``: family, id, H, the five metrics). The vehicles fly there at the world's
speed, so every policy pays the same transit. Summaries overall, per world, K, user count and
family, and issue 16's targets checked (``targets``, for the checkpoint and ``kmeans-scored``: ≥
0.95 × the oracle's mean utility; ≥ both k-means baselines in mean and in every H bin with
``--min-bin`` scenarios or more). Run: ``.venv/bin/python benchmarks/fleet_policy.py --checkpoint
DIR --uavs 2,3,4 --users 20,50,100 --world closed-loop,closed-loop-moving``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from fleet_checkpoints import int_list

from policies.evaluation.fleet_evaluation import (
    FLEET_EVAL_POLICIES,
    build_fleet_candidate,
    evaluate_fleet,
)
from policies.learned.checkpoints import read_metadata
from policies.placements.fleet_scored import KMEANS_SCORED
from sim.fleet import FleetConfig
from sim.scenarios import generate_scenarios
from sim.world import get_world

RESULTS = Path(__file__).parent / "results" / "fleet_policy.json"
FAMILIES = ("uniform", "hotspots", "mixture")
TESTED = ("fleet-checkpoint", "kmeans-scored")
"""The policies checked against the targets: the checkpoint, and the k-means scored on the
model (a placement, not learned: the bar a learned policy has to pass)."""


def _evaluate_cell(
    candidates: dict[str, Any], world: Any, k: int, users: int, args: argparse.Namespace
) -> dict[str, list[dict[str, Any]]]:
    """Every candidate on this cell's held-out scenarios (``--per-family`` of each family):
    their rows, tagged with the cell."""
    fleet = FleetConfig(n_uavs=k)
    moving = world.mobility.model != "static"
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in candidates}
    for f, family in enumerate(FAMILIES):
        seed = args.seed + 1000 * k + 10 * users + f
        scenarios = generate_scenarios(
            args.per_family, users, seed, family=family, total_load_bps=40e6 * k
        )
        for name, build in candidates.items():
            candidate = build(k, world, fleet)
            # Placements follow moving users by re-placing (the oracle every --oracle-replan
            # decisions: each search takes seconds); with static users once is enough.
            every = 1 if name == KMEANS_SCORED else world.episode_steps
            if moving:
                every = args.oracle_replan if name == "fleet-oracle" else 1
            started = time.perf_counter()
            summary = evaluate_fleet(
                candidate, scenarios, k, world, fleet, every, args.seed, name=name,
                progress=False,
            )  # fmt: skip
            seconds = time.perf_counter() - started
            for row in summary["scenarios"]:
                rows[name].append(
                    {"world": world.name, "uavs": k, "users": users, "family": family,
                     "replan_every": every, "seconds": round(seconds / len(scenarios), 2), **row}
                )  # fmt: skip
    return rows


def _summary(rows: dict[str, list[dict[str, Any]]], key: str | None = None) -> dict[str, Any]:
    """Means per policy (over all rows, or per value of ``key``), ratio to the oracle."""
    metrics = ("utility", "served_fraction", "jain_fairness", "min_throughput_bps", "handovers")
    table: dict[str, Any] = {}
    for name, entries in rows.items():
        table[name] = {f"mean_{m}": float(np.mean([r[m] for r in entries])) for m in metrics}
        table[name]["n_scenarios"] = len(entries)
    oracle = table.get("fleet-oracle", {}).get("mean_utility")
    for row in table.values():
        row["ratio_to_oracle"] = row["mean_utility"] / oracle if oracle else None
    return table


def _by(rows: dict[str, list[dict[str, Any]]], key: Any) -> dict[str, Any]:
    groups = sorted({key(r) for r in next(iter(rows.values()))})
    return {
        str(g): _summary({n: [r for r in e if key(r) == g] for n, e in rows.items()})
        for g in groups
    }


def _targets(rows: dict[str, list[dict[str, Any]]], min_bin: int, name: str) -> dict[str, Any]:
    """Issue 16's targets for policy ``name``: >= 0.95 x the oracle's mean utility, and >= both
    k-means baselines in mean and in every H bin (width 0.05) with at least ``min_bin``
    scenarios."""
    overall = _summary(rows)
    ours = overall[name]["mean_utility"]
    bins = _by(rows, lambda r: round(np.floor(r["heterogeneity"] / 0.05) * 0.05, 2))
    checked = {b: t for b, t in bins.items() if t[name]["n_scenarios"] >= min_bin}
    baselines = ("kmeans-min-distance", "kmeans-load-weighted")
    failing = [
        b for b, t in checked.items()
        if any(t[name]["mean_utility"] < t[n]["mean_utility"] for n in baselines)
    ]  # fmt: skip
    return {
        "ratio_to_oracle": overall[name]["ratio_to_oracle"],
        "ratio_to_oracle_target": 0.95,
        "met_oracle": (overall[name]["ratio_to_oracle"] or 0) >= 0.95,
        "at_least_both_kmeans_in_mean": all(ours >= overall[n]["mean_utility"] for n in baselines),
        "h_bins_checked": sorted(checked),
        "h_bins_below_a_kmeans": failing,
        "min_scenarios_per_bin": min_bin,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--checkpoint", type=Path, help="a fleet checkpoint (without: the placements alone)"
    )
    parser.add_argument(
        "--uavs", type=int_list, default="2", help="fleet sizes, comma-separated (2,3,4)"
    )
    parser.add_argument(
        "--users", type=int_list, default="20", help="user counts, comma-separated (20,50,100)"
    )
    parser.add_argument("--per-family", type=int, default=10)
    parser.add_argument(
        "--world", default="closed-loop", help="worlds, comma-separated (closed-loop-moving)"
    )
    parser.add_argument("--episode-steps", type=int, default=None)
    parser.add_argument(
        "--oracle-replan",
        type=int,
        default=25,
        help="with moving users: the oracle re-places every N decisions (k-means every one)",
    )
    parser.add_argument("--min-bin", type=int, default=10, help="H bins checked from N scenarios")
    parser.add_argument("--seed", type=int, default=777)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    started = time.perf_counter()
    candidates: dict[str, Any] = {
        name: (lambda k, w, f, n=name: build_fleet_candidate(n, k, w, f, args.seed)[1])
        for name in FLEET_EVAL_POLICIES
    }
    if args.checkpoint is not None:
        checkpoint = str(args.checkpoint)
        candidates = {
            "fleet-checkpoint": lambda k, w, f: build_fleet_candidate(checkpoint, k, w, f)[1],
            **candidates,
        }
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in candidates}
    for world_name in args.world.split(","):
        world = get_world(world_name.strip())
        if args.episode_steps:
            world = replace(world, episode_steps=args.episode_steps)
        for k in args.uavs:
            for users in args.users:
                cell = _evaluate_cell(candidates, world, k, users, args)
                for name, entries in cell.items():
                    rows[name] += entries
                summary = _summary(cell)
                print(
                    f"{world.name} K={k} U={users}: "
                    + "  ".join(
                        f"{n} {t['mean_utility']:.3f} ({t['ratio_to_oracle']:.3f})"
                        for n, t in summary.items()
                    ),
                    flush=True,
                )
    meta = read_metadata(Path(args.checkpoint)) if args.checkpoint else {}
    report = {
        "benchmark": "fleet_policy",
        "command": "python benchmarks/fleet_policy.py " + " ".join(sys.argv[1:]),
        "checkpoint": {
            key: meta.get(key)
            for key in (
                "algorithm",
                "action",
                "prior",
                "residual_radius_m",
                "n_uavs_trained",
                "episodes",
                "timesteps",
                "seed",
                "wall_time_s",
                "command",
            )
        }
        if meta
        else None,
        "families": list(FAMILIES),
        "scenarios_per_family_per_cell": args.per_family,
        "seed": args.seed,
        "overall": _summary(rows),
        "by_world": _by(rows, lambda r: r["world"]),
        "by_uavs": _by(rows, lambda r: r["uavs"]),
        "by_users": _by(rows, lambda r: r["users"]),
        "by_family": _by(rows, lambda r: r["family"]),
        "targets": {name: _targets(rows, args.min_bin, name) for name in TESTED if name in rows},
        "rows": rows,
        "wall_time_s": round(time.perf_counter() - started, 1),
        "python": platform.python_version(),
        "machine": {"cpu": platform.machine(), "cores": os.cpu_count()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    for name, row in report["overall"].items():
        print(
            f"{name:22s} utility {row['mean_utility']:.3f} ({row['ratio_to_oracle']:.3f} of the "
            f"oracle)  served {row['mean_served_fraction']:.3f}  Jain "
            f"{row['mean_jain_fairness']:.3f}  min {row['mean_min_throughput_bps'] / 1e6:.2f} "
            f"Mbit/s  handovers {row['mean_handovers']:.1f}  [{row['n_scenarios']} scenarios]"
        )
    print(json.dumps(report["targets"], indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
