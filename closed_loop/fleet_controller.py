"""The simulated network controller of a fleet: K vehicles, K access points, one report.

The fleet's counterpart of :mod:`closed_loop.controller`. Every step it

1. reads each vehicle's *true* position from its own autopilot over MAVLink
   (:class:`~closed_loop.controller.TruePosition` with the vehicle's system id: one connection
   per vehicle, each with its own :class:`~service.frames.FrameConfig`, since every vehicle has
   its own home);
2. simulates the step with :class:`sim.fleet.FleetModel` at those K positions: users associate
   with the strongest AP (with hysteresis) and hand over as vehicles and users move; queues,
   associations and handover counts carry over from step to step, as in the fleet environment;
3. POSTs one report of all users to ``tupa serve --fleet-file`` (``POST /v1/reports`` is the
   same for one vehicle or a fleet) and reads every vehicle's target from the answer's
   ``targets`` (``{"uav1": {"x_m": .., "y_m": .., "z_m": ..}, ...}``).

What it records per step (:class:`FleetStepRecord`): every vehicle's position and target, the
network utility over all users, each UAV's own utility, the served-user fraction, Jain's
fairness index of per-user throughput, the minimum user throughput and the handovers.

Users can be any object with ``xy_m`` (U, 2), ``load_bps`` (U,) and ``advance(dt_s, rng)``:
:class:`sim.users.UserDynamics` (one scenario under one world's mobility and demand) or
:class:`GroupedUsers` (groups of users, each under its own mobility: hot spots of which one
walks, as ``tupa demo --uavs K`` plays).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import httpx
import numpy as np

from closed_loop.controller import report_body
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel, FleetState
from sim.users import UserDynamics
from sim.world import Demand, Mobility

__all__ = [
    "FleetMeasurement",
    "FleetStepRecord",
    "FleetUsers",
    "GroupedUsers",
    "SimulatedFleetNetwork",
    "run_fleet_scenario",
    "summarise",
]


class FleetUsers(Protocol):
    """What the fleet controller needs of its users."""

    xy_m: np.ndarray
    load_bps: np.ndarray

    def advance(self, dt_s: float, rng: np.random.Generator) -> None: ...


class GroupedUsers:
    """Users in groups, each group a :class:`sim.users.UserDynamics` under its own mobility
    and demand (e.g. hot spots, one of them walking as a group); positions and loads are the
    groups' concatenated in order, ``group`` (U,) says which group each user is in.

    Every group draws from the generator it is given (at construction and in
    :meth:`advance`), in group order: deterministic given the generator's seed. A static group
    draws nothing.
    """

    def __init__(
        self,
        groups: Sequence[tuple[np.ndarray, np.ndarray, Mobility, Demand]],
        area: AreaConfig,
        rng: np.random.Generator,
    ) -> None:
        if not groups:
            raise InputError("groups: need at least one group of users")
        self.groups = [
            UserDynamics(xy, load, mobility, demand, area, rng)
            for xy, load, mobility, demand in groups
        ]
        self.group = np.concatenate(
            [np.full(len(g.load_bps), i, dtype=np.int64) for i, g in enumerate(self.groups)]
        )
        self._collect()

    def advance(self, dt_s: float, rng: np.random.Generator) -> None:
        for g in self.groups:
            g.advance(dt_s, rng)
        self._collect()

    def centres_m(self) -> np.ndarray:
        """Each group's centre (G, 2): its users' mean position now."""
        return np.array([g.xy_m.mean(axis=0) for g in self.groups])

    def _collect(self) -> None:
        self.xy_m = np.concatenate([g.xy_m for g in self.groups])
        self.load_bps = np.concatenate([g.load_bps for g in self.groups])
        self.xy_m.setflags(write=False)
        self.load_bps.setflags(write=False)


@dataclass(frozen=True)
class FleetMeasurement:
    """One simulated step of the fleet: per user (U,), per UAV (K,), over all users."""

    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray
    association: np.ndarray  # each user's AP: the vehicle's index in the fleet
    uav_utility: np.ndarray
    utility: float
    served_fraction: float
    jain_fairness: float
    min_throughput_bps: float
    handovers: int  # in this step
    handovers_total: int


@dataclass
class SimulatedFleetNetwork:
    """The users, measured wherever the K vehicles are, with :class:`sim.fleet.FleetModel`
    (queues, associations and handovers carried over between steps; sampled fading from
    ``seed``). ``users_rng`` is what the users draw from as they move (the generator they were
    built with, for a reproducible motion)."""

    users: FleetUsers
    fleet: FleetConfig
    network: NetworkConfig = field(default_factory=NetworkConfig)
    area: AreaConfig = field(default_factory=AreaConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    seed: int = 0
    users_rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def __post_init__(self) -> None:
        self.model = FleetModel(self.fleet, self.network, self.area, self.utility)
        self.rng = np.random.default_rng(self.seed)
        self.state: FleetState | None = None
        self._steps = 0

    @property
    def n_uavs(self) -> int:
        return self.fleet.n_uavs

    def measure(self, uav_xyz_m: np.ndarray, step_s: float = 1.0) -> FleetMeasurement:
        """Simulate ``step_s`` with the vehicles at ``uav_xyz_m`` (K, 3), in fleet order. The
        users move (and change their demand) by one step first, except on the first call."""
        if self._steps:
            self.users.advance(step_s, self.users_rng)
        self._steps += 1
        result = self.model.step(
            np.asarray(uav_xyz_m, dtype=float),
            self.users.xy_m,
            self.users.load_bps,
            self.state,
            self.rng,
            step_s,
        )
        self.state = result.state
        return FleetMeasurement(
            throughput_bps=result.throughput_bps[0],
            delay_s=result.delay_s[0],
            plr=result.plr[0],
            association=result.association[0],
            uav_utility=result.uav_utility[0],
            utility=float(result.utility[0]),
            served_fraction=float(result.served_fraction[0]),
            jain_fairness=float(result.jain_fairness[0]),
            min_throughput_bps=float(result.min_throughput_bps[0]),
            handovers=int(np.count_nonzero(result.handover[0])),
            handovers_total=int(result.handovers[0]),
        )

    def report(self, measured: FleetMeasurement, timestamp_s: float) -> dict[str, Any]:
        """The ``POST /v1/reports`` body: every user, whichever vehicle serves it."""
        return report_body(
            self.users.xy_m,
            self.users.load_bps,
            measured.throughput_bps,
            measured.delay_s,
            measured.plr,
            timestamp_s,
        )


@dataclass
class FleetStepRecord:
    """One step of the fleet's loop, as recorded (JSON-ready)."""

    step: int
    positions_m: dict[str, tuple[float, float, float]]
    targets_m: dict[str, tuple[float, float, float] | None]
    utility: float
    uav_utility: list[float]
    served_fraction: float
    jain_fairness: float
    min_throughput_bps: float
    handovers: int
    handovers_total: int
    association: list[int]
    users_xy_m: list[list[float]]
    load_bps: list[float]


