"""Fleet policies for serving: the users' report and where the flying vehicles are in, one
target per vehicle out, for however many vehicles fly *now*.

A fleet in the air loses and regains vehicles (a lost link, a battery swap), so a served fleet
policy is asked for K targets with K the vehicles it may command at that moment, and must cover
every user with them (the service's degraded mode). The placements of
:mod:`policies.placements.fleet_baselines` and :mod:`policies.placements.fleet_oracle` take K at
construction; a :class:`FleetPlacementPolicy` keeps one per K it has been asked for and re-places
every decision, as :class:`policies.adapters.StaticPolicy` does for one vehicle.

Names (``tupa serve --policy``): :data:`FLEET_POLICIES`. The fleet oracle searches with the
fleet network model and takes seconds a decision (``python benchmarks/fleet_speed.py``; docs/
results.md, "Fleets"): serve it only where a decision period allows that. The same objects are
what ``tupa eval --uavs K`` evaluates (:func:`resolve_fleet_policy`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
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
    "ReportedAssociation",
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
    vehicles' order: the service assigns them (:func:`sim.fleet_targets.assign_targets`)."""

    name: str
    spec: str
    kind: str
    separation_m: float

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray: ...

    def reset(self) -> None:
        """Forget what was remembered from earlier decisions (the users' APs): a new episode."""
        ...

    def describe(self) -> dict[str, Any]: ...


