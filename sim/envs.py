"""Gymnasium environments: a UAV carrying a Wi-Fi access point over one scenario per episode.

``tupa/FapDiscrete-v0``   13 sequential moves on the zone grid (stay; ±1 or ±5 zones along x, y,
                          z); moves that would leave the volume are masked (``action_masks()``,
                          ``info["action_mask"]``); one taken anyway leaves the UAV where it is
                          and sets ``info["refused_move"]``.
``tupa/FapContinuous-v0`` ``Box(0, 1, (3,))``: absolute coordinates in the volume.

An episode is ``episode_steps`` (T = 100) steps of ``step_s`` (S = 1 s) on one scenario; the
reward is the step's network utility. Scenarios come from a fixed list cycled in order (the
paper's specialization strategy) or from a seeded generator (generalization). By default the UAV
is at its target at the start of each step, as in the paper; ``max_speed_mps`` makes a move take
flight time instead. Queues carry over between the steps of an episode.

``reset`` places the UAV at the start position and simulates one step there, so the first
observation carries real network metrics, as the service's first report would.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.network import NetworkModel, QueueState, StepResult
from sim.observation import UserReports, build_observation, observation_shape
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import network_utility
from sim.zones import MOVES, grid_shape, move_mask, zone_index, zone_position

__all__ = [
    "CONTINUOUS_ENV_ID",
    "DISCRETE_ENV_ID",
    "MOVES",
    "EnvConfig",
    "FapContinuousEnv",
    "FapDiscreteEnv",
    "ScenarioCycle",
    "ScenarioStream",
    "action_to_position",
    "position_to_action",
    "register_envs",
]

DISCRETE_ENV_ID = "tupa/FapDiscrete-v0"
CONTINUOUS_ENV_ID = "tupa/FapContinuous-v0"


class ScenarioCycle:
    """A fixed list of scenarios served in order, wrapping around (specialization)."""

    def __init__(self, scenarios: Sequence[Scenario]) -> None:
        if not scenarios:
            raise ValueError("scenarios: the list is empty")
        self.scenarios = list(scenarios)
        self._next = 0

    def next(self, rng: np.random.Generator) -> Scenario:
        scenario = self.scenarios[self._next]
        self._next = (self._next + 1) % len(self.scenarios)
        return scenario


@dataclass
class ScenarioStream:
    """Fresh generated scenarios, one per episode, drawn from the environment's RNG."""

    n_users: int = 3
    area: AreaConfig = field(default_factory=AreaConfig)
    total_load_bps: float = 40e6

    def next(self, rng: np.random.Generator) -> Scenario:
        seed = int(rng.integers(2**63 - 1))
        return generate_scenarios(
            1, self.n_users, seed=seed, area=self.area, total_load_bps=self.total_load_bps
        )[0]


