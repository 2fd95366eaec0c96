"""The world a policy lives in, as one frozen value: flight, decisions, users, reports.

Training, ``tupa eval``, ``tupa demo``, the benchmarks and the service's decision cadence all
take a :class:`World`, so a policy is trained in the world it serves in. Two presets matter:

``paper``        the paper's protocol (§IV): the UAV is at its target at the start of every
                 step (no flight), users and loads fixed for the episode, the decision sees the
                 report of the step that just ended, a static policy starts at its placement.
                 It reproduces the paper's figures and stays as it is.
``closed-loop``  what the service meets: the vehicle flies as the loop's autopilot does — at
                 most 10 m/s horizontally and 3 m/s vertically, accelerating and braking at
                 2.5 m/s² (a small multirotor in GUIDED / OFFBOARD; :mod:`sim.dynamics`), a new
                 target reaching it 0.05 s into the period (:data:`LOOP_LATENCY_S`) — every
                 policy starts at home (the area's centre, lowest level) and the decision sees
                 the report of the period that just ended, measured where the vehicle is (the
                 loop of ``tupa demo``: the network controller reports once a period, the
                 service decides on each report).
``closed-loop-moving`` the same with users walking (random waypoint, 0.5–1.5 m/s) and their
                 demand changing (a user's load stepping up or down, users going quiet and
                 coming back).

Every knob can be changed from the command line with ``--world-set key=value`` (dotted keys,
e.g. ``flight.horizontal_mps=5`` or ``mobility.model=group``): :func:`world_with` parses and
checks them, one-line errors naming the field. ``envelope=FILE`` gives the vehicles a flight-safety
envelope (a ``tupa-envelope/1`` file, :mod:`sim.envelope`): every flight then follows the routes
the service's vehicle link streams (:mod:`sim.envelope.flight`), targets are moved to legal
points, and starts too.

Actions become targets in :mod:`sim.geometry` (:func:`~sim.geometry.move_target`,
:func:`~sim.geometry.unit_to_m`): one code path for the environments and the service. The
vehicle flies toward its target through :func:`fly`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from sim.channel import area_site
from sim.config import AreaConfig, NetworkConfig, UtilityConfig, check_environment, site_path
from sim.envelope.files import ENVELOPE_FORMAT
from sim.envelope.flight import (
    canonical_document,
    envelope_for,
    fly_route,
    fly_vehicle_period,
    legal_position,
    read_document,
)
from sim.envelope.route import Route
from sim.envelope.volume import Envelope
from sim.errors import InputError
from sim.flight import Flight, fly, fly_many
from sim.geometry import clip_to_volume, zone_position

__all__ = [
    "WORLDS",
    "Demand",
    "Mobility",
    "ReportModel",
    "World",
    "get_world",
    "world_with",
]

MobilityModel = Literal["static", "random-waypoint", "group"]
MOBILITY_MODELS: tuple[str, ...] = ("static", "random-waypoint", "group")
HOMES: tuple[str, ...] = ("centre", "random")


@dataclass(frozen=True)
class Mobility:
    """How users move within an episode (``static``: they do not).

    ``random-waypoint``: each moving user walks in a straight line to a uniformly drawn point of
    the area at a speed drawn from ``speed_mps``, pauses for a time drawn from ``pause_s``, and
    draws again. ``group``: the moving users keep their offsets from one leader that does the
    same (a group walking together). ``moving_fraction`` of the users move (at least one when
    the fraction is above 0). Pedestrians: 0.5–1.5 m/s; vehicles: about 5–15 m/s.
    """

    model: str = "static"
    speed_mps: tuple[float, float] = (0.5, 1.5)
    pause_s: tuple[float, float] = (0.0, 10.0)
    moving_fraction: float = 1.0

    def __post_init__(self) -> None:
        if self.model not in MOBILITY_MODELS:
            raise InputError(
                f"mobility.model: must be one of {', '.join(MOBILITY_MODELS)}, got {self.model!r}"
            )
        _check_range("mobility.speed_mps", self.speed_mps, positive=True)
        _check_range("mobility.pause_s", self.pause_s, positive=False)
        if not 0.0 <= self.moving_fraction <= 1.0:
            raise InputError(
                f"mobility.moving_fraction: must lie in [0, 1], got {self.moving_fraction}"
            )

    @property
    def static(self) -> bool:
        return self.model == "static" or self.moving_fraction == 0.0


@dataclass(frozen=True)
class Demand:
    """How users' offered loads change within an episode (rates 0: they do not).

    Each user independently, at ``step_rate_per_s``, has its load multiplied by a factor drawn
    log-uniformly from ``step_factor`` (kept within ``step_factor`` of its initial load); at
    ``quiet_rate_per_s`` it goes quiet (offers nothing) for a time drawn from ``quiet_s``, then
    comes back with its load. At least one user always offers traffic.
    """

    step_rate_per_s: float = 0.0
    step_factor: tuple[float, float] = (0.25, 4.0)
    quiet_rate_per_s: float = 0.0
    quiet_s: tuple[float, float] = (5.0, 30.0)

    def __post_init__(self) -> None:
        for name in ("step_rate_per_s", "quiet_rate_per_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"demand.{name}: must be >= 0, got {value}")
        _check_range("demand.step_factor", self.step_factor, positive=True)
        _check_range("demand.quiet_s", self.quiet_s, positive=True)

    @property
    def static(self) -> bool:
        return self.step_rate_per_s == 0.0 and self.quiet_rate_per_s == 0.0


@dataclass(frozen=True)
class ReportModel:
    """What the decision knows about the network: the users' reports.

    ``age_steps``: the decision sees the report of that many steps before the one that just
    ended (0: the paper; 1: the closed loop, where the network controller reports what it
    measured over the last period while the vehicle has flown on). ``position_noise_m``: the
    standard deviation of Gaussian noise on each reported user coordinate.
    """

    age_steps: int = 0
    position_noise_m: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.age_steps, int) and 0 <= self.age_steps <= 10):
            raise InputError(
                f"reports.age_steps: must be an integer in 0..10, got {self.age_steps}"
            )
        if not (math.isfinite(self.position_noise_m) and self.position_noise_m >= 0):
            raise InputError(f"reports.position_noise_m: must be >= 0, got {self.position_noise_m}")


@dataclass(frozen=True)
class World:
    """Everything about an episode except the scenario and the policy; see the module doc."""

    name: str = "paper"
    step_s: float = 1.0  # decision period S
    episode_steps: int = 100  # T
    home: str | tuple[float, float, float] = "centre"  # "centre", "random" or (x, y, z) metres
    static_start: str = "placement"  # a static policy starts at its placement, or at "home"
    flight: Flight = field(default_factory=lambda: Flight(None, None))
    mobility: Mobility = field(default_factory=Mobility)
    demand: Demand = field(default_factory=Demand)
    reports: ReportModel = field(default_factory=ReportModel)
    stochastic: bool = True  # sampled fading; False: the model's expected mode
    area: AreaConfig = field(default_factory=AreaConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    envelope: str | None = None
    """The vehicles' flight-safety envelope, a ``tupa-envelope/1`` document (given as a dict or
    its JSON text, kept as canonical JSON text: the world stays a frozen, hashable value), or
    None: the area's box, flown straight as :func:`fly` flies. With one, every flight follows
    the routes the service's link streams (:mod:`sim.envelope.flight`). Over a site there is
    always one (the area's box when none is given), which holds the site's buildings
    (:mod:`sim.envelope.buildings`)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.step_s) and self.step_s > 0):
            raise InputError(f"step_s: must be > 0, got {self.step_s}")
        if not (isinstance(self.episode_steps, int) and self.episode_steps >= 1):
            raise InputError(f"episode_steps: must be an integer >= 1, got {self.episode_steps}")
        if isinstance(self.home, str):
            if self.home not in HOMES:
                raise InputError(
                    f"home: must be one of {', '.join(HOMES)} or x,y,z in metres, got {self.home!r}"
                )
        else:
            home = tuple(float(v) for v in self.home)
            area = self.area
            inside = (
                len(home) == 3
                and 0 <= home[0] <= area.size_x_m
                and 0 <= home[1] <= area.size_y_m
                and area.z_min_m <= home[2] <= area.z_max_m
            )
            if not inside:
                raise InputError(f"home: {self.home} is not a point of the UAV's volume")
            object.__setattr__(self, "home", home)
        if self.static_start not in ("placement", "home"):
            raise InputError(
                f"static_start: must be 'placement' or 'home', got {self.static_start!r}"
            )
        if self.envelope is None and site_path(self.area.environment) is not None:
            # Over a site the buildings are exclusions (sim.envelope.buildings): always flown.

            object.__setattr__(self, "envelope", {"format": ENVELOPE_FORMAT})
        if self.envelope is not None:
            try:
                document = canonical_document(self.envelope, self.area)
            except InputError as exc:
                raise InputError(f"envelope: {exc}") from None
            object.__setattr__(self, "envelope", document)

    @property
    def users_change(self) -> bool:
        """Whether users move or change their demand within an episode."""
        return not (self.mobility.static and self.demand.static)

    def home_position(self, rng: np.random.Generator | None = None) -> np.ndarray:
        """Where the vehicle starts (3,), metres: ``centre`` is the zone at the area's middle at
        the lowest level (the paper's start), ``random`` a uniformly drawn zone and level."""
        area = self.area
        if isinstance(self.home, tuple):
            return np.array(self.home, dtype=float)
        if self.home == "random":
            if rng is None:
                raise ValueError("home: 'random' needs a random generator")
            shape = [area.n_zones_x, area.n_zones_y, area.n_levels_z]
            return zone_position(rng.integers(0, shape), area)
        return zone_position(np.array([area.n_zones_x // 2, area.n_zones_y // 2, 0]), area)

    @property
    def environment(self) -> str:
        """What stands on the ground (the area's channel environment, :mod:`sim.channel`)."""
        return self.area.environment

    @property
    def flight_envelope(self) -> Envelope | None:
        """The parsed envelope (built once per document and area), or None without one."""
        if self.envelope is None:
            return None

        return envelope_for(self.envelope, self.area)

    def fly(self, position_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
        """Where the vehicle is one decision period after heading for ``target_m`` (along a
        route planned from ``position_m`` when the world has an envelope: :meth:`fly_route`)."""
        if self.envelope is None:
            return fly(position_m, target_m, self.flight, self.step_s)
        return self.fly_route(position_m, target_m)[0]

    def fly_period(
        self,
        positions_m: np.ndarray,
        velocities_mps: np.ndarray,
        previous_targets_m: np.ndarray,
        targets_m: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One decision period of flight without an envelope, for each row (E, 3) of
        independent vehicles: (positions, velocities) at its end. Toward the previous target for
        the flight's ``latency_s`` (at most the period), then toward the new one; with
        acceleration limits as the loop's autopilot flies (:mod:`sim.dynamics`, the velocity
        carried in and out), else at the speed caps (:func:`fly_many`; velocities returned
        zero). With neither latency nor acceleration, exactly :func:`fly_many` of the new
        targets."""
        positions = np.asarray(positions_m, dtype=float).reshape(-1, 3)
        targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
        flight, step_s = self.flight, self.step_s
        latency_s = min(flight.latency_s, step_s)  # a decision reaches the vehicle in its period
        if flight.accelerates:
            from sim.dynamics import fly_accelerating

            assert flight.horizontal_mps is not None and flight.vertical_mps is not None
            assert flight.accel_mps2 is not None
            flown, velocities = fly_accelerating(
                positions, velocities_mps, previous_targets_m, targets,
                duration_s=step_s, latency_s=latency_s,
                max_h_mps=flight.horizontal_mps, max_v_mps=flight.vertical_mps,
                accel_h_mps2=flight.accel_mps2, accel_v_mps2=flight.accel_mps2,
            )  # fmt: skip
            return clip_to_volume(flown, self.area), velocities
        if latency_s > 0:
            previous = np.asarray(previous_targets_m, dtype=float).reshape(-1, 3)
            positions = fly_many(positions, previous, flight, latency_s)
            flown = fly_many(positions, targets, flight, step_s - latency_s)
        else:
            flown = fly_many(positions, targets, flight, step_s)
        return flown, np.zeros_like(flown)

    def fly_route(
        self, position_m: np.ndarray, target_m: np.ndarray, route: Route | None = None
    ) -> tuple[np.ndarray, Route]:
        """:meth:`fly` keeping the route across periods, as the vehicle link does: pass back the
        route returned (planned again only when the legal target changes, or it holds). See
        :func:`sim.envelope.flight.fly_route`; with no envelope, :func:`fly`'s flight."""

        return fly_route(
            self.flight_envelope, position_m, target_m, self.flight, self.step_s, route
        )

    def fly_routes_period(
        self,
        positions_m: np.ndarray,
        velocities_mps: np.ndarray,
        targets_m: np.ndarray,
        routes: Sequence[Route | None] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, list[Route]]:
        """One decision period inside the world's envelope for each row (E, 3) of independent
        vehicles (:func:`sim.envelope.flight.fly_vehicle_period`: with an acceleration limit as
        the loop flies the link's routes, latency and velocity carried; else at the speed caps
        or at once): (positions, velocities, routes) at its end, each route to pass back next
        period; velocities zero without an acceleration limit."""

        envelope = self.flight_envelope
        positions = np.asarray(positions_m, dtype=float).reshape(-1, 3)
        targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
        velocities = np.asarray(velocities_mps, dtype=float).reshape(-1, 3)
        kept = [None] * len(positions) if routes is None else list(routes)
        out, out_velocity = np.empty_like(positions), np.empty_like(positions)
        flown_routes: list[Route] = []
        for e in range(len(positions)):
            period = fly_vehicle_period(
                envelope, positions[e], velocities[e], targets[e], self.flight, self.step_s,
                kept[e],
            )  # fmt: skip
            out[e], out_velocity[e] = period.flown.position_m, period.velocity_mps
            flown_routes.append(period.flown.route)
        return out, out_velocity, flown_routes

    def legal_start(self, xyz_m: np.ndarray) -> np.ndarray:
        """Where a vehicle asked to start at ``xyz_m`` starts: there, or with an envelope the
        nearest legal point (:func:`sim.envelope.flight.legal_position`, searching further when
        none is near)."""
        if self.envelope is None:
            return np.asarray(xyz_m, dtype=float)

        return legal_position(self.flight_envelope, xyz_m, search=True)

    def to_dict(self) -> dict[str, Any]:
        """The world as JSON-able values (the envelope as its document)."""
        out = dataclasses.asdict(self)
        if self.envelope is not None:
            out["envelope"] = json.loads(self.envelope)
        return out


def _check_range(name: str, value: tuple[float, float], positive: bool) -> None:
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: must be two numbers low,high, got {value!r}") from None
    ok = math.isfinite(low) and math.isfinite(high) and low <= high
    ok = ok and (low > 0 if positive else low >= 0)
    if not ok:
        bound = "> 0" if positive else ">= 0"
        raise InputError(f"{name}: need {bound} and low <= high, got {value!r}")


# --------------------------------------------------------------------------------------------
# Presets and overrides

PAPER = World()
LOOP_ACCEL_MPS2 = 2.5
"""The loop's autopilots' acceleration limit, horizontal and vertical (ArduCopter's
``WPNAV_ACCEL``/``PILOT_ACCEL_Z`` defaults, the autopilot simulator's)."""
LOOP_LATENCY_S = 0.05
"""From a report to the new setpoint on the autopilot, in the loop with decisions on each report
(``TUPA_DECISION_MODE=on-report``; ``tupa demo``): fitted to a demo track by
``benchmarks/loop_latency.py``."""
CLOSED_LOOP = World(
    name="closed-loop",
    static_start="home",
    flight=Flight(10.0, 3.0, LOOP_ACCEL_MPS2, LOOP_LATENCY_S),
    reports=ReportModel(age_steps=0),
)
CLOSED_LOOP_MOVING = replace(
    CLOSED_LOOP,
    name="closed-loop-moving",
    mobility=Mobility(model="random-waypoint", speed_mps=(0.5, 1.5), pause_s=(0.0, 10.0)),
    demand=Demand(step_rate_per_s=0.005, quiet_rate_per_s=0.002),
)
WORLDS: dict[str, World] = {w.name: w for w in (PAPER, CLOSED_LOOP, CLOSED_LOOP_MOVING)}


def episode_worlds(world: World | Sequence[World] | None) -> list[World]:
    """The worlds an environment draws each episode's world from (single UAV and fleet alike):
    ``None`` is [:data:`PAPER`], one world is a list of it, a sequence is kept in its order.
    ValueError naming ``world`` for an empty list, or for worlds that differ in anything but
    their area's channel environment: one area and one network, so that one observation space
    and one kind of network model serve every episode."""
    worlds = [PAPER] if world is None else [world] if isinstance(world, World) else list(world)
    if not worlds:
        raise ValueError("world: the list of worlds is empty")
    area, network = worlds[0].area, worlds[0].network
    if any(
        replace(w.area, environment=area.environment) != area or w.network != network
        for w in worlds
    ):
        raise ValueError(
            "world: the worlds of one environment must share the area (their channel "
            "environments may differ) and the network"
        )
    return worlds


def get_world(name: str) -> World:
    """The preset called ``name``; ``InputError`` naming the choices otherwise."""
    try:
        return WORLDS[name]
    except KeyError:
        raise InputError(f"world: must be one of {', '.join(WORLDS)}, got {name!r}") from None


def world_with(world: World, settings: Iterable[str] | Mapping[str, Any]) -> World:
    """``world`` with ``key=value`` settings applied (dotted keys reach nested parts).

    Values are parsed by the field's type: numbers, ``none`` for an optional speed, ``a,b`` for
    ranges, ``true``/``false``; ``home`` takes ``centre``, ``random`` or ``x,y,z``. Unknown keys
    and bad values raise ``InputError`` naming the key. The result's name gets a ``*`` so a
    changed world is never mistaken for its preset.
    """
    items = settings.items() if isinstance(settings, Mapping) else (_split(s) for s in settings)
    changed = False
    for key, raw in items:
        world = _set(world, key, raw)
        changed = True
    if changed and not world.name.endswith("*"):
        world = replace(world, name=world.name + "*")
    return world


def _split(setting: str) -> tuple[str, str]:
    key, sep, value = setting.partition("=")
    if not sep or not key.strip():
        raise InputError(f"--world-set: expected key=value, got {setting!r}")
    return key.strip(), value.strip()


_NESTED = ("flight", "mobility", "demand", "reports")
_SETTABLE_TOP = (
    "step_s",
    "episode_steps",
    "home",
    "static_start",
    "stochastic",
    "environment",
    "envelope",
)


def _set(world: World, key: str, raw: Any) -> World:
    head, _, rest = key.partition(".")
    if head in _NESTED and rest:
        part = getattr(world, head)
        names = {f.name: f for f in fields(part)}
        if rest not in names:
            raise InputError(
                f"world.{key}: unknown setting (choices: {', '.join(f'{head}.{n}' for n in names)})"
            )
        value = _parse(f"world.{key}", raw, getattr(part, rest))
        return replace(world, **{head: _replace(part, key, rest, value)})
    if key == "environment" and not rest:
        # One line naming world.environment; a site must be there, sound and cover the area.
        environment = check_environment(str(raw).strip(), "world.environment", on_disk=True)
        area = replace(world.area, environment=environment)
        try:
            area_site(area)
        except InputError as exc:
            raise InputError(f"world.{exc}") from None
        return replace(world, area=area)
    if key == "envelope" and not rest:
        return _with_envelope(world, raw)
    if key in _SETTABLE_TOP and not rest:
        value = raw
        if key == "home" and isinstance(raw, str) and raw not in HOMES:
            value = _parse(f"world.{key}", raw, (0.0, 0.0, 0.0))
        elif key != "home":
            value = _parse(f"world.{key}", raw, getattr(world, key))
        return replace(world, **{key: value})
    choices = [*_SETTABLE_TOP] + [f"{n}.*" for n in _NESTED]
    raise InputError(f"world.{key}: unknown setting (choices: {', '.join(choices)})")


def _with_envelope(world: World, raw: Any) -> World:
    """``envelope=FILE`` (a ``tupa-envelope/1`` file), a document (dict), or ``none``."""
    document, where = raw, ""
    if raw is None or (isinstance(raw, str) and raw.strip().lower() == "none"):
        document = None
    elif isinstance(raw, str | Path):
        where = f"{str(raw).strip()}: "
        try:
            document = read_document(str(raw).strip())
        except InputError as exc:
            raise InputError(f"world.envelope: {exc}") from None
    try:
        return replace(world, envelope=document)
    except InputError as exc:
        detail = str(exc).removeprefix("envelope: ")
        raise InputError(f"world.envelope: {where}{detail}") from None


def _replace(part: Any, key: str, name: str, value: Any) -> Any:
    try:
        return replace(part, **{name: value})
    except InputError:
        raise
    except (TypeError, ValueError) as exc:
        raise InputError(f"world.{key}: {exc}") from None


def _parse(key: str, raw: Any, current: Any) -> Any:
    if not isinstance(raw, str):
        return raw
    text = raw.strip().lower()
    try:
        if isinstance(current, bool):
            if text not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return text in ("true", "1", "yes")
        if isinstance(current, tuple):
            parts = tuple(float(p) for p in text.split(","))
            if len(parts) != len(current):
                raise ValueError
            return parts
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float) or current is None:
            if text == "none":
                return None
            return float(text)
        return raw.strip()
    except ValueError:
        raise InputError(f"{key}: cannot read {raw!r} as a value of this setting") from None
