"""Evaluate a placement policy on a scenario set: one stochastic episode per scenario.

Protocol (:func:`evaluate_policy`), for scenario i of the set:

* one environment (``FapContinuousEnv`` unless the policy asks for the discrete one) with the
  paper's episode (``episode_steps`` steps of 1 s), fading sampled (stochastic mode) and the
  chosen queueing variant;
* ``reset(seed=seed + i)``: every policy sees the same fading draws on the same scenario (the
  model draws the same number of random numbers per step wherever the UAV is), so differences
  between policies are the policies', not the dice's;
* a static policy's UAV starts the episode at its position (the reset step is simulated there
  and not scored), then holds it for every step; an acting policy (:class:`EpisodePolicy`)
  starts wherever it asks (the environment's default start if it says ``None``) and picks an
  action every step from the observation.

Per scenario, all as means over the ``episode_steps`` scored steps:

* ``utility``: the step's network utility (paper eq. 1), the episode's mean reward;
* ``throughput_bps``: aggregate throughput of all users (bit/s);
* ``delay_s``: the users' mean delay (the mean over users of each user's mean delay, s);
* ``plr``: the users' mean packet loss ratio;
* ``heterogeneity``: the scenario's heterogeneity index H (paper eq. 3).

These are the quantities the utility is made of (up to its normalisation and clipping). The
summary has the mean, the median and the 25th percentile (linear interpolation) of ``utility``
over the scenarios.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from policies.baselines import PlacementPolicy, UsersLike
from sim.config import AreaConfig, NetworkConfig, Queueing, UtilityConfig
from sim.envs import EnvConfig, FapContinuousEnv, FapDiscreteEnv
from sim.scenarios import Scenario
from sim.utility import heterogeneity_index

EnvKind = Literal["continuous", "discrete"]
HETEROGENEITY_BIN_WIDTH = 0.05
REFERENCE_POLICY = "min-distance"


@runtime_checkable
class EpisodePolicy(Protocol):
    """A policy that acts every step (a trained agent), or a static one wrapped as such.

    ``env_kind`` picks the environment whose action space ``act`` answers in: ``"continuous"``
    (``FapContinuous``: absolute coordinates in [0, 1]³) or ``"discrete"`` (``FapDiscrete``: 13
    moves, masks in ``info["action_mask"]``). ``begin_episode`` is called before each reset with
    the scenario; it returns the UAV's start position (3,) in metres, or ``None`` for the
    environment's default start. ``act`` gets the latest observation and info (from the reset,
    then from each step) and returns the next action.
    """

    name: str
    env_kind: EnvKind

    def begin_episode(self, scenario: UsersLike, area: AreaConfig) -> np.ndarray | None: ...

    def act(self, observation: np.ndarray, info: dict[str, Any]) -> Any: ...


@dataclass
class StaticAgent:
    """A :class:`~policies.baselines.PlacementPolicy` as an :class:`EpisodePolicy`: it starts
    at its position and answers every step with the continuous action that keeps it there."""

    policy: PlacementPolicy
    env_kind: EnvKind = "continuous"

    def __post_init__(self) -> None:
        self.name = self.policy.name
        self._action = np.zeros(3)

    def begin_episode(self, scenario: UsersLike, area: AreaConfig) -> np.ndarray:
        target_m = np.asarray(self.policy.place(scenario), dtype=float)
        self._action = position_to_action_f64(target_m, area)
        return target_m

    def act(self, observation: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return self._action


def position_to_action_f64(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The continuous environment's action for ``xyz_m`` in float64 (``sim.envs``'s
    ``position_to_action`` rounds to float32, which moves the UAV by up to ~30 µm: harmless,
    but then the evaluated position would not be exactly the policy's)."""
    span_z = area.z_max_m - area.z_min_m
    action = np.array(
        [
            xyz_m[0] / area.size_x_m,
            xyz_m[1] / area.size_y_m,
            (xyz_m[2] - area.z_min_m) / span_z if span_z > 0 else 0.0,
        ]
    )
    return np.clip(action, 0.0, 1.0)


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


def evaluate_policy(
    policy: PlacementPolicy | EpisodePolicy,
    scenarios: Sequence[Scenario],
    area: AreaConfig,
    seed: int = 0,
    queueing: Queueing = "fq-codel",
    episode_steps: int = 100,
    progress: bool = True,
    network: NetworkConfig | None = None,
    utility: UtilityConfig = UtilityConfig(),
    expected: bool = False,
) -> dict[str, Any]:
    """Run one episode per scenario and summarise (see the module doc for the protocol).

    Returns ``{"policy", "n_scenarios", "mean_utility", "median_utility", "p25_utility",
    "seed", "queueing", "episode_steps", "mode", "scenarios": [{"id", "utility",
    "heterogeneity", "throughput_bps", "delay_s", "plr", "uav_xyz_m"}]}`` (``uav_xyz_m``: where
    the UAV ended the episode),
    plain floats and strings, ready for JSON. Deterministic given the arguments.
    ``network`` defaults to the paper's configuration; ``queueing`` overrides its queueing.
    ``expected=True`` runs the deterministic expected model instead (no fading draws): the
    game the oracle optimises, for checking it.
    """
    if not scenarios:
        raise ValueError("scenarios: the set is empty")
    if episode_steps < 1:
        raise ValueError(f"episode_steps: must be >= 1, got {episode_steps}")
    if seed < 0:
        raise ValueError(f"seed: must be >= 0, got {seed}")
    agent = as_episode_policy(policy)
    config = EnvConfig(
        episode_steps=episode_steps,
        expected=expected,
        network=(network or NetworkConfig()).with_queueing(queueing),
        utility=utility,
        area=area,
    )
    env_class = FapDiscreteEnv if agent.env_kind == "discrete" else FapContinuousEnv
    env = env_class(scenarios, config=config)

    rows = []
    for i, scenario in enumerate(_progress(scenarios, agent.name, progress)):
        options: dict[str, Any] = {"scenario": scenario}
        start_m = agent.begin_episode(scenario, area)
        if start_m is not None:
            options["uav_xyz_m"] = np.asarray(start_m, dtype=float)
        observation, info = env.reset(seed=seed + i, options=options)
        utilities = np.empty(episode_steps)
        throughput = np.empty(episode_steps)
        delay = np.empty(episode_steps)
        plr = np.empty(episode_steps)
        for t in range(episode_steps):
            observation, reward, terminated, truncated, info = env.step(
                agent.act(observation, info)
            )
            utilities[t] = reward
            throughput[t] = np.sum(info["throughput_bps"])
            delay[t] = np.mean(info["delay_s"])
            plr[t] = np.mean(info["plr"])
            if terminated or (truncated and t < episode_steps - 1):
                raise RuntimeError(f"episode of scenario {scenario.id} ended after {t + 1} steps")
        rows.append(
            {
                "id": scenario.id,
                "utility": float(utilities.mean()),
                "heterogeneity": heterogeneity_index(scenario.users_xy_m, scenario.load_bps, area),
                "throughput_bps": float(throughput.mean()),
                "delay_s": float(delay.mean()),
                "plr": float(plr.mean()),
                "uav_xyz_m": [float(v) for v in info["uav_xyz_m"]],
            }
        )
    values = np.array([row["utility"] for row in rows])
    return {
        "policy": agent.name,
        "n_scenarios": len(rows),
        "mean_utility": float(values.mean()),
        "median_utility": float(np.median(values)),
        "p25_utility": float(np.percentile(values, 25)),
        "seed": seed,
        "queueing": queueing,
        "episode_steps": episode_steps,
        "mode": "expected" if expected else "stochastic",
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
