"""Environments for a fleet of UAVs: a PettingZoo ``ParallelEnv`` (one agent per UAV) and a
Gymnasium wrapper with the joint observation and action (centralised training).

The world is the single-UAV environments' (:mod:`sim.envs`): a :class:`sim.world.World` gives
the decision period, the episode's length, where the vehicles start, how they fly
(:func:`sim.flight.fly`), how users move and change their demand
(:class:`sim.users.UserDynamics`), how old and how noisy the report a decision sees is; the
network is the fleet model (:class:`sim.fleet.FleetModel`: K access points, association with
hysteresis, handovers, distinct or shared channels). One step:

1. each agent's action becomes its vehicle's target, as in the single environments: one of the
   13 discrete moves from the zone the vehicle is in (:func:`sim.geometry.move_target`; moves
   that leave the volume are masked, ``info["action_mask"]``, :meth:`FleetParallelEnv.
   action_masks`), or absolute coordinates in ``[0, 1]³`` (:func:`sim.geometry.unit_to_m`);
2. the set of targets is separated (:func:`sim.geometry.enforce_separation`, the fleet's
   ``separation_m``, lower agent index first) — the hard constraint; a vehicle whose flight to
   its target would come closer than the separation to another's holds where it is for this
   decision, as the service holds it (:func:`sim.fleet_targets.hold_crossing_paths`, the one
   rule; ``info["path_holds"]`` counts them); the vehicles fly toward their targets; a vehicle
   that would end the period too close to another anyway goes round it, or holds where it was
   when no detour is clear (:func:`sim.geometry.hold_separation`). In a
   world with an envelope the targets are also made legal, each vehicle flies the route the
   service's link would stream, and a vehicle whose *path* would pass closer than the
   separation to another's holds for the period, lower indices flying first
   (:func:`sim.envelope.flight.fly_fleet`; ``held`` says which);
3. users move; the fleet model simulates the period (queues and associations carried over);
4. every agent gets the same reward, the network utility over all users (cooperative).

**Observation** of agent k, float32 ``(9, n_zones_x, n_zones_y)`` in [0, 1]: the single-UAV
builder's six maps at its own position (:func:`sim.observation.build_observation`, the report
the world lets the decision see), then three more, complemented (1 − value) like the paper's:

6. other UAVs in the zone, over K − 1 (all ones for K = 1);
7. users in the zone that k serves (associated with its AP), over the number of users;
8. users in the zone that another UAV serves, over the number of users.

The channels do not depend on K, so one network (parameters shared across agents) can fly any
fleet. The association shown is the one of the report the decision sees.
:func:`sim.fleet_observation.fleet_observations` builds it (training, evaluation and serving).

``info`` of every agent: its position, target, the action mask and refused move (discrete),
its own UAV utility, and the fleet's utility, served-user fraction, Jain fairness, minimum
user throughput, and the handovers and path holds so far. ``reset(options=...)`` takes ``scenario``,
``users_seed`` and ``uav_xyz_m`` (K, 3) as the single environments do.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from sim.envs import ScenarioCycle, ScenariosByEnvironment
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel, FleetState, FleetStepResult
from sim.fleet_observation import FLEET_MAPS, fleet_maps, fleet_observations
from sim.fleet_targets import hold_crossing_paths
from sim.geometry import (
    MOVES,
    clip_to_volume,
    enforce_separation,
    hold_separation,
    move_mask,
    move_masks,
    move_targets,
    unit_to_m_many,
    zone_index,
    zone_indices,
    zone_position,
)
from sim.observation import UserReports
from sim.scenarios import Scenario, ScenarioSampler
from sim.users import UserDynamics, episode_users
from sim.world import World, episode_worlds

if TYPE_CHECKING:
    from sim.envelope.route import Route

__all__ = [
    "ACTION_KINDS",
    "FLEET_CONTINUOUS_ENV_ID",
    "FLEET_DISCRETE_ENV_ID",
    "FLEET_MAPS",
    "FleetContinuousGymEnv",
    "FleetDiscreteGymEnv",
    "FleetGymEnv",
    "FleetParallelEnv",
    "fleet_homes",
    "fleet_maps",
    "fleet_observations",
    "parallel_env",
]

FLEET_DISCRETE_ENV_ID = "tupa/FleetDiscrete-v0"
FLEET_CONTINUOUS_ENV_ID = "tupa/FleetContinuous-v0"
ACTION_KINDS: tuple[str, ...] = ("discrete", "continuous")


def fleet_homes(
    world: World, n_uavs: int, separation_m: float, rng: np.random.Generator | None = None
) -> np.ndarray:
    """Where K vehicles start (K, 3): the world's home for the first, the next ones one zone
    east, west, two east, ... of it (clipped into the volume), then separated.

    With ``home="random"`` each vehicle draws its own zone. Deterministic given ``rng``."""
    area = world.area
    if world.home == "random":
        starts = np.stack([world.home_position(rng) for _ in range(n_uavs)])
    else:
        base = world.home_position(rng)
        shifts = [0] + [s for j in range(1, n_uavs) for s in (j, -j)]
        starts = np.stack(
            [base + np.array([shifts[k] * area.zone_m, 0.0, 0.0]) for k in range(n_uavs)]
        )
    return enforce_separation(clip_to_volume(starts, area), separation_m, world.area)


class FleetParallelEnv(ParallelEnv):
    """K UAVs, one agent each, one shared reward; see the module doc.

    ``n_uavs`` (1..8) or ``fleet`` (a :class:`sim.fleet.FleetConfig`: channels, separation,
    hysteresis, handover outage) say how many; 3 when neither does. ``action_kind`` is
    ``discrete`` (13 moves) or ``continuous`` (coordinates in [0, 1]³). ``scenarios``: a list
    cycled in order or a sampler (:class:`sim.scenarios.ScenarioSampler` by default; a
    :class:`sim.envs.ScenariosByEnvironment` gives each episode its world's environment's);
    ``world`` a :class:`sim.world.World` (``paper`` by default) or a list of them that share
    the area and differ in their channel environment, one drawn for each episode as the single
    environments draw it (:func:`sim.world.episode_worlds`)."""

    metadata = {"name": "tupa_fleet_v0", "render_modes": [], "is_parallelizable": True}  # noqa: RUF012
    render_mode = None  # nothing to render (PettingZoo's wrappers and SuperSuit read it)

    def __init__(
        self,
        n_uavs: int | None = None,
        action_kind: str = "discrete",
        scenarios: Sequence[Scenario] | Any | None = None,
        world: World | Sequence[World] | None = None,
        fleet: FleetConfig | None = None,
        model: FleetModel | None = None,
    ) -> None:
        if action_kind not in ACTION_KINDS:
            raise InputError(
                f"action_kind: must be one of {', '.join(ACTION_KINDS)}, got {action_kind!r}"
            )
        if fleet is None:
            fleet = FleetConfig(n_uavs=3 if n_uavs is None else n_uavs)
        elif n_uavs is not None and n_uavs != fleet.n_uavs:
            raise InputError(f"n_uavs: {n_uavs!r} disagrees with the fleet's {fleet.n_uavs}")
        self.fleet = fleet
        self.worlds = episode_worlds(world)
        self.world = self.worlds[0]
        self.area = self.world.area
        self.action_kind = action_kind
        if model is None:
            model = FleetModel(fleet, self.world.network, self.area, self.world.utility)
        elif model.fleet != fleet or model.area != self.area:
            raise ValueError("model: must be built for this fleet and the world's area")
        # One fleet model per channel environment: an episode runs in its world's.
        self._models = {self.area.environment: model}
        for w in self.worlds[1:]:
            if w.area.environment not in self._models:
                self._models[w.area.environment] = FleetModel(fleet, w.network, w.area, w.utility)
        self.model = model
        if scenarios is None:
            scenarios = ScenarioSampler(area=self.area)
        elif not hasattr(scenarios, "sample"):
            scenarios = ScenarioCycle(scenarios)
        self.scenarios = scenarios
        self.possible_agents = [f"uav_{k}" for k in range(fleet.n_uavs)]
        self.agents: list[str] = []
        self._obs_space = spaces.Box(
            0.0, 1.0, (FLEET_MAPS, self.area.n_zones_x, self.area.n_zones_y), dtype=np.float32
        )
        if action_kind == "discrete":
            self._act_space: spaces.Space = spaces.Discrete(len(MOVES))
        else:
            self._act_space = spaces.Box(0.0, 1.0, (3,), dtype=np.float32)
        self.np_random, _ = seeding.np_random(None)
        self.scenario: Scenario | None = None
        self.users: UserDynamics | None = None
        self.uav_xyz_m = np.zeros((fleet.n_uavs, 3))
        self.target_xyz_m = np.zeros((fleet.n_uavs, 3))
        self.uav_velocity_mps = np.zeros((fleet.n_uavs, 3))  # when the flight accelerates
        self._routes: list[Route | None] = [None] * fleet.n_uavs  # with an envelope
        self.held = np.zeros(fleet.n_uavs, dtype=bool)
        """With an envelope: which vehicles held in the last step for the separation."""
        self._state: FleetState | None = None
        self._reports: deque[tuple[UserReports, np.ndarray]] = deque(maxlen=1)
        self._users_rng = np.random.default_rng(0)
        self._steps = 0
        self._path_holds = 0
        self._refused = np.zeros(fleet.n_uavs, dtype=bool)
        self._index = np.zeros((fleet.n_uavs, 3), dtype=np.int64)
        self.last_result: FleetStepResult | None = None

    # -- spaces ------------------------------------------------------------------------------
    def observation_space(self, agent: str) -> spaces.Space:
        """The same space object for every agent (PettingZoo asks for one object per agent)."""
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space:
        return self._act_space

    @property
    def n_uavs(self) -> int:
        return self.fleet.n_uavs

    # -- PettingZoo API ----------------------------------------------------------------------
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
            for k, agent in enumerate(self.possible_agents):
                self.action_space(agent).seed(seed + k)
        options = options or {}
        rng = self.np_random
        if len(self.worlds) > 1:
            self.world = self.worlds[int(rng.integers(len(self.worlds)))]
            self.area = self.world.area
            self.model = self._models[self.area.environment]
        world = self.world
        source = self.scenarios
        if isinstance(source, ScenariosByEnvironment):
            source = source.of(self.area.environment)
        self.scenario = options.get("scenario") or source.sample(rng)
        self.users, self._users_rng = episode_users(
            self.scenario.users_xy_m, self.scenario.load_bps, world, self.area, rng,
            options.get("users_seed"),
        )  # fmt: skip
        self._state = None
        self._steps = 0
        self._path_holds = 0
        self._refused = np.zeros(self.n_uavs, dtype=bool)
        self._reports = deque(maxlen=world.reports.age_steps + 1)
        start = options.get("uav_xyz_m")
        if start is not None:
            start = np.asarray(start, dtype=float)
            if start.shape != (self.n_uavs, 3) or not np.all(np.isfinite(start)):
                raise InputError(
                    f"uav_xyz_m: must be ({self.n_uavs}, 3) finite positions, got {start.shape}"
                )
            start = clip_to_volume(start, self.area)
            if self.action_kind == "discrete":
                start = np.stack(
                    [zone_position(zone_index(p, self.area), self.area) for p in start]
                )
            start = enforce_separation(start, self.fleet.separation_m, self.area)
        else:
            start = fleet_homes(world, self.n_uavs, self.fleet.separation_m, rng)
        if world.envelope is not None:
            from sim.envelope.flight import separated_legal_targets

            start = separated_legal_targets(
                world.flight_envelope, start, self.fleet.separation_m, self.area, search=True
            )
        self.uav_xyz_m = start
        self.uav_velocity_mps = np.zeros((self.n_uavs, 3))
        self._routes = [None] * self.n_uavs
        self.held = np.zeros(self.n_uavs, dtype=bool)
        self.target_xyz_m = start.copy()
        self._moved()
        self.agents = list(self.possible_agents)
        result = self._simulate()
        observations = self._observe(result)
        return observations, self._infos(result)

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        if not self.agents:
            raise RuntimeError("step() called before reset() or after the episode ended")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: no action for {', '.join(missing)}")
        chosen = [self._check_action(actions[agent]) for agent in self.possible_agents]
        if self.action_kind == "discrete":
            targets, self._refused = move_targets(
                np.array(chosen), self.uav_xyz_m, self.area, self._index
            )
        else:
            targets = unit_to_m_many(np.array(chosen), self.area)
        return self._step_toward(targets)

    def step_to(self, targets_m: Any) -> tuple[dict, dict, dict, dict, dict]:
        """:meth:`step` with targets (K, 3) in metres (what a placement re-placed every
        decision feeds the environment); clipped into the volume, then separated."""
        if not self.agents:
            raise RuntimeError("step_to() called before reset() or after the episode ended")
        targets = np.asarray(targets_m, dtype=float)
        if targets.shape != (self.n_uavs, 3) or not np.all(np.isfinite(targets)):
            raise ValueError(
                f"targets_m: must be ({self.n_uavs}, 3) finite numbers, got shape {targets.shape}"
            )
        self._refused = np.zeros(self.n_uavs, dtype=bool)
        return self._step_toward(clip_to_volume(targets, self.area))

    def action_masks(self) -> dict[str, np.ndarray]:
        """Each agent's mask of the moves that keep its target inside the volume."""
        return {agent: self._mask(k) for k, agent in enumerate(self.possible_agents)}

    def state(self) -> np.ndarray:
        """The joint observation (K, 9, n_x, n_y) of the report the decision sees."""
        return self._joint_observation()

    def close(self) -> None:
        pass

    # -- helpers ------------------------------------------------------------------------------
    def _mask(self, k: int) -> np.ndarray:
        return move_mask(self._index[k], self.area)

    def _moved(self) -> None:
        """The vehicles are somewhere new: their zones (the discrete moves start there)."""
        self._index = zone_indices(self.uav_xyz_m, self.area)

    def _check_action(self, action: Any) -> Any:
        """One agent's action, checked: a move number, or coordinates (3,) in [0, 1]."""
        if self.action_kind == "discrete":
            if isinstance(action, np.ndarray) and action.shape in ((), (1,)):
                action = action.reshape(()).item()
            if (
                isinstance(action, bool | np.bool_)
                or not isinstance(action, int | np.integer)
                or not 0 <= action < len(MOVES)
            ):
                raise ValueError(
                    f"action: must be an integer in [0, {len(MOVES) - 1}], got {action!r}"
                )
            return int(action)
        a = np.asarray(action, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be 3 finite numbers in [0, 1], got {action!r}")
        if np.any(a < -1e-6) or np.any(a > 1.0 + 1e-6):
            raise ValueError(f"action: coordinates must lie in [0, 1], got {a.tolist()}")
        return a

    def _step_toward(self, targets: np.ndarray) -> tuple[dict, dict, dict, dict, dict]:
        world = self.world
        sep = self.fleet.separation_m
        previous_targets = self.target_xyz_m
        if world.envelope is None:
            separated = enforce_separation(targets, sep, self.area)
            self.target_xyz_m = self._hold_crossing_paths(separated, None)
            # The single environment's flight, every vehicle at once (world.fly_period).
            flown, self.uav_velocity_mps = world.fly_period(
                self.uav_xyz_m, self.uav_velocity_mps, previous_targets, self.target_xyz_m
            )
            self.uav_xyz_m = hold_separation(self.uav_xyz_m, flown, sep, self.area)
            # A vehicle held or sent round another stops there (a stand-in, as the hold is).
            self.uav_velocity_mps[np.any(self.uav_xyz_m != flown, axis=1)] = 0.0
        else:
            self._fly_routes(targets)
        self._moved()
        assert self.users is not None
        self.users.advance(world.step_s, self._users_rng)
        result = self._simulate()
        self._steps += 1
        reward = float(result.utility[0])
        truncated = self._steps >= world.episode_steps
        observations = self._observe(result)
        infos = self._infos(result)
        agents = self.agents
        rewards = dict.fromkeys(agents, reward)
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, truncated)
        if truncated:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _fly_routes(self, targets: np.ndarray) -> None:
        """With an envelope: legal, separated targets, each vehicle along the route the link
        would stream, a vehicle whose path would pass too close to another's held for the
        period (:func:`sim.envelope.flight.fly_fleet`)."""
        from sim.envelope.flight import fly_fleet, separated_legal_targets

        world = self.world
        envelope = world.flight_envelope
        sep = self.fleet.separation_m
        legal = separated_legal_targets(envelope, targets, sep, self.area)
        self.target_xyz_m = self._hold_crossing_paths(legal, envelope)
        flight = fly_fleet(
            envelope, self.uav_xyz_m, self.target_xyz_m, world.flight, world.step_s, sep,
            self._routes, self.uav_velocity_mps,
        )  # fmt: skip
        self.uav_xyz_m = flight.positions_m
        if flight.velocities_mps is not None:
            self.uav_velocity_mps = flight.velocities_mps
        self._routes = list(flight.routes)
        self.held = np.array(flight.held, dtype=bool)

    def _hold_crossing_paths(self, targets: np.ndarray, envelope: Any) -> np.ndarray:
        """The decision's targets with each vehicle whose flight there would come too close to
        another's held where it is, as the service holds it
        (:func:`sim.fleet_targets.hold_crossing_paths`; counted in ``info["path_holds"]``)."""
        holds = hold_crossing_paths(
            [envelope] * self.n_uavs, self.uav_xyz_m, targets, self.world.flight,
            self.fleet.separation_m, self.area,
        )  # fmt: skip
        self._path_holds += sum(holds.held)
        return holds.targets_m

    def _simulate(self) -> FleetStepResult:
        users = self.users
        assert users is not None
        result = self.model.step(
            self.uav_xyz_m,
            users.xy_m,
            users.load_bps,
            self._state,
            self.np_random if self.world.stochastic else None,
            self.world.step_s,
        )
        self._state = result.state
        self.last_result = result
        return result

    def _observe(self, result: FleetStepResult) -> dict[str, np.ndarray]:
        users = self.users
        assert users is not None
        xy = users.xy_m
        noise_m = self.world.reports.position_noise_m
        if noise_m > 0:
            upper = [self.area.size_x_m, self.area.size_y_m]
            xy = np.clip(xy + self.np_random.normal(0.0, noise_m, xy.shape), 0.0, upper)
        report = UserReports(
            xy[:, 0],
            xy[:, 1],
            users.load_bps,
            result.throughput_bps[0],
            result.delay_s[0],
            result.plr[0],
        )
        self._reports.append((report, result.association[0]))
        joint = self._joint_observation()
        return {agent: joint[k] for k, agent in enumerate(self.agents)}

    def _joint_observation(self) -> np.ndarray:
        report, association = self._reports[0]
        return fleet_observations(self.uav_xyz_m, report, association, self.world)

    @property
    def reports(self) -> UserReports:
        """The report the decision sees now (the oldest the world's report age keeps)."""
        return self._reports[0][0]

    @property
    def reported_association(self) -> np.ndarray:
        """The users' APs (U,) in the report the decision sees now."""
        return self._reports[0][1]

    def _infos(self, result: FleetStepResult) -> dict[str, dict[str, Any]]:
        common = {
            "utility": float(result.utility[0]),
            "served_fraction": float(result.served_fraction[0]),
            "jain_fairness": float(result.jain_fairness[0]),
            "min_throughput_bps": float(result.min_throughput_bps[0]),
            "handovers": int(result.handovers[0]),
            "path_holds": self._path_holds,
            "scenario_id": self.scenario.id if self.scenario is not None else "",
        }
        infos = {}
        served = np.bincount(result.association[0], minlength=self.n_uavs).tolist()
        uav_utility = result.uav_utility[0].tolist()
        discrete = self.action_kind == "discrete"
        if discrete:
            # int8, PettingZoo's convention (Gymnasium samples with int8 masks); a fresh array.
            masks = move_masks(self._index, self.area).astype(np.int8)
            refused = self._refused.tolist()
        for k, agent in enumerate(self.agents):
            info = dict(common)
            info["uav_xyz_m"] = self.uav_xyz_m[k].copy()
            info["target_xyz_m"] = self.target_xyz_m[k].copy()
            info["uav_utility"] = uav_utility[k]
            info["users_served"] = served[k]
            if discrete:
                info["action_mask"] = masks[k]
                info["refused_move"] = refused[k]
            infos[agent] = info
        self._refused = np.zeros(self.n_uavs, dtype=bool)
        return infos