class PositionSource(Protocol):
    """Where a vehicle is (area frame), waiting up to ``timeout_s`` for a first fix."""

    def wait(self, timeout_s: float) -> tuple[float, float, float]: ...


def parse_targets(
    answer: Mapping[str, Any], vehicle_ids: Sequence[str]
) -> dict[str, tuple[float, float, float] | None]:
    """Every vehicle's target from a fleet service's report answer (``targets``; ``None`` for
    a vehicle without one yet, or before the first decision)."""
    targets = answer.get("targets") or {}
    out: dict[str, tuple[float, float, float] | None] = {}
    for vid in vehicle_ids:
        t = targets.get(vid)
        out[vid] = (float(t["x_m"]), float(t["y_m"]), float(t["z_m"])) if t else None
    return out


def run_fleet_scenario(
    network: SimulatedFleetNetwork,
    vehicles: Mapping[str, PositionSource],
    client: httpx.Client,
    steps: int,
    step_s: float = 1.0,
    on_step: Callable[[FleetStepRecord], None] | None = None,
) -> list[FleetStepRecord]:
    """Play ``steps`` steps in real time: read every vehicle's true position, measure there,
    POST one report of all users, record, wait for the next tick.

    ``vehicles`` maps each vehicle's id (the fleet file's) to its position source, in the
    fleet's order: the i-th vehicle carries AP i. ``client`` carries the service's base URL and
    token. Raises ``httpx.HTTPStatusError`` when the service refuses a report.
    """
    if len(vehicles) != network.n_uavs:
        raise InputError(
            f"vehicles: {len(vehicles)} given for a fleet of {network.n_uavs} access points"
        )
    ids = list(vehicles)
    records: list[FleetStepRecord] = []
    next_at = time.monotonic()
    for step in range(steps):
        positions: dict[str, tuple[float, float, float]] = {}
        for vid in ids:
            x, y, z = vehicles[vid].wait(30.0)
            positions[vid] = (float(x), float(y), float(z))
        measured = network.measure(np.array([positions[vid] for vid in ids]), step_s)
        response = client.post("/v1/reports", json=network.report(measured, time.time()))
        response.raise_for_status()
        record = FleetStepRecord(
            step=step,
            positions_m=positions,
            targets_m=parse_targets(response.json(), ids),
            utility=measured.utility,
            uav_utility=[float(v) for v in measured.uav_utility],
            served_fraction=measured.served_fraction,
            jain_fairness=measured.jain_fairness,
            min_throughput_bps=measured.min_throughput_bps,
            handovers=measured.handovers,
            handovers_total=measured.handovers_total,
            association=[int(a) for a in measured.association],
            users_xy_m=network.users.xy_m.tolist(),
            load_bps=network.users.load_bps.tolist(),
        )
        records.append(record)
        if on_step is not None:
            on_step(record)
        next_at += step_s
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # the controller's reporting period (real time)
        else:
            next_at = time.monotonic()
    return records


def summarise(records: Sequence[FleetStepRecord]) -> dict[str, float]:
    """A loop's metrics: the means over its steps of the utility, the served-user fraction,
    Jain's fairness and the minimum user throughput; the handovers over the whole run."""
    if not records:
        raise InputError("records: need at least one step to summarise")
    return {
        "utility": float(np.mean([r.utility for r in records])),
        "served_fraction": float(np.mean([r.served_fraction for r in records])),
        "jain_fairness": float(np.mean([r.jain_fairness for r in records])),
        "min_throughput_bps": float(np.mean([r.min_throughput_bps for r in records])),
        "handovers": int(records[-1].handovers_total),
        "steps": len(records),
    }
