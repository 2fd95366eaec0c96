"""Who has the vehicle: the service, its pilot, its autopilot, or an operator who released it.

The rule the vehicle link follows (one place, pure functions, so that it can be read and tested
without a vehicle):

* The service **holds** the vehicle from start-up (or from an operator's hand-back) until the
  vehicle leaves the service's hands on its own. While it holds it, it streams setpoints and may
  ask for the guided mode (GUIDED on ArduPilot, OFFBOARD on PX4) — during its own take-off
  sequence, and for a short window after a *new* target (the link's business, not this module's).
* The vehicle **leaves** the service's hands when, outside the service's own take-off sequence,
  its HEARTBEAT shows: a mode change to any mode other than the guided mode (a pilot's RC switch,
  a ground station's command, a failsafe), a return or landing mode (also found at start-up), or
  a disarm. Leaving a take-off mode for a hold mode (PX4's AUTO.TAKEOFF -> AUTO.LOITER) is the
  autopilot's normal course, not a leave.
* A vehicle the link finds **armed when it starts** (its first HEARTBEAT: a service started or
  restarted beside a vehicle that flies) is the service's only in the guided mode (a previous
  run's stream), a take-off mode or the autopilot's hold (PX4's AUTO.LOITER, where its
  offboard-loss failsafe holds a vehicle whose stream stopped, as a restart stops it; that hold
  starting *after* the link started, with the failsafe shown, before the link streamed anything,
  is the same case). In any other mode — a pilot took it while the service was away — it is
  not: the service leaves it alone until an operator hands it back.
* Who has it then: ``autopilot`` when the new mode is a return, landing or termination mode, or
  the vehicle showed a failsafe (HEARTBEAT ``system_status`` CRITICAL or EMERGENCY, or a
  STATUSTEXT naming a failsafe or of CRITICAL severity or worse, within
  :data:`FAILSAFE_EVIDENCE_S`), or the change happened while the link was lost (PX4's
  lost-setpoint failsafe); ``pilot`` otherwise.
* Once left, the service streams nothing and asks for nothing until an **operator** hands the
  vehicle back (``PUT /v1/vehicle/control``), which is refused while the vehicle is in a return,
  landing or termination mode or shows a failsafe: the pilot takes it out of that mode first.
  An operator may also release the vehicle (holder ``operator``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from service.modes import GUIDED_MODE_NAME, Flavour

ControlHolder = Literal["service", "pilot", "autopilot", "operator"]

RETURN_OR_LAND_MODES: dict[str, frozenset[str]] = {
    "ardupilot": frozenset({"RTL", "SMART_RTL", "AUTO_RTL", "LAND", "BRAKE"}),
    "px4": frozenset({"AUTO.RTL", "AUTO.LAND", "AUTO.PRECLAND", "AUTO.RTGS", "TERMINATION"}),
}
"""Modes in which the autopilot brings the vehicle back, lands it, brakes it for a fence, or
ends the flight: the service never asks for the guided mode while the vehicle is in one."""

TAKEOFF_MODES: dict[str, frozenset[str]] = {
    "ardupilot": frozenset(),
    "px4": frozenset({"AUTO.TAKEOFF"}),
}
"""Modes an autopilot leaves by itself when a take-off is done (for its hold mode)."""

HOLD_MODES: dict[str, frozenset[str]] = {
    "ardupilot": frozenset(),
    "px4": frozenset({"AUTO.LOITER"}),
}
"""The autopilot's hold when the stream of setpoints stops (PX4's offboard-loss failsafe; an
ArduCopter in GUIDED keeps its last target)."""

FAILSAFE_EVIDENCE_S = 5.0
"""A failsafe STATUSTEXT this recent explains a mode change as the autopilot's."""

MAV_STATE_CRITICAL = 5
MAV_STATE_EMERGENCY = 6
"""HEARTBEAT.system_status values with which both autopilots flag an active failsafe."""


@dataclass(frozen=True)
class Control:
    """Who has the vehicle, why, and since when (monotonic seconds)."""

    holder: ControlHolder
    reason: str
    since_s: float

    @property
    def service_has_it(self) -> bool:
        return self.holder == "service"


@dataclass(frozen=True)
class Observation:
    """What one vehicle HEARTBEAT (and the link around it) shows, for :func:`after_heartbeat`."""

    flavour: Flavour
    mode: str
    armed: bool
    previous_mode: str | None
    """The mode of the previous HEARTBEAT (None: the first one since the link started)."""
    previous_armed: bool | None
    failsafe_flagged: bool = False
    """HEARTBEAT.system_status CRITICAL or EMERGENCY."""
    failsafe_text: str | None = None
    """The vehicle's latest failsafe STATUSTEXT within :data:`FAILSAFE_EVIDENCE_S`, if any."""
    after_link_loss: bool = False
    """The first HEARTBEAT after the link was lost."""
    at_start: bool = False
    """The first HEARTBEAT since the link started (not the baseline after a hand-back)."""
    streamed: bool = True
    """The link has streamed a setpoint since it started."""


