"""Placement in every channel environment: where each policy flies, and what it achieves.

For each environment of :data:`sim.config.ENVIRONMENTS` (the paper's ``open`` field and ITU-R's
urban classes, :mod:`sim.channel`) and each held-out scenario family, it runs ``tupa eval``'s
protocol (:func:`policies.evaluation.evaluation.evaluate_policy`) in a world (``paper``: the
teleport protocol, or ``closed-loop``) for ``min-distance``, ``load-weighted``, ``min-distance-env``
(min-distance at the altitude of best mean SNR), the shipped checkpoints and the oracle, and
records each policy's mean utility, its ratio to the oracle, the oracle's gain over
min-distance, and the altitudes the policies end at. Writes
``benchmarks/results/environments.json`` and ``environments.md`` (the tables).

    python benchmarks/environments.py                       # 40 scenarios a set, 3 users
    python benchmarks/environments.py --scenarios 10 --world closed-loop

A benchmark, not a test: minutes on 2 cores. Of the shipped checkpoints, ``ddqn-dr`` and
``ddpg-residual-dr`` were trained in the open environment only (they show what that costs in a
town) and ``ddpg-residual-towns`` in the four urban classes (one drawn per episode).
"""

from __future__ import annotations

import argparse
import json
import os
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
TEST_SEED = 8_800_000  # held-out sets: TEST_SEED + a hash of (family, users)
FAMILIES = ("exponential", "uniform", "hotspots", "corners")
PLACEMENTS = ("min-distance", "load-weighted", "min-distance-env", "oracle")


def _run(job: tuple[str, str, str, int, int, str]) -> dict[str, Any]:
    """One policy on one set in one environment (runs in a worker process)."""
    import torch

    torch.set_num_threads(1)
    from dataclasses import replace

    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import resolve_policy
    from sim.config import AreaConfig
    from sim.scenarios import generate_scenarios
    from sim.world import get_world

    world_name, environment, family, users, n, spec = job
    area = AreaConfig(environment=environment)
    world = replace(get_world(world_name), area=area)
    seed = TEST_SEED + zlib.crc32(f"{family}/{users}".encode()) % 100_000
    scenarios = generate_scenarios(n, users, seed=seed, family=family, area=area)
    result = evaluate_policy(resolve_policy(spec, world), scenarios, world, progress=False)
    return {
        "mean": result["mean_utility"],
        "utilities": [row["utility"] for row in result["scenarios"]],
        "altitudes_m": [row["uav_xyz_m"][2] for row in result["scenarios"]],
        "policy": result["policy"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="paper", help="paper (teleport) or closed-loop")
    parser.add_argument("--scenarios", type=int, default=40, help="per set (default 40)")
    parser.add_argument("--users", type=int, default=3)
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        type=Path,
        help="a checkpoint to add (repeatable; default: the shipped ones only)",
    )
    parser.add_argument(
        "--environments", default=None, help="comma-separated (default: all of them)"
    )
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS / "environments.json")
    args = parser.parse_args()

    from policies.adapters import default_name
    from policies.learned.checkpoints import read_metadata
    from service.policy_runtime import SHIPPED_CHECKPOINTS
    from sim.config import ENVIRONMENTS

    checkpoints = [str(p) for p in sorted(SHIPPED_CHECKPOINTS.glob("*.zip"))]
    checkpoints += [str(p) for p in args.checkpoint]
    environments = (
        [e.strip() for e in args.environments.split(",")] if args.environments else ENVIRONMENTS
    )
    specs = [*PLACEMENTS, *checkpoints]
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    jobs = [
        (args.world, environment, family, args.users, args.scenarios, spec)
        for environment in environments
        for family in families
        for spec in specs
    ]
    started = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        done = list(pool.map(_run, jobs, chunksize=1))
    names = {spec: spec for spec in PLACEMENTS}
    for path in checkpoints:
        names[path] = default_name(read_metadata(Path(path)), Path(path))
        if path not in map(str, SHIPPED_CHECKPOINTS.glob("*.zip")):
            names[path] = f"{names[path]} ({path})"

    table: dict[str, dict[str, Any]] = {}
    for environment in environments:
        by_policy: dict[str, dict[str, list[float]]] = {}
        for job, result in zip(jobs, done, strict=True):
            if job[1] != environment:
                continue
            entry = by_policy.setdefault(names[job[5]], {"utilities": [], "altitudes_m": []})
            entry["utilities"] += result["utilities"]
            entry["altitudes_m"] += result["altitudes_m"]
        oracle = np.array(by_policy["oracle"]["utilities"])
        plain = np.array(by_policy["min-distance"]["utilities"])
        table[environment] = {
            "oracle_gain_over_min_distance": float(oracle.mean() / plain.mean()),
            "policies": {
                name: {
                    "mean_utility": float(np.mean(e["utilities"])),
                    "ratio_to_oracle": float(np.mean(e["utilities"]) / oracle.mean()),
                    "mean_altitude_m": float(np.mean(e["altitudes_m"])),
                    "altitude_quartiles_m": [
                        float(q) for q in np.percentile(e["altitudes_m"], [25, 50, 75])
                    ],
                }
                for name, e in by_policy.items()
            },
        }
    document = {
        "benchmark": "environments",
        "world": args.world,
        "users": args.users,
        "families": families,
        "scenarios_per_set": args.scenarios,
        "wall_s": round(time.perf_counter() - started, 1),
        "command": "python benchmarks/environments.py " + " ".join(sys.argv[1:]),
        "environments": table,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    markdown = render(document)
    args.out.with_suffix(".md").write_text(markdown)
    print(markdown)
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")


def render(document: dict[str, Any]) -> str:
    """The markdown tables: mean utility (ratio to the oracle) and mean altitude per policy."""
    environments = document["environments"]
    policies = list(next(iter(environments.values()))["policies"])
    lines = [
        f"World `{document['world']}`, {document['users']} users, "
        f"{document['scenarios_per_set']} scenarios × {len(document['families'])} families "
        f"per environment (`{document['command'].strip()}`).",
        "",
        "| environment | oracle / min-distance | "
        + " | ".join(f"{p} (× oracle, mean z)" for p in policies)
        + " |",
        "| --- | --- | " + " | ".join("---" for _ in policies) + " |",
    ]
    for environment, entry in environments.items():
        cells = [
            f"{v['mean_utility']:.3f} ({v['ratio_to_oracle']:.3f}, {v['mean_altitude_m']:.0f} m)"
            for v in (entry["policies"][p] for p in policies)
        ]
        gain = entry["oracle_gain_over_min_distance"]
        lines.append(f"| {environment} | {gain:.3f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
