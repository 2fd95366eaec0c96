"""Evaluate a policy on a scenario set in a world: one episode per scenario.

Protocol (:func:`evaluate_policy`), for scenario i of the set, in a :class:`sim.world.World`
(``paper`` by default, the paper's protocol; ``closed-loop`` flies):

* every policy is a :class:`policies.interface.Policy` (a static placement is wrapped in
  :class:`policies.adapters.StaticPolicy`), run by :func:`run_episode` exactly as the service
  runs it: each step it decides a target from the report the decision sees
  (``info["reports"]``) and the vehicle's position, and the environment
  (:meth:`sim.envs.FapContinuousEnv.step_to`) flies the vehicle toward it under the world's limits;
* ``reset(seed=seed + i)``: every policy sees the same fading draws, user motion and demand
  changes on the same scenario (the model draws the same number of random numbers per step
  wherever the UAV is), so differences between policies are the policies', not the dice's;
* a static placement is re-placed every step from the report. Where the world says
  ``static_start="placement"`` (the paper), its vehicle starts the episode at its placement;
  otherwise every policy starts at the world's home. The ``oracle`` re-placed every step is the
  *tracking oracle*: the best static position for the latest report, found with the model,
  flown to under the same limits.

Per scenario, all as means over the ``episode_steps`` scored steps:

* ``utility``: the step's network utility (paper eq. 1), the episode's mean reward;
* ``throughput_bps``: aggregate throughput of all users (bit/s);
* ``delay_s``: the users' mean delay (the mean over users of each user's mean delay, s);
* ``plr``: the users' mean packet loss ratio;
* ``heterogeneity``: the scenario's heterogeneity index H (paper eq. 3), at the episode start;
* ``time_to_final_s``: when the utility settled: the first step whose 5-step moving mean lies
  within 0.01 of the final utility (the mean of the last 10 steps), in seconds from the start;
* ``trace``: the utility of every step (4 decimals), for the utility-over-time figures.

The summary has the mean, the median and the 25th percentile (linear interpolation) of
``utility`` over the scenarios, and the mean ``time_to_final_s``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from policies.adapters import StaticPolicy
from policies.interface import Placement, Policy
from sim.envs import FapContinuousEnv
from sim.scenarios import Scenario
from sim.utility import heterogeneity_index
from sim.world import PAPER, World

HETEROGENEITY_BIN_WIDTH = 0.05
REFERENCE_POLICY = "min-distance"
SETTLED_WITHIN = 0.01  # time_to_final_s: how close to the final utility counts as settled
SETTLE_WINDOW = 5  # steps of the moving mean compared with the final utility
FINAL_STEPS = 10  # steps averaged for the final utility


def as_policy(policy: Policy | Placement) -> Policy:
    """``policy`` itself if it decides targets, else a placement wrapped in
    :class:`~policies.adapters.StaticPolicy`."""
    if isinstance(policy, Policy):
        return policy
    return StaticPolicy(policy)


@dataclass
class Episode:
    """One episode's per-step series (``episode_steps`` long) and its last info."""

    utility: np.ndarray
    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray
    final_info: dict[str, Any]


def run_episode(
    policy: Policy,
    scenario: Scenario,
    world: World,
    seed: int,
    users_seed: int | None = None,
    env: FapContinuousEnv | None = None,
) -> Episode:
    """Run ``policy`` for one episode of ``scenario`` in ``world``, from ``reset(seed=seed)``.

    ``users_seed`` fixes the users' own generator (moving users, changing demand) so several
    runs meet the same users; ``env`` reuses an environment (its world must be ``world``).
    """
    env = env if env is not None else FapContinuousEnv([scenario], world=world)
    options: dict[str, Any] = {"scenario": scenario}
    if users_seed is not None:
        options["users_seed"] = users_seed
    start_m = policy.begin_episode(scenario, world)
    if start_m is not None:
        options["uav_xyz_m"] = np.asarray(start_m, dtype=float)
    _, info = env.reset(seed=seed, options=options)
    steps = world.episode_steps
    series = np.empty((4, steps))
    for t in range(steps):
        target_m = policy.decide(info["reports"], info["uav_xyz_m"])
        _, reward, terminated, truncated, info = env.step_to(target_m)
        series[:, t] = (
            reward,
            np.sum(info["throughput_bps"]),
            np.mean(info["delay_s"]),
            np.mean(info["plr"]),
        )
        if terminated or (truncated and t < steps - 1):
            raise RuntimeError(f"episode of scenario {scenario.id} ended after {t + 1} steps")
    return Episode(*series, final_info=info)


def _progress(iterable: Sequence[Scenario], label: str, enabled: bool) -> Any:
    if not enabled:
        return iterable
    from tqdm import tqdm

    # disable=None: shown on a terminal, silent when stderr is a file or a pipe.
    return tqdm(iterable, desc=label, unit="scenario", file=sys.stderr, disable=None, leave=False)


def time_to_final_s(trace: np.ndarray, step_s: float) -> float:
    """Seconds until the utility settled (see the module doc), from a per-step ``trace``."""
    final = float(np.mean(trace[-FINAL_STEPS:]))
    window = min(SETTLE_WINDOW, len(trace))
    moving = np.convolve(trace, np.ones(window) / window, mode="valid")
    settled = np.flatnonzero(np.abs(moving - final) <= SETTLED_WITHIN)
    first = int(settled[0]) if len(settled) else len(moving) - 1
    return (first + 1) * step_s


