"""Speed of the embedded network model, on one core.

Measures, and writes to benchmarks/results/sim_speed.json:

- environment steps per second (``tupa/FapDiscrete-v0`` through ``gym.make``, 3 users, stochastic
  mode, observation included), and how it scales with 3, 30 and 300 users;
- (position × user) evaluations per second of one batched ``NetworkModel.step`` over the grid;
- the time of one oracle search over the full grid (3 users).

Targets (issue 2): >= 10,000 steps/s; >= 1,000,000 evaluations/s; oracle < 50 ms.
Run: ``.venv/bin/python benchmarks/sim_speed.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import sim.envs  # noqa: F401  (registers the environments)
from sim.config import AreaConfig
from sim.envs import DISCRETE_ENV_ID, ScenarioCycle
from sim.network import NetworkModel
from sim.scenarios import generate_scenarios

RESULTS = Path(__file__).parent / "results" / "sim_speed.json"


def best_of(repeats: int, fn) -> float:
    """Smallest wall time of ``repeats`` runs (the least disturbed by other load)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def env_steps_per_s(n_users: int, steps: int, repeats: int) -> float:
    scenarios = generate_scenarios(20, n_users, seed=1)
    env = gym.make(DISCRETE_ENV_ID, scenarios=ScenarioCycle(scenarios))
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def run() -> None:
        _, info = env.reset()
        for _ in range(steps):
            action = int(rng.choice(np.flatnonzero(info["action_mask"])))
            _, _, _, truncated, info = env.step(action)
            if truncated:
                _, info = env.reset()

    run()  # warm-up: numba kernels load from cache, gymnasium checks run once
    return steps / best_of(repeats, run)


def batch_evaluations_per_s(repeats: int) -> tuple[float, int]:
    model = NetworkModel()
    scenario = generate_scenarios(1, 3, seed=2)[0]
    grid = AreaConfig().grid_positions_m()
    positions = np.tile(grid, (10, 1))

    def run() -> None:
        model.step(positions, scenario.users_xy_m, scenario.load_bps)

    run()
    return positions.shape[0] * scenario.n_users / best_of(repeats, run), positions.shape[0]


def oracle_search_s(repeats: int) -> float:
    from policies.oracle import OraclePolicy

    oracle = OraclePolicy()
    scenarios = generate_scenarios(repeats, 3, seed=3)
    oracle.place(scenarios[0])
    times = []
    for scenario in scenarios:
        start = time.perf_counter()
        oracle.place(scenario)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    repeats = 2 if args.quick else 5
    steps = 2000 if args.quick else 10000

    scaling = {}
    for n_users in (3, 30, 300):
        n = steps if n_users < 300 else steps // 5
        scaling[str(n_users)] = round(env_steps_per_s(n_users, n, repeats))
        print(f"env steps/s with {n_users:>3} users: {scaling[str(n_users)]:>8,}")
    evals, batch = batch_evaluations_per_s(repeats)
    print(f"batch evaluations/s (B={batch}, U=3): {evals:,.0f}")
    oracle_s = oracle_search_s(5 if args.quick else 20)
    print(f"oracle search (full grid + refinement, 3 users): {oracle_s * 1e3:.1f} ms")

    result = {
        "benchmark": "sim_speed",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores_used": 1},
        "python": platform.python_version(),
        "env_steps_per_s": {"n_users": scaling},
        "batch_position_user_evaluations_per_s": round(evals),
        "oracle_search_ms": round(oracle_s * 1e3, 2),
        "targets": {
            "env_steps_per_s_3_users": 10_000,
            "batch_evaluations_per_s": 1_000_000,
            "oracle_search_ms": 50,
        },
        "met": {
            "env_steps_per_s_3_users": scaling["3"] >= 10_000,
            "batch_evaluations_per_s": evals >= 1_000_000,
            "oracle_search_ms": oracle_s * 1e3 < 50,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
