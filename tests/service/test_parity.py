"""Env-vs-service parity: one recorded closed-loop episode, replayed through the service's
decision path, must give exactly the targets the environment chose.

The environment flies an episode in the ``closed-loop`` world (flight limits, reports one step
old) with a checkpoint acting through the environment's action space, as in training (a DDQN
move masked by ``info["action_mask"]``, a DDPG action, or a residual one through
:class:`policies.learned.residual_env.ResidualActions`); every step records the report the decision
saw, where the vehicle was and the target the action became. The same reports then go to a
:class:`PlacementService` serving the same policy, its link replaying the recorded vehicle
positions: each decision's target must equal the environment's, to the bit. A difference in the
observation, the mask, the move rule or the coordinates mapping between training and serving
fails here.

The link is a replay of recorded telemetry (what the vehicle reported), not a MAVLink link: the
decision path is what is under test; the real links are tested in ``test_placement.py`` and the
end-to-end tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policies.adapters import StaticPolicy
from policies.learned.checkpoints import load_checkpoint
from policies.learned.residual import residual_radius
from policies.learned.residual_env import ResidualActions
from policies.registry import make_placement
from service.decisions import Report
from service.placement import PlacementService
from service.policy_runtime import SHIPPED_CHECKPOINTS, load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkState
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.observation import UserReports
from sim.scenarios import generate_scenarios
from sim.world import get_world

WORLD = get_world("closed-loop-moving")
STEPS = 40


@dataclass
class ReplayLink:
    """Telemetry replayed from a recording: the vehicle is where the environment had it."""

    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    targets: list[tuple[float, float, float]] = field(default_factory=list)

    def start(self) -> ReplayLink:
        return self

    def close(self) -> None:
        pass

    def arm_and_takeoff(self, timeout_s: float = 300.0) -> None:
        pass

    def state(self) -> LinkState:
        return LinkState(
            link="up",
            flavour="px4",
            mode="OFFBOARD",
            armed=True,
            position_m=self.position_m,
            relative_alt_m=self.position_m[2],
            heartbeat_age_s=0.0,
            target_m=self.targets[-1] if self.targets else None,
            streaming=bool(self.targets),
            takeoff="airborne",
        )

    def set_target(self, target_m: Any) -> tuple[float, float, float]:
        target = tuple(float(v) for v in target_m)
        self.targets.append(target)  # type: ignore[arg-type]
        return target  # type: ignore[return-value]


Step = tuple[UserReports, np.ndarray, np.ndarray]


def _scenario(seed: int) -> Any:
    return generate_scenarios(1, 5, seed=seed, family="hotspots")[0]


def record_training(checkpoint: Path, seed: int) -> list[Step]:
    """(report seen, vehicle position at the decision, target chosen) for every step, the
    checkpoint acting through the environment's action space as in training."""
    model, metadata = load_checkpoint(checkpoint, WORLD.area, device="cpu")
    ddqn = metadata["algorithm"] == "ddqn"
    env: Any = FapDiscreteEnv(world=WORLD) if ddqn else FapContinuousEnv(world=WORLD)
    radius_m = residual_radius(metadata)
    if radius_m is not None:
        env = ResidualActions(env, radius_m)
    observation, info = env.reset(seed=seed, options={"scenario": _scenario(seed)})
    steps = []
    for _ in range(STEPS):
        seen, vehicle = info["reports"], info["uav_xyz_m"]
        if ddqn:
            action: Any = int(model.masked_predict(observation[None], info["action_mask"][None])[0])
        else:
            action = model.predict(observation, deterministic=True)[0]
        observation, _, _, _, info = env.step(action)
        steps.append((seen, vehicle, info["target_xyz_m"]))
    return steps


def record_placement(name: str, seed: int) -> list[Step]:
    """The same for a placement re-placed every step, as ``tupa eval`` runs it."""
    policy = StaticPolicy(make_placement(name, WORLD))
    env = FapContinuousEnv(world=WORLD)
    scenario = _scenario(seed)
    policy.begin_episode(scenario, WORLD)
    _, info = env.reset(seed=seed, options={"scenario": scenario})
    steps = []
    for _ in range(STEPS):
        seen, vehicle = info["reports"], info["uav_xyz_m"]
        _, _, _, _, info = env.step_to(policy.decide(seen, vehicle))
        steps.append((seen, vehicle, info["target_xyz_m"]))
    return steps


def replay(spec: str, steps: list[Step]) -> list[Any]:
    link = ReplayLink()
    settings = ServiceSettings(
        mavlink="tcp:127.0.0.1:1", api_token="t", policy=spec, decision_mode="on-report"
    )
    service = PlacementService(settings, link, load_policy(spec))
    targets = []
    for i, (seen, vehicle, _) in enumerate(steps):
        link.position_m = tuple(float(v) for v in vehicle)  # type: ignore[assignment]
        ids = tuple(f"u{k}" for k in range(len(seen.x_m)))
        decision = service.submit_report(Report(float(i + 1), ids, seen))
        assert decision is not None
        targets.append(decision.target_m)
    return targets


CHECKPOINTS = sorted(SHIPPED_CHECKPOINTS.glob("*.zip"))


@pytest.mark.parametrize("checkpoint", CHECKPOINTS, ids=[p.stem for p in CHECKPOINTS])
def test_service_decides_the_environments_targets_for_a_checkpoint(checkpoint: Path) -> None:
    steps = record_training(checkpoint, seed=3)
    served = replay(str(checkpoint), steps)
    assert served == [tuple(float(v) for v in target) for _, _, target in steps]
    # The episode went somewhere: a test of "stay" everywhere would prove little.
    assert len({tuple(np.round(t, 3)) for _, _, t in steps}) > 1


@pytest.mark.parametrize("name", ["min-distance", "load-weighted", "oracle"])
def test_service_decides_the_environments_targets_for_a_baseline(name: str) -> None:
    steps = record_placement(name, seed=5)
    served = replay(name, steps)
    assert served == [tuple(float(v) for v in target) for _, _, target in steps]


def test_the_service_decides_at_its_worlds_period_and_names_a_bad_world() -> None:
    import argparse

    from api.cli import register, settings_from_args
    from sim.errors import InputError

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["serve", "--policy", "min-distance"]
    assert settings_from_args(parser.parse_args(base)).decision_period_s == WORLD.step_s
    explicit = settings_from_args(parser.parse_args([*base, "--step-s", "0.5"]))
    assert explicit.decision_period_s == 0.5
    with pytest.raises(InputError, match=r"world: .*must be one of paper, closed-loop"):
        settings_from_args(parser.parse_args([*base, "--world", "mars"]))
    with pytest.raises(InputError, match="step_s"):
        settings_from_args(parser.parse_args([*base, "--step-s", "0"]))