@dataclass(frozen=True)
class EnvConfig:
    """Episode settings; the defaults are the paper's."""

    episode_steps: int = 100
    step_s: float = 1.0
    expected: bool = False  # deterministic network model (no fading draws)
    max_speed_mps: float | None = None  # None: the UAV is at its target at each step's start
    start: str = "centre"  # "centre" (zone at the middle, lowest level) or "random"
    network: NetworkConfig = field(default_factory=NetworkConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    area: AreaConfig = field(default_factory=AreaConfig)

    def __post_init__(self) -> None:
        if self.episode_steps < 1:
            raise ValueError(f"episode_steps: must be >= 1, got {self.episode_steps}")
        if not self.step_s > 0:
            raise ValueError(f"step_s: must be > 0, got {self.step_s}")
        if self.max_speed_mps is not None and not self.max_speed_mps > 0:
            raise ValueError(f"max_speed_mps: must be > 0 or None, got {self.max_speed_mps}")
        if self.start not in ("centre", "random"):
            raise ValueError(f"start: must be 'centre' or 'random', got {self.start!r}")


class _FapEnv(gym.Env, ABC):
    """What both action spaces share: scenarios, the network model, the episode, observations."""

    metadata = {"render_modes": []}  # noqa: RUF012 (gymnasium's convention)

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioCycle | ScenarioStream | None = None,
        config: EnvConfig | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        self.config = config or EnvConfig()
        area = self.config.area
        if scenarios is None:
            scenarios = ScenarioStream(area=area)
        elif not isinstance(scenarios, ScenarioCycle | ScenarioStream):
            scenarios = ScenarioCycle(scenarios)
        self.scenarios = scenarios
        self.model = model or NetworkModel(self.config.network, area)
        self.observation_space = spaces.Box(0.0, 1.0, observation_shape(area), dtype=np.float32)
        self._grid_shape = grid_shape(area)
        self.scenario: Scenario | None = None
        self.uav_xyz_m = np.zeros(3)
        self.target_xyz_m = np.zeros(3)
        self._queues: QueueState | None = None
        self._steps = 0

    @abstractmethod
    def _target_from_action(self, action: Any) -> np.ndarray:
        """Validate an action and turn it into the UAV's next target position (m)."""

    def _extra_info(self) -> dict[str, Any]:
        return {}

    # -- gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        self.scenario = options.get("scenario") or self.scenarios.next(self.np_random)
        self._queues = None
        self._steps = 0
        start = options.get("uav_xyz_m")
        self.uav_xyz_m = (
            self._snap(np.asarray(start, dtype=float)) if start is not None else self._start()
        )
        self.target_xyz_m = self.uav_xyz_m.copy()
        result = self._simulate()
        return self._observe(result), self._info(result, self._utility(result))

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.scenario is None:
            raise RuntimeError("step() called before reset()")
        self.target_xyz_m = self._target_from_action(action)
        self.uav_xyz_m = self._fly(self.uav_xyz_m, self.target_xyz_m)
        result = self._simulate()
        self._steps += 1
        reward = self._utility(result)
        truncated = self._steps >= self.config.episode_steps
        return self._observe(result), reward, False, truncated, self._info(result, reward)

    # -- helpers -----------------------------------------------------------------------------
    def _start(self) -> np.ndarray:
        area = self.config.area
        if self.config.start == "random":
            index = self.np_random.integers(0, self._grid_shape)
        else:
            index = np.array([area.n_zones_x // 2, area.n_zones_y // 2, 0])
        return self._position_of(index)

    def _position_of(self, index: np.ndarray) -> np.ndarray:
        return zone_position(index, self.config.area)

    def _snap(self, xyz_m: np.ndarray) -> np.ndarray:
        """A start position given in options: kept as is (continuous) or snapped (discrete)."""
        return self._clip_to_volume(xyz_m)

    def _clip_to_volume(self, xyz_m: np.ndarray) -> np.ndarray:
        area = self.config.area
        return np.clip(
            xyz_m, [0.0, 0.0, area.z_min_m], [area.size_x_m, area.size_y_m, area.z_max_m]
        )

    def _fly(self, position: np.ndarray, target: np.ndarray) -> np.ndarray:
        speed = self.config.max_speed_mps
        if speed is None:
            return target.copy()
        gap = target - position
        distance = float(np.linalg.norm(gap))
        reach = speed * self.config.step_s
        return target.copy() if distance <= reach else position + gap * (reach / distance)

    def _simulate(self) -> StepResult:
        scenario = self.scenario
        assert scenario is not None
        result = self.model.step(
            self.uav_xyz_m[None, :],
            scenario.users_xy_m,
            scenario.load_bps,
            self._queues,
            None if self.config.expected else self.np_random,
            self.config.step_s,
        )
        self._queues = result.state
        return result

    def _utility(self, result: StepResult) -> float:
        assert self.scenario is not None
        return float(
            network_utility(
                result.throughput_bps[0],
                result.delay_s[0],
                result.plr[0],
                self.scenario.load_bps,
                self.config.utility,
            )
        )

    def _observe(self, result: StepResult) -> np.ndarray:
        assert self.scenario is not None
        reports = UserReports.from_metrics(
            self.scenario.users_xy_m,
            self.scenario.load_bps,
            result.throughput_bps[0],
            result.delay_s[0],
            result.plr[0],
        )
        return build_observation(
            self.uav_xyz_m, reports, self.config.area, self.config.utility.delay_ref_s
        )

    def _info(self, result: StepResult, utility: float) -> dict[str, Any]:
        assert self.scenario is not None
        info = {
            "scenario_id": self.scenario.id,
            "uav_xyz_m": self.uav_xyz_m.copy(),
            "target_xyz_m": self.target_xyz_m.copy(),
            "utility": utility,
            "throughput_bps": result.throughput_bps[0],
            "delay_s": result.delay_s[0],
            "plr": result.plr[0],
        }
        info.update(self._extra_info())
        return info


class FapDiscreteEnv(_FapEnv):
    """Sequential moves on the zone grid; invalid moves are masked."""

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioCycle | ScenarioStream | None = None,
        config: EnvConfig | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        super().__init__(scenarios, config, model)
        self.action_space = spaces.Discrete(len(MOVES))
        self._set_target_index(np.zeros(3, dtype=np.int64))
        self._refused = False

    def action_masks(self) -> np.ndarray:
        """Boolean mask of the moves that keep the UAV inside the volume (``stay`` always)."""
        return self._mask.copy()

    def _set_target_index(self, index: np.ndarray) -> None:
        self._target_index = index
        self._mask = move_mask(index, self.config.area)

    def _snap(self, xyz_m: np.ndarray) -> np.ndarray:
        self._set_target_index(self._index_of(xyz_m))
        return self._position_of(self._target_index)

    def _start(self) -> np.ndarray:
        position = super()._start()
        self._set_target_index(self._index_of(position))
        return position

    def _index_of(self, xyz_m: np.ndarray) -> np.ndarray:
        return zone_index(xyz_m, self.config.area)

    def _target_from_action(self, action: Any) -> np.ndarray:
        if not self.action_space.contains(action) and not (
            isinstance(action, np.ndarray | np.integer) and self.action_space.contains(int(action))
        ):
            raise ValueError(f"action: must be an integer in [0, {len(MOVES) - 1}], got {action!r}")
        a = int(action)
        self._refused = not self._mask[a]
        if not self._refused:
            self._set_target_index(self._target_index + MOVES[a])
        return self._position_of(self._target_index)

    def _extra_info(self) -> dict[str, Any]:
        refused, self._refused = self._refused, False
        return {"action_mask": self.action_masks(), "refused_move": refused}


class FapContinuousEnv(_FapEnv):
    """Absolute coordinates: an action (x, y, z) in [0, 1]³ maps linearly onto the volume."""

    def __init__(
        self,
        scenarios: Sequence[Scenario] | ScenarioCycle | ScenarioStream | None = None,
        config: EnvConfig | None = None,
        model: NetworkModel | None = None,
    ) -> None:
        super().__init__(scenarios, config, model)
        self.action_space = spaces.Box(0.0, 1.0, (3,), dtype=np.float32)

    def _target_from_action(self, action: Any) -> np.ndarray:
        a = np.asarray(action, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be 3 finite numbers in [0, 1], got {action!r}")
        if np.any(a < -1e-6) or np.any(a > 1.0 + 1e-6):
            raise ValueError(f"action: coordinates must lie in [0, 1], got {a.tolist()}")
        return action_to_position(np.clip(a, 0.0, 1.0), self.config.area)


def action_to_position(action: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Map a normalised (x, y, z) in [0, 1]³ to the volume, in metres."""
    return np.array(
        [
            action[0] * area.size_x_m,
            action[1] * area.size_y_m,
            area.z_min_m + action[2] * (area.z_max_m - area.z_min_m),
        ]
    )


def position_to_action(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Inverse of :func:`action_to_position`."""
    return np.array(
        [
            xyz_m[0] / area.size_x_m,
            xyz_m[1] / area.size_y_m,
            (xyz_m[2] - area.z_min_m) / (area.z_max_m - area.z_min_m),
        ],
        dtype=np.float32,
    )


def register_envs() -> None:
    """Register both environments with gymnasium (idempotent)."""
    for env_id, entry in (
        (DISCRETE_ENV_ID, "sim.envs:FapDiscreteEnv"),
        (CONTINUOUS_ENV_ID, "sim.envs:FapContinuousEnv"),
    ):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry)


register_envs()
