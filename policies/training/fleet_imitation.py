"""Imitation of the fleet's search oracle: supervised pretraining of the shared network.

Reinforcement learning from the fleet's one shared reward (the network utility over all users)
has to find out which UAV's action helped; the fleet policies trained that way ended below the
k-means placements (docs/results.md, "Fleets"). The search oracle
(:class:`policies.placements.fleet_oracle.FleetOracle`, flown from where the fleet is) already knows
a better placement for a report, so its answer gives every agent a supervised target:

1. **Teacher episodes.** Fleets fly training scenarios (the run's sampler and world, the
   preset's training episode: its length and random starts) toward the oracle's placement,
   searched from where the fleet is every ``replan_every`` decisions and held in between, each
   UAV taking its target by least travel (:func:`sim.geometry.assign_targets`), as the
   evaluation and the service fly it. At every decision each agent's observation is recorded
   with the teacher's action, in the policy's own action space:

   - **residual** (DDPG): the action that moves its prior place (its share of the
     load-weighted k-means placement) onto an oracle target. The targets are matched to the
     priors by least total distance, so a mere change of which UAV takes which place is never
     learned as a move; the action is ``(target_xy − prior_xy) / radius`` and
     ``(target_z − z_min) / band``, clipped to [-1, 1]
     (:func:`policies.learned.fleet_residual.fleet_residual_targets` inverted);
   - **moves** (DDQN): of the 13 discrete moves allowed from its zone, the one whose target
     lies nearest its own oracle target (:func:`teacher_moves`); the fleet flies those moves,
     so the states are those a fleet flying moves sees.

   The oracle runs with a cheaper search (:data:`TEACHERS`): ``search`` (no random restarts,
   no pair moves, one sweep over the area) is 2–4 times faster and, flown from the fleet,
   scores as the full search does at K = 3 and 4 but clearly below it at K = 2, where the
   restarts matter; ``local`` refines the k-means placements only, so its targets stay near
   the prior (``benchmarks/fleet_teacher.py``).
2. **Fit.** The network that :func:`policies.training.fleet_training.train_fleet` builds is fitted
   to those actions (:func:`fit_actor`): the DDPG actor by mean squared error, the DDQN's
   Q-network by cross-entropy over the allowed moves (its outputs read as logits, so its
   greedy move is the predicted one); Adam, mini-batches, optionally each turned by one of the
   square area's eight symmetries (:func:`symmetry`); episodes, not single decisions, split
   into fit and validation parts so correlated decisions never straddle them; the epoch with
   the least validation loss kept and copied into the target network.
3. **DAgger** (Ross, Gordon & Bagnell 2011), optional: the fitted policy flies more episodes
   (``learner``), the oracle labels every state the learner reaches, and the fit is redone on
   all the data so far, so the policy learns to recover from its own mistakes, which a
   teacher's flight never shows it.

Reinforcement learning may continue from the fit (``episodes`` > 0). Teacher episodes are
drawn from their own seeds (``seed``, episode index) and can be spread over ``workers``
processes with the same result.

Measured (docs/results.md, "The oracle as a teacher"), none of this yet flies better than
load-weighted k-means, so ``--imitate`` is experimental.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from policies.interface import ReportedUsers
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.learned.fleet_residual import KMeansPrior
from policies.placements.fleet_oracle import FleetOracle, FleetOracleConfig
from policies.training.training import episode_bar
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import (
    MOVES,
    assign_targets,
    move_masks,
    move_targets,
    zone_indices,
)
from sim.scenarios import ScenarioSampler
from sim.world import World

__all__ = [
    "TEACHERS",
    "ImitationConfig",
    "TeacherData",
    "collect_teacher_data",
    "fit_actor",
    "symmetry",
    "teacher_actions",
    "teacher_moves",
    "teacher_oracle",
]

TEACHERS: dict[str, dict[str, Any]] = {
    "search": {"restarts": 0, "pair_stride": 0, "sweeps": 1},
    "local": {"restarts": 0, "pair_stride": 0, "sweeps": 0},
}
"""The teachers: the fleet oracle's search settings over :class:`FleetOracleConfig`'s defaults.
``search``: one coordinate-descent sweep over the whole area from the k-means placements, then
refinement; ``local``: the k-means placements refined only (compass moves from half a zone
down), so its targets stay near the prior a residual action corrects."""

_TEACHER_SEED_OFFSET = 50_000


@dataclass(frozen=True)
class ImitationConfig:
    """How the shared actor imitates the oracle (module doc). ``episodes``: teacher-flown fleet
    episodes; ``replan_every``: decisions a teacher placement is held."""

    episodes: int
    replan_every: int = 10
    epochs: int = 40
    batch_size: int = 256
    learning_rate: float = 1e-3
    validation_fraction: float = 0.1
    workers: int = 1
    horizon_steps: int = 100
    """The episode the teacher scores a placement over (the evaluation's, not the shorter
    training episode: a placement is judged by where the fleet ends up)."""
    teacher: str = "search"
    """Which search teaches (:data:`TEACHERS`)."""
    symmetries: bool = False
    """Fit each mini-batch under one of the area's symmetries (:func:`symmetry`), drawn at
    random: the physics has no preferred direction, so a teacher decision mirrored or
    rotated is a decision too, so eight times the distinct targets for nothing."""

    def __post_init__(self) -> None:
        for name in ("episodes", "replan_every", "epochs", "batch_size", "workers",
                     "horizon_steps"):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InputError(f"{name}: must be an integer >= 1, got {value!r}")
        if not (np.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise InputError(f"learning_rate: must be > 0, got {self.learning_rate!r}")
        if self.teacher not in TEACHERS:
            raise InputError(f"teacher: one of {', '.join(TEACHERS)}, got {self.teacher!r}")
        if not 0 < self.validation_fraction < 1:
            raise InputError(
                f"validation_fraction: must be in (0, 1), got {self.validation_fraction!r}"
            )


@dataclass(frozen=True)
class TeacherData:
    """Agent decisions from teacher episodes: observations (N, 9, n_x, n_y) float32; the
    actions, residual (N, 3) float32 or moves (N,) int64; the episode each came from (N,); the
    move masks (N, 13) for moves (None for residual actions); and how many residual actions had
    to be clipped to [-1, 1] (the oracle's target beyond the residual radius)."""

    observations: np.ndarray
    actions: np.ndarray
    episodes: np.ndarray
    clipped: int
    oracle_calls: int
    masks: np.ndarray | None = None

    @property
    def moves(self) -> bool:
        return self.masks is not None

    def __add__(self, other: TeacherData) -> TeacherData:
        """Both sets of decisions (DAgger's aggregate); their episodes must be numbered apart."""
        if self.moves != other.moves:
            raise ValueError("teacher data: cannot add moves to residual actions")
        if np.intersect1d(self.episodes, other.episodes).size:
            raise ValueError("teacher data: the two sets share episode numbers")
        return TeacherData(
            observations=np.concatenate([self.observations, other.observations]),
            actions=np.concatenate([self.actions, other.actions]),
            episodes=np.concatenate([self.episodes, other.episodes]),
            clipped=self.clipped + other.clipped,
            oracle_calls=self.oracle_calls + other.oracle_calls,
            masks=None if self.masks is None else np.concatenate([self.masks, other.masks]),
        )


def teacher_actions(
    targets_m: np.ndarray, priors_m: np.ndarray, world: World, radius_m: float
) -> tuple[np.ndarray, int]:
    """The residual actions (K, 3) that send each UAV to its target (K, 3) from its prior place
    (K, 3), clipped to [-1, 1]; and how many components had to be clipped."""
    area = world.area
    raw = np.column_stack(
        [
            (targets_m[:, :2] - priors_m[:, :2]) / radius_m,
            (targets_m[:, 2] - area.z_min_m) / (area.z_max_m - area.z_min_m),
        ]
    )
    clipped = np.clip(raw, -1.0, 1.0)
    return clipped, int(np.count_nonzero(np.abs(raw - clipped) > 1e-9))


def teacher_moves(
    here_m: np.ndarray, targets_m: np.ndarray, area: AreaConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Each UAV's discrete move (K,) toward its target (K, 3) from the zone it is in
    (:func:`sim.geometry.move_target`): the allowed move whose target lies nearest, ties to the
    lower move number ("stay" first); and the UAVs' move masks (K, 13)."""
    index = zone_indices(np.asarray(here_m, dtype=float), area)
    masks = move_masks(index, area)
    every = np.tile(np.arange(len(MOVES)), len(index))  # each UAV's 13 moves, in turn
    landing, _ = move_targets(every, np.repeat(here_m, len(MOVES), axis=0), area)
    gap = landing.reshape(len(index), len(MOVES), 3) - np.asarray(targets_m)[:, None, :]
    distance = np.where(masks, np.linalg.norm(gap, axis=2), np.inf)
    return np.argmin(distance, axis=1), masks


def _axes(element: int) -> tuple[list[int], np.ndarray]:
    """How symmetry ``element`` (:func:`symmetry`) turns a vector (x, y, z): its components
    reordered by the first, then multiplied by the second."""
    order = [1, 0, 2] if element & 4 else [0, 1, 2]
    return order, np.array([-1 if element & 1 else 1, -1 if element & 2 else 1, 1])


def _move_permutation(element: int) -> np.ndarray:
    """Move numbers (13,) under symmetry ``element``: move m becomes ``permutation[m]``."""
    order, signs = _axes(element)
    where = {tuple(step): m for m, step in enumerate(MOVES.tolist())}
    return np.array([where[tuple(step)] for step in (MOVES[:, order] * signs).tolist()])


_MOVE_PERMUTATIONS = th.as_tensor(np.stack([_move_permutation(e) for e in range(8)]))


def symmetry(
    observations: th.Tensor, actions: th.Tensor, element: int, masks: th.Tensor | None = None
) -> tuple[th.Tensor, ...]:
    """Observations (N, C, n_x, n_y) and actions under one symmetry of the square area,
    ``element`` 0–7 (bits: 4 swap x and y, 1 mirror x, 2 mirror y; 0 is the identity). Every
    map is a map of the area, so it turns as the area does. Residual actions (N, 3): their
    horizontal part turns with it and their altitude stays. Moves (N,) with their masks
    (N, 13), given as ``masks``: each move becomes the turned move, and the masks are permuted
    alike; returns ``(observations, moves, masks)`` then."""
    x = observations
    if element & 4:
        x = x.transpose(2, 3)
    if element & 1:
        x = x.flip(2)
    if element & 2:
        x = x.flip(3)
    if masks is not None:
        permutation = _MOVE_PERMUTATIONS[element].to(actions.device)
        turned = th.empty_like(masks)
        turned[:, permutation] = masks
        return x, permutation[actions], turned
    order, signs = _axes(element)
    return x, actions[:, order] * actions.new_tensor(signs.astype(np.float32))


def teacher_oracle(
    n_uavs: int, world: World, horizon_steps: int, teacher: str = "search"
) -> FleetOracle:
    """The fleet oracle with a teacher's search (:data:`TEACHERS`) over ``world``, scoring
    episodes of ``horizon_steps`` decisions."""
    if teacher not in TEACHERS:
        raise InputError(f"teacher: one of {', '.join(TEACHERS)}, got {teacher!r}")
    config = replace(
        FleetOracleConfig(episode_steps=horizon_steps, step_s=world.step_s),
        **TEACHERS[teacher],
    )
    return FleetOracle(
        fleet=FleetConfig(n_uavs=n_uavs),
        area=world.area,
        network=world.network,
        utility=world.utility,
        config=config,
    )


def _collect(
    args: tuple[
        int, World, ScenarioSampler, int, list[int], ImitationConfig, float | None, Path | None
    ],
) -> dict:
    """Teacher episodes ``indices`` of one run (a worker's share); ``radius_m`` None: moves;
    ``learner``: the checkpoint that flies (the teacher's own actions fly when None)."""
    n_uavs, world, sampler, seed, indices, imitation, radius_m, learner = args
    replan_every = imitation.replan_every
    env = FleetParallelEnv(n_uavs=n_uavs, action_kind="continuous", scenarios=sampler, world=world)
    oracle = teacher_oracle(n_uavs, world, imitation.horizon_steps, imitation.teacher)
    prior = KMeansPrior(world.area, env.fleet.separation_m)
    policy = None
    if learner is not None:
        policy = FleetCheckpointPolicy.load(
            learner, world.area, env.fleet.separation_m, world=world
        )
    observations, actions, episodes, masks = [], [], [], []
    clipped, calls = 0, 0
    for index in indices:
        obs, _ = env.reset(seed=_TEACHER_SEED_OFFSET + 1000 * seed + index)
        held: np.ndarray | None = None
        step = 0
        while env.agents:
            here = env.uav_xyz_m
            if held is None or step % replan_every == 0:
                users = ReportedUsers.of(env.reports)
                held = oracle.place_from(users, here, env.reported_association, world.flight)
                calls += 1
            targets = assign_targets(here, held)  # what the teacher's fleet flies
            seen = np.stack([obs[a] for a in env.possible_agents])
            observations.append(seen)
            episodes.append(np.full(n_uavs, index))
            if radius_m is None:  # each UAV's move toward its own target
                moves, mask = teacher_moves(here, targets, world.area)
                actions.append(moves)
                masks.append(mask)
                if policy is None:  # the teacher's fleet flies the moves, not the targets
                    targets, _ = move_targets(moves, here, world.area)
            else:
                priors = assign_targets(here, prior.place(env.reports, n_uavs))
                # Each prior's correction: the oracle target nearest it (the set matched to the
                # priors by least total distance), so a permutation is never learned as a move.
                matched = assign_targets(priors, held)
                action, n_clipped = teacher_actions(matched, priors, world, radius_m)
                clipped += n_clipped
                actions.append(action.astype(np.float32))
            if policy is not None:  # the learner flies; the teacher only labels
                targets = policy.targets(seen, env.reports, here, env.reported_association)
            obs, _, _, _, _ = env.step_to(targets)
            step += 1
    return {
        "observations": np.concatenate(observations).astype(np.float32),
        "actions": np.concatenate(actions),
        "episodes": np.concatenate(episodes),
        "masks": np.concatenate(masks) if masks else None,
        "clipped": clipped,
        "calls": calls,
    }


def collect_teacher_data(
    n_uavs: int,
    world: World,
    sampler: ScenarioSampler,
    imitation: ImitationConfig,
    radius_m: float | None,
    seed: int = 1,
    progress: bool = True,
    learner: Path | None = None,
    first_episode: int = 0,
) -> TeacherData:
    """Fly ``imitation.episodes`` teacher episodes (module doc), numbered from
    ``first_episode``, and return their decisions: residual actions within ``radius_m``, or
    moves when it is None. With a ``learner`` checkpoint the learner flies them and the teacher
    labels every state it visits (a DAgger round)."""
    n = imitation.episodes
    workers = min(imitation.workers, n)
    chunks = [
        list(range(first_episode + start, first_episode + n, workers * 4))
        for start in range(workers * 4)
    ]
    jobs = [
        (n_uavs, world, sampler, seed, chunk, imitation, radius_m, learner)
        for chunk in chunks
        if chunk
    ]
    who = "learner" if learner is not None else "teacher"
    bar = episode_bar(n, f"oracle {who} K={n_uavs}") if progress else None
    parts: list[dict] = []
    with contextlib.ExitStack() as stack:
        if workers == 1:
            results: Iterator[dict] = map(_collect, jobs)
        else:
            pool = stack.enter_context(mp.get_context("spawn").Pool(workers))
            results = pool.imap(_collect, jobs)
        for job, part in zip(jobs, results, strict=True):
            parts.append(part)
            if bar is not None:
                bar.update(len(job[4]))
    if bar is not None:
        bar.close()
    order = np.argsort(np.concatenate([p["episodes"] for p in parts]), kind="stable")
    return TeacherData(
        observations=np.concatenate([p["observations"] for p in parts])[order],
        actions=np.concatenate([p["actions"] for p in parts])[order],
        episodes=np.concatenate([p["episodes"] for p in parts])[order],
        clipped=sum(p["clipped"] for p in parts),
        oracle_calls=sum(p["calls"] for p in parts),
        masks=None if radius_m is not None else np.concatenate([p["masks"] for p in parts])[order],
    )


def fit_actor(
    model: Any, data: TeacherData, imitation: ImitationConfig, seed: int = 1,
    progress: bool = True,
) -> dict[str, Any]:  # fmt: skip
    """Fit ``model``'s network to the teacher's actions (module doc) and give its target network
    the same weights: a DDPG actor to residual actions (mean squared error), or a masked DDQN's
    Q-network to moves (cross-entropy over the allowed moves, its outputs read as the moves'
    logits, so the greedy move is the predicted one). Returns the fit's record: samples, epochs,
    the best epoch and its validation loss, and the loss of the zero action beside it (residual:
    the k-means prior) or the moves' validation accuracy beside "stay"'s."""
    rng = np.random.default_rng(seed)
    episodes = np.unique(data.episodes)
    n_valid = max(1, round(len(episodes) * imitation.validation_fraction))
    if len(episodes) < 2:
        raise InputError("imitation episodes: need at least 2 (one is held out for validation)")
    held_out = rng.choice(episodes, size=n_valid, replace=False)
    valid = np.isin(data.episodes, held_out)
    device = model.device
    x_fit = th.as_tensor(data.observations[~valid], device=device)
    y_fit = th.as_tensor(data.actions[~valid], device=device)
    x_val = th.as_tensor(data.observations[valid], device=device)
    y_val = th.as_tensor(data.actions[valid], device=device)
    if data.moves:
        network, target = model.q_net, model.q_net_target
        m_fit = th.as_tensor(data.masks[~valid], device=device)
        m_val = th.as_tensor(data.masks[valid], device=device)
    else:
        network, target = model.actor, model.actor_target
        m_fit = m_val = None

    def losses(x: th.Tensor, y: th.Tensor, m: th.Tensor | None) -> th.Tensor:
        """Per-sample losses of a batch."""
        out = network(x)
        if m is None:
            return th.mean((out - y) ** 2, dim=1)
        return th.nn.functional.cross_entropy(out.masked_fill(~m, -1e9), y, reduction="none")

    def validation() -> tuple[float, float]:
        """The validation loss and (moves) accuracy."""
        network.eval()
        total, right = [], 0
        with th.no_grad():
            for i in range(0, len(x_val), 1024):
                part = slice(i, i + 1024)
                m = None if m_val is None else m_val[part]
                total.append(losses(x_val[part], y_val[part], m))
                if m is not None:
                    picked = network(x_val[part]).masked_fill(~m, -th.inf).argmax(dim=1)
                    right += int((picked == y_val[part]).sum())
        return float(th.cat(total).mean()), right / max(1, len(x_val))

    optimizer = th.optim.Adam(network.parameters(), lr=imitation.learning_rate)
    generator = th.Generator().manual_seed(seed)
    n_x, n_y = data.observations.shape[2:]
    symmetric = imitation.symmetries and n_x == n_y  # swapping x and y needs a square grid
    error, accuracy = validation()
    best = (error, 0, {k: v.clone() for k, v in network.state_dict().items()}, accuracy)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=imitation.epochs, desc="imitation fit", unit="epoch", dynamic_ncols=True)
    for epoch in range(1, imitation.epochs + 1):
        network.train()
        order = th.randperm(len(x_fit), generator=generator)
        for i in range(0, len(order), imitation.batch_size):
            batch = order[i : i + imitation.batch_size]
            x, y = x_fit[batch], y_fit[batch]
            m = None if m_fit is None else m_fit[batch]
            if symmetric:
                element = int(th.randint(8, (1,), generator=generator))
                if m is None:
                    x, y = symmetry(x, y, element)
                else:
                    x, y, m = symmetry(x, y, element, m)
            loss = losses(x, y, m).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        error, accuracy = validation()
        if error < best[0]:
            best = (error, epoch, {k: v.clone() for k, v in network.state_dict().items()}, accuracy)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(validation_loss=f"{error:.4f}", best=f"{best[0]:.4f}")
    if bar is not None:
        bar.close()
    network.load_state_dict(best[2])
    target.load_state_dict(best[2])
    network.eval()
    record: dict[str, Any] = {
        "samples": len(data.actions),
        "fit_samples": int((~valid).sum()),
        "validation_samples": int(valid.sum()),
        "teacher_episodes": len(episodes),
        "oracle_calls": data.oracle_calls,
        "epochs": imitation.epochs,
        "symmetries": 8 if symmetric else 1,
        "best_epoch": best[1],
    }
    if data.moves:
        return {
            **record,
            "validation_cross_entropy": round(best[0], 6),
            "validation_accuracy": round(best[3], 4),
            "stay_validation_accuracy": round(float((y_val == 0).float().mean()), 4),
        }
    return {
        **record,
        "clipped_components": data.clipped,
        "validation_mse": round(best[0], 6),
        "zero_action_validation_mse": round(float(th.mean(y_val**2)), 6),
    }
