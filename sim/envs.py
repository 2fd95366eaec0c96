"""Gymnasium environments: a UAV carrying a Wi-Fi access point over one scenario per episode.

``tupa/FapDiscrete-v0``   13 moves on the zone grid (stay; ±1 or ±5 zones along x, y, z), taken
                          from the zone the vehicle is in (:func:`sim.geometry.move_target`); moves
                          that would leave the volume are masked (``action_masks()``,
                          ``info["action_mask"]``); one taken anyway targets the vehicle's own
                          zone and sets ``info["refused_move"]``.
``tupa/FapContinuous-v0`` ``Box(0, 1, (3,))``: absolute coordinates in the volume
                          (:func:`sim.geometry.unit_to_m`).

Everything about the episode but the scenario comes from a :class:`sim.world.World` (the
``paper`` preset by default): ``episode_steps`` steps of ``step_s``, the vehicle's start
(``home``), its flight toward each step's target (none under the paper's protocol: it is there at
once), users that move and change their demand, and how old the report the decision sees is. A
step: the action becomes the target, the vehicle flies toward it for ``step_s``, the users move,
the network is simulated at the vehicle's new position (queues carried over from the previous
step), the reward is that step's network utility, and the observation is built from the report
the world lets the decision see (:func:`sim.observation.build_observation`, the service's
builder) at the vehicle's position. ``info["reports"]`` is that report, what a placement policy
re-placing from reports gets.

Scenarios come from a fixed list cycled in order (the paper's specialization strategy), or from
a :class:`sim.scenarios.ScenarioSampler` (a fresh generated scenario per episode, its family and
user count drawn too: generalization and domain randomisation). ``world`` may also be
a sequence of worlds with one area, one drawn per episode.

A world with an envelope (:attr:`sim.world.World.envelope`; every world over a site has one)
flies the vehicle along the route the service's link would stream
(:meth:`sim.world.World.fly_routes_period`, kept across steps and planned again when the legal
target changes): a target inside an exclusion or outside the inclusion is
moved to the nearest legal point (``info["target_xyz_m"]`` is that point), the start too.

``reset`` places the vehicle at home (or ``options["uav_xyz_m"]``) and simulates one step there,
so the first observation carries real network metrics, as the service's first report would.
The users' motion and demand draw from their own generator, seeded from the reset's seed (or
``options["users_seed"]``), so they are the same whatever the policy does.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sim.config import AreaConfig
from sim.geometry import (
    MOVES,
    clip_to_volume,
    m_to_unit,
    move_mask,
    move_target,
    unit_to_m,
    zone_index,
    zone_position,
)
from sim.network import NetworkModel, QueueState, StepResult
from sim.observation import UserReports, build_observation, observation_shape
from sim.scenarios import Scenario, ScenarioSampler
from sim.users import UserDynamics, episode_users
from sim.utility import network_utility
from sim.world import World, episode_worlds

if TYPE_CHECKING:
    from sim.envelope.route import Route

__all__ = [
    "CONTINUOUS_ENV_ID",
    "DISCRETE_ENV_ID",
    "MOVES",
    "FapContinuousEnv",
    "FapDiscreteEnv",
    "ScenarioCycle",
    "ScenarioSource",
    "position_to_action",
    "register_envs",
]

DISCRETE_ENV_ID = "tupa/FapDiscrete-v0"
CONTINUOUS_ENV_ID = "tupa/FapContinuous-v0"


class ScenarioSource(Protocol):
    """Where an environment gets each episode's scenario (a :class:`ScenarioSampler` too)."""

    def sample(self, rng: np.random.Generator) -> Scenario: ...


