"""How good the fleet's search oracle is, and how far the k-means baselines are below it.

Writes benchmarks/results/fleet_oracle.json (and prints the same):

1. **Search oracle vs the true optimum on small cases.** K = 2 UAVs on a coarse grid (every
   4th zone in x and y, every altitude level: 100 positions per UAV, 4,950 placements) and
   K = 3 on a coarser one (every 5th zone: 64 positions, 41,664 placements); 3 and 6 users,
   uniform and hot-spot families; each scenario solved exhaustively (every placement scored
   over the episode, expected mode). Against it, the search oracle
   (:class:`policies.placements.fleet_oracle.FleetOracle`) restricted to the same grid
   (``candidates_m``, no refinement), with and without its pair moves: its score over the optimum's,
   the worst gap, how often it reaches the optimum. For K = 2 the pair moves on that grid are
   themselves exhaustive, so the case without them is the test of coordinate descent; for K = 3
   neither is. And the default oracle (finer grid, refinement) over the same optimum (it may exceed
   it: it is not restricted to the coarse grid).
2. **k-means baselines vs the oracle** on cells of K = 2 and 3, 20 and 50 users, uniform,
   hot-spot and mixture families: mean utility of ``kmeans-min-distance``,
   ``kmeans-load-weighted`` and the oracle, with the served-user fraction, Jain's fairness index
   of per-user throughput and the minimum user throughput of each (means over the episode's
   scored steps, then over scenarios).

Loads: 40 Mbit/s per UAV in total (Λ = 40·K Mbit/s), so that a fleet is needed and placement
matters; distinct channels; the episode is ``--episode-steps`` steps (default 30, expected
mode, after one warm-up step). Deterministic given ``--seed``.
Run: ``.venv/bin/python benchmarks/fleet_oracle.py [--quick]``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import time
from pathlib import Path

import numpy as np

from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_oracle import (
    FleetOracle,
    FleetOracleConfig,
    fleet_episode_utility,
    separated,
)
from policies.placements.oracle import coarse_grid_positions_m
from sim.config import AreaConfig
from sim.fleet import FleetConfig, FleetModel
from sim.scenarios import Scenario, generate_scenarios

RESULTS = Path(__file__).parent / "results" / "fleet_oracle.json"
AREA = AreaConfig()


def scenarios(n: int, n_users: int, family: str, k: int, seed: int) -> list[Scenario]:
    return generate_scenarios(n, n_users, seed, family=family, total_load_bps=40e6 * k)


def exhaustive(model: FleetModel, grid: np.ndarray, scenario: Scenario, steps: int) -> float:
    """The best score over every separated placement of the fleet's K UAVs on ``grid``
    (unordered: the model is symmetric in the UAVs' labels)."""
    k = model.fleet.n_uavs
    combos = np.array(list(itertools.combinations(range(len(grid)), k)))
    best = -np.inf
    for chunk in np.array_split(combos, max(1, len(combos) // 2000)):
        fleets = grid[chunk]  # (B, K, 3)
        fleets = fleets[separated(fleets, model.fleet.separation_m)]
        if len(fleets):
            best = max(best, float(fleet_episode_utility(model, fleets, scenario, steps).max()))
    return best


def held_metrics(
    model: FleetModel, positions: np.ndarray, scenario: Scenario, steps: int
) -> dict[str, float]:
    """Means over an episode's scored steps of a held placement (expected mode)."""
    state, rows = None, []
    for t in range(steps + 1):
        result = model.step(positions, scenario.users_xy_m, scenario.load_bps, state)
        state = result.state
        if t >= 1:
            rows.append(
                (
                    result.utility[0],
                    result.served_fraction[0],
                    result.jain_fairness[0],
                    result.min_throughput_bps[0],
                )
            )
    mean = np.mean(rows, axis=0)
    return {
        "utility": float(mean[0]),
        "served_fraction": float(mean[1]),
        "jain_fairness": float(mean[2]),
        "min_throughput_bps": float(mean[3]),
    }


def part_exhaustive(args: argparse.Namespace) -> dict:
    cells = {}
    for k, stride in ((2, 4), (3, 5)):
        grid = coarse_grid_positions_m(AREA, stride)
        fleet = FleetConfig(n_uavs=k)
        model = FleetModel(fleet, area=AREA)
        searches = {
            "oracle_on_grid": FleetOracle(
                fleet, AREA, candidates_m=grid,
                config=FleetOracleConfig(episode_steps=args.episode_steps, refine=False,
                                         seed=args.seed),
            ),
            "oracle_on_grid_no_pair_moves": FleetOracle(
                fleet, AREA, candidates_m=grid,
                config=FleetOracleConfig(episode_steps=args.episode_steps, refine=False,
                                         pair_stride=0, seed=args.seed),
            ),
            "default_oracle": FleetOracle(
                fleet, AREA, config=FleetOracleConfig(episode_steps=args.episode_steps,
                                                      seed=args.seed),
            ),
        }  # fmt: skip
        for family in ("uniform", "hotspots"):
            for n_users in (3, 6):
                optimum, exhaustive_s = [], []
                found: dict[str, list[float]] = {name: [] for name in searches}
                search_s: dict[str, list[float]] = {name: [] for name in searches}
                for scenario in scenarios(args.small_scenarios, n_users, family, k, args.seed):
                    start = time.perf_counter()
                    optimum.append(exhaustive(model, grid, scenario, args.episode_steps))
                    exhaustive_s.append(time.perf_counter() - start)
                    for name, oracle in searches.items():
                        start = time.perf_counter()
                        found[name].append(oracle.search(scenario).utility)
                        search_s[name].append(time.perf_counter() - start)
                best = np.array(optimum)
                cell: dict[str, float | int | dict] = {
                    "scenarios": len(best),
                    "grid_positions_per_uav": len(grid),
                    "optimum_mean": float(best.mean()),
                    "exhaustive_s_mean": float(np.mean(exhaustive_s)),
                }
                for name, values in found.items():
                    ratio = np.array(values) / best
                    cell[name] = {
                        "over_optimum_mean": float(ratio.mean()),
                        "over_optimum_min": float(ratio.min()),
                        "gap_max": float((best - np.array(values)).max()),
                        "reaches_optimum": float(np.mean(np.array(values) >= best - 1e-12)),
                        "search_s_mean": float(np.mean(search_s[name])),
                    }
                key = f"K{k}-{n_users}u-{family}"
                cells[key] = cell
                print(
                    f"{key:16s} optimum {cell['optimum_mean']:.4f} ({len(grid)} positions/UAV)"
                    + "".join(
                        f" | {name}: mean {cell[name]['over_optimum_mean']:.4f} "
                        f"min {cell[name]['over_optimum_min']:.4f} "
                        f"hits {cell[name]['reaches_optimum']:.0%}"
                        for name in searches
                    )
                )
    return {
        "grids": "K = 2: every 4th zone in x and y, every level (100 positions per UAV); "
        "K = 3: every 5th zone, every level (64 positions per UAV)",
        "note": "ratios over the grid's exhaustive optimum; oracle_on_grid* search that grid "
        "only (starts snapped onto it, no refinement); default_oracle is the oracle as shipped "
        "(finer grid, refinement), so it may exceed the coarse grid's optimum",
        "cells": cells,
    }


def part_baselines(args: argparse.Namespace) -> dict:
    cells = {}
    for k in (2, 3):
        fleet = FleetConfig(n_uavs=k)
        model = FleetModel(fleet, area=AREA)
        oracle = FleetOracle(
            fleet, AREA, config=FleetOracleConfig(episode_steps=args.episode_steps, seed=args.seed)
        )
        placements = {
            "kmeans-min-distance": KMeansPlacement(k, AREA, seed=args.seed),
            "kmeans-load-weighted": KMeansPlacement(k, AREA, load_weighted=True, seed=args.seed),
        }
        for n_users in (20, 50):
            for family in ("uniform", "hotspots", "mixture"):
                per_policy: dict[str, list[dict[str, float]]] = {
                    name: [] for name in [*placements, "fleet-oracle"]
                }
                search_s = []
                for scenario in scenarios(args.scenarios, n_users, family, k, args.seed):
                    for name, placement in placements.items():
                        per_policy[name].append(
                            held_metrics(
                                model, placement.place(scenario), scenario, args.episode_steps
                            )
                        )
                    start = time.perf_counter()
                    positions = oracle.place(scenario)
                    search_s.append(time.perf_counter() - start)
                    per_policy["fleet-oracle"].append(
                        held_metrics(model, positions, scenario, args.episode_steps)
                    )
                cell = {
                    name: {
                        metric: float(np.mean([row[metric] for row in rows])) for metric in rows[0]
                    }
                    for name, rows in per_policy.items()
                }
                cell["oracle_search_s_mean"] = float(np.mean(search_s))
                cell["scenarios"] = args.scenarios
                key = f"K{k}-{n_users}u-{family}"
                cells[key] = cell
                print(
                    f"{key:18s} utility: kmeans {cell['kmeans-min-distance']['utility']:.4f}  "
                    f"load-weighted {cell['kmeans-load-weighted']['utility']:.4f}  oracle "
                    f"{cell['fleet-oracle']['utility']:.4f}  "
                    f"(search {cell['oracle_search_s_mean']:.1f} s)"
                )
    return {"cells": cells}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer scenarios")
    parser.add_argument("--scenarios", type=int, default=5, help="per baseline cell")
    parser.add_argument("--small-scenarios", type=int, default=8, help="per exhaustive cell")
    parser.add_argument("--episode-steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.quick:
        args.scenarios, args.small_scenarios = 1, 2
    start = time.perf_counter()
    small = part_exhaustive(args)
    baselines = part_baselines(args)
    result = {
        "benchmark": "fleet_oracle",
        "python": platform.python_version(),
        "machine": {"cpu": platform.machine(), "cores_used": 1},
        "episode_steps": args.episode_steps,
        "seed": args.seed,
        "load": "40 Mbit/s per UAV in total, distinct channels, expected mode",
        "oracle_vs_exhaustive": small,
        "baselines_vs_oracle": baselines,
        "wall_s": round(time.perf_counter() - start, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
