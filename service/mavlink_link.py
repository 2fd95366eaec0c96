"""The service's MAVLink link to the vehicle, on pymavlink: telemetry in, setpoints out.

:class:`MavlinkLink` owns one pymavlink connection (any connection string pymavlink knows:
``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, a serial device) and runs all of
its I/O in background threads, so that callers (the placement loop, the HTTP side) never block::

    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:5760", area=AreaConfig()))
    link.start()
    link.arm_and_takeoff()            # only when asked: a service never arms by surprise
    link.set_target((250.0, 250.0, 50.0))  # area frame, metres; clamped to the geofence
    print(link.state())               # position in the area frame, mode, armed, link health
    link.close()

What the I/O thread does, in a loop:

* sends our own HEARTBEAT at 1 Hz (an onboard controller or a GCS; autopilot INVALID);
* reads the vehicle's HEARTBEAT (flavour from its ``autopilot`` field, mode, armed),
  GLOBAL_POSITION_INT, LOCAL_POSITION_NED, EXTENDED_SYS_STATE, EKF_STATUS_REPORT (ArduPilot),
  COMMAND_ACK, and STATUSTEXT (logged, and the latest kept in :meth:`MavlinkLink.state`);
* asks for the telemetry it needs with SET_MESSAGE_INTERVAL (and, on ArduPilot, the older
  REQUEST_DATA_STREAM if no SET_MESSAGE_INTERVAL is accepted);
* streams the current target as SET_POSITION_TARGET_LOCAL_NED (position only, type_mask 3576,
  MAV_FRAME_LOCAL_NED) at ``setpoint_rate_hz`` while the link is up; a *new* target goes out at
  the loop's next iteration (a few ms: the loop waits at most 5 ms for input) rather than at the
  next tick, and the steady schedule restarts from that send, so the rate never drops below
  ``setpoint_rate_hz`` (immediate sends are at least ``setpoint_min_gap_s`` apart, so a burst of
  decisions cannot flood the link);
* asks for the flavour's guided mode while a target is set: GUIDED at once on ArduPilot; on PX4
  OFFBOARD only after the stream has run ``px4_stream_lead_s`` (PX4 refuses it before), retrying;
* counts the vehicle's messages that fail the MAVLink 2 signature check (``signing_failures``:
  a wrong key on one side, or an unsigned vehicle while we sign); such messages are dropped, so
  a vehicle we cannot authenticate never comes ``up`` and is never commanded;
* watches the link: no vehicle HEARTBEAT for ``heartbeat_timeout_s`` -> ``link_lost``, streaming
  stops, the connection is recreated with backoff; when the vehicle is back, telemetry is asked
  for again and the latest target streams again. The mode is not forced back after a loss: a pilot
  who took over keeps control until the next :meth:`MavlinkLink.set_target`.

:meth:`MavlinkLink.arm_and_takeoff` runs the take-off sequence the real autopilots need (its
docstring has the steps) in its own worker thread and returns a Future. Every command goes out
with all seven params as the MAVLink message set defines them (:mod:`service.mavlink_commands`).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Literal, Self

from service.frames import FrameConfig, area_to_ned, ned_to_area
from service.geofence import clamp_to_area
from sim.config import AreaConfig

# MAVLink 2 is needed for signing; pymavlink picks the wire version from this variable when its
# dialect module is first loaded (it would also switch on the first MAVLink 2 packet it sees).
os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from service import mavlink_commands

log = logging.getLogger(__name__)

LinkHealth = Literal["connecting", "up", "link_lost"]
Flavour = Literal["ardupilot", "px4", "generic"]

TAKEOFF_TIMEOUT_S = 300.0
"""How long the take-off sequence keeps trying by default: a real autopilot needs a GPS lock and
its pre-arm checks first (ArduCopter SITL ~40 s from boot, a real vehicle minutes)."""
COMMAND_RESEND_S = 1.0
"""A command not answered within this is sent again (the same command: all are idempotent)."""
STEP_TIMEOUT_S = 10.0
"""How long one step of an attempt (an ACK, a mode seen in HEARTBEAT, armed) may take."""
MODE_SETTLE_S = 1.0
"""ArduPilot: GUIDED must hold this long in HEARTBEAT before the vehicle is armed (a mode switch
read at start-up changed it back 0.2 s after it was granted on a real ArduCopter SITL)."""
CLIMB_START_S = 10.0
"""After an accepted take-off the vehicle must leave the ground within this (PX4 accepts a
take-off it then does not fly, and disarms it ~10 s later)."""
CLIMB_MIN_MPS = 0.5
"""Slowest average climb accepted on the way to the take-off altitude."""
IN_AIR_ALT_M = 1.0
"""Armed and this high above home: flying (a vehicle found flying is taken over, not armed)."""
LIFTOFF_ALT_M = 0.3
LIFTOFF_WAIT_S = 3.0
"""A refused take-off is still a take-off if the vehicle is this high within this time."""
RETRY_MIN_S = 1.0
RETRY_MAX_S = 10.0
"""Backoff between take-off attempts: doubles from min to max."""
POSITION_FRESH_S = 2.0
"""LOCAL_POSITION_NED older than this does not count as a position estimate."""
REFUSAL_TEXT_WAIT_S = 0.5
"""How long a refusal waits for the vehicle's STATUSTEXT that explains it."""
STATUS_TEXTS_KEPT = 8
"""How many of the vehicle's latest STATUSTEXTs :meth:`VehicleLinkBase.state` shows."""

EKF_POSITION_FLAGS = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS


