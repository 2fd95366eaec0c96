"""A trained checkpoint as an acting policy, for evaluation now and for the service later."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from policies.baselines import UsersLike
from policies.checkpoints import load_checkpoint
from policies.residual import residual_radius, residual_target
from sim.config import AreaConfig
from sim.world import World, position_to_coordinates


class TrainedAgent:
    """A DDQN or DDPG checkpoint answering every step from the observation (deterministic).

    DDQN acts in ``tupa/FapDiscrete`` (13 moves, masked with ``info["action_mask"]``), DDPG in
    ``tupa/FapContinuous`` (absolute coordinates). Episodes start at the world's home, as in
    training's evaluation.
    """

    def __init__(self, model: Any, metadata: dict[str, Any], name: str | None = None) -> None:
        self.model = model
        self.metadata = metadata
        self.algorithm: str = metadata["algorithm"]
        self.residual_radius_m = residual_radius(metadata)
        self.env_kind = "discrete" if self.algorithm == "ddqn" else "continuous"
        self.name = name or default_name(metadata, None)
        self.area = AreaConfig()

    @classmethod
    def load(
        cls,
        path: Path,
        area: AreaConfig = AreaConfig(),
        name: str | None = None,
        device: str = "auto",
        allowed_dirs: Sequence[Path] | None = None,
        max_bytes: int | None = None,
    ) -> TrainedAgent:
        """Load a checkpoint (``CheckpointError``, an ``InputError``, naming the file and the
        problem if it is unusable). ``allowed_dirs`` and ``max_bytes`` restrict which files
        may be loaded (see :func:`policies.checkpoints.read_checkpoint`)."""
        model, metadata = load_checkpoint(
            path, area, device=device, allowed_dirs=allowed_dirs, max_bytes=max_bytes
        )
        return cls(model, metadata, name or default_name(metadata, Path(path)))

    def begin_episode(self, scenario: UsersLike, world: World) -> np.ndarray | None:
        self.area = world.area
        return None

    def act(self, observation: np.ndarray, info: dict[str, Any]) -> Any:
        if self.algorithm == "ddqn":
            return int(self.model.masked_predict(observation[None], info["action_mask"][None])[0])
        action, _ = self.model.predict(observation, deterministic=True)
        if self.residual_radius_m is not None:
            target = residual_target(action, info["reports"], self.area, self.residual_radius_m)
            return position_to_coordinates(target, self.area)
        return np.asarray(action, dtype=np.float32)


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
