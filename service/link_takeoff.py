"""The arm-and-takeoff sequence of the vehicle link (:class:`TakeoffMixin`), for both backends.

:meth:`TakeoffMixin.arm_and_takeoff` starts it in a worker thread and documents its steps; the
worker drives the vehicle through the backend's hooks (``_ask``, ``_ask_arm``,
``_send_guided_mode_request``) and waits on the link's own state under ``self._cond``. It is a
mixin of :class:`service.vehicle_link.VehicleLinkBase`, whose ``__init__`` creates the state it
uses (``_takeoff*``, ``_hold_setpoints``, the vehicle's mode, position and STATUSTEXTs).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING

from service import control as vehicle_control
from service import mavlink_commands
from service.control import Control
from service.modes import Flavour, set_mode_numbers
from service.vehicle_mavlink import mavlink, result_name

if TYPE_CHECKING:
    from service.vehicle_link import VehicleLinkBase

    _Base = VehicleLinkBase
else:
    _Base = object

log = logging.getLogger("service.vehicle_link")

POSITION_FRESH_S = 2.0
"""LOCAL_POSITION_NED older than this does not count as a position estimate."""
TAKEOFF_TIMEOUT_S = 300.0
"""How long the take-off sequence keeps trying by default: a real autopilot needs a GPS lock and
its pre-arm checks first (ArduCopter SITL ~40 s from boot, a real vehicle minutes)."""
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
REFUSAL_TEXT_WAIT_S = 0.5
"""How long a refusal waits for the vehicle's STATUSTEXT that explains it."""
EKF_POSITION_FLAGS = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS


def ekf_position_ok(flags: int) -> bool:
    """ArduPilot's EKF_STATUS_REPORT.flags allow arming in GUIDED: an absolute horizontal position
    (or its prediction, which is what ArduCopter checks while disarmed) and no constant-position
    mode (the EKF's "no GPS yet" state)."""
    return bool(flags & EKF_POSITION_FLAGS) and not flags & mavlink.EKF_CONST_POS_MODE


class TakeoffRefused(Exception):  # noqa: N818 (a refusal, not a programming error)
    """One take-off attempt failed (a refusal, a mode change, no climb): the sequence restarts."""


class TakeoffMixin(_Base):
    """The take-off sequence (module doc)."""

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
            self._set_control(Control("service", "its take-off sequence", time.monotonic()))
        self._workers.append(worker)
        worker.start()
        return future

    # ------------------------------------------------------------------ the take-off sequence

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
                        failsafe = self._failsafe_acting()
                        if failsafe is not None:  # the autopilot's: never retried over it
                            self._set_control(Control("autopilot", failsafe, time.monotonic()))
                    log.warning("take-off attempt failed: %s", reason)
                    if failsafe is not None:
                        raise RuntimeError(
                            f"the autopilot's failsafe acted during the take-off ({failsafe}): "
                            "not retried"
                        ) from None
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
                mode = self._mode_locked()
                if vehicle_control.is_return_or_land(self._flavour, mode):
                    self._set_control(
                        Control("autopilot", f"the vehicle is in {mode}", time.monotonic())
                    )
            log.info("airborne at %.1f m above home", alt_now_m)
            future.set_result(None)
        except Exception as exc:
            with self._cond:
                self._takeoff = f"failed: {exc}"
                self._takeoff_phase = None
                self._hold_setpoints = False
            log.warning("arm and takeoff failed: %s", exc)
            future.set_exception(exc)

    def _failsafe_acting(self) -> str | None:
        """Why the autopilot's own failsafe has the vehicle now, or None (call under
        ``self._cond``): a failsafe flagged in its HEARTBEAT, or a return or landing mode with a
        failsafe STATUSTEXT in the last ``FAILSAFE_EVIDENCE_S`` (PX4's "Failsafe activated" and
        AUTO.LAND while a take-off climbs). A take-off attempt that failed so is not retried:
        arming again would fight the failsafe."""
        mode = self._mode_locked()
        if self._failsafe_flagged():
            return f"failsafe flagged in HEARTBEAT, mode {mode}"
        text = self._failsafe_text
        if (
            text is not None
            and time.monotonic() - text[0] <= vehicle_control.FAILSAFE_EVIDENCE_S
            and vehicle_control.is_return_or_land(self._flavour, mode)
        ):
            return f"{mode} after {text[1]!r}"
        return None

    def _takeoff_attempt(self, alt_rel_m: float, deadline: float) -> None:
        """One pass of the sequence (see :meth:`arm_and_takeoff`); TakeoffRefused to retry."""
        with self._cond:
            self._takeoff_attempts += 1
        self._set_phase("waiting for the vehicle")
        self._wait_for(lambda: self._health == "up", deadline, "the vehicle's HEARTBEAT")
        with self._cond:
            mode = self._mode_locked()
            if (
                self._takeoff_attempts == 1
                and self._armed
                and not vehicle_control.may_take_at_start(self._flavour, mode)
            ):
                # Armed in someone else's mode before the sequence did anything: a pilot (or
                # the autopilot) has it, on the ground or flying; not taken, not retried.
                now = time.monotonic()
                seen = self._observation(None, None, False, at_start=True, now=now)
                why = f"the vehicle was found armed in {mode} before its take-off"
                self._set_control(Control(vehicle_control.holder_after_leaving(seen), why, now))
                raise RuntimeError(f"{why}: left to whoever flies it (an operator hands it back)")
            if self._in_air():
                log.info("the vehicle is already flying: taken over without arming")
                return
        self._set_phase("waiting for a position estimate")
        self._wait_for(self._position_estimate_ok, deadline, "a position estimate")
        if self.config.autopilot_fence:
            self._set_phase("putting the envelope on the autopilot as its fence")
            self._wait_for(
                lambda: self._fence == "uploaded" or self._fence.startswith("failed"),
                deadline,
                "the autopilot's fence",
            )
            with self._cond:
                if self._fence != "uploaded":
                    raise TakeoffRefused(
                        f"the autopilot's fence is not on the vehicle: {self._fence}"
                    )
        with self._cond:
            flavour = self._flavour
        if flavour == "ardupilot":
            self._ensure_mode("ardupilot", "GUIDED", deadline)
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

    def _ensure_mode(self, flavour: Flavour, name: str, deadline: float) -> None:
        """Ask for mode ``name`` until HEARTBEAT shows it, held for ``MODE_SETTLE_S``."""
        with self._cond:
            already = self._mode_is(name)
        if not already:
            self._set_phase(f"asking for {name}")
            asked_at = time.monotonic()
            params = mavlink_commands.set_mode(*set_mode_numbers(flavour, name))
            result = self._ask(mavlink.MAV_CMD_DO_SET_MODE, params, STEP_TIMEOUT_S)
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