class ScenariosByEnvironment:
    """One scenario source per channel environment: an episode draws from the source of the
    environment its world is in (training over several sites: each site's users stand on its own
    walkable ground). The environments look the source up themselves (:meth:`of`)."""

    def __init__(self, sources: Mapping[str, ScenarioSource]) -> None:
        if not sources:
            raise ValueError("sources: none given")
        self.sources = dict(sources)

    def of(self, environment: str) -> ScenarioSource:
        """The source of ``environment``; ValueError naming it when there is none."""
        try:
            return self.sources[environment]
        except KeyError:
            known = ", ".join(self.sources)
            raise ValueError(f"scenarios: none for environment {environment!r} ({known})") from None

    def sample(self, rng: np.random.Generator) -> Scenario:
        """Refused: which source depends on the episode's environment (:meth:`of`)."""
        raise TypeError("ScenariosByEnvironment.sample: use .of(environment).sample(rng)")


class ScenarioCycle:
    """A fixed list of scenarios served in order, wrapping around (specialization)."""

    def __init__(self, scenarios: Sequence[Scenario]) -> None:
        if not scenarios:
            raise ValueError("scenarios: the list is empty")
        self.scenarios = list(scenarios)
        self._next = 0

    def sample(self, rng: np.random.Generator) -> Scenario:
        """The next scenario of the list (``rng`` unused: the order is the list's)."""
        return self.next(rng)

    def next(self, rng: np.random.Generator) -> Scenario:
        scenario = self.scenarios[self._next]
        self._next = (self._next + 1) % len(self.scenarios)
        return scenario


