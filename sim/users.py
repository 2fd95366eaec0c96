"""Users within an episode: where they are and what they offer, step by step.

:class:`UserDynamics` starts from a scenario (positions and loads at time 0) and advances by one
decision period at a time under the world's :class:`~sim.world.Mobility` and
:class:`~sim.world.Demand`. With both static (the paper) it never draws a random number and its
arrays never change. All draws come from the generator passed in, so an episode is reproducible
from the environment's seed.

**On a site** (``area.environment`` ``site:PATH``, :mod:`sim.sites`) users walk on walkable
ground only. The scenario's users must start on it (InputError naming the first one inside a
building, :func:`sim.scenarios.check_scenario_area`). A walker's waypoints are drawn on walkable
ground (drawn again up to :data:`~sim.sites.ground.PLACEMENT_TRIES` times, then the nearest
walkable cell's centre). A step is *cancelled* when the straight segment from where the user was
to where the step would take it crosses a building (:func:`sim.sites.ground.walkable_path`,
sampled at most half a cell apart): the user stays where it was for this step, and a walker
picks a new leg (a new waypoint; no pause). In the ``group`` model the leader moves freely and
each user's step is cancelled on its own, so the group bunches up against walls. Reported
positions are therefore always on walkable ground; a path may clip the corner of a building
between two samples. Outside a site nothing changes (the same draws, bit for bit).
"""

from __future__ import annotations

import math

import numpy as np

from sim.channel import area_site
from sim.config import AreaConfig
from sim.sites.ground import PLACEMENT_TRIES, check_walkable, walkable_at, walkable_path
from sim.world import Demand, Mobility, World


def episode_users(
    users_xy_m: np.ndarray,
    load_bps: np.ndarray,
    world: World,
    area: AreaConfig,
    rng: np.random.Generator,
    users_seed: int | None = None,
) -> tuple[UserDynamics, np.random.Generator]:
    """An episode's users and the generator they draw from (the environments' reset).

    The users draw from their own generator, seeded by ``users_seed`` or, when not given, by a
    draw from the episode's ``rng``: every policy meets the same user motion and demand, and a
    controller outside the environment can replay it. Static users draw nothing from ``rng``
    (the paper's episodes keep their random streams)."""
    if users_seed is None:
        users_seed = int(rng.integers(2**63 - 1)) if world.users_change else 0
    users_rng = np.random.default_rng(users_seed)
    users = UserDynamics(users_xy_m, load_bps, world.mobility, world.demand, area, users_rng)
    return users, users_rng