def evaluate_policy(
    policy: Policy | Placement,
    scenarios: Sequence[Scenario],
    world: World = PAPER,
    seed: int = 0,
    progress: bool = True,
    on_scenario: Callable[[], object] | None = None,
) -> dict[str, Any]:
    """Run one episode per scenario in ``world`` and summarise (see the module doc).
    ``progress``: a bar on standard error (on a terminal only); ``on_scenario`` is called after
    each scenario (a caller's own progress).

    Returns ``{"policy", "world", "environment", "n_scenarios", "mean_utility", "median_utility",
    "p25_utility", "mean_time_to_final_s", "seed", "queueing", "episode_steps", "mode",
    "scenarios": [{"id", "utility", "heterogeneity", "throughput_bps", "delay_s", "plr",
    "time_to_final_s", "uav_xyz_m", "trace"}]}`` (``uav_xyz_m``: where the UAV ended the
    episode), plain floats and strings, ready for JSON. Deterministic given the arguments.
    """
    if not scenarios:
        raise ValueError("scenarios: the set is empty")
    if seed < 0:
        raise ValueError(f"seed: must be >= 0, got {seed}")
    agent = as_policy(policy)
    env = FapContinuousEnv(scenarios, world=world)
    rows = []
    for i, scenario in enumerate(_progress(scenarios, agent.name, progress)):
        episode = run_episode(agent, scenario, world, seed + i, env=env)
        rows.append(
            {
                "id": scenario.id,
                "utility": float(episode.utility.mean()),
                "heterogeneity": heterogeneity_index(
                    scenario.users_xy_m, scenario.load_bps, world.area
                ),
                "throughput_bps": float(episode.throughput_bps.mean()),
                "delay_s": float(episode.delay_s.mean()),
                "plr": float(episode.plr.mean()),
                "time_to_final_s": time_to_final_s(episode.utility, world.step_s),
                "uav_xyz_m": [float(v) for v in episode.final_info["uav_xyz_m"]],
                "trace": [round(float(u), 4) for u in episode.utility],
            }
        )
        if on_scenario is not None:
            on_scenario()
    values = np.array([row["utility"] for row in rows])
    return {
        "policy": agent.name,
        "world": world.name,
        "environment": world.environment,
        "n_scenarios": len(rows),
        "mean_utility": float(values.mean()),
        "median_utility": float(np.median(values)),
        "p25_utility": float(np.percentile(values, 25)),
        "mean_time_to_final_s": float(np.mean([row["time_to_final_s"] for row in rows])),
        "seed": seed,
        "queueing": world.network.queue.queueing,
        "episode_steps": world.episode_steps,
        "mode": "stochastic" if world.stochastic else "expected",
        "scenarios": rows,
    }


# --------------------------------------------------------------------------------------------
# Tables


def heterogeneity_bin(h: float, width: float = HETEROGENEITY_BIN_WIDTH) -> int:
    """Index of the bin [i·width, (i+1)·width) holding ``h`` (H = 1 goes in the last bin);
    rounds first so that H = 0.1 lands in [0.10, 0.15), as ``sim.scenarios`` bins it."""
    n_bins = round(1.0 / width)
    return min(max(math.floor(round(h * n_bins, 9)), 0), n_bins - 1)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = [
        "  ".join(
            cell.ljust(w) if i == 0 else cell.rjust(w)
            for i, (cell, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in [header, *rows]
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_results(results: Sequence[dict[str, Any]]) -> str:
    """Two text tables for the terminal.

    The summary: each policy's mean, median and 25th-percentile utility. Then the mean utility
    per heterogeneity bin of width 0.05 (empty bins left out), one column per policy, and when
    ``min-distance`` (the paper's baseline) is among the results, each other policy's gain over
    it in that bin (ratio of mean utilities, the paper's "4x"), which shows where the gains are.
    The results must cover the same scenarios in the same order.
    """
    if not results:
        return "no results"
    summary = _table(
        ["policy", "scenarios", "mean", "median", "p25"],
        [
            [
                r["policy"],
                str(r["n_scenarios"]),
                f"{r['mean_utility']:.3f}",
                f"{r['median_utility']:.3f}",
                f"{r['p25_utility']:.3f}",
            ]
            for r in results
        ],
    )
    names = [r["policy"] for r in results]
    reference = names.index(REFERENCE_POLICY) if REFERENCE_POLICY in names else None
    bins = np.array([heterogeneity_bin(s["heterogeneity"]) for s in results[0]["scenarios"]])
    utility = np.array([[s["utility"] for s in r["scenarios"]] for r in results])  # (P, N)
    header = ["H bin", "n", *names]
    gains = [] if reference is None else [p for p in range(len(results)) if p != reference]
    header += [f"{names[p]}/{REFERENCE_POLICY}" for p in gains]
    rows = []
    width = HETEROGENEITY_BIN_WIDTH
    for b in np.unique(bins):
        mask = bins == b
        means = utility[:, mask].mean(axis=1)
        row = [f"[{b * width:.2f}, {(b + 1) * width:.2f})", str(int(mask.sum()))]
        row += [f"{m:.3f}" for m in means]
        if reference is not None:
            ref = means[reference]
            row += [f"{means[p] / ref:.2f}x" if ref > 0 else "-" for p in gains]
        rows.append(row)
    by_bin = _table(header, rows)
    return f"{summary}\n\nmean utility by heterogeneity index H\n{by_bin}"
