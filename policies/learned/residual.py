"""DDPG's *residual* action: a correction to the load-weighted placement.

The paper's DDPG outputs absolute coordinates. Learned from scratch in a few minutes on a laptop
CPU, such an actor lands below the one-line ``load-weighted`` baseline (the placement that
minimises the load-weighted distance to the users) on most scenario families: that baseline
already captures most of what traffic-aware placement gains, and the actor must first rediscover
it. With ``action = "residual"`` the actor outputs ``delta`` in [-1, 1]³ instead, and the target
is the load-weighted placement of the reported users moved by ``delta``:

* x, y: the placement plus ``delta_xy · radius_m`` (clipped to the area);
* z: the minimum altitude plus ``max(delta_z, 0)`` of the altitude band (the load-weighted
  placement flies lowest, where every distance is shortest).

The actor starts at ``delta = 0`` (its last layer zeroed), so an untrained policy *is* the
load-weighted baseline, and training learns what the baseline misses: the MAC (airtime, queues,
the 802.11 performance anomaly), which the users' positions and loads alone do not show. It is
still the paper's DDPG (actor-critic, the same observation, the same critic); only the action's
frame moves. :func:`residual_target` is the one function both the training environment's wrapper
(:class:`policies.learned.residual_env.ResidualActions`) and the service use, so they agree to the
bit (``tests/service/test_parity.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from policies.interface import ReportedUsers
from policies.placements.baselines import MinDistancePlacement
from sim.config import AreaConfig
from sim.geometry import clip_to_volume
from sim.observation import UserReports

RESIDUAL_RADIUS_M = 125.0
"""How far (m) the actor may move the target from the load-weighted placement, per axis."""


def residual_target(
    delta: np.ndarray,
    reports: UserReports,
    area: AreaConfig,
    radius_m: float = RESIDUAL_RADIUS_M,
) -> np.ndarray:
    """The target (3,), metres, for the residual action ``delta`` given the users' reports."""
    d = np.clip(np.asarray(delta, dtype=float).reshape(3), -1.0, 1.0)
    prior = MinDistancePlacement(area, load_weighted=True).place(ReportedUsers.of(reports))
    target = np.array(
        [
            prior[0] + d[0] * radius_m,
            prior[1] + d[1] * radius_m,
            area.z_min_m + max(d[2], 0.0) * (area.z_max_m - area.z_min_m),
        ]
    )
    return clip_to_volume(target, area)


def residual_radius(metadata: dict[str, Any]) -> float | None:
    """A checkpoint's residual radius (m) from its metadata; ``None`` for absolute actions."""
    radius_m = metadata.get("residual_radius_m")
    if metadata.get("action") != "residual" or not radius_m:
        return None
    return float(radius_m)


def residual_metadata(action: str) -> dict[str, Any]:
    """What a training run records about its action, read back by :func:`residual_radius`."""
    return {
        "action": action,
        "residual_radius_m": RESIDUAL_RADIUS_M if action == "residual" else None,
    }
