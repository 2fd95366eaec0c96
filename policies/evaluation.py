"""Evaluate a placement policy on a scenario set in a world: one episode per scenario.

Protocol (:func:`evaluate_policy`), for scenario i of the set, in a :class:`sim.world.World`
(``paper`` by default, the paper's protocol; ``closed-loop`` flies):

* one environment (``FapContinuousEnv`` unless the policy asks for the discrete one) with the
  world's episode (``episode_steps`` steps of ``step_s``), flight, users and reports;
* ``reset(seed=seed + i)``: every policy sees the same fading draws, user motion and demand
  changes on the same scenario (the model draws the same number of random numbers per step
  wherever the UAV is), so differences between policies are the policies', not the dice's;
* a static placement policy (:class:`StaticAgent`) is re-placed every step from the report the
  decision sees (``info["reports"]``: users' reported positions and offered loads), the vehicle
  flying there under the world's limits. Where the world says ``static_start="placement"`` (the
  paper), its vehicle starts the episode at its placement; otherwise every policy starts at the
  world's home. The ``oracle`` re-placed every step is the *tracking oracle*: the best static
  position for the latest report, found with the model, flown to under the same limits;
* an acting policy (:class:`EpisodePolicy`) starts where it asks (the world's home if it says
  ``None``) and picks an action every step from the observation.

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
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from policies.baselines import PlacementPolicy, ReportedUsers, UsersLike
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.scenarios import Scenario
from sim.utility import heterogeneity_index
from sim.world import PAPER, World, position_to_coordinates

EnvKind = Literal["continuous", "discrete"]
HETEROGENEITY_BIN_WIDTH = 0.05
REFERENCE_POLICY = "min-distance"
SETTLED_WITHIN = 0.01  # time_to_final_s: how close to the final utility counts as settled
SETTLE_WINDOW = 5  # steps of the moving mean compared with the final utility
FINAL_STEPS = 10  # steps averaged for the final utility


@runtime_checkable
class EpisodePolicy(Protocol):
    """A policy that acts every step (a trained agent), or a static one wrapped as such.

    ``env_kind`` picks the environment whose action space ``act`` answers in: ``"continuous"``
    (``FapContinuous``: absolute coordinates in [0, 1]³) or ``"discrete"`` (``FapDiscrete``: 13
    moves, masks in ``info["action_mask"]``). ``begin_episode`` is called before each reset with
    the scenario and the world; it returns the UAV's start position (3,) in metres, or ``None``
    for the world's home. ``act`` gets the latest observation and info (from the reset, then
    from each step) and returns the next action.
    """

    name: str
    env_kind: EnvKind

    def begin_episode(self, scenario: UsersLike, world: World) -> np.ndarray | None: ...

    def act(self, observation: np.ndarray, info: dict[str, Any]) -> Any: ...


@dataclass
class StaticAgent:
    """A :class:`~policies.baselines.PlacementPolicy` as an :class:`EpisodePolicy`: every step
    it places from the report the decision sees and answers with the continuous action that
    targets that placement. Placements are cached for identical reports (static users), and a
    policy with ``track(users, previous_m)`` (the oracle) is asked through it, so it can start
    its search from where it placed last."""

    policy: PlacementPolicy
    env_kind: EnvKind = "continuous"
    _world: World = field(default=PAPER, init=False, repr=False)
    _last_key: tuple[bytes, bytes] | None = field(default=None, init=False, repr=False)
    _target_m: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.name = self.policy.name

    def place(self, users: UsersLike) -> np.ndarray:
        """The placement for ``users`` (cached while they do not change)."""
        key = (users.users_xy_m.tobytes(), users.load_bps.tobytes())
        if key != self._last_key or self._target_m is None:
            track = getattr(self.policy, "track", None)
            previous = self._target_m
            target = track(users, previous) if track is not None else self.policy.place(users)
            self._target_m = np.asarray(target, dtype=float)
            self._last_key = key
        return self._target_m

    def begin_episode(self, scenario: UsersLike, world: World) -> np.ndarray | None:
        self._world = world
        self._last_key = self._target_m = None
        if world.static_start == "placement":
            return self.place(scenario)
        return None

    def act(self, observation: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        target_m = self.place(ReportedUsers.of(info["reports"]))
        return position_to_coordinates(target_m, self._world.area)


def as_episode_policy(policy: PlacementPolicy | EpisodePolicy) -> EpisodePolicy:
    """``policy`` itself if it acts every step, else wrapped in :class:`StaticAgent`."""
    if isinstance(policy, EpisodePolicy):
        return policy
    return StaticAgent(policy)


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
    policy: PlacementPolicy | EpisodePolicy,
    scenarios: Sequence[Scenario],
    world: World = PAPER,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, Any]:
    """Run one episode per scenario in ``world`` and summarise (see the module doc).

    Returns ``{"policy", "world", "n_scenarios", "mean_utility", "median_utility",
    "p25_utility", "mean_time_to_final_s", "seed", "queueing", "episode_steps", "mode",
    "scenarios": [{"id", "utility", "heterogeneity", "throughput_bps", "delay_s", "plr",
    "time_to_final_s", "uav_xyz_m", "trace"}]}`` (``uav_xyz_m``: where the UAV ended the
    episode), plain floats and strings, ready for JSON. Deterministic given the arguments.
    """
    if not scenarios:
        raise ValueError("scenarios: the set is empty")
    if seed < 0:
        raise ValueError(f"seed: must be >= 0, got {seed}")
    agent = as_episode_policy(policy)
    env_class = FapDiscreteEnv if agent.env_kind == "discrete" else FapContinuousEnv
    env = env_class(scenarios, world=world)
    area = world.area
    steps = world.episode_steps

    rows = []
    for i, scenario in enumerate(_progress(scenarios, agent.name, progress)):
        options: dict[str, Any] = {"scenario": scenario}
        start_m = agent.begin_episode(scenario, world)
        if start_m is not None:
            options["uav_xyz_m"] = np.asarray(start_m, dtype=float)
        observation, info = env.reset(seed=seed + i, options=options)
        utilities = np.empty(steps)
        throughput = np.empty(steps)
        delay = np.empty(steps)
        plr = np.empty(steps)
        for t in range(steps):
            observation, reward, terminated, truncated, info = env.step(
                agent.act(observation, info)
            )
            utilities[t] = reward
            throughput[t] = np.sum(info["throughput_bps"])
            delay[t] = np.mean(info["delay_s"])
            plr[t] = np.mean(info["plr"])
            if terminated or (truncated and t < steps - 1):
                raise RuntimeError(f"episode of scenario {scenario.id} ended after {t + 1} steps")
        rows.append(
            {
                "id": scenario.id,
                "utility": float(utilities.mean()),
                "heterogeneity": heterogeneity_index(scenario.users_xy_m, scenario.load_bps, area),
                "throughput_bps": float(throughput.mean()),
                "delay_s": float(delay.mean()),
                "plr": float(plr.mean()),
                "time_to_final_s": time_to_final_s(utilities, world.step_s),
                "uav_xyz_m": [float(v) for v in info["uav_xyz_m"]],
                "trace": [round(float(u), 4) for u in utilities],
            }
        )
    values = np.array([row["utility"] for row in rows])
    return {
        "policy": agent.name,
        "world": world.name,
        "n_scenarios": len(rows),
        "mean_utility": float(values.mean()),
        "median_utility": float(np.median(values)),
        "p25_utility": float(np.percentile(values, 25)),
        "mean_time_to_final_s": float(np.mean([row["time_to_final_s"] for row in rows])),
        "seed": seed,
        "queueing": world.network.queue.queueing,
        "episode_steps": steps,
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
