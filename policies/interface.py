"""What a policy is: the two protocols everything else in ``policies`` implements or adapts.

* :class:`Placement`: a *static* placement. Users' ground positions and offered loads in (what
  the users' reports carry), one UAV position out. ``min-distance``, ``load-weighted``
  (:mod:`policies.placements.baselines`) and the ``oracle`` (:mod:`policies.placements.oracle`) are
  placements.
* :class:`Policy`: what the evaluation and the service run. It decides the vehicle's next
  target from the latest reports and where the vehicle is, once per decision period. A
  placement becomes one by being re-placed every decision, a trained checkpoint by acting on
  the observation built at the vehicle (:mod:`policies.adapters` has both adapters;
  :mod:`policies.registry` builds either from a name or a checkpoint path).

Positions and targets are float64 arrays (3,): x, y, z in metres, area frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from sim.observation import UserReports
from sim.world import World

PolicyKind = Literal["moves", "coordinates", "placement"]
"""How a policy reaches its target: a DDQN's discrete ``moves``, a DDPG's absolute
``coordinates`` (or a residual correction), or a static ``placement`` re-placed every decision."""


class UsersLike(Protocol):
    """Anything carrying users' positions and offered loads: a ``sim.scenarios.Scenario``, a
    ``Case``, or the users of the latest reports (:class:`ReportedUsers`)."""

    @property
    def users_xy_m(self) -> np.ndarray:
        """(U, 2) ground positions in the area frame, metres."""
        ...

    @property
    def load_bps(self) -> np.ndarray:
        """(U,) uplink offered load of each user, bit/s."""
        ...


@dataclass(frozen=True)
class ReportedUsers:
    """The users of a report (:class:`sim.observation.UserReports`) as :class:`UsersLike`: what
    a placement re-placed from reports sees."""

    users_xy_m: np.ndarray
    load_bps: np.ndarray

    @classmethod
    def of(cls, reports: UserReports) -> ReportedUsers:
        xy = np.column_stack([reports.x_m, reports.y_m]).astype(float)
        return cls(xy, np.asarray(reports.offered_bps, dtype=float))


@runtime_checkable
class Placement(Protocol):
    """A static placement: users' positions and loads in, one UAV position out.

    ``place`` returns a float64 array (3,) — x, y, z in metres, area frame — inside the volume
    ``[0, size_x_m] × [0, size_y_m] × [z_min_m, z_max_m]`` of the placement's area. A placement
    may also offer ``track(users, previous_m)``: the same answer, found faster by starting from
    where it placed last (the oracle does).
    """

    name: str

    def place(self, users: UsersLike) -> np.ndarray: ...


@runtime_checkable
class Policy(Protocol):
    """Something that picks the vehicle's next target, once per decision period.

    ``spec`` is what it was built from (a placement's name or a checkpoint path), ``kind`` how it
    reaches its targets. ``begin_episode`` is called when a new episode (evaluation) starts, with
    the scenario's true users and the world: the policy forgets what it remembered of the last
    one and returns where the vehicle should start (``None``: the world's home). ``decide`` gets
    the report the decision sees and the vehicle's position and returns the target (3,), metres,
    area frame, inside the volume. ``describe`` is what the service shows of it.
    """

    name: str
    spec: str
    kind: PolicyKind

    def begin_episode(self, users: UsersLike, world: World) -> np.ndarray | None: ...

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray: ...

    def describe(self) -> dict[str, Any]: ...