def ekf_position_ok(flags: int) -> bool:
    """ArduPilot's EKF_STATUS_REPORT.flags allow arming in GUIDED: an absolute horizontal position
    (or its prediction, which is what ArduCopter checks while disarmed) and no constant-position
    mode (the EKF's "no GPS yet" state)."""
    return bool(flags & EKF_POSITION_FLAGS) and not flags & mavlink.EKF_CONST_POS_MODE


def result_name(result: int | None) -> str:
    """``ACCEPTED``, ``FAILED``, ... for a MAV_RESULT; ``no answer`` for None."""
    if result is None:
        return "no answer"
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else f"result {result}"


class TakeoffRefused(Exception):  # noqa: N818 (a refusal, not a programming error)
    """One take-off attempt failed (a refusal, a mode change, no climb): the sequence restarts."""


POSITION_ONLY_TYPE_MASK = 3576
"""SET_POSITION_TARGET_LOCAL_NED type_mask: use x, y, z only (ignore velocity, accel, yaw)."""

ARDUPILOT_GUIDED = 4
PX4_MAIN_AUTO = 4
PX4_MAIN_OFFBOARD = 6

ARDUPILOT_COPTER_MODES = {
    0: "STABILIZE",
    1: "ACRO",
    2: "ALT_HOLD",
    3: "AUTO",
    4: "GUIDED",
    5: "LOITER",
    6: "RTL",
    7: "CIRCLE",
    9: "LAND",
    16: "POSHOLD",
    17: "BRAKE",
    20: "GUIDED_NOGPS",
    21: "SMART_RTL",
}
PX4_MAIN_MODES = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
}
PX4_AUTO_SUB_MODES = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
}
GUIDED_MODE_NAME: dict[str, str] = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}


def flavour_of(autopilot: int) -> Flavour:
    """The flavour for a HEARTBEAT ``autopilot`` value."""
    if autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    if autopilot == mavlink.MAV_AUTOPILOT_PX4:
        return "px4"
    return "generic"


def mode_name(flavour: Flavour, custom_mode: int) -> str:
    """A readable name for HEARTBEAT ``custom_mode`` (``MODE(n)`` when unknown)."""
    if flavour == "ardupilot":
        return ARDUPILOT_COPTER_MODES.get(custom_mode, f"MODE({custom_mode})")
    if flavour == "px4":
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        name = PX4_MAIN_MODES.get(main, f"MODE({main})")
        if main == PX4_MAIN_AUTO:
            return f"AUTO.{PX4_AUTO_SUB_MODES.get(sub, str(sub))}"
        return name
    return f"MODE({custom_mode})"


def signing_key_from_passphrase(passphrase: str) -> bytes:
    """A 32-byte MAVLink 2 signing key from a passphrase (SHA-256, as MAVProxy does)."""
    return hashlib.sha256(passphrase.encode()).digest()


@dataclass(frozen=True)
class LinkConfig:
    """Everything :class:`MavlinkLink` needs; only ``url`` has no default."""

    url: str
    """A pymavlink connection string: ``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:...``."""
    area: AreaConfig = AreaConfig()
    """The area volume: targets are clamped into it (the geofence)."""
    frames: FrameConfig = FrameConfig()  # noqa: RUF009 (frozen, so sharing it is safe)
    """Where the area frame sits in the vehicle's local NED frame."""
    setpoint_rate_hz: float = 10.0
    """How often the current target is sent (PX4 needs more than 2 Hz)."""
    setpoint_min_gap_s: float = 0.02
    """A new target is sent at once, but never sooner than this after the previous setpoint."""
    telemetry_rate_hz: float = 10.0
    """Rate asked for GLOBAL_POSITION_INT and LOCAL_POSITION_NED."""
    heartbeat_timeout_s: float = 3.0
    """No vehicle HEARTBEAT for this long: the link is lost."""
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 3.0
    """Backoff between attempts to recreate the connection: doubles from min to max."""
    px4_stream_lead_s: float = 1.2
    """PX4: how long the setpoint stream runs before OFFBOARD is asked for."""
    mode_retry_s: float = 0.5
    mode_request_window_s: float = 15.0
    """After a target is set, the guided mode is asked for (every ``mode_retry_s``) this long."""
    signing_key: bytes | None = None
    """Optional 32-byte MAVLink 2 signing key, the same as the vehicle's."""
    source_system: int = 255
    source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
    heartbeat_type: int = mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    """Our HEARTBEAT type: MAV_TYPE_ONBOARD_CONTROLLER (companion computer) or MAV_TYPE_GCS."""

    def __post_init__(self) -> None:
        for name in (
            "setpoint_rate_hz",
            "telemetry_rate_hz",
            "heartbeat_timeout_s",
            "reconnect_min_s",
            "reconnect_max_s",
            "mode_retry_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value!r}")
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError(f"signing_key: must be 32 bytes, got {len(self.signing_key)}")


@dataclass(frozen=True)
class LinkState:
    """A snapshot of the link and the vehicle, as :meth:`MavlinkLink.state` returns it."""

    link: LinkHealth
    """``connecting`` (never heard the vehicle), ``up``, or ``link_lost``."""
    flavour: Flavour | None
    """From the vehicle's HEARTBEAT; None before the first one."""
    mode: str | None
    armed: bool
    position_m: tuple[float, float, float] | None
    """Vehicle position in the area frame (x east, y north, z up), metres."""
    relative_alt_m: float | None
    """Altitude above home, metres (GLOBAL_POSITION_INT)."""
    heartbeat_age_s: float | None
    """Seconds since the vehicle's last HEARTBEAT; None before the first one."""
    target_m: tuple[float, float, float] | None
    """The (geofenced) target being streamed, area frame."""
    streaming: bool
    takeoff: str
    """``idle``, ``running``, ``airborne`` or ``failed: <reason>``."""
    counters: dict[str, int] = field(default_factory=dict)
    takeoff_phase: str | None = None
    """While the take-off runs: the step it is at (``waiting for a position estimate``, ...)."""
    takeoff_attempts: int = 0
    """How many times the take-off sequence has started (it starts again after a refusal)."""
    takeoff_last_refusal: str | None = None
    """Why the last attempt failed, with what the vehicle said about it (its STATUSTEXT)."""
    status_texts: tuple[str, ...] = ()
    """The vehicle's latest STATUSTEXT messages, oldest first, as ``SEVERITY: text``."""


