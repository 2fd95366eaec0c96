"""Fleet policies for serving: the users' report and where the flying vehicles are in, one
target per vehicle out, for however many vehicles fly *now*.

A fleet in the air loses and regains vehicles (a lost link, a battery swap), so a served fleet
policy is asked for K targets with K the vehicles it may command at that moment, and must cover
every user with them (the service's degraded mode). The placements of
:mod:`policies.placements.fleet_baselines` and :mod:`policies.placements.fleet_oracle` take K at
construction; a :class:`FleetPlacementPolicy` keeps one per K it has been asked for and re-places
every decision, as :class:`policies.adapters.StaticPolicy` does for one vehicle.

Names (``tupa serve --policy``): :data:`FLEET_POLICIES`. The fleet oracle searches with the
fleet network model (1.5 s with 2 UAVs and 20 users, 6 s with 3 and 50, 21 s with 4 and 100 on
one core): serve it only where a decision period allows that.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from policies.adapters import default_name
from policies.interface import ReportedUsers
from policies.placements.fleet_baselines import FLEET_BASELINES, KMeansPlacement
from policies.placements.fleet_oracle import FLEET_ORACLE, FleetOracle, FleetOracleConfig
from policies.placements.fleet_scored import KMEANS_SCORED, ScoredKMeansPlacement
from policies.registry import PLACEMENTS, close_names, unknown_name
from sim.association import associate_at
from sim.errors import InputError
from sim.fleet import MAX_UAVS, FleetConfig
from sim.fleet_observation import fleet_observations
from sim.observation import UserReports
from sim.world import World

__all__ = [
    "DEFAULT_FLEET_POLICY",
    "FLEET_POLICIES",
    "FleetCheckpointServing",
    "FleetPlacementPolicy",
    "FleetPolicy",
    "resolve_fleet_policy",
]

FLEET_POLICIES: tuple[str, ...] = (*reversed(FLEET_BASELINES), KMEANS_SCORED, FLEET_ORACLE)
"""What a fleet can be served with: ``kmeans-load-weighted``, ``kmeans-min-distance``,
``kmeans-scored`` and ``fleet-oracle``."""
DEFAULT_FLEET_POLICY = KMEANS_SCORED
"""What a fleet is served with unless a policy is named: k-means partitions scored on the fleet
model, above both k-means placements on the held-out grid (docs/results.md, "Fleets") at tens
of milliseconds a decision (the fleet oracle takes seconds, see the module doc)."""


class FleetPolicy(Protocol):
    """What the service asks of a fleet policy: ``decide_fleet(reports, vehicles_xyz_m)`` gives
    one target (K, 3), metres, area frame, for each of the K vehicles in ``vehicles_xyz_m``
    (K, 3), separated by ``separation_m`` and inside the area volume. Targets need not be in the
    vehicles' order: the service assigns them (:func:`service.fleet_targets.assign_targets`)."""

    name: str
    spec: str
    kind: str
    separation_m: float

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray: ...

    def describe(self) -> dict[str, Any]: ...


@dataclass
class FleetPlacementPolicy:
    """A fleet placement (k-means baseline or search oracle) re-placed at every decision for
    the K vehicles that fly now; one placement object per K, built when first needed."""

    spec: str
    world: World
    separation_m: float = FleetConfig().separation_m
    kind: str = "placement"
    _placements: dict[int, Any] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.spec not in FLEET_POLICIES:
            raise InputError(f"policy: a fleet is served by one of {', '.join(FLEET_POLICIES)}")
        if not (np.isfinite(self.separation_m) and self.separation_m > 0):
            raise InputError(f"separation_m: must be > 0, got {self.separation_m!r}")

    @property
    def name(self) -> str:
        return self.spec

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        k = len(np.asarray(vehicles_xyz_m))
        if not 1 <= k <= MAX_UAVS:
            raise InputError(f"vehicles_xyz_m: 1..{MAX_UAVS} vehicles, got {k}")
        placement, users = self._placement(k), ReportedUsers.of(reports)
        if hasattr(placement, "place_from"):  # it scores from where the fleet is
            return placement.place_from(users, vehicles_xyz_m, None, self.world.flight)
        return np.asarray(placement.place(users), dtype=float)

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "spec": self.spec,
            "metadata": {"fleet": True, "separation_m": self.separation_m},
        }

    def _placement(self, k: int) -> Any:
        if k not in self._placements:
            world, sep = self.world, self.separation_m
            fleet = FleetConfig(n_uavs=k, separation_m=sep)
            # The model-scored placements score with the decision period as the model's step.
            if self.spec == FLEET_ORACLE:
                config = FleetOracleConfig(step_s=world.step_s)
                self._placements[k] = FleetOracle(
                    fleet, world.area, world.network, world.utility, config
                )
            elif self.spec == KMEANS_SCORED:
                self._placements[k] = ScoredKMeansPlacement(
                    fleet, world.area, world.network, world.utility, step_s=world.step_s
                )
            else:
                weighted = self.spec == "kmeans-load-weighted"
                self._placements[k] = KMeansPlacement(k, world.area, weighted, sep)
        return self._placements[k]