class ReportedAssociation:
    """Which AP each reported user is on, as a fleet policy deciding from reports needs it (a
    report does not carry it): estimated with the fleet model's own rule
    (:func:`sim.association.associate_at`: the strongest mean received power at the vehicles'
    positions, with ``hysteresis_db``), remembered from one decision to the next as stations
    remember their AP, and started afresh when the number of users or of vehicles changes or
    at :meth:`reset` (a new episode). The one rule of serving and evaluation."""

    def __init__(self, world: World, hysteresis_db: float = FleetConfig().hysteresis_db) -> None:
        self.world = world
        self.hysteresis_db = float(hysteresis_db)
        self._current: np.ndarray | None = None
        self._key: tuple[int, int] | None = None

    def reset(self) -> None:
        self._current = self._key = None

    def at(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        """The users' APs (U,), index into ``vehicles_xyz_m`` (K, 3); ``NOT_ASSOCIATED``
        for a user no AP reaches."""
        vehicles = np.asarray(vehicles_xyz_m, dtype=float)
        xy = np.column_stack([reports.x_m, reports.y_m])
        key = (len(vehicles), len(xy))
        current = self._current if key == self._key else None
        association, _ = associate_at(
            vehicles[None], xy, self.world.area, self.world.network.radio, current,
            self.hysteresis_db,
        )  # fmt: skip
        self._current, self._key = association, key
        return association[0]


@dataclass
class FleetPlacementPolicy:
    """A fleet placement (k-means baseline, ``kmeans-scored`` or the search oracle) re-placed
    at every decision for the K vehicles that fly now; one placement object per K, built when
    first needed, scoring (``kmeans-scored``, ``fleet-oracle``) with the world's decision
    period and episode, on a fleet like ``fleet`` (channels, hysteresis, served ratio; K and the
    separation are set per K; None: the defaults), the search seeded with ``seed``. The users'
    APs a model-scored placement starts from: :class:`ReportedAssociation`."""

    spec: str
    world: World
    separation_m: float = FleetConfig().separation_m
    kind: str = "placement"
    fleet: FleetConfig | None = None
    seed: int = 0
    built: Any = None
    """A placement object already built for ``fleet.n_uavs`` vehicles (``place(users)``, and
    ``place_from`` where it scores from where the fleet is), decided with as a named one is
    (``spec`` is then just its name): :meth:`around`."""
    _placements: dict[int, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    _association: ReportedAssociation = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.built is None and self.spec not in FLEET_POLICIES:
            raise InputError(f"policy: a fleet is served by one of {', '.join(FLEET_POLICIES)}")
        if self.built is not None:
            if self.fleet is None:
                raise InputError("fleet: a built placement needs the fleet it was built for")
            self._placements[self.fleet.n_uavs] = self.built
        if not (np.isfinite(self.separation_m) and self.separation_m > 0):
            raise InputError(f"separation_m: must be > 0, got {self.separation_m!r}")
        hysteresis_db = (self.fleet or FleetConfig()).hysteresis_db
        self._association = ReportedAssociation(self.world, hysteresis_db)

    @classmethod
    def around(cls, placement: Any, world: World, fleet: FleetConfig) -> FleetPlacementPolicy:
        """``placement``, built for ``fleet.n_uavs`` vehicles, as a fleet policy (see
        ``built``)."""
        name = str(getattr(placement, "name", "") or type(placement).__name__)
        return cls(name, world, fleet.separation_m, fleet=fleet, built=placement)

    @property
    def name(self) -> str:
        return self.spec

    def reset(self) -> None:
        """Forget the users' APs (a new episode)."""
        self._association.reset()

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        vehicles = np.asarray(vehicles_xyz_m, dtype=float)
        k = len(vehicles)
        if not 1 <= k <= MAX_UAVS:
            raise InputError(f"vehicles_xyz_m: 1..{MAX_UAVS} vehicles, got {k}")
        placement, users = self._placement(k), ReportedUsers.of(reports)
        if hasattr(placement, "place_from"):  # it scores from where the fleet is
            association = self._association.at(reports, vehicles)
            return placement.place_from(users, vehicles, association, self.world.flight)
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
            if self.built is not None:
                raise InputError(
                    f"vehicles_xyz_m: {self.spec} was built for {self.fleet.n_uavs} vehicles, "
                    f"got {k}"
                )
            world = self.world
            fleet = replace(self.fleet or FleetConfig(), n_uavs=k, separation_m=self.separation_m)
            # The model-scored placements score with the decision period as the model's step.
            if self.spec == FLEET_ORACLE:
                config = FleetOracleConfig(
                    episode_steps=world.episode_steps, step_s=world.step_s, seed=self.seed
                )
                self._placements[k] = FleetOracle(
                    fleet, world.area, world.network, world.utility, config
                )
            elif self.spec == KMEANS_SCORED:
                self._placements[k] = ScoredKMeansPlacement(
                    fleet, world.area, world.network, world.utility, world.episode_steps,
                    world.step_s,
                )  # fmt: skip
            else:
                weighted = self.spec == "kmeans-load-weighted"
                self._placements[k] = KMeansPlacement(k, world.area, weighted, self.separation_m)
        return self._placements[k]


class FleetCheckpointServing:
    """A fleet checkpoint (:class:`policies.learned.fleet_checkpoint.FleetCheckpointPolicy`, or
    any policy with its ``targets(observations, reports, uav_xyz_m, association)``) deciding
    for the vehicles that fly now, from reports.

    The observation is the environments' (:func:`sim.fleet_observation.fleet_observations`) at the
    vehicles' positions, with the users' APs of :class:`ReportedAssociation` (a report does not
    carry them)."""

    kind = "coordinates"

    def __init__(
        self,
        policy: Any,
        spec: str,
        world: World,
        hysteresis_db: float = FleetConfig().hysteresis_db,
    ) -> None:
        self.policy = policy
        self.spec = spec
        self.world = world
        self.separation_m = policy.separation_m
        self._association = ReportedAssociation(world, hysteresis_db)

    @property
    def name(self) -> str:
        """The checkpoint's name, as single-UAV checkpoints are named
        (``ddpg-residual-fleet-shared`` style, or the metadata's ``name`` for a shipped one)."""
        return default_name(self.policy.metadata, Path(self.spec) if self.spec else None)

    def reset(self) -> None:
        """Forget the users' APs (a new episode)."""
        self._association.reset()

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        vehicles = np.asarray(vehicles_xyz_m, dtype=float)
        association = self._association.at(reports, vehicles)
        observations = fleet_observations(vehicles, reports, association, self.world)
        return self.policy.targets(observations, reports, vehicles, association)

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
    *,
    fleet: FleetConfig | None = None,
    seed: int = 0,
) -> FleetPlacementPolicy | FleetCheckpointServing:
    """The fleet policy ``spec`` for ``world``, as served and as evaluated: a name of
    :data:`FLEET_POLICIES` (a :class:`FleetPlacementPolicy` on a fleet like ``fleet``, seeded
    with ``seed``), or a fleet checkpoint (a directory or ``model.zip`` written by ``tupa train
    --uavs K``; only from ``allowed_dirs`` when given, within ``max_bytes``). InputError naming
    ``policy`` otherwise (with the close names for a misspelt one)."""
    spec = str(spec).strip()
    template = replace(fleet or FleetConfig(), separation_m=float(separation_m))
    if spec in FLEET_POLICIES:
        return FleetPlacementPolicy(spec, world, float(separation_m), fleet=template, seed=seed)
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
    return FleetCheckpointServing(policy, spec, world, template.hysteresis_db)