def is_return_or_land(flavour: Flavour | None, mode: str | None) -> bool:
    """The mode is one in which the service never asks for the guided mode."""
    return flavour is not None and mode in RETURN_OR_LAND_MODES.get(flavour, frozenset())


def is_failsafe_text(severity: int, text: str) -> bool:
    """A STATUSTEXT that announces a failsafe: it says so, or is CRITICAL or worse (MAVLink
    severities 0-2: EMERGENCY, ALERT, CRITICAL)."""
    return severity <= 2 or "failsafe" in text.lower()


def after_heartbeat(control: Control, seen: Observation, now_s: float) -> Control:
    """The control after a vehicle HEARTBEAT outside the service's take-off sequence: unchanged
    unless the service held the vehicle and the HEARTBEAT shows that it left (module docstring).
    """
    if not control.service_has_it:
        return control
    guided = GUIDED_MODE_NAME.get(seen.flavour)
    before = seen.previous_mode
    why: str | None = None
    if seen.previous_armed and not seen.armed:
        why = f"disarmed in {seen.mode}"
    elif before is not None and seen.mode != before and seen.mode != guided:
        from_takeoff = before in TAKEOFF_MODES.get(seen.flavour, frozenset())
        if not (from_takeoff or _stream_stopped_before_start(seen)) or is_return_or_land(
            seen.flavour, seen.mode
        ):
            why = f"left {before} for {seen.mode}"
    elif seen.at_start and seen.armed and not may_take_at_start(seen.flavour, seen.mode):
        why = f"was found armed in {seen.mode} when the link started"
    if why is None and is_return_or_land(seen.flavour, seen.mode):
        why = f"in {seen.mode}"
    if why is None:
        return control
    details = []
    if seen.after_link_loss:
        details.append("while the link was lost")
    if seen.failsafe_flagged:
        details.append("failsafe flagged in HEARTBEAT")
    if seen.failsafe_text is not None:
        details.append(f"vehicle said: {seen.failsafe_text}")
    reason = "the vehicle " + why + (f" ({'; '.join(details)})" if details else "")
    return Control(holder_after_leaving(seen), reason, now_s)


def holder_after_leaving(seen: Observation) -> ControlHolder:
    """Who has a vehicle that has left the service's hands (module docstring): the autopilot
    in a return or landing mode, with a failsafe shown or after a link loss; else its pilot."""
    autopilot = (
        is_return_or_land(seen.flavour, seen.mode)
        or seen.failsafe_flagged
        or seen.failsafe_text is not None
        or seen.after_link_loss
    )
    return "autopilot" if autopilot else "pilot"


def may_take_at_start(flavour: Flavour | None, mode: str | None) -> bool:
    """Whether a vehicle found armed in ``mode`` when the link starts is the service's: the
    guided mode, a take-off mode or the autopilot's hold (module docstring)."""
    if flavour is None or mode is None:
        return False
    return (
        mode == GUIDED_MODE_NAME.get(flavour)
        or mode in TAKEOFF_MODES.get(flavour, frozenset())
        or mode in HOLD_MODES.get(flavour, frozenset())
    )


def _stream_stopped_before_start(seen: Observation) -> bool:
    """The guided mode left for the autopilot's hold by a failsafe, before this link streamed
    anything: the stream that stopped was a previous run's (a restart), the hold the one a
    link starting a moment later would have found (module docstring)."""
    return (
        not seen.streamed
        and seen.previous_mode == GUIDED_MODE_NAME.get(seen.flavour)
        and seen.mode in HOLD_MODES.get(seen.flavour, frozenset())
        and (seen.failsafe_flagged or seen.failsafe_text is not None)
        and not seen.after_link_loss
    )


def handback_refusal(
    flavour: Flavour | None, mode: str | None, link_up: bool, failsafe_flagged: bool
) -> str | None:
    """Why an operator cannot hand the vehicle back to the service now, or None when it can."""
    if not link_up:
        return "the vehicle's link is not up"
    if is_return_or_land(flavour, mode):
        return f"the vehicle is in {mode}: switch it out of that mode from the ground station first"
    if failsafe_flagged:
        return "the vehicle flags a failsafe: clear it from the ground station first"
    return None