class VehicleLinkBase(ABC):
    """What every vehicle link shares, whatever speaks MAVLink for it (pymavlink or MAVSDK): the
    vehicle state it exposes (:meth:`state`), the geofenced target it streams (:meth:`set_target`,
    :meth:`clear_target`), the arm-and-takeoff worker's bookkeeping, and the thread lifecycle.

    A backend implements ``_run`` (the I/O thread), ``_ask`` and ``_ask_arm`` (used by
    the shared take-off sequence) and ``_release`` (drop the connection), keeps the fields below
    up to date under ``self._cond``, and passes the vehicle's STATUSTEXTs to
    ``_note_status_text``.
    """

    _thread_name = "vehicle-link"

    def __init__(self, config: LinkConfig) -> None:
        self.config = config
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._workers: list[threading.Thread] = []
        self.counters: Counter[str] = Counter(
            dict.fromkeys(
                ("setpoints_sent", "geofence_clamps", "reconnects", "connect_failures"), 0
            )
        )
        # Vehicle state (under self._cond).
        self._health: LinkHealth = "connecting"
        self._flavour: Flavour | None = None
        self._custom_mode: int | None = None
        self._armed = False
        self._last_hb: float | None = None
        self._ned: tuple[float, float, float] | None = None
        self._position_at: float | None = None
        self._relative_alt_m: float | None = None
        self._home_amsl_m: float | None = None
        self._ekf_flags: int | None = None  # ArduPilot's EKF_STATUS_REPORT.flags, when it sends it
        self._status_texts: deque[tuple[float, str]] = deque(maxlen=STATUS_TEXTS_KEPT)
        # Streaming state.
        self._target_m: tuple[float, float, float] | None = None
        self._target_dirty = False  # a new target not sent yet: send it at once
        self._hold_setpoints = False
        self._stream_since: float | None = None
        self._mode_wanted_until = 0.0
        # Take-off bookkeeping (under self._cond).
        self._takeoff = "idle"
        self._takeoff_phase: str | None = None
        self._takeoff_attempts = 0
        self._takeoff_last_refusal: str | None = None

    # Implemented by each backend.
    @abstractmethod
    def _run(self) -> None:
        """The I/O thread: connect, read telemetry, stream setpoints, until ``_stop`` is set."""

    @abstractmethod
    def _ask(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        """Send a COMMAND_LONG (again, while unanswered) and wait up to ``timeout_s`` for its
        final COMMAND_ACK: the MAV_RESULT, or None when no answer came."""

    @abstractmethod
    def _ask_arm(self, timeout_s: float) -> int | None:
        """Ask the vehicle to arm (never forced), once: MAV_RESULT_ACCEPTED, another MAV_RESULT
        for a refusal, or None when no answer came."""

    @abstractmethod
    def _release(self) -> None:
        """Drop the connection (called once the threads have stopped)."""

    # ------------------------------------------------------------------ public API

    def start(self) -> Self:
        """Start the I/O thread (returns at once; the link comes up in the background)."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop every thread and drop the connection (safe to call twice)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for thread in [self._thread, *self._workers]:
            if thread is not None:
                thread.join(timeout_s)
        self._thread = None
        self._release()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def state(self) -> LinkState:
        """A consistent snapshot (never blocks on I/O)."""
        now = time.monotonic()
        with self._cond:
            position = ned_to_area(*self._ned, self.config.frames) if self._ned else None
            mode = self._mode_locked()
            return LinkState(
                link=self._health,
                flavour=self._flavour,
                mode=mode,
                armed=self._armed,
                position_m=position,
                relative_alt_m=self._relative_alt_m,
                heartbeat_age_s=None if self._last_hb is None else now - self._last_hb,
                target_m=self._target_m,
                streaming=self._streaming_now(),
                takeoff=self._takeoff,
                counters=dict(self.counters),
                takeoff_phase=self._takeoff_phase,
                takeoff_attempts=self._takeoff_attempts,
                takeoff_last_refusal=self._takeoff_last_refusal,
                status_texts=tuple(text for _, text in self._status_texts),
            )

    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        """Stream ``target_m`` (area frame, metres) from now on; returns the geofenced target.

        A target outside the area volume is clamped to it (logged and counted); NaN or infinite
        coordinates raise ValueError and change nothing.
        """
        try:
            clamped, was_clamped = clamp_to_area(target_m, self.config.area)
        except ValueError:
            with self._cond:
                self.counters["targets_rejected"] += 1
            raise
        with self._cond:
            if was_clamped:
                self.counters["geofence_clamps"] += 1
                log.warning("target %s outside the geofence: clamped to %s", target_m, clamped)
            if clamped != self._target_m:
                self._target_dirty = True
                self._cond.notify_all()  # wakes an I/O loop waiting on it: out at once
            self._target_m = clamped
            self._mode_wanted_until = time.monotonic() + self.config.mode_request_window_s
        return clamped

    def clear_target(self) -> None:
        """Stop streaming setpoints (the vehicle keeps its own behaviour for a lost stream)."""
        with self._cond:
            self._target_m = None
            self._stream_since = None

    def arm_and_takeoff(
        self, z_m: float | None = None, timeout_s: float = TAKEOFF_TIMEOUT_S
    ) -> Future[None]:
        """Arm and climb to ``z_m`` (area frame; default the area's ``z_min_m``), in a worker.

        The sequence the real autopilots need, started again with backoff after any refusal
        until ``timeout_s`` (a real GPS lock takes minutes, not seconds):

        1. the vehicle's HEARTBEAT; a vehicle already armed and in the air is taken over as it
           is (a restart), without arming;
        2. a usable position estimate: LOCAL_POSITION_NED arriving, and on ArduPilot its
           EKF_STATUS_REPORT showing an absolute horizontal position out of constant-position
           mode (ArduCopter refuses to arm in GUIDED before that, "Need Position Estimate");
        3. ArduPilot: GUIDED asked for and *seen in HEARTBEAT*, held for ``MODE_SETTLE_S``; the
           vehicle is never armed in another mode (an RC mode switch can change it at any time);
        4. arm, then MAV_CMD_NAV_TAKEOFF at once (both autopilots disarm a vehicle left armed on
           the ground for ~10 s): altitude above home on ArduPilot, AMSL on PX4, position and yaw
           NaN (:mod:`service.mavlink_commands`);
        5. the climb confirmed: the vehicle leaves the ground within ``CLIMB_START_S`` and reaches
           90 % of the altitude; disarming or (ArduPilot) leaving GUIDED on the way is a failure.

        Position setpoints are held back until the vehicle is airborne (on ArduPilot a setpoint
        while the take-off is still on the ground cancels it). Progress, the attempt count, the
        last refusal and the vehicle's STATUSTEXTs are in :meth:`state`. The Future completes when
        airborne, or with the reason it gave up.
        """
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s: must be a positive number, got {timeout_s!r}")
        area = self.config.area
        z_m = area.z_min_m if z_m is None else min(max(float(z_m), area.z_min_m), area.z_max_m)
        future: Future[None] = Future()
        worker = threading.Thread(
            target=self._takeoff_worker,
            args=(z_m, timeout_s, future),
            name=f"{self._thread_name}-takeoff",
            daemon=True,
        )
        with self._cond:
            self._takeoff = "running"
            self._takeoff_phase = "starting"
            self._takeoff_attempts = 0
            self._takeoff_last_refusal = None
            self._hold_setpoints = True
        self._workers.append(worker)
        worker.start()
        return future

    def _streaming_now(self) -> bool:
        return self._health == "up" and self._target_m is not None and not self._hold_setpoints

    def _guided_mode_due(self, now: float) -> Flavour | None:
        """The flavour when the guided mode (GUIDED / OFFBOARD) should be asked for now, counted
        as a mode request; None when not: no target streams, the request window is closed, the
        vehicle is already in it, or (PX4) the stream has not run ``px4_stream_lead_s`` yet."""
        with self._cond:
            flavour = self._flavour
            if (
                flavour not in GUIDED_MODE_NAME
                or not self._streaming_now()
                or now > self._mode_wanted_until
                or self._custom_mode is None
                or mode_name(flavour, self._custom_mode) == GUIDED_MODE_NAME[flavour]
            ):
                return None
            if flavour == "px4" and (
                self._stream_since is None
                or now - self._stream_since < self.config.px4_stream_lead_s
            ):
                return None
            self.counters["mode_requests"] += 1
            return flavour

    # ------------------------------------------------------------------ the take-off sequence

    def _note_status_text(self, severity: int, text: str) -> None:
        """A STATUSTEXT from the vehicle: logged and kept for :meth:`state` (call under no lock)."""
        text = text.strip()
        if not text:
            return
        entry = mavlink.enums["MAV_SEVERITY"].get(severity)
        name = entry.name.removeprefix("MAV_SEVERITY_") if entry is not None else str(severity)
        with self._cond:
            self._status_texts.append((time.monotonic(), f"{name}: {text}"))
            self._cond.notify_all()
        level = logging.WARNING if severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "vehicle says: %s", text)

    def _texts_since(self, since: float) -> str:
        """The vehicle's STATUSTEXTs since ``since`` (monotonic), for a refusal's reason; waits
        up to ``REFUSAL_TEXT_WAIT_S`` for one (a refusal's text may come just after its ACK)."""
        until = time.monotonic() + REFUSAL_TEXT_WAIT_S
        with self._cond:
            while True:
                texts = [text for at, text in self._status_texts if at >= since]
                remaining = until - time.monotonic()
                if texts or remaining <= 0 or self._stop.is_set():
                    break
                self._cond.wait(remaining)
        return "; vehicle said: " + " | ".join(texts) if texts else ""

    def _set_phase(self, phase: str) -> None:
        with self._cond:
            self._takeoff_phase = phase
        log.info("take-off: %s", phase)

    def _in_air(self) -> bool:
        """Armed and at least ``IN_AIR_ALT_M`` above home (call under ``self._cond``)."""
        return self._armed and (self._relative_alt_m or 0.0) >= IN_AIR_ALT_M

    def _position_estimate_ok(self) -> bool:
        """A usable position estimate (call under ``self._cond``): LOCAL_POSITION_NED arriving
        (neither autopilot sends it without a local origin), a home altitude, and, where the
        vehicle sends EKF_STATUS_REPORT (ArduPilot), its flags as ArduCopter needs them to arm in
        GUIDED: an absolute horizontal position (or its prediction), not constant-position mode."""
        now = time.monotonic()
        if self._position_at is None or now - self._position_at > POSITION_FRESH_S:
            return False
        if self._home_amsl_m is None:
            return False
        if self._flavour == "ardupilot" and self._ekf_flags is not None:
            return ekf_position_ok(self._ekf_flags)
        return True

    def _mode_locked(self) -> str | None:
        """The mode the vehicle's HEARTBEAT shows, None before one (call under ``self._cond``)."""
        if self._flavour is None or self._custom_mode is None:
            return None
        return mode_name(self._flavour, self._custom_mode)

    def _mode_is(self, name: str) -> bool:
        """The vehicle's HEARTBEAT shows mode ``name`` (call under ``self._cond``)."""
        return self._mode_locked() == name

    def _mode_now(self) -> str:
        with self._cond:
            return self._mode_locked() or "unknown"

    def _wait_for(self, condition: Callable[[], bool], deadline: float, what: str) -> None:
        """Wait (under ``self._cond``) until ``condition()``; TimeoutError at ``deadline``."""
        with self._cond:
            while not condition():
                remaining = deadline - time.monotonic()
                if self._stop.is_set():
                    raise RuntimeError("link closed")
                if remaining <= 0:
                    raise TimeoutError(f"timed out waiting for {what}")
                self._cond.wait(min(remaining, 0.2))

    def _step(self, condition: Callable[[], bool], deadline: float, what: str) -> None:
        """Wait for one step of an attempt: up to ``STEP_TIMEOUT_S`` (a failed attempt), never
        past the sequence's ``deadline`` (the end)."""
        step_deadline = min(deadline, time.monotonic() + STEP_TIMEOUT_S)
        try:
            self._wait_for(condition, step_deadline, what)
        except TimeoutError:
            if time.monotonic() >= deadline:
                raise
            raise TakeoffRefused(f"timed out waiting for {what}") from None

    def _takeoff_worker(self, z_m: float, timeout_s: float, future: Future[None]) -> None:
        deadline = time.monotonic() + timeout_s
        alt_rel_m = z_m - self.config.frames.area_origin_down_m
        backoff_s = RETRY_MIN_S
        try:
            while True:
                try:
                    self._takeoff_attempt(alt_rel_m, deadline)
                    break
                except TakeoffRefused as refusal:
                    reason = str(refusal)
                    with self._cond:
                        self._takeoff_last_refusal = reason
                        self.counters["takeoff_refusals"] += 1
                    log.warning("take-off attempt failed: %s", reason)
                    if time.monotonic() + backoff_s >= deadline:
                        raise TimeoutError(
                            f"not airborne after {timeout_s:.0f} s; last refusal: {reason}"
                        ) from None
                    self._set_phase(f"retrying in {backoff_s:.0f} s")
                    if self._stop.wait(backoff_s):
                        raise RuntimeError("link closed") from None
                    backoff_s = min(backoff_s * 2, RETRY_MAX_S)
            with self._cond:
                self._takeoff = "airborne"
                self._takeoff_phase = None
                self._hold_setpoints = False
                self._mode_wanted_until = time.monotonic() + self.config.mode_request_window_s
                alt_now_m = self._relative_alt_m or 0.0
            log.info("airborne at %.1f m above home", alt_now_m)
            future.set_result(None)
        except Exception as exc:
            with self._cond:
                self._takeoff = f"failed: {exc}"
                self._takeoff_phase = None
                self._hold_setpoints = False
            log.warning("arm and takeoff failed: %s", exc)
            future.set_exception(exc)

    def _takeoff_attempt(self, alt_rel_m: float, deadline: float) -> None:
        """One pass of the sequence (see :meth:`arm_and_takeoff`); TakeoffRefused to retry."""
        with self._cond:
            self._takeoff_attempts += 1
        self._set_phase("waiting for the vehicle")
        self._wait_for(lambda: self._health == "up", deadline, "the vehicle's HEARTBEAT")
        with self._cond:
            if self._in_air():
                log.info("the vehicle is already flying: taken over without arming")
                return
        self._set_phase("waiting for a position estimate")
        self._wait_for(self._position_estimate_ok, deadline, "a position estimate")
        with self._cond:
            flavour = self._flavour
        if flavour == "ardupilot":
            self._ensure_mode("GUIDED", ARDUPILOT_GUIDED, deadline)
        with self._cond:
            armed = self._armed
        if not armed:
            if flavour == "ardupilot" and not self._mode_stays("GUIDED", 0.0):
                raise TakeoffRefused(f"left GUIDED before arming (now {self._mode_now()})")
            self._set_phase("arming")
            asked_at = time.monotonic()
            result = self._ask_arm(STEP_TIMEOUT_S)
            if result != mavlink.MAV_RESULT_ACCEPTED:
                raise TakeoffRefused(
                    f"arming refused ({result_name(result)}){self._texts_since(asked_at)}"
                )
            self._step(lambda: self._armed, deadline, "the vehicle to report armed")
        if flavour == "ardupilot" and not self._mode_stays("GUIDED", 0.0):
            raise TakeoffRefused(f"left GUIDED before the take-off (now {self._mode_now()})")
        with self._cond:
            if self._in_air():
                return  # armed in the air: the setpoints take it from here
            home_amsl_m = self._home_amsl_m or 0.0
        alt_param = alt_rel_m + home_amsl_m if flavour == "px4" else alt_rel_m
        self._set_phase("taking off")
        asked_at = time.monotonic()
        result = self._ask(
            mavlink.MAV_CMD_NAV_TAKEOFF, mavlink_commands.takeoff(alt_param), STEP_TIMEOUT_S
        )
        if result != mavlink.MAV_RESULT_ACCEPTED and not self._leaving_the_ground():
            raise TakeoffRefused(
                f"take-off refused ({result_name(result)}){self._texts_since(asked_at)}"
            )
        self._confirm_climb(flavour, alt_rel_m, deadline, asked_at)

    def _leaving_the_ground(self) -> bool:
        """Armed and climbing within ``LIFTOFF_WAIT_S``: a take-off whose ACCEPTED was lost is
        refused when sent again (ArduCopter takes off only from the ground), yet it flies."""
        try:
            self._wait_for(
                lambda: self._armed and (self._relative_alt_m or 0.0) >= LIFTOFF_ALT_M,
                time.monotonic() + LIFTOFF_WAIT_S,
                "lift-off",
            )
        except TimeoutError:
            return False
        return True

    def _ensure_mode(self, name: str, custom_mode: int, deadline: float) -> None:
        """Ask for mode ``name`` until HEARTBEAT shows it, held for ``MODE_SETTLE_S``."""
        with self._cond:
            already = self._mode_is(name)
        if not already:
            self._set_phase(f"asking for {name}")
            asked_at = time.monotonic()
            result = self._ask(
                mavlink.MAV_CMD_DO_SET_MODE, mavlink_commands.set_mode(custom_mode), STEP_TIMEOUT_S
            )
            if result != mavlink.MAV_RESULT_ACCEPTED:
                raise TakeoffRefused(
                    f"{name} refused ({result_name(result)}){self._texts_since(asked_at)}"
                )
            self._step(lambda: self._mode_is(name), deadline, f"HEARTBEAT to show {name}")
        self._set_phase(f"confirming {name}")
        if not self._mode_stays(name, MODE_SETTLE_S):
            raise TakeoffRefused(f"{name} did not hold (now {self._mode_now()})")

    def _mode_stays(self, name: str, hold_s: float) -> bool:
        """The vehicle is in mode ``name`` and still is ``hold_s`` later."""
        until = time.monotonic() + hold_s
        with self._cond:
            while True:
                if not self._mode_is(name) or self._health != "up":
                    return False
                remaining = until - time.monotonic()
                if remaining <= 0 or self._stop.is_set():
                    return True
                self._cond.wait(min(remaining, 0.2))

    def _confirm_climb(
        self, flavour: Flavour | None, alt_rel_m: float, deadline: float, asked_at: float
    ) -> None:
        """Wait until 90 % of ``alt_rel_m``: leaving the ground within ``CLIMB_START_S``, at no
        less than ``CLIMB_MIN_MPS`` on average, armed (and in GUIDED on ArduPilot) all along."""
        self._set_phase("climbing")
        airborne_alt_m = max(alt_rel_m * 0.9, alt_rel_m - 1.0)
        started = time.monotonic()
        climb_by = min(deadline, started + CLIMB_START_S + alt_rel_m / CLIMB_MIN_MPS)
        with self._cond:
            while True:
                alt_m = self._relative_alt_m or 0.0
                if alt_m >= airborne_alt_m and self._armed:
                    return
                now = time.monotonic()
                why = ""
                if self._stop.is_set():
                    raise RuntimeError("link closed")
                if not self._armed:
                    why = "disarmed during the take-off"
                elif flavour == "ardupilot" and not self._mode_is("GUIDED"):
                    why = "left GUIDED during the take-off"
                elif now - started > CLIMB_START_S and alt_m < IN_AIR_ALT_M:
                    why = f"on the ground {CLIMB_START_S:.0f} s after an accepted take-off"
                elif now > climb_by:
                    if now >= deadline:
                        raise TimeoutError(f"timed out waiting for {airborne_alt_m:.1f} m")
                    why = f"climb too slow: {alt_m:.1f} m after {now - started:.0f} s"
                if why:
                    break
                self._cond.wait(0.2)
        raise TakeoffRefused(why + self._texts_since(asked_at))


class MavlinkLink(VehicleLinkBase):
    """The MAVLink link and setpoint streamer. See the module docstring."""

    _thread_name = "mavlink-link"

    def __init__(self, config: LinkConfig) -> None:
        super().__init__(config)
        self._send_lock = threading.Lock()
        self._conn: Any = None
        self._transport_dead = False
        self._t0 = time.monotonic()
        self.counters["signing_failures"] = 0
        self._target_sys = 1
        self._target_comp = 1
        self._landed_state: int | None = None
        self._acks: dict[int, tuple[int, int]] = {}
        self._ack_seq = 0
        self._up_since = 0.0
        self._interval_accepted = False
        self._fallback_streams_sent = False

    def _ask_arm(self, timeout_s: float) -> int | None:
        return self._ask(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink_commands.arm(), timeout_s)

    def _release(self) -> None:
        self._close_conn()

    # ------------------------------------------------------------------ connection

    def _open_conn(self) -> bool:
        config = self.config
        try:
            conn = mavutil.mavlink_connection(
                config.url,
                source_system=config.source_system,
                source_component=config.source_component,
                dialect="ardupilotmega",
                autoreconnect=False,
                retries=1,
            )
        except (OSError, ValueError) as exc:
            log.debug("cannot open %s: %s", config.url, exc)
            return False
        # pymavlink prints on a closed TCP socket; we notice it ourselves instead.
        conn.handle_eof = self._on_transport_dead
        conn.handle_disconnect = self._on_transport_dead
        if config.signing_key is not None:
            conn.setup_signing(config.signing_key, sign_outgoing=True)
        with self._send_lock:
            self._conn = conn
        self._transport_dead = False
        log.info("MAVLink connection open: %s", config.url)
        return True

    def _on_transport_dead(self) -> None:
        self._transport_dead = True

    def _close_conn(self) -> None:
        with self._send_lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    def _send(self, fn: Callable[[Any], None]) -> bool:
        """Run ``fn(mav)`` on the current connection under the send lock; False if none."""
        with self._send_lock:
            conn = self._conn
            if conn is None:
                return False
            try:
                fn(conn.mav)
            except OSError as exc:
                log.debug("send failed: %s", exc)
                self._transport_dead = True
                return False
            return True

    # ------------------------------------------------------------------ the I/O loop

    def _run(self) -> None:
        config = self.config
        backoff_s = config.reconnect_min_s
        next_open = 0.0
        opened_at = 0.0
        ever_opened = False
        next_heartbeat = 0.0
        next_setpoint = 0.0
        next_mode_request = 0.0
        next_telemetry_request = 0.0
        setpoint_period_s = 1.0 / config.setpoint_rate_hz
        last_setpoint = -math.inf
        while not self._stop.is_set():
            now = time.monotonic()
            self._check_heartbeat(now)
            if self._conn is None:
                if now < next_open:
                    self._stop.wait(min(0.05, next_open - now))
                    continue
                if self._open_conn():
                    if ever_opened:
                        self.counters["reconnects"] += 1
                    ever_opened = True
                    opened_at = now
                    next_heartbeat = 0.0
                    backoff_s = config.reconnect_min_s
                else:
                    self.counters["connect_failures"] += 1
                    next_open = now + backoff_s
                    backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                continue
            try:
                self._receive(timeout_s=0.005)
            except Exception:  # a broken transport or a parser surprise: recreate it
                log.exception("MAVLink receive failed; recreating the connection")
                self._transport_dead = True
            now = time.monotonic()
            health = self._check_heartbeat(now)
            with self._cond:
                silent_since = max(opened_at, self._last_hb or 0.0)
            if self._transport_dead or (
                health != "up" and now - silent_since > config.heartbeat_timeout_s
            ):
                self._close_conn()
                next_open = now + backoff_s
                backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                continue
            if now >= next_heartbeat:
                next_heartbeat = now + 1.0
                self._send(
                    lambda mav: mav.heartbeat_send(
                        config.heartbeat_type,
                        mavlink.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        mavlink.MAV_STATE_ACTIVE,
                    )
                )
            if health != "up":
                continue
            if now >= next_telemetry_request:
                next_telemetry_request = now + 2.0
                self._request_telemetry(now)
            with self._cond:
                dirty = self._target_dirty
            if dirty and now - last_setpoint >= config.setpoint_min_gap_s:
                # A new target: on the wire now, and the steady schedule restarts from here.
                next_setpoint = now + setpoint_period_s
                last_setpoint = now
                self._send_setpoint(now)
            elif now >= next_setpoint:
                next_setpoint = max(next_setpoint + setpoint_period_s, now - setpoint_period_s)
                last_setpoint = now
                self._send_setpoint(now)
            if now >= next_mode_request:
                next_mode_request = now + config.mode_retry_s
                self._request_guided_mode(now)

    def _check_heartbeat(self, now: float) -> LinkHealth:
        """Declare the link lost after ``heartbeat_timeout_s`` without a vehicle HEARTBEAT."""
        with self._cond:
            last_hb = self._last_hb
            timeout_s = self.config.heartbeat_timeout_s
            if self._health == "up" and last_hb is not None and now - last_hb > timeout_s:
                self._health = "link_lost"
                self._stream_since = None
                log.warning("no HEARTBEAT for %.1f s: link lost", now - last_hb)
            return self._health

    def _receive(self, timeout_s: float) -> None:
        conn = self._conn
        message = conn.recv_match(blocking=True, timeout=timeout_s)
        count = 0
        while message is not None and count < 200:
            self._handle(message)
            count += 1
            message = conn.recv_msg()

    def _handle(self, message: Any) -> None:
        kind = message.get_type()
        now = time.monotonic()
        if kind == "STATUSTEXT":
            if self._from_vehicle(message):
                self._note_status_text(message.severity, message.text)
            return
        with self._cond:
            if kind == "HEARTBEAT":
                if message.autopilot == mavlink.MAV_AUTOPILOT_INVALID or message.type in (
                    mavlink.MAV_TYPE_GCS,
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                ):
                    return  # another ground station or companion, not the vehicle
                header = message.get_header()
                if (
                    self.config.signing_key is None
                    and getattr(header, "incompat_flags", 0) & mavlink.MAVLINK_IFLAG_SIGNED
                ):
                    # It signs, we cannot: it will most likely ignore what we send.
                    self.counters["signed_vehicle_without_key"] += 1
                self._target_sys, self._target_comp = header.srcSystem, header.srcComponent
                self._flavour = flavour_of(message.autopilot)
                self._custom_mode = message.custom_mode
                self._armed = bool(message.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._last_hb = now
                if self._health != "up":
                    log.info("vehicle HEARTBEAT (%s): link up", self._flavour)
                    self._health = "up"
                    self._up_since = now
                    self._position_at = None
                    self._ekf_flags = None
                    self._interval_accepted = False
                    self._fallback_streams_sent = False
            elif kind == "LOCAL_POSITION_NED":
                self._ned = (message.x, message.y, message.z)
                self._position_at = now
            elif kind == "GLOBAL_POSITION_INT":
                self._relative_alt_m = message.relative_alt / 1000.0
                self._home_amsl_m = (message.alt - message.relative_alt) / 1000.0
            elif kind == "EXTENDED_SYS_STATE":
                self._landed_state = message.landed_state
            elif kind == "EKF_STATUS_REPORT":
                self._ekf_flags = message.flags
            elif kind == "COMMAND_ACK":
                if message.result == mavlink.MAV_RESULT_IN_PROGRESS:
                    return  # not the final answer
                self._ack_seq += 1
                self._acks[message.command] = (self._ack_seq, message.result)
                if (
                    message.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
                    and message.result == mavlink.MAV_RESULT_ACCEPTED
                ):
                    self._interval_accepted = True
            elif kind == "BAD_DATA":
                self.counters["bad_data"] += 1
                if "signature" in str(getattr(message, "reason", "")).lower():
                    self.counters["signing_failures"] += 1
                return
            else:
                return
            self._cond.notify_all()

    def _from_vehicle(self, message: Any) -> bool:
        """The message comes from the vehicle's system (any of its components)."""
        with self._cond:
            return message.get_srcSystem() == self._target_sys and self._last_hb is not None

    def _request_telemetry(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for what we need (every 2 s until it all comes); on ArduPilot
        also EKF_STATUS_REPORT (the take-off waits on its flags), and the older
        REQUEST_DATA_STREAM once if no SET_MESSAGE_INTERVAL was accepted 1.5 s after the link
        came up (an old firmware, or a router that filters it). A real ArduCopter accepts at once
        but sends no LOCAL_POSITION_NED until its EKF has an origin (~20 s): missing positions
        alone are no reason to fall back."""
        with self._cond:
            flavour = self._flavour
            positions_fresh = self._position_at is not None and now - self._position_at < 1.0
            ekf_missing = flavour == "ardupilot" and self._ekf_flags is None
            use_fallback = (
                flavour == "ardupilot"
                and not self._interval_accepted
                and not self._fallback_streams_sent
                and now - self._up_since > 1.5
            )
            if use_fallback:
                self._fallback_streams_sent = True
            sys_id, comp_id = self._target_sys, self._target_comp
        if positions_fresh and not ekf_missing and not use_fallback:
            return
        rate_hz = self.config.telemetry_rate_hz
        wanted = [
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, rate_hz),
            (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, rate_hz),
            (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0),
        ]
        if flavour == "ardupilot":
            wanted.append((mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2.0))
        for message_id, hz in wanted:
            self._send_command_long(
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                mavlink_commands.set_message_interval(message_id, hz),
            )
        if use_fallback:
            log.info("SET_MESSAGE_INTERVAL not accepted: REQUEST_DATA_STREAM fallback")
            for stream in (mavlink.MAV_DATA_STREAM_POSITION, mavlink.MAV_DATA_STREAM_EXTRA3):
                self._send(
                    lambda mav, s=stream: mav.request_data_stream_send(
                        sys_id, comp_id, s, int(rate_hz), 1
                    )
                )

    def _send_setpoint(self, now: float) -> None:
        with self._cond:
            self._target_dirty = False
            if not self._streaming_now():
                self._stream_since = None
                return
            assert self._target_m is not None
            north_m, east_m, down_m = area_to_ned(*self._target_m, self.config.frames)
            sys_id, comp_id = self._target_sys, self._target_comp
            if self._stream_since is None:
                self._stream_since = now
        time_boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        fields = (
            time_boot_ms,
            sys_id,
            comp_id,
            mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_TYPE_MASK,
            north_m,
            east_m,
            down_m,
            *([0.0] * 8),  # velocity, acceleration, yaw, yaw rate: ignored by the type_mask
        )
        sent = self._send(lambda mav: mav.set_position_target_local_ned_send(*fields))
        if sent:
            with self._cond:
                self.counters["setpoints_sent"] += 1

    def _request_guided_mode(self, now: float) -> None:
        """Ask for GUIDED / OFFBOARD while a target streams and the request window is open."""
        flavour = self._guided_mode_due(now)
        if flavour is None:
            return
        main = ARDUPILOT_GUIDED if flavour == "ardupilot" else PX4_MAIN_OFFBOARD
        self._send_command_long(mavlink.MAV_CMD_DO_SET_MODE, mavlink_commands.set_mode(main))

    def _send_command_long(self, command: int, params: mavlink_commands.Params) -> bool:
        """Send COMMAND_LONG ``command`` with its seven ``params`` to the vehicle."""
        values = list(params)
        with self._cond:
            sys_id, comp_id = self._target_sys, self._target_comp
        return self._send(lambda mav: mav.command_long_send(sys_id, comp_id, command, 0, *values))

    # ------------------------------------------------------------------ arm and takeoff

    def _ask(self, command: int, params: mavlink_commands.Params, timeout_s: float) -> int | None:
        """COMMAND_LONG, re-sent every ``COMMAND_RESEND_S`` until the vehicle answers (a lossy
        radio loses commands and ACKs) or ``timeout_s`` passes: the first final COMMAND_ACK's
        result, or None."""
        with self._cond:
            seq_before = self._ack_seq  # only an ACK newer than this answers us
        ask_until = time.monotonic() + timeout_s
        while not self._stop.is_set():
            with self._cond:
                self.counters["commands_sent"] += 1
            self._send_command_long(command, params)
            resend_at = min(ask_until, time.monotonic() + COMMAND_RESEND_S)
            with self._cond:
                while not self._stop.is_set():
                    seq, result = self._acks.get(command, (0, -1))
                    if seq > seq_before:
                        return result
                    remaining = resend_at - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
            if time.monotonic() >= ask_until:
                return None
        return None