class UserDynamics:
    """Positions (U, 2) and offered loads (U,) of a scenario's users as time passes.

    ``xy_m`` and ``load_bps`` are read-only arrays that :meth:`advance` replaces rather than
    changes, so a caller may keep them (in a report, an ``info``) without copying. On a site
    (module doc) users start and stay on walkable ground; a user that starts inside a building
    is an InputError naming it.
    """

    def __init__(
        self,
        users_xy_m: np.ndarray,
        load_bps: np.ndarray,
        mobility: Mobility,
        demand: Demand,
        area: AreaConfig,
        rng: np.random.Generator,
    ) -> None:
        self.area = area
        self.mobility = mobility
        self.demand = demand
        self.xy_m = _frozen(np.array(users_xy_m, dtype=float))
        self._site = area_site(area)
        if self._site is not None:
            check_walkable(self._site, self.xy_m, area.environment)
        self.base_load_bps = _frozen(np.array(load_bps, dtype=float))
        self.load_bps = self.base_load_bps
        n = len(self.load_bps)
        self._factor = np.ones(n)
        self._quiet_left_s = np.zeros(n)
        self._moving = np.zeros(n, dtype=bool)
        if not mobility.static:
            count = max(1, round(mobility.moving_fraction * n))
            self._moving[rng.choice(n, size=count, replace=False)] = True
        walkers = 1 if mobility.model == "group" else n
        self._waypoint = np.zeros((walkers, 2))
        self._speed = np.zeros(walkers)
        self._pause_left_s = np.zeros(walkers)
        if mobility.model == "group":
            self._leader = self.xy_m[self._moving].mean(axis=0)
            self._offsets = self.xy_m - self._leader
        for w in range(walkers if not mobility.static else 0):
            self._new_leg(w, rng)

    def advance(self, dt_s: float, rng: np.random.Generator) -> None:
        """Move the users and change their demand by ``dt_s`` seconds."""
        if not self.mobility.static:
            self._walk(dt_s, rng)
        if not self.demand.static:
            self._change_demand(dt_s, rng)

    # -- mobility -------------------------------------------------------------------------------
    def _new_leg(self, walker: int, rng: np.random.Generator) -> None:
        area = self.area
        upper = [area.size_x_m, area.size_y_m]
        self._waypoint[walker] = rng.uniform([0.0, 0.0], upper)
        if self._site is not None:  # a waypoint on walkable ground (module doc)
            for _ in range(PLACEMENT_TRIES):
                if walkable_at(self._site, self._waypoint[walker])[0]:
                    break
                self._waypoint[walker] = rng.uniform([0.0, 0.0], upper)
            else:
                from sim.sites.ground import nearest_walkable_xy

                self._waypoint[walker] = nearest_walkable_xy(
                    self._site, self._waypoint[walker], *upper
                )[0]
        self._speed[walker] = rng.uniform(*self.mobility.speed_mps)

    def _walk(self, dt_s: float, rng: np.random.Generator) -> None:
        site = self._site
        if self.mobility.model == "group":
            self._leader = self._step_walker(0, self._leader, dt_s, rng)
            upper = [self.area.size_x_m, self.area.size_y_m]
            moved = np.clip(self._leader + self._offsets, 0.0, upper)
            if site is not None:  # each user's step into a building is cancelled
                for u in np.flatnonzero(self._moving):
                    if not walkable_path(site, self.xy_m[u], moved[u]):
                        moved[u] = self.xy_m[u]
            self.xy_m = _frozen(np.where(self._moving[:, None], moved, self.xy_m))
            return
        xy = self.xy_m.copy()
        for u in np.flatnonzero(self._moving):
            step = self._step_walker(u, xy[u], dt_s, rng)
            if site is not None and not walkable_path(site, xy[u], step):
                self._pause_left_s[u] = 0.0  # the step is cancelled: a new leg instead
                self._new_leg(u, rng)
                continue
            xy[u] = step
        self.xy_m = _frozen(xy)

    def _step_walker(
        self, w: int, xy: np.ndarray, dt_s: float, rng: np.random.Generator
    ) -> np.ndarray:
        """One walker's random-waypoint motion for ``dt_s``: walk, arrive, pause, draw again."""
        left_s = dt_s
        xy = xy.copy()
        for _ in range(8):  # bounded: legs and pauses that fit within one step
            if left_s <= 0:
                break
            if self._pause_left_s[w] > 0:
                waited = min(self._pause_left_s[w], left_s)
                self._pause_left_s[w] -= waited
                left_s -= waited
                if self._pause_left_s[w] <= 0:
                    self._new_leg(w, rng)
                continue
            gap = self._waypoint[w] - xy
            distance = math.hypot(gap[0], gap[1])
            reach = self._speed[w] * left_s
            if distance > reach:
                return xy + gap * (reach / distance)
            xy = self._waypoint[w].copy()
            left_s -= distance / self._speed[w]
            self._pause_left_s[w] = rng.uniform(*self.mobility.pause_s)
            if self._pause_left_s[w] <= 0:
                self._new_leg(w, rng)
        return xy

    # -- demand ---------------------------------------------------------------------------------
    def _change_demand(self, dt_s: float, rng: np.random.Generator) -> None:
        d = self.demand
        n = len(self.load_bps)
        steps = rng.random(n) < -math.expm1(-d.step_rate_per_s * dt_s)
        if steps.any():
            low, high = (math.log(v) for v in d.step_factor)
            jump = np.exp(rng.uniform(low, high, n))
            self._factor[steps] = np.clip(self._factor[steps] * jump[steps], *d.step_factor)
        quiet = self._quiet_left_s > 0
        self._quiet_left_s[quiet] = np.maximum(self._quiet_left_s[quiet] - dt_s, 0.0)
        going = (~quiet) & (rng.random(n) < -math.expm1(-d.quiet_rate_per_s * dt_s))
        for u in np.flatnonzero(going):
            active = (self._quiet_left_s <= 0).sum()
            if active > 1:  # at least one user keeps offering traffic
                self._quiet_left_s[u] = rng.uniform(*d.quiet_s)
        self.load_bps = _frozen(
            np.where(self._quiet_left_s > 0, 0.0, self.base_load_bps * self._factor)
        )


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array
