"""Evaluate a fleet policy on a scenario set: one episode of the fleet environment per scenario
(``tupa eval --uavs K``, ``benchmarks/fleet_policy.py``).

Protocol (:func:`evaluate_fleet`), for scenario i of the set, K UAVs, a
:class:`sim.world.World`:

* the fleet environment (:class:`sim.fleet_env.FleetParallelEnv`, continuous actions) is reset
  with ``seed + i`` from the fleet's homes (:func:`sim.fleet_env.fleet_homes`), so every policy
  meets the same fading draws, user motion and demand changes on the same scenario;
* every decision is the one ``tupa serve`` would take (:func:`as_fleet_policy`: the same
  :meth:`~policies.fleet_policy.FleetPolicy.decide_fleet`, from the report the decision sees and
  where the vehicles are, the users' APs estimated by the one rule of
  :class:`~policies.fleet_policy.ReportedAssociation`, each target given to the vehicle with the
  least total flight, :func:`sim.geometry.assign_targets`, as the service assigns them); a fleet
  checkpoint (:class:`policies.learned.fleet_checkpoint.FleetCheckpointPolicy`) decides every
  step; a placement (the k-means baselines of :mod:`policies.placements.fleet_baselines`,
  ``kmeans-scored``, the search oracle of :mod:`policies.placements.fleet_oracle`, which score
  from where the fleet is) is placed on the first report and re-placed every ``replan_every``
  decisions, held in between; the environment flies the vehicles toward the targets under the
  world's limits (every policy pays the same transit).

Per scenario (a row of the document), over the episode's ``episode_steps`` decisions:

* ``utility``: the mean network utility over all users (the fleet's shared reward);
* ``served_fraction``: the mean fraction of users served (connected, and getting at least the
  fleet's served ratio of their offered load: :class:`sim.fleet.FleetModel`);
* ``jain_fairness``: the mean Jain index of the users' throughput;
* ``min_throughput_bps``: the mean of each step's lowest user throughput;
* ``handovers``: handovers over the episode (users moved from one UAV's AP to another's);
* ``heterogeneity``: the scenario's heterogeneity index H (paper eq. 3), as ``tupa eval``;
* ``id``: the scenario's id.

The document (:data:`FLEET_EVAL_FORMAT`) carries the policy's name, K, the world and its
episode, the seed, the means over scenarios (``mean_<metric>``) and the rows; plain JSON numbers,
deterministic given the arguments. :func:`build_fleet_candidate` turns a name or a checkpoint
path into what is evaluated; :func:`add_ratio_to_oracle` adds the per-scenario ratio of the
utility to the oracle's.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from policies.fleet_policy import (
    FleetCheckpointServing,
    FleetPlacementPolicy,
    FleetPolicy,
    resolve_fleet_policy,
)
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.placements.fleet_baselines import FLEET_BASELINES
from policies.placements.fleet_oracle import FLEET_ORACLE
from policies.placements.fleet_scored import KMEANS_SCORED
from sim.errors import InputError
from sim.fleet import MAX_UAVS, FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets
from sim.scenarios import Scenario, heterogeneity_indices
from sim.world import World

__all__ = [
    "FLEET_EVAL_FORMAT",
    "FLEET_EVAL_POLICIES",
    "FLEET_METRICS",
    "FLEET_ORACLE",
    "FleetPlacement",
    "add_ratio_to_oracle",
    "as_fleet_policy",
    "build_fleet_candidate",
    "check_fleet_size",
    "evaluate_fleet",
    "format_fleet_results",
]

FLEET_EVAL_FORMAT = "tupa-fleet-eval/1"
FLEET_EVAL_POLICIES: tuple[str, ...] = (*FLEET_BASELINES, KMEANS_SCORED, FLEET_ORACLE)
"""The fleet policies evaluated by name; anything else must be a fleet checkpoint."""
FLEET_METRICS: tuple[str, ...] = (
    "utility",
    "served_fraction",
    "jain_fairness",
    "min_throughput_bps",
    "handovers",
)
"""Each row's metrics (module doc), in the order tables and figures show them."""
_STEP_METRICS = FLEET_METRICS[:4]  # averaged over the episode's steps; handovers are counted


class FleetPlacement(Protocol):
    """A placement of the whole fleet from the users' report (k-means baselines, oracle):
    ``place(users)`` with ``users_xy_m`` (U, 2) and ``load_bps`` (U,) gives (K, 3) metres."""

    def place(self, users: Any) -> np.ndarray: ...


def as_fleet_policy(
    policy: FleetPolicy | FleetCheckpointPolicy | FleetPlacement, world: World, fleet: FleetConfig
) -> FleetPolicy:
    """What ``policy`` decides as when served (:class:`policies.fleet_policy.FleetPolicy`): a
    served policy as it is, a checkpoint (anything with ``targets``) as
    :class:`~policies.fleet_policy.FleetCheckpointServing`, a placement built for ``fleet``'s K
    as :class:`~policies.fleet_policy.FleetPlacementPolicy`."""
    if hasattr(policy, "decide_fleet"):
        return policy  # type: ignore[return-value]
    if hasattr(policy, "targets"):
        return FleetCheckpointServing(policy, "", world, fleet.hysteresis_db)
    return FleetPlacementPolicy.around(policy, world, fleet)


