"""A fleet checkpoint as a fleet policy: :class:`FleetCheckpointPolicy` (K observations → K
targets) and what deciding with one needs (:data:`FLEET_ALGORITHMS`,
:func:`fleet_observation_shape`). Training them is :mod:`policies.training.fleet_training`'s job;
this module imports no training library, so that evaluation, imitation and serving load checkpoints
without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from policies.learned.checkpoints import load_checkpoint
from policies.learned.fleet_residual import DEFAULT_PRIOR, fleet_residual_targets, make_prior
from policies.learned.residual import residual_radius
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import MAX_UAVS, FleetConfig
from sim.fleet_observation import FLEET_MAPS
from sim.geometry import (
    enforce_separation,
    move_masks,
    move_targets,
    unit_to_m_many,
    zone_indices,
)
from sim.observation import UserReports
from sim.world import World, get_world

__all__ = ["FLEET_ALGORITHMS", "FleetCheckpointPolicy", "fleet_observation_shape"]

FLEET_ALGORITHMS: tuple[str, ...] = ("ddpg", "ddqn")
"""Algorithms a fleet trains with: the paper's two, one network shared by every UAV. DDQN's
agents move by the 13 discrete moves, each masked to its own zone (the masks reach the learner
through the bridge's infos: :class:`_SeededVecEnv`)."""


def fleet_observation_shape(area: AreaConfig) -> tuple[int, int, int]:
    """One fleet agent's observation shape: (9, n_zones_x, n_zones_y)."""
    return (FLEET_MAPS, area.n_zones_x, area.n_zones_y)


class FleetCheckpointPolicy:
    """A shared-parameter fleet checkpoint as a fleet policy: K observations → K targets.

    ``targets(observations, reports, uav_xyz_m)`` takes the K agents' observations
    (K, 9, n_x, n_y), acts with the one network on each (deterministic) and maps the actions to
    targets: absolute coordinates in [0, 1]³ to metres, or residual actions around the
    checkpoint's prior (its metadata's ``prior``; ``kmeans-load-weighted`` when it names none)
    for ``reports`` and the UAVs at ``uav_xyz_m``
    (:func:`policies.learned.fleet_residual.fleet_residual_targets`, as in training); the set is
    separated (:func:`sim.geometry.enforce_separation`, lower index first). Any K works: the
    network never sees K.

    ``world``: where it flies (network, decision period, flight), which a ``kmeans-scored``
    prior scores on; by default the world the checkpoint trained in (its metadata's name)."""

    name = "fleet-checkpoint"

    def __init__(
        self,
        model: Any,
        metadata: dict[str, Any],
        area: AreaConfig | None = None,
        separation_m: float = FleetConfig().separation_m,
        world: World | None = None,
    ) -> None:
        algorithm, action = metadata.get("algorithm"), metadata.get("action", "coordinates")
        allowed = ("moves",) if algorithm == "ddqn" else ("coordinates", "residual")
        if algorithm not in FLEET_ALGORITHMS or action not in allowed:
            raise InputError(
                f"action: a fleet {algorithm} checkpoint acts with {' or '.join(allowed)}, "
                f"got {action!r}"
            )
        self.algorithm = algorithm
        if not (np.isfinite(separation_m) and separation_m > 0):
            raise InputError(f"separation_m: must be > 0, got {separation_m!r}")
        self.model = model
        self.metadata = metadata
        self.area = area or AreaConfig()
        self.separation_m = float(separation_m)
        self.shape = fleet_observation_shape(self.area)
        self.residual_radius_m = residual_radius(metadata)
        """Residual actions' radius (m); None: absolute coordinates."""
        self.world = world or _trained_world(metadata)
        self.prior = make_prior(
            metadata.get("prior") or DEFAULT_PRIOR,
            self.area,
            self.separation_m,
            self.world,
            int(metadata.get("prior_score_steps") or self.world.episode_steps),
        )

    @classmethod
    def load(
        cls,
        path: Path | str,
        area: AreaConfig | None = None,
        separation_m: float = FleetConfig().separation_m,
        device: str = "cpu",
        allowed_dirs: Sequence[Path] | None = None,
        max_bytes: int | None = None,
        world: World | None = None,
    ) -> FleetCheckpointPolicy:
        """Load a checkpoint written by :func:`train_fleet` (shape and algorithm checked;
        ``allowed_dirs`` and ``max_bytes`` as for
        :func:`policies.learned.checkpoints.load_checkpoint`; ``world`` as for the class)."""
        area = area or AreaConfig()
        model, meta = load_checkpoint(
            path,
            area,
            device=device,
            allowed_dirs=allowed_dirs,
            max_bytes=max_bytes,
            observation_shape=fleet_observation_shape(area),
        )
        if not meta.get("fleet"):
            raise InputError("policy: not a fleet checkpoint (tupa train --uavs K writes those)")
        return cls(model, meta, area, separation_m, world)

    def targets(
        self,
        observations: np.ndarray,
        reports: UserReports | None = None,
        uav_xyz_m: np.ndarray | None = None,
        association: np.ndarray | None = None,
    ) -> np.ndarray:
        """Targets (K, 3) in metres for observations (K, 9, n_x, n_y); a residual checkpoint
        needs the report the observations were built from and the UAVs' positions (K, 3), and
        one on the ``kmeans-scored`` prior the users' APs in that report (U,; ``None``: none
        yet)."""
        obs = np.asarray(observations, dtype=np.float32)
        if obs.ndim != 4 or obs.shape[1:] != self.shape or not 1 <= len(obs) <= MAX_UAVS:
            raise InputError(
                f"observations: must be (K, {', '.join(map(str, self.shape))}) with K in "
                f"1..{MAX_UAVS}, got {obs.shape}"
            )
        if self.algorithm == "ddqn":  # moves from each UAV's zone, masked to the volume
            if uav_xyz_m is None:
                raise InputError("uav_xyz_m: a DDQN fleet checkpoint moves from where UAVs are")
            here = np.asarray(uav_xyz_m, dtype=float)
            index = zone_indices(here, self.area)
            moves, _ = self.model.predict(
                obs, deterministic=True, action_masks=move_masks(index, self.area)
            )
            targets, _ = move_targets(np.asarray(moves).reshape(-1), here, self.area, index)
            return enforce_separation(targets, self.separation_m, self.area)
        actions, _ = self.model.predict(obs, deterministic=True)
        actions = np.asarray(actions, dtype=float).reshape(len(obs), 3)
        if self.residual_radius_m is not None:
            if reports is None or uav_xyz_m is None:
                raise InputError("reports, uav_xyz_m: a residual fleet checkpoint needs both")
            return fleet_residual_targets(
                actions,
                reports,
                uav_xyz_m,
                self.area,
                self.separation_m,
                self.residual_radius_m,
                self.prior,
                association,
                self.world.flight,
            )
        targets = unit_to_m_many(actions, self.area)
        return enforce_separation(targets, self.separation_m, self.area)


def _trained_world(metadata: dict[str, Any]) -> World:
    """The world a fleet checkpoint trained in, by its metadata's name (``closed-loop`` when it
    names none or one this version does not know)."""
    name = (metadata.get("world") or {}).get("name")
    try:
        return get_world(name) if isinstance(name, str) else get_world("closed-loop")
    except InputError:
        return get_world("closed-loop")
