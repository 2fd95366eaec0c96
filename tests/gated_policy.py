"""A deliberately slow policy for tests of how the service copes with slow decisions: each
decision waits until the test lets it through, so "slow" is a matter of the test's order of
events, not of the machine's speed."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from sim.observation import UserReports

WAIT_S = 20.0
"""Bound on every wait here (never reached when the service behaves)."""


class GatedPolicy:
    """A policy whose decisions take as long as the test says: ``decide`` records the report's
    marker (its first user's ``x_m``) and returns a target at that x only once the test lets
    one decision through (:meth:`release`) or opens the gate for good (:meth:`open`)."""

    name = spec = "gated"
    kind = "placement"

    def __init__(self, opened: bool = False) -> None:
        self.seen: list[float] = []
        self.started_at: list[float] = []  # monotonic
        self._passes = 0
        self._open = opened
        self._cond = threading.Condition()

    def begin_episode(self, users: Any, world: Any) -> None:
        return None

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "spec": self.spec, "metadata": None}

    def _wait_for_the_gate(self, marker: float) -> None:
        with self._cond:
            self.seen.append(marker)
            self.started_at.append(time.monotonic())
            self._cond.notify_all()
            if not self._cond.wait_for(lambda: self._open or self._passes > 0, WAIT_S):
                raise RuntimeError("the test never let this decision through")
            if not self._open:
                self._passes -= 1

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        marker = float(reports.x_m[0])
        self._wait_for_the_gate(marker)
        return np.array([marker, 100.0, 30.0])

    def release(self, n: int = 1) -> None:
        with self._cond:
            self._passes += n
            self._cond.notify_all()

    def open(self) -> None:
        with self._cond:
            self._open = True
            self._cond.notify_all()

    def wait_started(self, count: int) -> None:
        """Wait until ``count`` decisions have started."""
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.seen) >= count, WAIT_S):
                raise AssertionError(f"{count} decisions did not start: {self.seen}")


class GatedFleetPolicy(GatedPolicy):
    """:class:`GatedPolicy` for a fleet: the inner fleet policy decides once let through."""

    def __init__(self, inner: Any) -> None:
        super().__init__()
        self.inner = inner
        self.separation_m = inner.separation_m

    def decide_fleet(self, reports: UserReports, vehicles_xyz_m: np.ndarray) -> np.ndarray:
        self._wait_for_the_gate(float(reports.x_m[0]))
        return self.inner.decide_fleet(reports, vehicles_xyz_m)
