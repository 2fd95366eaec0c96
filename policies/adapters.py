"""The two adapters that make a :class:`~policies.interface.Policy` of anything that places a
UAV; the evaluation (``tupa eval``, the benchmarks, training's curve points) and the service run
the same objects, so they decide alike (``tests/service/test_parity.py``).

* :class:`StaticPolicy`: a :class:`~policies.interface.Placement` re-placed every decision from
  the users the report shows. Placements are cached for identical reports (static users), and a
  placement with ``track(users, previous_m)`` (the oracle) is asked through it, so it starts
  its search from where it placed last: re-placed every period, the oracle is the *tracking
  oracle*, the upper bound of the closed loop.
* :class:`CheckpointPolicy`: a trained DDQN or DDPG checkpoint (deterministic). The observation
  is built by the same :func:`sim.observation.build_observation` the environments use, at the
  vehicle's position; a DDQN move is chosen among the valid ones and becomes a target with
  :func:`sim.geometry.move_target` (from the zone the vehicle is in, as the discrete environment
  does); a DDPG action becomes a target with :func:`sim.geometry.unit_to_m`, or, for a residual
  checkpoint, with :func:`policies.learned.residual.residual_target`.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.interface import Placement, PolicyKind, ReportedUsers, UsersLike
from policies.learned.checkpoints import load_checkpoint
from policies.learned.residual import residual_radius, residual_target
from sim.geometry import move_target, unit_to_m, valid_moves
from sim.observation import UserReports, build_observation
from sim.world import PAPER, World


@dataclass
class StaticPolicy:
    """A placement as a policy: re-placed on every decision from the reported users."""

    placement: Placement
    spec: str = ""
    kind: PolicyKind = field(default="placement", init=False)
    _last_key: tuple[bytes, bytes] | None = field(default=None, init=False, repr=False)
    _target_m: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.name: str = self.placement.name
        self.spec = self.spec or self.name

    def place(self, users: UsersLike) -> np.ndarray:
        """The placement for ``users`` (cached while they do not change)."""
        key = (users.users_xy_m.tobytes(), users.load_bps.tobytes())
        if key != self._last_key or self._target_m is None:
            track = getattr(self.placement, "track", None)
            previous = self._target_m
            target = track(users, previous) if track is not None else self.placement.place(users)
            self._target_m = np.asarray(target, dtype=float)
            self._last_key = key
        return self._target_m.copy()

    def begin_episode(self, users: UsersLike, world: World) -> np.ndarray | None:
        """Forget the last placement; start at the placement where the world says so (the
        paper's protocol), else at the world's home."""
        self._last_key = self._target_m = None
        if world.static_start == "placement":
            return self.place(users)
        return None

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        return self.place(ReportedUsers.of(reports))

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "spec": self.spec, "metadata": None}


class CheckpointPolicy:
    """A DDQN (``kind="moves"``) or DDPG (``kind="coordinates"``) checkpoint as a policy.

    ``world`` gives the area and the utility's delay reference the observation is built with;
    :meth:`begin_episode` replaces it. Decisions are serialised (torch modules are not meant
    for concurrent forward passes), so one instance may serve several threads.
    """

    def __init__(
        self,
        model: Any,
        metadata: dict[str, Any],
        name: str | None = None,
        spec: str = "",
        world: World = PAPER,
    ) -> None:
        self.model = model
        self.metadata = metadata
        self.algorithm: str = metadata["algorithm"]
        self.kind: PolicyKind = "moves" if self.algorithm == "ddqn" else "coordinates"
        self.residual_radius_m = residual_radius(metadata)
        self.name = name or default_name(metadata, None)
        self.spec = spec or self.name
        self.world = world
        self._lock = threading.Lock()

    @classmethod
    def load(
        cls,
        path: Path | str,
        world: World = PAPER,
        name: str | None = None,
        device: str = "auto",
        allowed_dirs: Sequence[Path] | None = None,
        max_bytes: int | None = None,
    ) -> CheckpointPolicy:
        """Load a checkpoint (``CheckpointError``, an ``InputError``, naming the file and the
        problem if it is unusable). ``allowed_dirs`` and ``max_bytes`` restrict which files
        may be loaded (see :func:`policies.learned.checkpoints.read_checkpoint`)."""
        model, metadata = load_checkpoint(
            path, world.area, device=device, allowed_dirs=allowed_dirs, max_bytes=max_bytes
        )
        return cls(model, metadata, name or default_name(metadata, Path(path)), str(path), world)

    def begin_episode(self, users: UsersLike, world: World) -> np.ndarray | None:
        self.world = world
        return None

    def observe(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        """The observation the policy acts on (the environments build the same)."""
        world = self.world
        return build_observation(vehicle_xyz_m, reports, world.area, world.utility.delay_ref_s)

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        area = self.world.area
        observation = self.observe(reports, vehicle_xyz_m)
        with self._lock:
            if self.kind == "moves":
                mask = valid_moves(vehicle_xyz_m, area)
                move = int(self.model.masked_predict(observation[None], mask[None])[0])
                return move_target(move, vehicle_xyz_m, area)[0]
            action, _ = self.model.predict(observation, deterministic=True)
        if self.residual_radius_m is not None:
            return residual_target(action, reports, area, self.residual_radius_m)
        return unit_to_m(np.asarray(action, dtype=float), area)

    def describe(self) -> dict[str, Any]:
        keep = ("algorithm", "strategy", "episodes", "seed", "git_commit", "wall_time_s")
        return {
            "name": self.name,
            "kind": self.kind,
            "spec": self.spec,
            "metadata": {k: self.metadata.get(k) for k in keep},
        }


def trained_environments(metadata: dict[str, Any]) -> list[str]:
    """The channel environments a checkpoint was trained in: the metadata's
    ``train_environments``, else its world's (``open`` for checkpoints from before towns)."""
    listed = metadata.get("train_environments")
    if isinstance(listed, list) and listed:
        return [str(e) for e in listed]
    world = metadata.get("world")
    area = world.get("area", {}) if isinstance(world, dict) else {}
    return [str(area.get("environment", "open")) if isinstance(area, dict) else "open"]


def default_name(metadata: dict[str, Any], path: Path | None) -> str:
    """A checkpoint's name: the metadata's ``name`` when it has one (the shipped checkpoints),
    else ``ddqn-gen10k`` style (algorithm, ``residual`` for residual actions, training
    strategy), else the file's name."""
    if isinstance(metadata.get("name"), str) and metadata["name"]:
        return metadata["name"]
    algorithm, strategy = metadata.get("algorithm"), metadata.get("strategy")
    if algorithm and strategy:
        residual = "-residual" if metadata.get("action") == "residual" else ""
        return f"{algorithm}{residual}-{strategy}"
    return path.stem if path is not None else str(algorithm)
