"""A vectorised environment for training: many episodes of one world stepping as one numpy batch.

:class:`FapVectorEnv` (a ``gymnasium.vector.VectorEnv``) runs ``num_envs`` independent episodes
of :class:`sim.envs.FapDiscreteEnv` (``kind="discrete"``) or :class:`sim.envs.FapContinuousEnv`
(``kind="continuous"``) in one :class:`sim.world.World`, with the same semantics, batched:

- ``reset`` places every vehicle at home and simulates one step there; ``step`` turns the E
  actions into targets (a move applies to the zone each vehicle is in, with one mask per
  environment), flies every vehicle toward its target, advances each environment's users (its
  own :class:`sim.users.UserDynamics` and generator, as the single environment's), simulates
  the cells with their queues carried over, and returns the utilities as rewards and the
  observations built from the report the world shows (report age) at each vehicle's position.
- With an envelope (:attr:`sim.world.World.envelope`), each vehicle flies its own route
  (:meth:`sim.world.World.fly_routes_period`: row e is the single environment's flight exactly).
- Flight, targets and masks are numpy over (E, 3) arrays (:meth:`sim.world.World.fly_period`,
  :func:`sim.geometry.move_targets`, :func:`sim.geometry.unit_to_m_many`,
  :func:`sim.geometry.valid_moves_many`): row e equals the scalar function exactly. The cells
  go through :meth:`sim.network.NetworkModel.step_many`, one call per user count (environments whose
  scenarios have different numbers of users are grouped by it), the utilities through
  :func:`sim.utility.network_utility` over (E, U), the observations through
  :func:`sim.observation.build_observations`.
- Every episode lasts ``world.episode_steps``: the environments run in lockstep, truncate
  together and reset together, at once (gymnasium 1.x's ``AutoresetMode.SAME_STEP``, declared
  in ``metadata``): the step that ends the episodes returns the new episodes' first
  observations and infos, the final ones in ``info["final_obs"]`` (an object array of E
  observations) and ``info["final_info"]`` (the final step's batched info), each with its
  ``"_final_obs"`` / ``"_final_info"`` mask, as ``SyncVectorEnv`` does.

Random numbers. ``reset(seed=s)`` gives environment e the generator the single environment's
``reset(seed=s + e)`` would have: it draws its scenarios (from a sampler), its users' seed
(moving users), its home (``home="random"``) and its report noise, in the single environment's
order. The rate manager's fading (stochastic mode) draws from one generator for the whole batch,
so stochastic episodes differ from the single environment's draw for draw; in expected mode
(``world.stochastic=False``) environment e gives exactly the rewards and observations of a
single environment reset with seed ``s + e`` (or the same scenario and ``users_seed``) and given
the same actions. A list of scenarios is cycled in order across the environments and episodes
(environment e takes the e-th of each round), like one :class:`sim.envs.ScenarioCycle`.

``info`` (batched, every key with its ``"_key"`` mask): ``scenario_id`` (object array),
``uav_xyz_m`` and ``target_xyz_m`` (E, 3), ``utility`` (E,) and, for the discrete kind,
``action_mask`` (E, 13) and ``refused_move`` (E,). Per-user metrics stay out of it (a training
step does not need them); :attr:`FapVectorEnv.users` and :attr:`FapVectorEnv.episode_scenarios`
hold each environment's users and scenario.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from sim.envs import ScenarioCycle, ScenarioSource
from sim.geometry import (
    MOVES,
    move_masks,
    move_targets,
    unit_to_m_many,
    zone_indices,
    zone_positions,
)
from sim.network import NetworkModel, QueueState
from sim.observation import build_observations, observation_shape
from sim.scenarios import Scenario, ScenarioSampler
from sim.users import UserDynamics
from sim.utility import network_utility
from sim.world import PAPER, World

if TYPE_CHECKING:
    from sim.envelope.route import Route

__all__ = [
    "KINDS",
    "FapVectorEnv",
]

KINDS: tuple[str, ...] = ("discrete", "continuous")
N_MOVES = len(MOVES)
# The spawn key of the batch's fading generator: a stream no environment's own seed gives.
_FADING_KEY = 0xFADE


# --------------------------------------------------------------------------------------------
# The vector environment


@dataclass
class _Group:
    """The environments whose scenarios have U users: one ``step_many`` call per step."""

    envs: np.ndarray  # (n,) environment numbers, ascending
    xy_m: np.ndarray  # (n, U, 2)
    load_bps: np.ndarray  # (n, U)
    reports: deque[tuple[np.ndarray, ...]]  # (x, y, offered, throughput, delay, plr), (n, U)
    rows: slice | np.ndarray  # where the group's rows go in (E, ...) arrays
    state: QueueState | None = None


class FapVectorEnv(VectorEnv):
    """``num_envs`` episodes of one world as one numpy batch (see the module doc)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int,
        kind: str = "discrete",
        scenarios: Sequence[Scenario] | ScenarioSource | None = None,
        world: World | Sequence[World] | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs: must be an integer >= 1, got {num_envs!r}")
        if kind not in KINDS:
            raise ValueError(f"kind: must be one of {', '.join(KINDS)}, got {kind!r}")
        if world is None:
            world = PAPER
        elif not isinstance(world, World):
            worlds = list(world)
            if len(worlds) != 1 or not isinstance(worlds[0], World):
                raise ValueError(
                    f"world: a vector environment runs one World, got {len(worlds)} worlds"
                )
            world = worlds[0]
        self.num_envs = int(num_envs)
        self.kind = kind
        self.world = world
        self.area = area = world.area
        if scenarios is None:
            scenarios = ScenarioSampler(area=area)
        elif not hasattr(scenarios, "sample"):
            scenarios = ScenarioCycle(scenarios)  # type: ignore[arg-type]
        self.scenarios: ScenarioSource = scenarios  # type: ignore[assignment]
        self.model = model or NetworkModel(world.network, area)
        self.single_observation_space = spaces.Box(
            0.0, 1.0, observation_shape(area), dtype=np.float32
        )
        self.single_action_space = (
            spaces.Discrete(N_MOVES)
            if kind == "discrete"
            else spaces.Box(0.0, 1.0, (3,), dtype=np.float32)
        )
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        # Per environment
        n = self.num_envs
        self.episode_scenarios: list[Scenario] = []
        self.users: list[UserDynamics] = []
        self.uav_xyz_m = np.zeros((n, 3))
        self.target_xyz_m = np.zeros((n, 3))
        self.uav_velocity_mps = np.zeros((n, 3))  # carried when the flight accelerates
        self._routes: list[Route | None] = [None] * n  # with an envelope: each one's route
        self._rngs: list[np.random.Generator] = []
        self._users_rngs: list[np.random.Generator] = []
        self._scenario_ids = np.full(n, None, dtype=object)
        self._index = np.zeros((n, 3), dtype=np.int64)
        self._mask = np.ones((n, N_MOVES), dtype=bool)
        self._refused = np.zeros(n, dtype=bool)
        self._groups: list[_Group] = []
        self._steps = 0
        self._started = False

    # -- gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode in every environment; see the module doc for ``seed``.

        ``options`` (this reset only): ``scenarios`` (E scenarios), ``users_seeds`` (E seeds of
        the users' generators), ``uav_xyz_m`` (E starts, metres), each replacing the draw."""
        if seed is not None or not self._rngs:
            seed = int(np.random.SeedSequence().generate_state(1)[0] if seed is None else seed)
            self._rngs = [seeding.np_random(seed + e)[0] for e in range(self.num_envs)]
            fading = np.random.SeedSequence(seed, spawn_key=(_FADING_KEY,))
            self._np_random = np.random.Generator(np.random.PCG64(fading))
            self._np_random_seed = seed
        return self._reset_all(options or {})

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if not self._started:
            raise RuntimeError("step() called before reset()")
        world = self.world
        previous_targets = self.target_xyz_m
        if self.kind == "discrete":
            moves = self._check_moves(actions)
            self.target_xyz_m, self._refused = move_targets(
                moves, self.uav_xyz_m, self.area, index=self._index
            )
        else:
            self.target_xyz_m = unit_to_m_many(self._check_coordinates(actions), self.area)
        if world.envelope is not None:  # the routes the vehicle link would stream
            self.uav_xyz_m, self.uav_velocity_mps, self._routes = world.fly_routes_period(
                self.uav_xyz_m, self.uav_velocity_mps, self.target_xyz_m, self._routes
            )
            self.target_xyz_m = np.array(
                [t if r.target_m is None else r.target_m for t, r in
                 zip(self.target_xyz_m, self._routes, strict=True)]
            )  # fmt: skip
        elif world.flight.teleports:
            self.uav_xyz_m = self.target_xyz_m.copy()
        else:  # velocities carried when the flight accelerates
            self.uav_xyz_m, self.uav_velocity_mps = world.fly_period(
                self.uav_xyz_m, self.uav_velocity_mps, previous_targets, self.target_xyz_m
            )
        self._moved()
        if world.users_change:
            for users, rng in zip(self.users, self._users_rngs, strict=True):
                users.advance(world.step_s, rng)
        rewards = self._simulate(refresh_users=world.users_change)
        self._steps += 1
        observations = self._observe()
        info = self._info(rewards)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.full(self.num_envs, self._steps >= world.episode_steps)
        if truncated[0]:  # every episode ends at once: reset them all in this step
            final_obs = np.empty(self.num_envs, dtype=object)
            for e, observation in enumerate(observations):
                final_obs[e] = observation  # row views of an array no later step reuses
            final_info = info
            observations, info = self._reset_all({})
            every = np.ones(self.num_envs, dtype=bool)
            info["final_obs"], info["_final_obs"] = final_obs, every
            info["final_info"], info["_final_info"] = final_info, every.copy()
        return observations, rewards, terminated, truncated, info

    def action_masks(self) -> np.ndarray:
        """Bool (E, 13): the moves each vehicle may take from the zone it is in (discrete)."""
        if self.kind != "discrete":
            raise AttributeError("action_masks: the continuous kind has no moves to mask")
        return self._mask.copy()

    # -- helpers -----------------------------------------------------------------------------
    def _reset_all(self, options: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode in every environment (each one's draws from its own generator)."""
        world, area, n = self.world, self.area, self.num_envs
        chosen = {
            name: _option(options, name, n) for name in ("scenarios", "users_seeds", "uav_xyz_m")
        }
        starts = np.empty((n, 3))
        self.episode_scenarios, self.users, self._users_rngs = [], [], []
        for e, rng in enumerate(self._rngs):
            # The single environment's reset, in its order of draws.
            scenario = chosen["scenarios"][e] if chosen["scenarios"] else None
            if scenario is None:
                scenario = self.scenarios.sample(rng)
            users_seed = chosen["users_seeds"][e] if chosen["users_seeds"] else None
            if users_seed is None:
                users_seed = int(rng.integers(2**63 - 1)) if world.users_change else 0
            users_rng = np.random.default_rng(users_seed)
            users = UserDynamics(
                scenario.users_xy_m, scenario.load_bps, world.mobility, world.demand, area,
                users_rng,
            )  # fmt: skip
            self.users.append(users)
            self._users_rngs.append(users_rng)
            self.episode_scenarios.append(scenario)
            start = chosen["uav_xyz_m"][e] if chosen["uav_xyz_m"] is not None else None
            starts[e] = world.home_position(rng) if start is None else start
        self._scenario_ids = np.empty(n, dtype=object)
        self._scenario_ids[:] = [s.id for s in self.episode_scenarios]
        starts = np.clip(
            starts, [0.0, 0.0, area.z_min_m], [area.size_x_m, area.size_y_m, area.z_max_m]
        )
        if self.kind == "discrete":  # starts are zone points, as the discrete env's
            starts = zone_positions(zone_indices(starts, area), area)
        if world.envelope is not None:  # legal starts, as the single environment's
            starts = np.array([world.legal_start(start) for start in starts])
        self.uav_xyz_m = starts
        self.uav_velocity_mps = np.zeros((n, 3))
        self._routes = [None] * n
        self.target_xyz_m = starts.copy()
        self._refused = np.zeros(n, dtype=bool)
        self._steps = 0
        self._moved()
        self._group_by_users()
        self._started = True
        rewards = self._simulate(refresh_users=False)
        return self._observe(), self._info(rewards)

    def _group_by_users(self) -> None:
        counts = np.array([len(users.load_bps) for users in self.users])
        self._groups = []
        for n_users in np.unique(counts):
            envs = np.flatnonzero(counts == n_users)
            self._groups.append(
                _Group(
                    envs=envs,
                    xy_m=np.stack([self.users[e].xy_m for e in envs]),
                    load_bps=np.stack([self.users[e].load_bps for e in envs]),
                    reports=deque(maxlen=self.world.reports.age_steps + 1),
                    rows=slice(None) if len(envs) == self.num_envs else envs,
                )
            )

    def _moved(self) -> None:
        """The vehicles are somewhere new: their zones (and, discrete, their move masks)."""
        if self.kind == "discrete":
            self._index = zone_indices(self.uav_xyz_m, self.area)
            self._mask = move_masks(self._index, self.area)

    def _simulate(self, refresh_users: bool) -> np.ndarray:
        """One step of every cell (queues carried over); the utilities (E,), the reports kept."""
        world = self.world
        rng = self.np_random if world.stochastic else None
        rewards = np.empty(self.num_envs)
        noise_m = world.reports.position_noise_m
        upper = [self.area.size_x_m, self.area.size_y_m]
        for group in self._groups:
            if refresh_users:
                group.xy_m = np.stack([self.users[e].xy_m for e in group.envs])
                group.load_bps = np.stack([self.users[e].load_bps for e in group.envs])
            result = self.model.step_many(
                self.uav_xyz_m[group.rows], group.xy_m, group.load_bps, group.state, rng,
                world.step_s,
            )  # fmt: skip
            group.state = result.state
            rewards[group.rows] = network_utility(
                result.throughput_bps, result.delay_s, result.plr, group.load_bps, world.utility
            )
            xy = group.xy_m
            if noise_m > 0:  # each environment's own draws, as the single env's
                noise = np.stack(
                    [self._rngs[e].normal(0.0, noise_m, xy.shape[1:]) for e in group.envs]
                )
                xy = np.clip(xy + noise, 0.0, upper)
            group.reports.append(
                (
                    np.ascontiguousarray(xy[..., 0]),
                    np.ascontiguousarray(xy[..., 1]),
                    group.load_bps,
                    result.throughput_bps,
                    result.delay_s,
                    result.plr,
                )
            )
        return rewards

    def _observe(self) -> np.ndarray:
        """Observations (E, 6, n_x, n_y) from the report each group's report age shows."""
        delay_ref_s = self.world.utility.delay_ref_s
        if len(self._groups) == 1:
            group = self._groups[0]
            return build_observations(self.uav_xyz_m, *group.reports[0], self.area, delay_ref_s)
        out = np.empty(self.observation_space.shape, dtype=np.float32)
        for group in self._groups:
            out[group.rows] = build_observations(
                self.uav_xyz_m[group.rows], *group.reports[0], self.area, delay_ref_s
            )
        return out

    def _info(self, rewards: np.ndarray) -> dict[str, Any]:
        n = self.num_envs
        info: dict[str, Any] = {
            "scenario_id": self._scenario_ids.copy(),
            "uav_xyz_m": self.uav_xyz_m.copy(),
            "target_xyz_m": self.target_xyz_m.copy(),
            "utility": rewards.copy(),
        }
        if self.kind == "discrete":
            info["action_mask"] = self._mask.copy()
            info["refused_move"] = self._refused.copy()
        for key in list(info):
            info[f"_{key}"] = np.ones(n, dtype=bool)
        return info

    def _check_moves(self, actions: Any) -> np.ndarray:
        n, top = self.num_envs, N_MOVES - 1
        moves = np.asarray(actions)
        if moves.shape == (n, 1):
            moves = moves.reshape(n)
        if moves.shape != (n,) or moves.dtype.kind not in "iu":
            raise ValueError(
                f"action: must be {n} integers in [0, {top}] (one per environment), "
                f"got {_describe(actions, moves)}"
            )
        bad = (moves < 0) | (moves > top)
        if bad.any():
            e = int(np.argmax(bad))
            raise ValueError(
                f"action: environment {e}: must be an integer in [0, {top}], got {moves[e]}"
            )
        return moves

    def _check_coordinates(self, actions: Any) -> np.ndarray:
        n = self.num_envs
        try:
            a = np.asarray(actions, dtype=float)
        except (TypeError, ValueError):
            a = np.empty(0)
        if a.shape != (n, 3):
            raise ValueError(
                f"action: must be {n} rows of 3 numbers in [0, 1] (one per environment), "
                f"got {_describe(actions, a)}"
            )
        bad = ~np.isfinite(a).all(axis=1) | (a < -1e-6).any(axis=1) | (a > 1.0 + 1e-6).any(axis=1)
        if bad.any():
            e = int(np.argmax(bad))
            raise ValueError(
                f"action: environment {e}: coordinates must be finite and lie in [0, 1], "
                f"got {a[e].tolist()}"
            )
        return a


def _option(options: dict[str, Any], name: str, n: int) -> Any:
    """A per-environment reset option: None, or ``n`` values (an (n, 3) array for starts)."""
    value = options.get(name)
    if value is None:
        return None
    if name == "uav_xyz_m":
        array = np.asarray(value, dtype=float)
        if array.shape != (n, 3) or not np.isfinite(array).all():
            raise ValueError(f"options: uav_xyz_m must be {n} finite (x, y, z) rows, metres")
        return array
    values = list(value)
    if len(values) != n:
        raise ValueError(f"options: {name} must hold one value per environment ({n})")
    return values


def _describe(actions: Any, array: np.ndarray) -> str:
    """A short, one-line account of a bad action batch."""
    if array.size <= 8:
        text = repr(actions).replace("\n", " ")
        return text if len(text) <= 120 else text[:117] + "..."
    return f"shape {array.shape}, dtype {array.dtype}"