def parallel_env(**kwargs: Any) -> FleetParallelEnv:
    """PettingZoo's conventional constructor: ``parallel_env(n_uavs=3, action_kind=...)``."""
    return FleetParallelEnv(**kwargs)


class FleetGymEnv(gym.Env):
    """The fleet as one Gymnasium agent (centralised training): the joint observation
    ``(K, 9, n_x, n_y)``, the joint action (``MultiDiscrete([13] * K)`` or ``Box(0, 1, (K,
    3))``), the shared reward. ``action_masks()`` is the K masks concatenated (K·13,), the
    layout sb3-contrib's maskable algorithms take for a MultiDiscrete space. ``info`` holds the
    fleet's metrics, every vehicle's position, the per-user metrics and associations."""

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(
        self,
        n_uavs: int | None = None,
        action_kind: str = "discrete",
        scenarios: Sequence[Scenario] | Any | None = None,
        world: World | Sequence[World] | None = None,
        fleet: FleetConfig | None = None,
        model: FleetModel | None = None,
    ) -> None:
        self.fleet_env = FleetParallelEnv(n_uavs, action_kind, scenarios, world, fleet, model)
        env = self.fleet_env
        k = env.n_uavs
        self.observation_space = spaces.Box(
            0.0, 1.0, (k, *env.observation_space(env.possible_agents[0]).shape), dtype=np.float32
        )
        if action_kind == "discrete":
            self.action_space = spaces.MultiDiscrete([len(MOVES)] * k)
        else:
            self.action_space = spaces.Box(0.0, 1.0, (k, 3), dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        env = self.fleet_env
        # The fleet env draws from its own generator, seeded from this one's every episode:
        # deterministic given the seed of the first reset.
        sub_seed = int(self.np_random.integers(2**31 - 1))
        observations, _ = env.reset(seed=sub_seed, options=options)
        return self._stack(observations), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        env = self.fleet_env
        a = np.asarray(action)
        if a.shape[:1] != (env.n_uavs,):
            raise ValueError(f"action: must hold one action per UAV ({env.n_uavs}), got {a.shape}")
        actions = {agent: a[k] for k, agent in enumerate(env.possible_agents)}
        observations, rewards, _, truncations, _ = env.step(actions)
        reward = rewards[env.possible_agents[0]]
        truncated = truncations[env.possible_agents[0]]
        return self._stack(observations), reward, False, truncated, self._info()

    def step_to(self, targets_m: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """:meth:`FleetParallelEnv.step_to` through the joint interface."""
        env = self.fleet_env
        observations, rewards, _, truncations, _ = env.step_to(targets_m)
        agent = env.possible_agents[0]
        return self._stack(observations), rewards[agent], False, truncations[agent], self._info()

    def action_masks(self) -> np.ndarray:
        masks = self.fleet_env.action_masks()
        return np.concatenate([masks[a] for a in self.fleet_env.possible_agents])

    def _stack(self, observations: dict[str, np.ndarray]) -> np.ndarray:
        if len(observations) == self.fleet_env.n_uavs:
            return np.stack([observations[a] for a in self.fleet_env.possible_agents])
        return self.fleet_env.state()

    def _info(self) -> dict[str, Any]:
        env = self.fleet_env
        result = env.last_result
        assert result is not None
        info: dict[str, Any] = {
            "utility": float(result.utility[0]),
            "uav_utility": result.uav_utility[0].copy(),
            "served_fraction": float(result.served_fraction[0]),
            "jain_fairness": float(result.jain_fairness[0]),
            "min_throughput_bps": float(result.min_throughput_bps[0]),
            "handovers": int(result.handovers[0]),
            "uav_xyz_m": env.uav_xyz_m.copy(),
            "target_xyz_m": env.target_xyz_m.copy(),
            "association": result.association[0].copy(),
            "throughput_bps": result.throughput_bps[0].copy(),
            "delay_s": result.delay_s[0].copy(),
            "plr": result.plr[0].copy(),
        }
        if env.action_kind == "discrete":
            info["action_mask"] = self.action_masks()
        return info


class FleetDiscreteGymEnv(FleetGymEnv):
    """:class:`FleetGymEnv` with the 13 discrete moves per UAV (``tupa/FleetDiscrete-v0``)."""

    def __init__(self, n_uavs: int | None = None, **kwargs: Any) -> None:
        super().__init__(n_uavs, "discrete", **kwargs)


class FleetContinuousGymEnv(FleetGymEnv):
    """:class:`FleetGymEnv` with absolute coordinates per UAV (``tupa/FleetContinuous-v0``)."""

    def __init__(self, n_uavs: int | None = None, **kwargs: Any) -> None:
        super().__init__(n_uavs, "continuous", **kwargs)
