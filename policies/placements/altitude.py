"""Utility against altitude: the best a placement can achieve at each altitude, per scenario.

Over free space (the paper's ``open`` channel) the lowest altitude is all but always best; over
a town (:mod:`sim.channel`'s urban classes), climbing raises the probability of line of sight
and lowers the mean excess loss but lengthens every path, so utility against altitude has an
interior maximum that depends on where the users are. :func:`altitude_profile` measures that
curve for one scenario: at each of ``levels`` altitudes from the area's floor to its ceiling, the
mean utility of an episode held at the best zone centre at that altitude (the model's expected
mode and the world's episode, scored as the oracle scores positions:
:func:`policies.placements.oracle.episode_utility`). ``tupa eval --altitude-profiles N`` writes the
first N scenarios' profiles into its results; ``tupa report`` draws them with where each policy
ended.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from policies.placements.oracle import episode_utility
from sim.network import NetworkModel
from sim.scenarios import Scenario
from sim.world import World

DEFAULT_LEVELS = 16  # 25 to 100 m: every 5 m


@dataclass(frozen=True)
class AltitudeProfile:
    """One scenario's curve: at each altitude, the best utility and the (x, y) achieving it."""

    scenario_id: str
    environment: str
    altitudes_m: np.ndarray  # (L,)
    best_utility: np.ndarray  # (L,)
    best_xy_m: np.ndarray  # (L, 2)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.scenario_id,
            "environment": self.environment,
            "altitudes_m": [round(float(z), 3) for z in self.altitudes_m],
            "best_utility": [float(u) for u in self.best_utility],
            "best_xy_m": [[round(float(x), 3), round(float(y), 3)] for x, y in self.best_xy_m],
        }


def altitude_profile(
    scenario: Scenario,
    world: World,
    levels: int = DEFAULT_LEVELS,
    model: NetworkModel | None = None,
) -> AltitudeProfile:
    """The best episode utility at each of ``levels`` altitudes, evenly spaced over the
    flight volume, for ``scenario``'s users at their start positions and loads (see the module
    doc). All zone centres at all levels go through the model as one batch; a few seconds for
    a scenario whose queues never settle, well under one for most."""
    if levels < 2:
        raise ValueError(f"levels: must be at least 2, got {levels}")
    area = world.area
    altitudes_m = np.linspace(area.z_min_m, area.z_max_m, levels)
    gx, gy, gz = np.meshgrid(
        area.zone_centres_x_m(), area.zone_centres_y_m(), altitudes_m, indexing="ij"
    )
    positions_m = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    utility = episode_utility(
        model or NetworkModel(world.network, area),
        positions_m,
        scenario,
        world.episode_steps,
        step_s=world.step_s,
        utility=world.utility,
    ).reshape(-1, levels)  # (zones, levels): the last axis is the altitude
    best = utility.argmax(axis=0)
    xy_m = positions_m.reshape(-1, levels, 3)[best, np.arange(levels), :2]
    return AltitudeProfile(
        scenario_id=scenario.id,
        environment=area.environment,
        altitudes_m=altitudes_m,
        best_utility=utility[best, np.arange(levels)],
        best_xy_m=xy_m,
    )
