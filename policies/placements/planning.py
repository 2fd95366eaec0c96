"""The planning oracle (``planning-oracle``): a receding-horizon planner over flown trajectories.

The tracking oracle (:meth:`policies.placements.oracle.OraclePlacement.track`, re-placed every
decision) asks *where is the best place to hold for an episode* and flies straight there. In a world
that flies (``closed-loop``: 10 m/s over a 500 m area, so a far target is tens of decisions away)
that ignores what the flight costs: the utility on the way, the backlog built while the vehicle is
far, the episode ending before the vehicle arrives. The planner asks instead *which trajectory
is best for the rest of the episode*, with the same model (expected mode) and the same flight,
and replans every decision from the latest report.

**A trajectory** is a sequence of ``horizon_steps`` (H) targets, one per decision period, the
last one then held (``A A A``: go to A and stay; ``W A A``: head for W for one period, then for
A). It is flown exactly as the world flies: :func:`sim.flight.fly_many` (the world's speed
limits, the same floats as :meth:`sim.world.World.fly`); with acceleration limits or a latency,
the world's ``fly_period`` with the velocity and the previous target carried from period to
period (the vehicle's own motion at the decision is the last period replayed with that flight
from what the planner knew then: exact in the world, the mean velocity elsewhere); with an
envelope, :meth:`sim.world.World.fly_route` with the route carried from period to period as the
environment carries it. Every candidate target is first made legal (clipped into the volume;
with an envelope, :func:`sim.envelope.paths.legal_target`), so every target the planner returns
is one the world would fly to unchanged.

**Its value** (:meth:`PlanningPolicy.score`) is the sum of the model's expected-mode utility over
the *rest of the episode* (``remaining_steps``, the decisions left; optionally discounted): the
H planned periods, then the flight on to the last target and the hold there. That tail is the
terminal value, computed by the same rollout rather than guessed: a trajectory that stops short
is charged for every period it spends short of a better place, and one that heads for a far
place is charged for the periods it spends getting there, so the planner neither prefers a
myopic stop nor an unreachable optimum. Queues are carried across every step, from the cell's
state after the period that just ended, which the planner follows with the model along where
the vehicle was, period by period, from empty queues at the episode's start (the environment's
reset step; a backlog built while the vehicle was far is still there when it plans). In a
deterministic world with static users the value of the tracking oracle's trajectory is exactly
what the world scores for it (``tests/policies/test_planning.py``). A candidate whose vehicle
stopped at its final target (moved less than ``settled_m``) with queues that no longer change
has reached a fixed point (the model is deterministic): its remaining steps are filled in
without being simulated, which is where the oracle's episodes save their time too. All
candidates advance together, one batched model call per step. ``rollout_steps`` caps the steps
simulated (the rest counted as the last one): off by default.

**What it knows**: the world (its flight, its envelope, its episode length, its model) and the
latest report; not the future draws. Users are planned where the latest report puts them, with
its loads: under random waypoint with unknown waypoints and demand that steps up and down
symmetrically in log, that is the statistics' central estimate over the next steps (the
tracking oracle assumes the same). In a world without episodes (the service, no
:meth:`~PlanningPolicy.begin_episode`) the rest of the episode is the world's
``episode_steps``, a constant receding window.

**Candidates** (:meth:`PlanningPolicy.plan`), in three stages, each one batch:

1. *Go and stay* (``A`` held) for every final target A among: the tracking oracle's answer for
   the latest report (exactly the target the ``oracle`` policy would fly to: the same
   :class:`~policies.adapters.StaticPolicy` over the same
   :class:`~policies.placements.oracle.OraclePlacement`, fed the same reports), the last decision's
   final target, where the vehicle is (stay), the ``min-distance``, ``load-weighted`` and
   ``min-distance-env`` positions, the best ``screen_top_k`` of a short screen of a coarse grid
   (every ``screen_stride``-th zone at every level) and the best ``screen_top_k`` to reach (the
   screen's value times the share of the remaining steps left once there at the speed caps), the
   tracking answer and the vehicle's position at every altitude level, points part-way from the
   vehicle to the tracking answer, where H periods' flight in each of ``ring_headings`` directions
   would take the vehicle (at its altitude and the answer's), and above each of the ``user_targets``
   busiest users (at the same two altitudes: serve some users soon, where the best place for
   all of them is far).
2. *Stop short, change level, two legs* for the best ``leg_targets`` final targets A of stage 1:
   points part-way to A and A at every altitude level, held; and ``W…W A…A``, a first target W
   for k = 1..H−1 periods — the vehicle's position or A at every altitude level, a point
   part-way to A, or another of those final targets — then A.
3. *Refinement*: a compass search (±x, ±y, ±z, ``refine_step_m``, halved when nothing improves)
   on the best trajectory's final target, its first legs kept, for ``refine_iterations``
   iterations.

The answer is the first target of the best trajectory (ties to the earliest candidate; the
tracking oracle's ``A A A`` is the first), so on the planner's own objective it is never below
the tracking oracle's trajectory, and it is deterministic for the same sequence of inputs (its
state — the tracking oracle's, the last plan, the followed queues and motion — is reset by
``begin_episode``).

Why this shape: the tracking oracle's answer is a near-optimal static target already (its
search is exhaustive over a grid, refined); what it misses is time — flight, backlog, the
episode's end — and the way there (altitude on the way, a nearer target that is reached sooner).
Stages 1 and 3 trade the target against the time to reach it, stage 2 the way there. An
exhaustive search over target sequences costs (targets)^H rollouts; this costs one to two
hundred trajectories in three batches, and
``benchmarks/planning_oracle.py`` measures the gap to an exhaustive search on small cases and
the cost per decision (``docs/planning.md``).

What it does not do: it plans for the model's expected mode, and the expected mode's utility is
not the mean utility under fading, so in a stochastic world a single scenario can go either
way (the benchmark counts them); users are not extrapolated along their walk (the latest
report's positions are kept); and K = 1 only: a fleet's planner is out of scope here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from policies.adapters import StaticPolicy
from policies.interface import Placement, PolicyKind, ReportedUsers, UsersLike
from policies.placements.baselines import MinDistancePlacement
from policies.placements.oracle import (
    OracleConfig,
    OraclePlacement,
    coarse_grid_positions_m,
    episode_utility,
)
from sim.flight import fly_many
from sim.geometry import clip_to_volume
from sim.network import NetworkModel, QueueState
from sim.observation import UserReports
from sim.utility import network_utility
from sim.world import PAPER, World

_DIRECTIONS = np.concatenate([np.eye(3), -np.eye(3)])


@dataclass(frozen=True)
class PlanningConfig:
    """Knobs of the planner (see the module doc); the defaults are the shipped reference."""

    horizon_steps: int = 3  # H: decision periods planned target by target
    discount: float = 1.0  # per-step discount of the value (1: the evaluation's plain mean)
    rollout_steps: int | None = None  # steps valued; None: the rest of the episode
    screen_stride: int = 4  # the coarse screen: every this many zones in x and y
    screen_steps: int = 3  # its horizon (steps after a warm-up step)
    screen_top_k: int = 4  # its best positions taken as final targets
    partway_fractions: tuple[float, ...] = (0.25, 0.5, 0.75)  # points part-way to a target
    ring_headings: int = 8  # stage 1: points H periods' flight away in this many directions
    user_targets: int = 8  # stage 1: above this many of the busiest users
    leg_targets: int = 3  # stage 2: best final targets given two-leg trajectories
    refine_iterations: int = 2  # stage 3: compass iterations on the best final target
    refine_step_m: float | None = None  # stage 3's first step; None: half a zone
    improvement_tol: float = 1e-9  # a candidate must beat the best by more than this
    # A vehicle that moved less than this in a step, its queues unchanged, has stopped: its
    # remaining steps repeat that step (exact when 0; an accelerating vehicle creeps toward its
    # target forever, so a few millimetres, utility-wise the same place).
    settled_m: float = 1e-3

    def __post_init__(self) -> None:
        for name in ("horizon_steps", "screen_stride", "screen_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in (
            "screen_top_k",
            "ring_headings",
            "user_targets",
            "leg_targets",
            "refine_iterations",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.rollout_steps is not None and self.rollout_steps < 1:
            raise ValueError(f"rollout_steps: must be >= 1 or None, got {self.rollout_steps}")
        if not 0.0 < self.discount <= 1.0:
            raise ValueError(f"discount: must lie in (0, 1], got {self.discount}")
        object.__setattr__(
            self, "partway_fractions", tuple(float(f) for f in self.partway_fractions)
        )
        if any(not 0.0 < f < 1.0 for f in self.partway_fractions):
            raise ValueError(
                f"partway_fractions: each must lie in (0, 1), got {self.partway_fractions}"
            )
        if self.refine_step_m is not None and not self.refine_step_m > 0:
            raise ValueError(f"refine_step_m: must be > 0 or None, got {self.refine_step_m}")
        if not self.settled_m >= 0:
            raise ValueError(f"settled_m: must be >= 0, got {self.settled_m}")
        if not self.improvement_tol >= 0:
            raise ValueError(f"improvement_tol: must be >= 0, got {self.improvement_tol}")


@dataclass(frozen=True)
class VehicleMotion:
    """What a flight that carries a velocity needs besides the position: the vehicle's velocity
    (3,), m/s, and the target it was flying to in the period that just ended (3,), metres."""

    velocity_mps: np.ndarray
    previous_target_m: np.ndarray


def _carries_velocity(world: World) -> bool:
    """Whether a period's flight depends on more than the position and the target: a world
    whose flight has acceleration limits or a latency (``Flight.stateless`` false; flown by
    ``World.fly_period``; with an envelope only when its routes are flown at the speed caps)."""
    return not world.flight.stateless and (world.envelope is None or world.flight.accelerates)


@dataclass(frozen=True)
class Plan:
    """One decision's plan: the target to fly to now (3,), the chosen trajectory (H, 3) and its
    value (summed utility over ``remaining_steps``), the tracking oracle's trajectory (H, 3)
    and its value on the same objective, and the number of trajectories scored."""

    target_m: np.ndarray
    trajectory_m: np.ndarray
    value: float
    tracking_trajectory_m: np.ndarray
    tracking_value: float
    remaining_steps: int
    trajectories_scored: int


class PlanningPolicy:
    """The planning oracle as a :class:`~policies.interface.Policy` (see the module doc).

    ``world`` is the world it plans in (its flight, envelope, episode length and model);
    :meth:`begin_episode` replaces it when the evaluation runs another one.
    """

    kind: PolicyKind = "coordinates"

    def __init__(
        self,
        world: World = PAPER,
        config: PlanningConfig = PlanningConfig(),
        name: str = "planning-oracle",
        spec: str = "",
    ) -> None:
        self.config = config
        self.name = name
        self.spec = spec or name
        self._setup(world)

    # -- the Policy protocol ------------------------------------------------------------------

    def begin_episode(self, users: UsersLike, world: World) -> np.ndarray | None:
        """Forget the last episode (the tracking oracle's state and the last plan); count the
        decisions of this one. Starts where the world starts a static policy: at the tracking
        oracle's placement under ``static_start="placement"`` (the paper), else at home."""
        if world != self.world:
            self._setup(world)
        self._reset()
        self._in_episode = True
        if world.static_start == "placement":
            return self._tracking.begin_episode(users, world)
        self._tracking.begin_episode(users, world)
        return None

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        """The first target of the best trajectory from the latest report (3,), metres."""
        if self._in_episode:
            remaining = max(1, self.world.episode_steps - self._decisions)
        else:
            remaining = self.world.episode_steps
        vehicle_m = np.asarray(vehicle_xyz_m, dtype=float).reshape(3)
        motion = self._motion(vehicle_m)
        users = ReportedUsers.of(reports)
        # The cell's state, followed with the model along where the vehicle was: the period
        # that just ended was spent at its position (from empty queues before the first).
        state = self._queues
        if state is None or state.arrays[0].shape[1] != len(users.load_bps):
            state = None
        self._queues = self.model.step(
            vehicle_m[None], users.users_xy_m, users.load_bps, state, None, self.world.step_s
        ).state
        plan = self.plan(users, vehicle_m, remaining, motion, self._queues)
        self._decisions += 1
        self._last_final_m = plan.trajectory_m[-1].copy()
        self._last = (vehicle_m.copy(), motion, plan.target_m.copy())
        return plan.target_m.copy()

    def _motion(self, vehicle_m: np.ndarray) -> VehicleMotion | None:
        """The vehicle's motion now, for a flight that carries a velocity (else None): the last
        period replayed with the world's flight from what the planner knew then (exact in the
        world itself); where that does not land where the vehicle is (a real vehicle), the mean
        velocity over the period; at rest before the first decision, or after a jump no period's
        flight makes."""
        if not _carries_velocity(self.world):
            return None
        if self._last is None:
            return VehicleMotion(np.zeros(3), vehicle_m.copy())
        position, motion, target = self._last
        assert motion is not None
        flown, velocity = self.world.fly_period(
            position[None], motion.velocity_mps[None], motion.previous_target_m[None], target[None]
        )
        if np.allclose(flown[0], vehicle_m, rtol=0.0, atol=1e-6):
            return VehicleMotion(velocity[0], target)
        flight, step_s = self.world.flight, self.world.step_s
        mean_mps = (vehicle_m - position) / step_s
        cap_h, cap_v = flight.horizontal_mps or np.inf, flight.vertical_mps or np.inf
        if np.hypot(*mean_mps[:2]) > 1.5 * cap_h or abs(mean_mps[2]) > 1.5 * cap_v:
            # Not one period's flight (the service's test decision, a vehicle that was moved):
            # nothing known of its motion, taken at rest.
            return VehicleMotion(np.zeros(3), vehicle_m.copy())
        return VehicleMotion(mean_mps, target)

    def describe(self) -> dict[str, Any]:
        c = self.config
        return {
            "name": self.name,
            "kind": self.kind,
            "spec": self.spec,
            "metadata": {"horizon_steps": c.horizon_steps, "discount": c.discount},
        }

    # -- planning -----------------------------------------------------------------------------

    def plan(
        self,
        users: UsersLike,
        vehicle_xyz_m: np.ndarray,
        remaining_steps: int | None = None,
        motion: VehicleMotion | None = None,
        queues: QueueState | None = None,
    ) -> Plan:
        """Plan from ``vehicle_xyz_m`` (and ``motion``, for a flight that carries a velocity;
        ``queues``, the cell's state after the period that just ended, see :meth:`score`) for
        ``users`` over ``remaining_steps`` (default: the world's episode). Advances the
        tracking oracle (it is asked for the latest report, as the ``oracle`` policy would be);
        otherwise pure."""
        c = self.config
        vehicle_m = np.asarray(vehicle_xyz_m, dtype=float).reshape(3)
        start_m = self._legal(vehicle_m[None])[0]
        remaining = self.world.episode_steps if remaining_steps is None else int(remaining_steps)
        if remaining < 1:
            raise ValueError(f"remaining_steps: must be >= 1, got {remaining}")
        users = ReportedUsers(
            np.asarray(users.users_xy_m, dtype=float), np.asarray(users.load_bps, dtype=float)
        )
        tracking_m = self._legal(self._tracking.place(users)[None])[0]

        # 1. Go and stay, for every final target.
        finals = self._final_targets(users, start_m, tracking_m, remaining)
        trajectories = np.repeat(finals[:, None, :], c.horizon_steps, axis=1)
        values = self.score(trajectories, users, vehicle_m, remaining, motion, queues)
        tracking_trajectory, tracking_value = trajectories[0].copy(), float(values[0])
        best = int(np.argmax(values))
        best_trajectory, best_value = trajectories[best].copy(), float(values[best])
        scored = len(trajectories)

        # 2. Two legs for the best few final targets.
        if c.horizon_steps > 1 and c.leg_targets > 0:
            order = np.argsort(-values, kind="stable")[: c.leg_targets]
            short = [self._partway(start_m, final) for final in finals[order]]
            short += [self._at_levels(final) for final in finals[order]]
            legs = np.concatenate(
                [
                    np.repeat(
                        _distinct(self._legal(np.concatenate(short)))[:, None], c.horizon_steps, 1
                    ),
                    self._two_legs(finals[order], start_m),
                ]
            )
            if len(legs):
                leg_values = self.score(legs, users, vehicle_m, remaining, motion, queues)
                scored += len(legs)
                winner = int(np.argmax(leg_values))
                if leg_values[winner] > best_value + c.improvement_tol:
                    best_trajectory, best_value = legs[winner].copy(), float(leg_values[winner])

        # 3. Compass refinement of the best trajectory's final target.
        step_m = c.refine_step_m or self.world.area.zone_m / 2.0
        for _ in range(c.refine_iterations):
            moved = self._legal(best_trajectory[-1] + step_m * _DIRECTIONS)
            keep = ~np.all(moved == best_trajectory[-1], axis=1)
            if not keep.any():
                step_m /= 2.0
                continue
            variants = np.repeat(best_trajectory[None], int(keep.sum()), axis=0)
            # The final target moves; the legs heading for it (all but the first legs' own
            # targets) move with it.
            final_legs = np.all(best_trajectory == best_trajectory[-1], axis=1)
            variants[:, final_legs] = moved[keep][:, None, :]
            variant_values = self.score(variants, users, vehicle_m, remaining, motion, queues)
            scored += len(variants)
            winner = int(np.argmax(variant_values))
            if variant_values[winner] > best_value + c.improvement_tol:
                best_trajectory, best_value = variants[winner].copy(), float(variant_values[winner])
            else:
                step_m /= 2.0
        return Plan(
            target_m=best_trajectory[0].copy(),
            trajectory_m=best_trajectory,
            value=best_value,
            tracking_trajectory_m=tracking_trajectory,
            tracking_value=tracking_value,
            remaining_steps=remaining,
            trajectories_scored=scored,
        )

    def score(
        self,
        trajectories_m: np.ndarray,
        users: UsersLike,
        start_m: np.ndarray,
        remaining_steps: int,
        motion: VehicleMotion | None = None,
        queues: QueueState | None = None,
    ) -> np.ndarray:
        """The value (N,) of each trajectory (N, H, 3) flown from ``start_m``: the model's
        expected-mode utility summed (discounted by ``config.discount`` per step) over
        ``remaining_steps`` steps, the last target held after the H-th, queues carried from
        ``queues`` (the cell's state, one row, after the period that just ended; None: one
        warm-up step at ``start_m`` from empty queues, as an episode starts); see the module
        doc. With ``config.rollout_steps`` below ``remaining_steps``, only that many steps are
        simulated and every later one counts as the last simulated. Targets are flown as given
        (the world legalises an illegal one).
        In a world whose flight carries a velocity (acceleration limits, latency: the world's
        ``fly_period``), ``motion`` is the vehicle's at ``start_m`` (None: at rest, its last
        target ``start_m``)."""
        c, world, model = self.config, self.world, self.model
        trajectories = np.asarray(trajectories_m, dtype=float)
        if trajectories.ndim != 3 or trajectories.shape[2] != 3:
            raise ValueError(f"trajectories_m: must be (N, H, 3), got {trajectories.shape}")
        n, horizon = trajectories.shape[:2]
        total = int(remaining_steps)
        steps = total if c.rollout_steps is None else min(total, c.rollout_steps)
        xy = np.asarray(users.users_xy_m, dtype=float)
        load = np.asarray(users.load_bps, dtype=float)
        start = np.asarray(start_m, dtype=float).reshape(1, 3)
        if queues is None:
            queues = model.step(start, xy, load, None, None, world.step_s).state
        queues = queues.map(lambda a: np.repeat(a[:1], n, axis=0))
        weights = c.discount ** np.arange(total)
        tails = np.append(np.cumsum(weights[::-1])[::-1], 0.0)  # tails[t]: steps t.. to the end
        values = np.zeros(n)
        position = np.repeat(start, n, axis=0)
        routes: list[Any] = [None] * n
        carried = _carries_velocity(world)
        if carried:
            motion = motion or VehicleMotion(np.zeros(3), start[0])
            velocity = np.repeat(motion.velocity_mps.reshape(1, 3), n, axis=0)
            previous = np.repeat(motion.previous_target_m.reshape(1, 3), n, axis=0)
        index = np.arange(n)  # the trajectories still simulated
        # With an acceleration limit the trajectories are scored as the open sky flies them
        # (their targets are legal points; a route's detour is not in the score): planning
        # every candidate's route would cost more than a decision may.
        routed = world.envelope is not None and not carried
        for t in range(steps):
            targets = trajectories[index, min(t, horizon - 1)]
            if routed:
                flown = np.empty_like(targets)
                for row, (i, p, goal) in enumerate(zip(index, position, targets, strict=True)):
                    flown[row], routes[i] = world.fly_route(p, goal, routes[i])
            elif carried:
                flown, velocity = world.fly_period(position, velocity, previous, targets)
                previous = targets
            else:
                flown = fly_many(position, targets, world.flight, world.step_s)
            result = model.step(flown, xy, load, queues, None, world.step_s)
            utility = network_utility(
                result.throughput_bps, result.delay_s, result.plr, load, world.utility
            )
            values[index] += weights[t] * utility
            new_queues = result.state
            if t >= horizon - 1 and t + 1 < total:
                # Stopped at its held target with queues unchanged: every later step repeats
                # this one (the model is deterministic), so its tail is filled in.
                still = np.all(np.abs(flown - position) <= c.settled_m, axis=1)
                settled = still & new_queues.same_as(queues)
                if settled.any():
                    values[index[settled]] += tails[t + 1] * utility[settled]
                    keep = ~settled
                    index, flown, utility = index[keep], flown[keep], utility[keep]
                    if carried:
                        velocity, previous = velocity[keep], previous[keep]
                    new_queues = new_queues.map(lambda a, keep=keep: a[keep])
                    if not len(index):
                        break
            position, queues = flown, new_queues
        if steps < total and len(index):  # the steps not simulated: as the last one
            values[index] += tails[steps] * utility
        return values

    # -- helpers ------------------------------------------------------------------------------

    def _setup(self, world: World) -> None:
        self.world = world
        area = world.area
        self.model = NetworkModel(world.network, area)
        oracle = OraclePlacement(
            area,
            world.network,
            world.utility,
            OracleConfig(episode_steps=world.episode_steps, step_s=world.step_s),
        )
        self._tracking = StaticPolicy(oracle, "oracle")
        self._baselines: tuple[Placement, ...] = (
            MinDistancePlacement(area),
            MinDistancePlacement(area, load_weighted=True),
            MinDistancePlacement(
                area, altitude="best-snr", frequency_hz=world.network.radio.frequency_hz
            ),
        )
        self._coarse_m = coarse_grid_positions_m(area, self.config.screen_stride)
        self._levels_m = area.altitude_levels_m()
        self._reset()
        self._in_episode = False

    def _reset(self) -> None:
        self._decisions = 0
        self._last: tuple[np.ndarray, VehicleMotion | None, np.ndarray] | None = None
        self._queues: QueueState | None = None
        self._last_final_m: np.ndarray | None = None
        oracle = self._tracking.placement
        if isinstance(oracle, OraclePlacement):
            oracle.reset_tracking()

    def _legal(self, points_m: np.ndarray) -> np.ndarray:
        """Each row of ``points_m`` (N, 3) made a target the world flies to unchanged: inside
        the volume and, with an envelope, its nearest legal point (a row with none is dropped
        — never the case for a sound envelope)."""
        points = clip_to_volume(np.asarray(points_m, dtype=float), self.world.area)
        envelope = self.world.flight_envelope
        if envelope is None:
            return points
        from sim.envelope.paths import legal_target

        legal = [legal_target(envelope, p) for p in points]
        return np.array([p for p in legal if p is not None], dtype=float).reshape(-1, 3)

    def _final_targets(
        self, users: ReportedUsers, start_m: np.ndarray, tracking_m: np.ndarray, remaining: int
    ) -> np.ndarray:
        """Stage 1's final targets (F, 3), legal and distinct, the tracking answer first."""
        c, world = self.config, self.world
        rows = [tracking_m[None]]
        if self._last_final_m is not None:
            rows.append(self._last_final_m[None])
        rows.append(start_m[None])
        rows.append(np.stack([b.place(users) for b in self._baselines]))
        if c.screen_top_k > 0:
            screen = episode_utility(
                self.model,
                self._coarse_m,
                users,
                c.screen_steps,
                1,
                world.step_s,
                world.utility,
            )
            top = np.argsort(-screen, kind="stable")[: c.screen_top_k]
            rows.append(self._coarse_m[top])
            # The best to reach: the screen's value counted only for the steps left once there.
            transit = self._transit_steps(start_m, self._coarse_m)
            reachable = screen * np.clip(remaining - transit, 0, None) / remaining
            top = np.argsort(-reachable, kind="stable")[: c.screen_top_k]
            rows.append(self._coarse_m[top])
        rows.append(self._at_levels(tracking_m))
        rows.append(self._at_levels(start_m))
        rows.append(self._partway(start_m, tracking_m))
        rows.append(self._ring(start_m, tracking_m[2]))
        if c.user_targets > 0:
            # Above the busiest users (a stable order: ties by index), at the vehicle's altitude
            # and at the tracking answer's: the places to serve some users soon.
            busiest = np.argsort(-users.load_bps, kind="stable")[: c.user_targets]
            above = np.column_stack([users.users_xy_m[busiest], np.full(len(busiest), 0.0)])
            for z_m in (start_m[2], tracking_m[2]):
                above[:, 2] = z_m
                rows.append(above.copy())
        return _distinct(self._legal(np.concatenate(rows)))

    def _ring(self, start_m: np.ndarray, other_z_m: float) -> np.ndarray:
        """Where the vehicle can be after H periods heading in each of ``ring_headings``
        directions, at its altitude and at ``other_z_m`` (nothing in a world that teleports)."""
        c, flight = self.config, self.world.flight
        if c.ring_headings == 0 or flight.horizontal_mps is None:
            return np.empty((0, 3))
        reach_m = flight.horizontal_mps * self.world.step_s * c.horizon_steps
        angles = 2.0 * np.pi * np.arange(c.ring_headings) / c.ring_headings
        ring = start_m + reach_m * np.stack(
            [np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1
        )
        lifted = ring.copy()
        lifted[:, 2] = other_z_m
        return np.concatenate([ring, lifted])

    def _transit_steps(self, start_m: np.ndarray, points_m: np.ndarray) -> np.ndarray:
        """Periods to fly from ``start_m`` to each of ``points_m`` at the speed caps (N,)."""
        flight, step_s = self.world.flight, self.world.step_s
        gap = np.abs(points_m - start_m)
        steps = np.zeros(len(points_m))
        if flight.horizontal_mps is not None:
            steps = np.hypot(gap[:, 0], gap[:, 1]) / (flight.horizontal_mps * step_s)
        if flight.vertical_mps is not None:
            steps = np.maximum(steps, gap[:, 2] / (flight.vertical_mps * step_s))
        return steps

    def _two_legs(self, finals_m: np.ndarray, start_m: np.ndarray) -> np.ndarray:
        """Stage 2's trajectories (N, H, 3): a first target for k periods, then the final (the
        first: the vehicle's position or the final at every level, a point part-way to the
        final, or another of ``finals_m``)."""
        horizon = self.config.horizon_steps
        out = []
        for final in finals_m:
            firsts = np.concatenate(
                [
                    self._at_levels(start_m),
                    self._at_levels(final),
                    self._partway(start_m, final),
                    finals_m,
                ]
            )
            firsts = _distinct(self._legal(firsts))
            firsts = firsts[~np.all(firsts == final, axis=1)]
            for k in range(1, horizon):
                for first in firsts:
                    out.append([first] * k + [final] * (horizon - k))
        return np.array(out, dtype=float).reshape(-1, horizon, 3)

    def _at_levels(self, point_m: np.ndarray) -> np.ndarray:
        """``point_m`` at every altitude level (L, 3)."""
        out = np.repeat(np.asarray(point_m, dtype=float)[None], len(self._levels_m), axis=0)
        out[:, 2] = self._levels_m
        return out

    def _partway(self, start_m: np.ndarray, end_m: np.ndarray) -> np.ndarray:
        fractions = np.asarray(self.config.partway_fractions, dtype=float)[:, None]
        return start_m + fractions * (end_m - start_m)


def _distinct(points_m: np.ndarray) -> np.ndarray:
    """The rows of ``points_m`` without exact repeats, in first-seen order."""
    seen: set[bytes] = set()
    keep = []
    for i, row in enumerate(points_m):
        key = row.tobytes()
        if key not in seen:
            seen.add(key)
            keep.append(i)
    return points_m[keep]