class _FapEnv(gym.Env, ABC):
    """What both action spaces share: scenarios, the world, the network model, observations."""

    metadata = {"render_modes": []}  # noqa: RUF012 (gymnasium's convention)

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioSource | None = None,
        world: World | Sequence[World] | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        worlds = episode_worlds(world)
        area = worlds[0].area
        self.worlds = worlds
        self.world = worlds[0]
        if scenarios is None:
            scenarios = ScenarioSampler(area=area)
        elif not hasattr(scenarios, "sample"):
            scenarios = ScenarioCycle(scenarios)  # type: ignore[arg-type]
        self.scenarios: ScenarioSource = scenarios  # type: ignore[assignment]
        # One network model per channel environment: an episode runs in its world's.
        self._models = {area.environment: model or NetworkModel(self.world.network, area)}
        for w in worlds[1:]:
            if w.area.environment not in self._models:
                self._models[w.area.environment] = NetworkModel(w.network, w.area)
        self.model = self._models[area.environment]
        self.area = area
        self.observation_space = spaces.Box(0.0, 1.0, observation_shape(area), dtype=np.float32)
        self.scenario: Scenario | None = None
        self.users: UserDynamics | None = None
        self.uav_xyz_m = np.zeros(3)
        self.target_xyz_m = np.zeros(3)
        self.uav_velocity_mps = np.zeros(3)  # carried across periods when the flight accelerates
        self._route: Route | None = None  # with an envelope: the route flown (kept across steps)
        self._queues: QueueState | None = None
        self._reports: deque[UserReports] = deque(maxlen=1)
        self._users_rng = np.random.default_rng(0)
        self._steps = 0
        self._refused = False

    @abstractmethod
    def _target_from_action(self, action: Any) -> np.ndarray:
        """Validate an action and turn it into the vehicle's next target position (m)."""

    def _extra_info(self) -> dict[str, Any]:
        return {}

    # -- gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
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
        self._queues = None
        self._steps = 0
        self._refused = False
        self._reports = deque(maxlen=world.reports.age_steps + 1)
        start = options.get("uav_xyz_m")
        self.uav_xyz_m = world.legal_start(
            self._place_start(np.asarray(start, dtype=float))
            if start is not None
            else self._place_start(world.home_position(rng))
        )
        self.target_xyz_m = self.uav_xyz_m.copy()
        self.uav_velocity_mps = np.zeros(3)
        self._route = None
        self._moved()
        result = self._simulate()
        return self._observe(result), self._info(result, self._utility(result))

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.scenario is None or self.users is None:
            raise RuntimeError("step() called before reset()")
        return self._step_toward(self._target_from_action(action))

    def step_to(self, target_m: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """:meth:`step` with a target in metres instead of an action: what a policy that
        decides targets (``policies.interface.Policy``: a placement re-placed every step, or a
        checkpoint deciding as the service does) feeds the environment. The target is clipped
        into the volume; ValueError for one that is not three finite numbers."""
        if self.scenario is None or self.users is None:
            raise RuntimeError("step_to() called before reset()")
        target = np.asarray(target_m, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)):
            raise ValueError(f"target_m: must be 3 finite numbers, got {target_m!r}")
        return self._step_toward(clip_to_volume(target, self.area))

    def _step_toward(
        self, target_m: np.ndarray
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.world.envelope is None:
            flown, velocity = self.world.fly_period(
                self.uav_xyz_m, self.uav_velocity_mps, self.target_xyz_m, target_m
            )
            self.uav_xyz_m, self.uav_velocity_mps = flown[0], velocity[0]
            self.target_xyz_m = target_m
        else:  # the route the vehicle link would stream, to the legal target
            flown, velocity, routes = self.world.fly_routes_period(
                self.uav_xyz_m, self.uav_velocity_mps, target_m, [self._route]
            )
            self.uav_xyz_m, self.uav_velocity_mps, self._route = flown[0], velocity[0], routes[0]
            legal = self._route.target_m
            self.target_xyz_m = target_m if legal is None else np.array(legal)
        self._moved()
        self.users.advance(self.world.step_s, self._users_rng)
        result = self._simulate()
        self._steps += 1
        reward = self._utility(result)
        truncated = self._steps >= self.world.episode_steps
        return self._observe(result), reward, False, truncated, self._info(result, reward)

    # -- helpers -----------------------------------------------------------------------------
    def _moved(self) -> None:
        """The vehicle is somewhere new (the discrete env updates its move mask)."""

    def _place_start(self, xyz_m: np.ndarray) -> np.ndarray:
        """A start position: kept as is, inside the volume (the discrete env snaps it)."""
        return clip_to_volume(xyz_m, self.area)

    def _simulate(self) -> StepResult:
        users = self.users
        assert users is not None
        result = self.model.step(
            self.uav_xyz_m[None, :],
            users.xy_m,
            users.load_bps,
            self._queues,
            self.np_random if self.world.stochastic else None,
            self.world.step_s,
        )
        self._queues = result.state
        return result

    def _utility(self, result: StepResult) -> float:
        assert self.users is not None
        return float(
            network_utility(
                result.throughput_bps[0],
                result.delay_s[0],
                result.plr[0],
                self.users.load_bps,
                self.world.utility,
            )
        )

    def _observe(self, result: StepResult) -> np.ndarray:
        """Record this step's report and build the observation from the one the world shows."""
        users = self.users
        assert users is not None
        xy = users.xy_m  # read-only, replaced (never changed) as users move: no copy needed
        noise_m = self.world.reports.position_noise_m
        if noise_m > 0:
            upper = [self.area.size_x_m, self.area.size_y_m]
            xy = np.clip(xy + self.np_random.normal(0.0, noise_m, xy.shape), 0.0, upper)
        self._reports.append(
            UserReports(
                xy[:, 0],
                xy[:, 1],
                users.load_bps,
                result.throughput_bps[0],
                result.delay_s[0],
                result.plr[0],
            )
        )
        return build_observation(
            self.uav_xyz_m, self.reports, self.area, self.world.utility.delay_ref_s
        )

    @property
    def reports(self) -> UserReports:
        """The report the decision sees now (the oldest one the world's report age keeps)."""
        return self._reports[0]

    def _info(self, result: StepResult, utility: float) -> dict[str, Any]:
        assert self.scenario is not None and self.users is not None
        info = {
            "scenario_id": self.scenario.id,
            "uav_xyz_m": self.uav_xyz_m.copy(),
            "target_xyz_m": self.target_xyz_m.copy(),
            "utility": utility,
            "throughput_bps": result.throughput_bps[0],
            "delay_s": result.delay_s[0],
            "plr": result.plr[0],
            # Copies: gymnasium wants no array shared between two calls' infos.
            "users_xy_m": self.users.xy_m.copy(),
            "load_bps": self.users.load_bps.copy(),
            "reports": UserReports(*(np.array(field) for field in self.reports)),
        }
        info.update(self._extra_info())
        return info


class ResetNeededError(gym.error.ResetNeeded, RuntimeError):
    """Something only an episode has (the action mask) was asked for before ``reset()``: the
    error Gymnasium's order check raises for ``step()``, and a ``RuntimeError``."""


class FapDiscreteEnv(_FapEnv):
    """13 moves on the zone grid, from the zone the vehicle is in; invalid moves are masked."""

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioSource | None = None,
        world: World | Sequence[World] | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        self._mask: np.ndarray | None = None  # known once an episode has started
        super().__init__(scenarios, world, model)
        self.action_space = spaces.Discrete(len(MOVES))

    def action_masks(self) -> np.ndarray:
        """Boolean mask of the moves that keep the target inside the volume (``stay`` always),
        from the zone the vehicle is in: :class:`ResetNeededError` before the first
        ``reset()``, as there is no vehicle yet (MaskablePPO asks after ``reset()``)."""
        if self._mask is None:
            raise ResetNeededError(
                "action_masks: call reset() first: the mask depends on where the episode starts"
            )
        return self._mask.copy()

    def _moved(self) -> None:
        self._index = zone_index(self.uav_xyz_m, self.area)
        self._mask = move_mask(self._index, self.area)

    def _place_start(self, xyz_m: np.ndarray) -> np.ndarray:
        """Starts are zone points: the centre of the zone (and level) holding ``xyz_m``."""
        return zone_position(zone_index(super()._place_start(xyz_m), self.area), self.area)

    def _target_from_action(self, action: Any) -> np.ndarray:
        if isinstance(action, np.ndarray) and action.shape in ((), (1,)):
            action = action.reshape(()).item()
        if isinstance(action, bool | np.bool_) or not isinstance(action, int | np.integer):
            raise ValueError(f"action: must be an integer in [0, {len(MOVES) - 1}], got {action!r}")
        if not 0 <= action < len(MOVES):
            raise ValueError(f"action: must be an integer in [0, {len(MOVES) - 1}], got {action!r}")
        target, self._refused = move_target(int(action), self.uav_xyz_m, self.area, self._index)
        return target

    def _extra_info(self) -> dict[str, Any]:
        refused, self._refused = self._refused, False
        return {"action_mask": self._mask.copy(), "refused_move": refused}


class FapContinuousEnv(_FapEnv):
    """Absolute coordinates: an action (x, y, z) in [0, 1]³ maps linearly onto the volume."""

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioSource | None = None,
        world: World | Sequence[World] | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        super().__init__(scenarios, world, model)
        self.action_space = spaces.Box(0.0, 1.0, (3,), dtype=np.float32)

    def _target_from_action(self, action: Any) -> np.ndarray:
        a = np.asarray(action, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be 3 finite numbers in [0, 1], got {action!r}")
        if np.any(a < -1e-6) or np.any(a > 1.0 + 1e-6):
            raise ValueError(f"action: coordinates must lie in [0, 1], got {a.tolist()}")
        return unit_to_m(a, self.area)


def position_to_action(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The continuous action for ``xyz_m``, as the action space's float32
    (:func:`sim.geometry.m_to_unit` keeps float64)."""
    return m_to_unit(xyz_m, area).astype(np.float32)


def register_envs() -> None:
    """Register the environments with gymnasium (idempotent): both single-UAV ones and the
    fleet's two joint ones (``n_uavs=`` and the fleet environment's other arguments pass
    through ``gym.make``)."""
    for env_id, entry in (
        (DISCRETE_ENV_ID, "sim.envs:FapDiscreteEnv"),
        (CONTINUOUS_ENV_ID, "sim.envs:FapContinuousEnv"),
        # The fleet's joint (centralised) environments; the PettingZoo one is
        # sim.fleet_env.parallel_env (PettingZoo keeps no registry).
        ("tupa/FleetDiscrete-v0", "sim.fleet_env:FleetDiscreteGymEnv"),
        ("tupa/FleetContinuous-v0", "sim.fleet_env:FleetContinuousGymEnv"),
    ):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry)


register_envs()
