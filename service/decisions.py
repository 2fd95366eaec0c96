"""The placement service's value types: a report, a decision and what became of a report, how
long decisions take, one vehicle as the API shows it. Shared by the service
(:mod:`service.placement`), the live view (:mod:`service.live_view`) and the API; they hold no
behaviour beyond building themselves."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from service.vehicle_link import LinkState
from sim.observation import UserReports

__all__ = [
    "AcceptedReport",
    "Decision",
    "DecisionTiming",
    "Report",
    "ReportOutcome",
    "ReportReceipt",
    "VehicleView",
    "restored_decision",
]

ReportOutcome = Literal["decided", "held", "superseded", "pending", "stored"]


@dataclass(frozen=True)
class Report:
    """One report of all users, as the network controller sends it (already validated)."""

    timestamp_s: float
    user_ids: tuple[str, ...]
    users: UserReports

    @classmethod
    def from_columns(
        cls, timestamp_s: float, user_ids: tuple[str, ...], columns: dict[str, np.ndarray]
    ) -> Report:
        """A report from one array per :class:`~sim.observation.UserReports` field (``x_m``,
        ``y_m``, ``offered_bps``, ``throughput_bps``, ``delay_s``, ``plr``), one entry a user."""
        return cls(timestamp_s, user_ids, UserReports(**columns))


@dataclass(frozen=True)
class Decision:
    """A target and where it came from."""

    target_m: tuple[float, float, float]
    source: str
    """``policy`` (decided from a report), ``restored`` (from the state file)."""
    policy: str
    decided_at: float
    """Unix time, seconds."""


@dataclass(frozen=True)
class ReportReceipt:
    """What became of an accepted report (:meth:`service.placement.PlacementService.submit`)."""

    outcome: ReportOutcome
    """``decided``: a decision was taken from this report (``decision`` is it). ``held``: a
    decision was attempted on it and the target is held (no link: it is decided once the link is
    back, if still fresh; a stale report; a target the geofence refused; a failing policy).
    ``superseded``: a newer report replaced it before a decision read it (``on-report``; answered
    at once, the newer one is decided instead). ``pending``: the decision taken from it had not
    ended within :data:`service.placement.REPORT_WAIT_PERIODS` decision periods of its arrival
    (it follows, unless a newer report replaces it: ``GET /v1/setpoint`` shows it). ``stored``:
    ``paced`` mode, kept for the next period's decision."""
    decision: Decision | None
    """``decided``: the decision taken from the report; otherwise the current one (None before
    the first)."""


@dataclass(frozen=True)
class AcceptedReport:
    """A report :meth:`service.placement.PlacementService.accept` took: its number, and when
    (monotonic)."""

    seq: int
    arrived: float


@dataclass(frozen=True)
class DecisionTiming:
    """How long decisions take against the decision period
    (:meth:`service.placement.PlacementService.decision_timing`).

    A decision is timed from the policy's call until its target (a fleet's: checked) is ready
    for the link; refused targets and failing policies are timed too."""

    mode: str
    """The decision mode, ``paced`` or ``on-report``."""
    period_s: float
    """The decision period."""
    timed: int
    """Decisions timed so far."""
    last_s: float | None
    """The last decision's duration (None before the first)."""
    max_s: float | None
    """The longest so far (None before the first)."""
    overruns: int
    """Decisions longer than ``period_s`` so far: while they happen, decisions come once per
    decision rather than once per period."""


def restored_decision(saved: Any) -> Decision:
    """A decision as the state file keeps it (``asdict``), shown again with source
    ``restored``; ValueError, KeyError or TypeError when it is not one."""
    target = tuple(float(v) for v in saved["target_m"])
    if len(target) != 3 or not all(math.isfinite(v) for v in target):
        raise ValueError(f"target_m: not three finite numbers: {target}")
    return Decision(target, "restored", str(saved.get("policy", "")), time.time())  # type: ignore[arg-type]


@dataclass(frozen=True)
class VehicleView:
    """One vehicle of the fleet as ``GET /v1/vehicles`` shows it."""

    id: str
    system_id: int | None
    """The system id the fleet file requires (None: any); the heard one is ``state.system_id``."""
    state: LinkState
    decision: Decision | None
    """The target it is flying to (None: not commanded now)."""
    problem: str | None
    """Why it is not commanded now (None: it is)."""