@dataclass
class _Decider:
    """Targets for one step, decided as the service decides (the same
    :meth:`~policies.fleet_policy.FleetPolicy.decide_fleet` from the report and where the
    vehicles are, each target to the vehicle with the least total flight); a placement's held
    for ``replan_every`` steps, a checkpoint's every step."""

    policy: FleetPolicy
    replan_every: int
    _held: np.ndarray | None = field(default=None, init=False)

    def __call__(self, env: FleetParallelEnv, step: int) -> np.ndarray:
        every = self.replan_every if self.policy.kind == "placement" else 1
        if self._held is None or step % every == 0:
            wanted = self.policy.decide_fleet(env.reports, env.uav_xyz_m)
            self._held = assign_targets(env.uav_xyz_m, np.asarray(wanted, dtype=float))
        return self._held


def _progress(items: Sequence[Scenario], label: str, enabled: bool) -> Iterable[Scenario]:
    if not enabled:
        return items
    from tqdm import tqdm

    # disable=None: shown on a terminal, silent when stderr is a file or a pipe.
    return tqdm(items, desc=label, unit="scenario", file=sys.stderr, disable=None, leave=False)


def evaluate_fleet(
    policy: FleetCheckpointPolicy | FleetPlacement,
    scenarios: Sequence[Scenario],
    n_uavs: int,
    world: World,
    fleet: FleetConfig | None = None,
    replan_every: int = 1,
    seed: int = 0,
    *,
    name: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run one fleet episode per scenario with ``policy`` (see the module doc) and return the
    ``tupa-fleet-eval/1`` document.

    ``policy``: a :class:`FleetCheckpointPolicy` (decides every step), or a placement with
    ``place(users) -> (K, 3)`` re-placed on the report the decision sees every
    ``replan_every`` steps. ``fleet`` (channels, separation, hysteresis) defaults to
    ``FleetConfig(n_uavs)``; ``name`` to the policy's own (``policy.name``, or the
    checkpoint's). ``progress``: a bar on stderr (shown on a terminal only).

    The document: ``{"format", "policy", "uavs", "world", "environment", "episode_steps",
    "step_s", "replan_every", "separation_m", "channel_mode", "seed", "n_scenarios",
    "mean_utility", "mean_served_fraction", "mean_jain_fairness", "mean_min_throughput_bps",
    "mean_handovers", "utilities", "scenarios": [{"id", "heterogeneity", "utility",
    "served_fraction", "jain_fairness", "min_throughput_bps", "handovers"}]}``
    (``utilities``: the rows' utilities in order)."""
    if not scenarios:
        raise InputError("scenarios: empty")
    if isinstance(replan_every, bool) or not isinstance(replan_every, int) or replan_every < 1:
        raise InputError(f"replan_every: must be an integer >= 1, got {replan_every!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputError(f"seed: must be an integer >= 0, got {seed!r}")
    fleet = fleet or FleetConfig(n_uavs=n_uavs)
    if fleet.n_uavs != n_uavs:
        raise InputError(f"n_uavs: {n_uavs} disagrees with the fleet's {fleet.n_uavs}")
    served = as_fleet_policy(policy, world, fleet)
    label = name or served.name
    env = FleetParallelEnv(action_kind="continuous", scenarios=list(scenarios), world=world,
                           fleet=fleet)  # fmt: skip
    heterogeneity = heterogeneity_indices(scenarios, world.area)
    rows: list[dict[str, Any]] = []
    for i, scenario in enumerate(_progress(scenarios, f"{label} K={n_uavs}", progress)):
        served.reset()  # a new episode: the users' APs start afresh
        decide = _Decider(served, replan_every)
        env.reset(seed=seed + i, options={"scenario": scenario})
        sums = dict.fromkeys(_STEP_METRICS, 0.0)
        steps, handovers = 0, 0
        while env.agents:
            *_, infos = env.step_to(decide(env, steps))
            info = infos[env.possible_agents[0]]
            for key in _STEP_METRICS:
                sums[key] += info[key]
            handovers = int(info["handovers"])  # so far in the episode
            steps += 1
        rows.append(
            {
                "id": scenario.id,
                "heterogeneity": float(heterogeneity[i]),
                **{key: float(sums[key] / steps) for key in _STEP_METRICS},
                "handovers": handovers,
            }
        )
    means = {f"mean_{key}": float(np.mean([row[key] for row in rows])) for key in FLEET_METRICS}
    return {
        "format": FLEET_EVAL_FORMAT,
        "policy": label,
        "uavs": n_uavs,
        "world": world.name,
        "environment": world.environment,
        "episode_steps": world.episode_steps,
        "step_s": world.step_s,
        "replan_every": replan_every,
        "separation_m": fleet.separation_m,
        "channel_mode": fleet.channel_mode,
        "seed": seed,
        "n_scenarios": len(rows),
        **means,
        "utilities": [row["utility"] for row in rows],
        "scenarios": rows,
    }


def build_fleet_candidate(
    spec: str,
    n_uavs: int,
    world: World,
    fleet: FleetConfig | None = None,
    seed: int = 0,
    option: str = "policy",
) -> tuple[str, FleetPolicy]:
    """``(name, policy)`` for ``spec``, to evaluate a fleet of ``n_uavs`` in ``world``: the
    policy ``tupa serve`` would serve for it (:func:`policies.fleet_policy.resolve_fleet_policy`
    on a fleet like ``fleet``; the search seeded with ``seed``).

    ``spec``: ``kmeans-min-distance``, ``kmeans-load-weighted``, ``kmeans-scored``,
    ``fleet-oracle`` (scoring over ``world``'s network, episode and decision period), or a
    fleet checkpoint (a ``tupa train --uavs K`` output directory or its ``model.zip``; any K).
    Anything else, a single-UAV policy or checkpoint included, is an :class:`InputError`
    naming ``option``."""
    from policies.registry import PLACEMENTS

    fleet = fleet or FleetConfig(n_uavs=n_uavs)
    if fleet.n_uavs != n_uavs:
        raise InputError(f"n_uavs: {n_uavs} disagrees with the fleet's {fleet.n_uavs}")
    spec = str(spec).strip()
    known = ", ".join(FLEET_EVAL_POLICIES)
    if spec in PLACEMENTS:
        raise InputError(
            f"{option}: {spec!r} places one UAV; a fleet is evaluated with {known} or a fleet "
            "checkpoint (tupa train --uavs K)"
        )
    if spec not in FLEET_EVAL_POLICIES and (not spec or not Path(spec).exists()):
        raise InputError(
            f"{option}: {spec!r} is neither a fleet policy ({known}) nor an existing checkpoint"
        )
    try:
        policy = resolve_fleet_policy(spec, world, fleet.separation_m, fleet=fleet, seed=seed)
    except InputError as exc:
        problem = str(exc).removeprefix("policy: ")
        raise InputError(f"{option}: {spec}: not a fleet checkpoint ({problem})") from None
    return policy.name, policy


def add_ratio_to_oracle(documents: Sequence[dict[str, Any]]) -> bool:
    """When ``fleet-oracle`` is among ``documents`` (all over the same scenarios, in the same
    order), add to every row ``ratio_to_oracle`` (its utility over the oracle's on that
    scenario; None where the oracle's is not positive) and to every document
    ``ratio_to_oracle`` (mean utility over the oracle's). Returns whether it did."""
    oracle = next((d for d in documents if d["policy"] == FLEET_ORACLE), None)
    if oracle is None:
        return False
    best = [row["utility"] for row in oracle["scenarios"]]
    for document in documents:
        for row, reference in zip(document["scenarios"], best, strict=True):
            row["ratio_to_oracle"] = row["utility"] / reference if reference > 0 else None
        mean = oracle["mean_utility"]
        document["ratio_to_oracle"] = document["mean_utility"] / mean if mean > 0 else None
    return True


def format_fleet_results(documents: Sequence[dict[str, Any]]) -> str:
    """A text table for the terminal: each policy's means over the scenarios (and its ratio to
    the oracle's mean utility when the oracle was evaluated)."""
    header = ["policy", "K", "n", "utility", "served", "Jain", "min Mbit/s", "handovers"]
    with_ratio = any("ratio_to_oracle" in d for d in documents)
    if with_ratio:
        header.append("/oracle")
    rows = []
    for d in documents:
        row = [
            d["policy"],
            str(d["uavs"]),
            str(d["n_scenarios"]),
            f"{d['mean_utility']:.3f}",
            f"{d['mean_served_fraction']:.3f}",
            f"{d['mean_jain_fairness']:.3f}",
            f"{d['mean_min_throughput_bps'] / 1e6:.2f}",
            f"{d['mean_handovers']:.1f}",
        ]
        if with_ratio:
            ratio = d.get("ratio_to_oracle")
            row.append("-" if ratio is None else f"{ratio:.3f}")
        rows.append(row)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in [header, *rows]
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def check_fleet_size(n_uavs: int, option: str = "--uavs") -> int:
    """``n_uavs`` if it is an integer in 2..8 (a fleet; one UAV is plain ``tupa eval``)."""
    if isinstance(n_uavs, bool) or not isinstance(n_uavs, int) or not 2 <= n_uavs <= MAX_UAVS:
        raise InputError(f"{option}: must be an integer in 2..{MAX_UAVS}, got {n_uavs!r}")
    return n_uavs
