"""Evaluation-vs-service parity for fleets: one episode of ``tupa eval --uavs K``, replayed
through the fleet service's decision path, must give the targets the evaluation flew.

:func:`policies.evaluation.fleet_evaluation.evaluate_fleet` runs a fleet episode in the
``closed-loop-moving`` world (flight limits, reports one step old; 30 steps); every step
records the report the decision saw, where the vehicles were, the targets the environment was
given and those it flew to (separated, a vehicle whose flight would cross another's held where
it is). The same reports then go to a :class:`FleetPlacementService` serving the same policy
(``tupa serve``'s loader), its K links replaying the recorded positions: each decision's targets
must equal those the environment was given, and the streamed ones those it flew to, to the
bit. A difference in the users' APs the policy decides from (a report does not carry them),
the observation, the placement's configuration, the assignment of targets to vehicles or the
guard and path holds between the world and the service fails here.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from policies.evaluation.fleet_evaluation import build_fleet_candidate, evaluate_fleet
from service.decisions import Report
from service.fleet_placement import FleetPlacementService, load_fleet_policy
from service.fleet_spec import FleetSpec, VehicleSpec
from service.policy_runtime import SHIPPED_FLEET
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets
from sim.scenarios import generate_scenarios
from sim.world import get_world
from tests.fakes import FakeLink

STEPS = 30
WORLD = replace(get_world("closed-loop-moving"), episode_steps=STEPS)
K = 3


def record_evaluation(spec: str, monkeypatch: pytest.MonkeyPatch) -> list[tuple[Any, ...]]:
    """(report seen, vehicles' positions, targets given, targets flown: separated, crossing
    paths held) for every step of one evaluated episode of ``spec`` (the evaluation's own loop,
    watched at the environment)."""
    steps: list[tuple[Any, ...]] = []
    step_to = FleetParallelEnv.step_to

    def watched(env: FleetParallelEnv, targets_m: Any) -> Any:
        seen, here, given = env.reports, env.uav_xyz_m.copy(), np.array(targets_m, dtype=float)
        out = step_to(env, targets_m)
        steps.append((seen, here, given, env.target_xyz_m.copy()))
        return out

    monkeypatch.setattr(FleetParallelEnv, "step_to", watched)
    scenario = generate_scenarios(1, 24, seed=7, family="hotspots", total_load_bps=150e6)
    _, policy = build_fleet_candidate(spec, K, WORLD)
    evaluate_fleet(policy, scenario, K, WORLD, progress=False)
    monkeypatch.setattr(FleetParallelEnv, "step_to", step_to)
    return steps


def replay(
    spec: str, steps: list[tuple[Any, ...]]
) -> tuple[list[np.ndarray], list[np.ndarray], list[int]]:
    """For the recorded reports, its links where the evaluation had the vehicles: the targets
    the fleet service decided (its policy's, each given to a vehicle, before its path guard),
    the targets it streamed, and the steps in which its path guard held a vehicle."""
    urls = tuple(f"tcp:127.0.0.1:{5760 + i}" for i in range(K))
    settings = ServiceSettings(
        fleet_mavlink=urls, mavlink=urls[0], insecure=True, decision_mode="on-report"
    )
    fleet = FleetSpec(
        tuple(VehicleSpec(f"uav{i + 1}", url, None) for i, url in enumerate(urls)),
        FleetConfig().separation_m,
    )
    links = {
        v.id: FakeLink(LinkConfig(v.mavlink, area=WORLD.area), position_m=steps[0][1][i],
                       system_id=i + 1)
        for i, v in enumerate(fleet.vehicles)
    }  # fmt: skip
    policy = load_fleet_policy(spec, WORLD, fleet.separation_m)
    decided: list[np.ndarray] = []
    decide_fleet = policy.decide_fleet

    def watched(reports: Any, vehicles: np.ndarray) -> np.ndarray:
        wanted = decide_fleet(reports, vehicles)
        decided.append(assign_targets(vehicles, np.asarray(wanted, dtype=float)))
        return wanted

    policy.decide_fleet = watched  # type: ignore[method-assign]
    service = FleetPlacementService(settings, links, policy, fleet, WORLD).start()
    served, held = [], []
    try:
        for i, (seen, vehicles, *_) in enumerate(steps):
            for link, position in zip(links.values(), vehicles, strict=True):
                link.place_at(position)
            holds = service.snapshot_counters().get("path_holds", 0)
            ids = tuple(f"u{n}" for n in range(len(seen.x_m)))
            assert service.submit_report(Report(float(i + 1), ids, seen)) is not None
            if service.snapshot_counters().get("path_holds", 0) > holds:
                held.append(i)
            served.append(np.array([link.state().target_m for link in links.values()]))
    finally:
        service.stop()
    return decided, served, held


SPECS = {
    "kmeans-scored": "kmeans-scored",
    "kmeans-load-weighted": "kmeans-load-weighted",
    "shipped-checkpoint": str(SHIPPED_FLEET),
}


@pytest.mark.parametrize("spec", list(SPECS.values()), ids=list(SPECS))
def test_the_fleet_service_decides_the_evaluations_targets(
    spec: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    steps = record_evaluation(spec, monkeypatch)
    assert len(steps) == STEPS
    decided, served, held = replay(spec, steps)
    for i, ((_, _, given, flown), mine, streamed) in enumerate(
        zip(steps, decided, served, strict=True)
    ):
        np.testing.assert_array_equal(mine, given, err_msg=f"step {i}: decided")
        np.testing.assert_array_equal(streamed, flown, err_msg=f"step {i}: streamed")
    # The episode went somewhere: the vehicles were sent to more than one place.
    assert len({np.round(t[2], 3).tobytes() for t in steps}) > 1
    if spec == SPECS["shipped-checkpoint"]:  # its flights cross: both held the same vehicles
        assert held and all(not np.array_equal(steps[i][2], steps[i][3]) for i in held)
