"""Speed of the embedded network model, on one core.

Measures, and writes to benchmarks/results/sim_speed.json:

- environment steps per second (``tupa/FapDiscrete-v0`` through ``gym.make``, 3 users, stochastic
  mode, observation included), and how it scales with 3, 30 and 300 users;
- single-environment loop iterations per second without the environment: ``NetworkModel.step``
  (one position, stochastic), ``network_utility`` and ``build_observation``, 3 users;
- batched environment steps per second: ``NetworkModel.step_many`` over E cells (stochastic),
  ``network_utility`` over (E, U) and ``build_observations``, E = 64 and 256, 3 users; counted
  as E environment steps per batch call;
- single-environment steps per second of ``sim.envs.FapDiscreteEnv`` itself (no gymnasium
  wrappers) in the paper world and the closed-loop world (flight, report age 1), 3 users,
  stochastic, observation included, random valid moves;
- the same in the closed-loop world in every channel environment (``open`` and the urban
  classes of :mod:`sim.channel`; target >= 10,000 each);
- vectorised-environment steps per second of ``sim.vector_env.FapVectorEnv`` (discrete,
  closed-loop world, stochastic, 3 users, random valid moves, autoresets included), E = 64 and
  256: the whole environment step (targets, flight, model, utility, observations, infos),
  counted as E environment steps per batch step;
- (position × user) evaluations per second of one batched ``NetworkModel.step`` over the grid;
- the time of one oracle search over the full grid (3 users).

Targets: >= 20,000 environment steps/s (issue: the environment step with observation on one
core, 3 users), which needs the model loop at >= 30,000 iterations/s; >= 1,000,000
evaluations/s; oracle < 50 ms.
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
from sim.config import ENVIRONMENTS, AreaConfig
from sim.envs import DISCRETE_ENV_ID, FapDiscreteEnv, ScenarioCycle
from sim.network import NetworkModel
from sim.observation import UserReports, build_observation, build_observations
from sim.scenarios import generate_scenarios
from sim.utility import network_utility
from sim.vector_env import FapVectorEnv
from sim.world import World, get_world, world_with

RESULTS = Path(__file__).parent / "results" / "sim_speed.json"


def best_of(repeats: int, fn) -> float:
    """Smallest wall time of ``repeats`` runs (the least disturbed by other load)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def random_walk_steps_per_s(env, steps: int, repeats: int) -> float:
    """Steps per second of ``env`` (a discrete environment) taking random valid moves; one
    untimed run first (numba kernels load from cache, gymnasium checks run once)."""
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def run() -> None:
        _, info = env.reset()
        for _ in range(steps):
            action = int(rng.choice(np.flatnonzero(info["action_mask"])))
            _, _, _, truncated, info = env.step(action)
            if truncated:
                _, info = env.reset()

    run()
    return steps / best_of(repeats, run)


def env_steps_per_s(n_users: int, steps: int, repeats: int) -> float:
    """``tupa/FapDiscrete-v0`` through ``gym.make`` (wrappers included), ``n_users`` users."""
    scenarios = generate_scenarios(20, n_users, seed=1)
    env = gym.make(DISCRETE_ENV_ID, scenarios=ScenarioCycle(scenarios))
    return random_walk_steps_per_s(env, steps, repeats)


def single_env_steps_per_s(world: World, steps: int, repeats: int) -> float:
    """``sim.envs.FapDiscreteEnv`` (no wrappers) in ``world``, 3 users, random valid moves."""
    env = FapDiscreteEnv(ScenarioCycle(generate_scenarios(20, 3, seed=1)), world=world)
    return random_walk_steps_per_s(env, steps, repeats)


def vector_env_steps_per_s(n_envs: int, world: World, calls: int, repeats: int) -> float:
    """``sim.vector_env.FapVectorEnv`` (discrete) in ``world``, 3 users, random valid moves:
    E environment steps per batch step."""
    env = FapVectorEnv(n_envs, "discrete", generate_scenarios(20, 3, seed=1), world)
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def run() -> None:
        masks = env.action_masks()
        for _ in range(calls):
            actions = np.argmax(rng.random(masks.shape) * masks, axis=1)  # uniform valid move
            _, _, _, _, info = env.step(actions)
            masks = info["action_mask"]

    run()
    return n_envs * calls / best_of(repeats, run)


