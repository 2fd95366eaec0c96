"""Speed of the fleet's environment, on one core.

Measures, and writes to benchmarks/results/fleet_speed.json:

- steps per second of ``sim.fleet_env.FleetParallelEnv`` (PettingZoo, discrete moves, every
  agent its own random valid move (:func:`random_valid_move`, as for the single env),
  closed-loop world: flight, report age 1; stochastic mode; observations of every agent and
  infos included; episodes reset when they end), with K = 3
  UAVs and 50 users (uniform and hot-spot families), distinct channels and a shared channel;
- the same with K = 1, 2, 4, 8 (distinct channels, 50 users), to see how it scales;
- in the same run, steps per second of the single-UAV environment ``sim.envs.FapDiscreteEnv``
  with 50 users in the same world, and the ratio fleet / single.

Target (issue 16): >= 5,000 env steps/s with K = 3 and 50 users. Best of ``--repeats`` rounds
(the least disturbed by other load on a shared machine), every configuration timed once per
round, interleaved, so that the fleet and the single environment meet the same load and their
ratio means something; the load average at the start is recorded.
Run: ``.venv/bin/python benchmarks/fleet_speed.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from sim.envs import FapDiscreteEnv
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.scenarios import ScenarioSampler
from sim.world import get_world

RESULTS = Path(__file__).parent / "results" / "fleet_speed.json"
WORLD = replace(get_world("closed-loop"), episode_steps=100)


def random_valid_move(mask: np.ndarray, rng: np.random.Generator) -> int:
    """A uniformly drawn valid move: one integer draw (``rng.choice`` costs three times as much,
    and the harness should not weigh on the environments it times)."""
    valid = np.flatnonzero(mask)
    return int(valid[rng.integers(len(valid))])


def fleet_runner(n_uavs: int, family: str, n_users: int, channel_mode: str, steps: int):
    """A function that runs ``steps`` steps of the fleet environment (random valid moves,
    resets included); one untimed run first (numba kernels load from cache)."""
    sampler = ScenarioSampler(families=(family,), users=(n_users, n_users))
    fleet = FleetConfig(n_uavs=n_uavs, channel_mode=channel_mode)
    env = FleetParallelEnv(n_uavs, "discrete", scenarios=sampler, world=WORLD, fleet=fleet)
    rng = np.random.default_rng(0)
    env.reset(seed=0)

    def run() -> None:
        _, infos = env.reset()
        for _ in range(steps):
            actions = {agent: random_valid_move(infos[agent]["action_mask"], rng)
                       for agent in env.agents}  # fmt: skip
            _, _, _, truncations, infos = env.step(actions)
            if truncations[env.possible_agents[0]]:
                _, infos = env.reset()

    run()
    return run


def single_runner(family: str, n_users: int, steps: int):
    """The same for the single-UAV environment."""
    sampler = ScenarioSampler(families=(family,), users=(n_users, n_users))
    env = FapDiscreteEnv(sampler, world=WORLD)
    rng = np.random.default_rng(0)
    env.reset(seed=0)

    def run() -> None:
        _, info = env.reset()
        for _ in range(steps):
            action = random_valid_move(info["action_mask"], rng)
            _, _, _, truncated, info = env.step(action)
            if truncated:
                _, info = env.reset()

    run()
    return run


def interleaved_steps_per_s(runners: dict, steps: int, repeats: int) -> dict[str, float]:
    """Steps per second of each runner, best of ``repeats`` rounds; each round times every
    runner once, so that all of them meet the same load on a shared machine."""
    best = dict.fromkeys(runners, float("inf"))
    for _ in range(repeats):
        for name, run in runners.items():
            start = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: steps / seconds for name, seconds in best.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    steps = 300 if args.quick else 1500
    repeats = 2 if args.quick else args.repeats
    load = os.getloadavg()[0]
    headline: dict[str, dict[str, float]] = {}
    for family in ("uniform", "hotspots"):
        runners = {"single": single_runner(family, 50, steps)}
        for mode in ("distinct", "shared"):
            runners[mode] = fleet_runner(3, family, 50, mode, steps)
        speed = interleaved_steps_per_s(runners, steps, repeats)
        single = speed["single"]
        cells = {"single_uav_env_steps_per_s": round(single)}
        for mode in ("distinct", "shared"):
            cells[f"fleet_{mode}_env_steps_per_s"] = round(speed[mode])
            cells[f"fleet_{mode}_over_single"] = round(speed[mode] / single, 3)
            print(f"K=3, 50 users, {family:8s} {mode:8s}: {speed[mode]:8.0f} steps/s "
                  f"(single UAV: {single:8.0f}, ratio {speed[mode] / single:.2f})")  # fmt: skip
        headline[family] = cells
    runners = {str(k): fleet_runner(k, "uniform", 50, "distinct", steps) for k in (1, 2, 4, 8)}
    scaling = {k: round(v) for k, v in interleaved_steps_per_s(runners, steps, repeats).items()}
    for k, value in scaling.items():
        print(f"K={k}, 50 users, uniform, distinct: {value:8d} steps/s")
    result = {
        "benchmark": "fleet_speed",
        "machine": {
            "cpu": platform.machine(),
            "cores_used": 1,
            "load_average_1min_at_start": round(load, 2),
            "cpu_count": os.cpu_count(),
        },
        "python": platform.python_version(),
        "world": WORLD.name,
        "env": "sim.fleet_env.FleetParallelEnv (discrete, stochastic, random valid moves)",
        "steps_per_repeat": steps,
        "repeats": repeats,
        "k3_50_users": headline,
        "k_scaling_50_users_uniform_distinct": scaling,
        "target_env_steps_per_s": 5000,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