class FleetCheckpointServing:
    """A shared-parameter fleet checkpoint
    (:class:`policies.learned.fleet_checkpoint.FleetCheckpointPolicy`) deciding for the vehicles
    that fly now, from reports.

    The observation is the environments' (:func:`sim.fleet_observation.fleet_observations`) at the
    vehicles' positions. Which AP each user is on (the fleet maps need it) is not in a report:
    it is estimated with the fleet model's own rule (:func:`sim.association.associate_at`: the
    strongest mean received power, with the fleet's hysteresis), remembered from one decision
    to the next as stations remember their AP, and started afresh when the users or the number
    of vehicles change."""

    kind = "coordinates"

    def __init__(self, policy: Any, spec: str, world: World) -> None:
        self.policy = policy
        self.spec = spec
        self.world = world
        self.separation_m = policy.separation_m
        self._association: np.ndarray | None = None
        self._association_key: tuple[int, int] | None = None

    @property
    def name(self) -> str:
        """The checkpoint's name, as single-UAV checkpoints are named
        (``ddpg-residual-fleet-shared`` style, or the metadata's ``name`` for a shipped one)."""
        return default_name(self.policy.metadata, Path(self.spec))

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        vehicles = np.asarray(vehicles_xyz_m, dtype=float)
        xy = np.column_stack([reports.x_m, reports.y_m])
        key = (len(vehicles), len(xy))
        current = self._association if key == self._association_key else None
        association, _ = associate_at(
            vehicles[None], xy, self.world.area, self.world.network.radio, current,
            FleetConfig().hysteresis_db,
        )  # fmt: skip
        self._association, self._association_key = association, key
        observations = fleet_observations(vehicles, reports, association[0], self.world)
        return self.policy.targets(observations, reports, vehicles, association[0])

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "spec": self.spec,
            "metadata": {**self.policy.metadata, "fleet": True},
        }


def resolve_fleet_policy(
    spec: str,
    world: World,
    separation_m: float,
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
) -> FleetPlacementPolicy | FleetCheckpointServing:
    """The fleet policy ``spec`` for ``world``: a name of :data:`FLEET_POLICIES`, or a fleet
    checkpoint (a directory or ``model.zip`` written by ``tupa train --uavs K``; only from
    ``allowed_dirs`` when given, within ``max_bytes``). InputError naming ``policy`` otherwise
    (with the close names for a misspelt one)."""
    spec = str(spec).strip()
    if spec in FLEET_POLICIES:
        return FleetPlacementPolicy(spec, world, float(separation_m))
    close = close_names(spec, FLEET_POLICIES)
    if spec in PLACEMENTS:  # a real name, of a single-vehicle policy: say that, not "misspelt"
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise InputError(
            f"policy: a fleet is served by one of {', '.join(FLEET_POLICIES)} or a fleet "
            f"checkpoint, got {spec!r} (a single-vehicle policy cannot drive a fleet{hint})"
        )
    if close:
        raise InputError(unknown_name(spec, close, FLEET_POLICIES, "policy"))
    path = Path(spec)
    if not spec or not (path.is_dir() or path.suffix == ".zip"):
        raise InputError(
            f"policy: a fleet is served by one of {', '.join(FLEET_POLICIES)} or a fleet "
            f"checkpoint, got {spec!r} (single-vehicle policies cannot drive a fleet)"
        )
    from policies.learned.checkpoints import CheckpointError
    from policies.learned.fleet_checkpoint import FleetCheckpointPolicy

    try:
        policy = FleetCheckpointPolicy.load(
            path,
            world.area,
            separation_m,
            allowed_dirs=allowed_dirs,
            max_bytes=max_bytes,
            world=world,
        )
    except CheckpointError as exc:
        raise InputError(f"policy: {exc.problem}") from None
    return FleetCheckpointServing(policy, spec, world)