def model_loop_steps_per_s(steps: int, repeats: int) -> float:
    """What the environment's step does, without the environment: model (one position,
    stochastic, queues carried over), utility, observation; 100-step episodes over 20 cells."""
    model = NetworkModel()
    area = AreaConfig()
    scenarios = generate_scenarios(20, 3, seed=1)
    gen = np.random.default_rng(0)
    grid = area.grid_positions_m()
    positions = grid[gen.integers(0, len(grid), steps)]
    rng = np.random.default_rng(0)

    def run() -> None:
        state = None
        scenario = scenarios[0]
        for i in range(steps):
            if i % 100 == 0:
                scenario = scenarios[(i // 100) % len(scenarios)]
                state = None
            uav = positions[i]
            xy, load = scenario.users_xy_m, scenario.load_bps
            result = model.step(uav[None, :], xy, load, state, rng, 1.0)
            state = result.state
            throughput, delay, plr = result.throughput_bps[0], result.delay_s[0], result.plr[0]
            float(network_utility(throughput, delay, plr, load))
            reports = UserReports(xy[:, 0], xy[:, 1], load, throughput, delay, plr)
            build_observation(uav, reports, area)

    run()  # warm-up: numba kernels load from cache
    return steps / best_of(repeats, run)


def batched_env_steps_per_s(n_envs: int, calls: int, repeats: int) -> float:
    """Environment steps per second of a vectorised step: E cells as one numpy batch."""
    model = NetworkModel()
    area = AreaConfig()
    scenarios = generate_scenarios(n_envs, 3, seed=4)
    users = np.stack([s.users_xy_m for s in scenarios])
    load = np.stack([s.load_bps for s in scenarios])
    gen = np.random.default_rng(0)
    grid = area.grid_positions_m()
    positions = grid[gen.integers(0, len(grid), (calls, n_envs))]
    rng = np.random.default_rng(0)

    def run() -> None:
        state = None
        for i in range(calls):
            uav = positions[i]
            result = model.step_many(uav, users, load, state, rng, 1.0)
            state = result.state
            network_utility(result.throughput_bps, result.delay_s, result.plr, load)
            build_observations(
                uav,
                users[..., 0],
                users[..., 1],
                load,
                result.throughput_bps,
                result.delay_s,
                result.plr,
                area,
            )

    run()
    return n_envs * calls / best_of(repeats, run)


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
    from policies.placements.oracle import OraclePlacement

    oracle = OraclePlacement()
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
    loop = model_loop_steps_per_s(steps, repeats)
    print(f"model loop (step + utility + observation, 3 users): {loop:>8,.0f} it/s")
    batched = {}
    for n_envs in (64, 256):
        calls = max(steps // n_envs, 20)
        batched[str(n_envs)] = round(batched_env_steps_per_s(n_envs, calls, repeats))
        print(f"batched env steps/s (E={n_envs}, 3 users): {batched[str(n_envs)]:>10,}")
    single = {}
    for name in ("paper", "closed-loop"):
        single[name] = round(single_env_steps_per_s(get_world(name), steps, repeats))
        print(f"FapDiscreteEnv steps/s ({name}, 3 users): {single[name]:>8,}")
    environments = {}
    for environment in ENVIRONMENTS:
        world = world_with(get_world("closed-loop"), [f"environment={environment}"])
        environments[environment] = round(single_env_steps_per_s(world, steps, repeats))
        print(
            f"FapDiscreteEnv steps/s (closed-loop, {environment}, 3 users): "
            f"{environments[environment]:>8,}"
        )
    vector = {}
    for n_envs in (64, 256):
        calls = max(steps // n_envs, 100)  # at least one autoreset (100-step episodes)
        vector[str(n_envs)] = round(
            vector_env_steps_per_s(n_envs, get_world("closed-loop"), calls, repeats)
        )
        print(
            f"FapVectorEnv steps/s (E={n_envs}, closed-loop, 3 users): {vector[str(n_envs)]:>10,}"
        )
    evals, batch = batch_evaluations_per_s(repeats)
    print(f"batch evaluations/s (B={batch}, U=3): {evals:,.0f}")
    oracle_s = oracle_search_s(5 if args.quick else 20)
    print(f"oracle search (full grid + refinement, 3 users): {oracle_s * 1e3:.1f} ms")

    result = {
        "benchmark": "sim_speed",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores_used": 1},
        "python": platform.python_version(),
        "env_steps_per_s": {"n_users": scaling},
        "model_loop_steps_per_s_3_users": round(loop),
        "batched_env_steps_per_s_3_users": {"n_envs": batched},
        "single_env_steps_per_s_3_users": {
            "env": "sim.envs.FapDiscreteEnv",
            "stochastic": True,
            "worlds": single,
        },
        "single_env_steps_per_s_3_users_by_environment": {
            "env": "sim.envs.FapDiscreteEnv",
            "world": "closed-loop",
            "stochastic": True,
            "environments": environments,
        },
        "vector_env_steps_per_s_3_users": {
            "env": "sim.vector_env.FapVectorEnv",
            "kind": "discrete",
            "world": "closed-loop",
            "stochastic": True,
            "n_envs": vector,
        },
        "batch_position_user_evaluations_per_s": round(evals),
        "oracle_search_ms": round(oracle_s * 1e3, 2),
        "targets": {
            "env_steps_per_s_3_users": 20_000,
            "model_loop_steps_per_s_3_users": 30_000,
            "batch_evaluations_per_s": 1_000_000,
            "oracle_search_ms": 50,
            "single_env_steps_per_s_3_users_every_environment": 10_000,
        },
        "met": {
            "env_steps_per_s_3_users": scaling["3"] >= 20_000,
            "model_loop_steps_per_s_3_users": loop >= 30_000,
            "batch_evaluations_per_s": evals >= 1_000_000,
            "oracle_search_ms": oracle_s * 1e3 < 50,
            "single_env_steps_per_s_3_users_every_environment": min(environments.values())
            >= 10_000,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
