"""The link's flight-safety duties beyond the envelope's routes (:class:`SafetyMixin`), for both
backends: the envelope's speed limit on the autopilot, the envelope as the autopilot's own fence,
and the battery reserve with the service's return home.

Each runs from the I/O loop of :class:`service.vehicle_link.VehicleLinkBase` (``_serve`` calls
``_speed_limit_step``, ``_fence_step`` and ``_check_battery_reserve`` when they are due); what
waits for the vehicle (a command's answer, the return) runs on a worker thread, never on the
loop. A mixin of ``VehicleLinkBase``, whose ``__init__`` creates the state it uses.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import TYPE_CHECKING

from service import control as vehicle_control
from service import mavlink_commands
from service.battery import reserve_reached, return_needs_pct
from service.control import Control
from service.fence import PARAM_TOLERANCE, FenceError, fence_plan
from service.frames import GeoPoint, global_to_ned
from service.link_takeoff import STEP_TIMEOUT_S
from service.mission_protocol import MissionError
from service.modes import GUIDED_MODE_NAME
from service.vehicle_mavlink import mavlink, result_name

if TYPE_CHECKING:
    from service.vehicle_link import VehicleLinkBase

    _Base = VehicleLinkBase
else:
    _Base = object

log = logging.getLogger("service.vehicle_link")

FENCE_RETRY_S = 10.0
"""After a failed fence upload, how long until the next try (nothing streams meanwhile)."""
HOME_REQUEST_PERIOD_S = 2.0
"""How often GPS_GLOBAL_ORIGIN is asked for while the fence waits for it."""
ORIGIN_MOVED_M = 0.05
"""An origin that moves more than this after the fence was uploaded puts it on again."""
PX4_SPEED_PARAM = "MPC_XY_VEL_MAX"
"""PX4's horizontal speed limit, in every mode (offboard included)."""
PX4_CAPPED_PARAMS = ("MPC_XY_CRUISE", "MPC_VEL_MANUAL", "MPC_VEL_MAN_BACK", "MPC_VEL_MAN_SIDE")
"""What PX4 lowers to that limit, and keeps (it commits them), when the limit is set below
them ("Cruise speed has been constrained by max speed"): the missions' and returns' cruise
speed and the pilot's. Read before the limit is lowered and set back after it is raised again
(those a PX4 does not have are skipped)."""
CAPPED_ANSWER_S = 0.5
"""How long each of those is waited for when read (an older PX4 lacks the last two)."""
SPEED_ANSWER_S = 3.0
"""How long a speed command or parameter waits for the vehicle's answer."""
SPEED_GIVE_BACK_S = SPEED_ANSWER_S + 2.0
"""How long closing the link waits for PX4's own speeds to be set back (a limit still waiting
for the vehicle's answer first: its PARAM_SET is not sent again after the give-back's)."""
SPEED_RETRY_S = 5.0
"""After an unanswered or refused speed limit, how long until it is asked for again."""
SPEED_AFTER_STREAM_S = 1.0
"""How long the stream runs in GUIDED before the speed limit is sent: ArduCopter resets GUIDED's
speed to WPNAV_SPEED when the first position target moves it into its position sub-mode (from
the take-off's), so a limit sent before that is lost (seen on its SITL)."""
SPEED_REASSERT_S = 10.0
"""The limit is sent again this often while the vehicle stays in GUIDED: any later switch of
GUIDED's sub-mode resets it the same way."""
RETURN_ATTEMPTS = 3
"""How many times the return home is asked for before the link gives up (and says so)."""
PACE_LEAD_S = 1.0
"""Until the autopilot holds the envelope's speed limit, a setpoint streams at most this many
seconds of flight at the limit ahead of the vehicle (:func:`paced_setpoint`)."""


def paced_setpoint(
    position_m: Sequence[float],
    setpoint_m: Sequence[float],
    max_speed_mps: float,
    brake_mps2: float,
) -> tuple[float, float, float]:
    """The point on the straight way from ``position_m`` to ``setpoint_m`` (area frame) no further
    ahead, horizontally, than ``lead = min(max_speed_mps * PACE_LEAD_S, max_speed_mps**2 /
    (2 * brake_mps2))``; ``setpoint_m`` itself when it is nearer.

    What the link streams while the autopilot's own speed limit is not (yet) the envelope's: an
    autopilot that flies towards a point at its own speed is kept to ``max_speed_mps`` by never
    being given a point further away than that lead — whether its position controller is
    proportional (speed = gain x distance, gain at most 1/s: PX4's and ArduPilot's default
    horizontal position gains are 0.95 and 1) or plans to stop at the point braking at up to
    ``brake_mps2`` (speed <= sqrt(2 x brake x distance)). The point lies on the vehicle's way to
    the route's setpoint, which the route already keeps legal."""
    here = [float(v) for v in position_m]
    there = [float(v) for v in setpoint_m]
    lead_m = min(max_speed_mps * PACE_LEAD_S, max_speed_mps**2 / (2.0 * brake_mps2))
    horizontal_m = math.hypot(there[0] - here[0], there[1] - here[1])
    if horizontal_m <= lead_m:
        return (there[0], there[1], there[2])
    share = lead_m / horizontal_m
    x, y, z = (a + share * (b - a) for a, b in zip(here, there, strict=True))
    return (x, y, z)


class SafetyMixin(_Base):
    """The speed limit, the autopilot's fence and the battery reserve (module doc)."""

    # ------------------------------------------------------------------ the speed limit

    def _speed_limit_held_locked(self) -> bool:
        """Whether the autopilot is known to fly no faster than the envelope's ``max_speed_mps``
        (call under ``self._cond``): ArduPilot took it for this stay in GUIDED; PX4's
        ``MPC_XY_VEL_MAX`` is confirmed at or below it. Until then setpoints are paced
        (:func:`paced_setpoint`)."""
        wanted_mps = self._routing.envelope.max_speed_mps
        if self._flavour == "px4":
            held_mps = self._speed_param_mps  # NaN while a set is unanswered: not held
        elif self._flavour == "ardupilot":
            held_mps = self._speed_limit_mps
        else:
            held_mps = None
        return held_mps is not None and held_mps <= wanted_mps

    def _paced_locked(
        self, setpoint_m: tuple[float, float, float], now: float
    ) -> tuple[float, float, float] | None:
        """``setpoint_m`` as it may stream now (call under ``self._cond``): itself while the
        autopilot holds the envelope's speed limit, otherwise paced from where the vehicle is;
        without a fresh position, the last setpoint streamed (None: none streamed yet)."""
        if self._speed_limit_held_locked():
            return setpoint_m
        position = self._position_locked(now)
        if position is None:
            return self._streamed_area_m
        return paced_setpoint(
            position, setpoint_m, self._routing.envelope.max_speed_mps, self.config.brake_mps2
        )

    def _speed_limit_step(self, now: float) -> None:
        """The envelope's ``max_speed_mps`` on the autopilot, asked on a worker (the I/O loop
        never waits for an answer), again after ``SPEED_RETRY_S`` when unanswered or refused.

        ArduPilot: as the guided mode's horizontal speed (MAV_CMD_DO_CHANGE_SPEED, ground
        speed), once the stream has run ``SPEED_AFTER_STREAM_S`` in GUIDED, again every
        ``SPEED_REASSERT_S`` while it stays and at once for a new envelope's; GUIDED's speed is
        the guided mode's own, so nothing is given back. PX4's offboard mode ignores that
        command and flies at ``MPC_XY_VEL_MAX``: :meth:`_px4_speed_step`."""
        with self._cond:
            flavour = self._flavour
        if flavour == "px4":
            self._px4_speed_step(now)
            return
        with self._cond:
            wanted_mps = self._routing.envelope.max_speed_mps
            if (
                self._speed_busy
                or flavour != "ardupilot"
                or not self._streaming_now()
                or self._stream_since is None
                or now - self._stream_since < SPEED_AFTER_STREAM_S
                or self._mode_locked() != GUIDED_MODE_NAME["ardupilot"]
                or (
                    self._speed_limit_mps == wanted_mps
                    and now - self._speed_set_at < SPEED_REASSERT_S
                )
            ):
                return
            self._speed_busy = True
            self._speed_next_try = now + SPEED_RETRY_S
        self._start_speed_worker(partial(self._speed_limit_worker, wanted_mps))

    def _start_speed_worker(self, work: Callable[[], None]) -> None:
        worker = threading.Thread(target=work, name=f"{self._thread_name}-speed", daemon=True)
        self._workers.append(worker)
        worker.start()

    def _px4_speed_step(self, now: float) -> None:
        """PX4: while the service flies the vehicle in OFFBOARD, its ``MPC_XY_VEL_MAX`` (the
        horizontal speed limit of every mode) is the envelope's ``max_speed_mps``, never above
        the vehicle's own; once the service no longer flies it (a hand-back, a pilot's switch,
        a failsafe, a return, the service stopping) the vehicle's own values are set back at
        once: the limit, then the speeds PX4 lowered to it (:data:`PX4_CAPPED_PARAMS`), all read
        when the service starts flying it (again at every start: a pilot may have changed
        them). A vehicle whose own limit is already at or below the envelope's is left
        alone."""
        with self._cond:
            if self._speed_busy or self._health != "up":
                return
            own = self._speed_params_own
            own_mps = None if own is None else own[PX4_SPEED_PARAM]
            set_mps = self._speed_param_mps
            flying_it = (
                not self._closing
                and self._streaming_now()
                and self._mode_locked() == GUIDED_MODE_NAME["px4"]
            )
            work: Callable[[], None]
            if flying_it:
                wanted = self._routing.envelope.max_speed_mps
                if own_mps is not None and set_mps == min(wanted, own_mps):
                    return
                work = partial(self._px4_speed_set, wanted)
            elif set_mps is not None and set_mps != own_mps:
                work = self._px4_speed_give_back
            elif set_mps is not None:  # left at its own: nothing to give back
                self._speed_params_own = self._speed_param_mps = None
                return
            else:
                return
            self._speed_busy = True
            self._speed_next_try = now + SPEED_RETRY_S
        self._start_speed_worker(work)

    def _px4_speed_set(self, wanted_mps: float) -> None:
        """Put ``wanted_mps`` (capped by the vehicle's own value) on ``MPC_XY_VEL_MAX``, the
        vehicle's own values read first."""
        with self._cond:
            own, set_mps = self._speed_params_own, self._speed_param_mps
        if own is None:
            own = self._read_px4_speeds()
            if own is None:
                self._speed_param_failed(f"could not read {PX4_SPEED_PARAM}")
                return
            with self._cond:
                self._speed_params_own = own
        own_mps = own[PX4_SPEED_PARAM]
        value = min(wanted_mps, own_mps)
        with self._cond:
            if set_mps in (None, own_mps) and value == own_mps:
                self._speed_param_mps = own_mps  # its own is the envelope's or lower
                self._speed_busy = False
                return
            # From the PARAM_SET on, the vehicle may hold the new value before it says so, or
            # its answer may be lost: until it answers, the limit on it is unknown (NaN, equal
            # to no value), and it is given back as though it had changed.
            self._speed_param_mps = math.nan
        if not self._px4_param_set(PX4_SPEED_PARAM, value):
            self._speed_param_failed(f"{PX4_SPEED_PARAM} {value:g} m/s not taken")
            return
        with self._cond:
            self._speed_busy = False
            self._speed_next_try = 0.0
            self.counters["speed_limits_set"] += value != set_mps
            self._speed_param_mps = value
            self._cond.notify_all()
        log.info(
            "%s is the envelope's %g m/s (the vehicle's own: %s)",
            PX4_SPEED_PARAM,
            value,
            _params_text(own),
        )

    def _px4_speed_give_back(self) -> None:
        """The vehicle's own speeds back: the limit first, then the speeds PX4 lowered to it."""
        with self._cond:
            own = self._speed_params_own
        assert own is not None
        why = self._give_back_px4_speeds(own)
        if why is not None:
            self._speed_param_failed(why)
            return
        with self._cond:
            self._speed_busy = False
            self._speed_next_try = 0.0
            self._speed_params_own = self._speed_param_mps = None  # read afresh next time
            self.counters["speed_limits_given_back"] += 1
            self._cond.notify_all()
        log.info("the vehicle's own speeds are back: %s", _params_text(own))

    def _read_px4_speeds(self) -> dict[str, float] | None:
        """The vehicle's own ``MPC_XY_VEL_MAX`` and those of :data:`PX4_CAPPED_PARAMS` it has;
        None when the limit itself does not answer."""
        limit = self._param_float(PX4_SPEED_PARAM, None, SPEED_ANSWER_S)
        if limit is None or not math.isfinite(limit):
            return None
        own = {PX4_SPEED_PARAM: limit}
        for name in PX4_CAPPED_PARAMS:
            value = self._param_float(name, None, CAPPED_ANSWER_S)
            if value is not None and math.isfinite(value):
                own[name] = value
        return own

    def _give_back_px4_speeds(self, own: dict[str, float]) -> str | None:
        """Set ``own`` back, the limit first (PX4 would cap the others again under a lower
        one); a capped speed is set only when it is not its own any more. Why not, or None."""
        if not self._px4_param_set(PX4_SPEED_PARAM, own[PX4_SPEED_PARAM]):
            return f"{PX4_SPEED_PARAM} {own[PX4_SPEED_PARAM]:g} m/s not taken"
        for name, value in own.items():
            if name == PX4_SPEED_PARAM:
                continue
            now = self._param_float(name, None, CAPPED_ANSWER_S)
            if now is not None and abs(now - value) <= PARAM_TOLERANCE:
                continue
            if not self._px4_param_set(name, value):
                return f"{name} {value:g} not taken"
        return None

    def _px4_param_set(self, name: str, value: float) -> bool:
        """Set a REAL32 parameter; whether the vehicle reported ``value`` back."""
        reported = self._param_float(name, value, SPEED_ANSWER_S)
        return reported is not None and abs(reported - value) <= PARAM_TOLERANCE

    def _speed_param_failed(self, why: str) -> None:
        with self._cond:
            self._speed_busy = False
            self.counters["speed_limit_failures"] += 1
            self._cond.notify_all()
        log.warning("the envelope's speed limit on the vehicle: %s", why)

    def _give_back_speed_param(self, timeout_s: float) -> None:
        """Before the link closes: a PX4's own speeds back if the service changed them
        (:meth:`_px4_speed_give_back`, run by the I/O loop), waited for up to ``timeout_s``;
        says so if they could not be."""
        with self._cond:
            self._closing = True
            if self._speed_param_mps is None or self._thread is None:
                return
            self._speed_next_try = 0.0
            self._cond.notify_all()
            given_back = self._cond.wait_for(lambda: self._speed_param_mps is None, timeout_s)
            own, now_mps = self._speed_params_own, self._speed_param_mps
        if not given_back and own is not None:
            log.error(
                "%s stays %s on the vehicle: set its own back (%s)",
                PX4_SPEED_PARAM,
                "unconfirmed" if now_mps is None or math.isnan(now_mps) else f"{now_mps:g} m/s",
                _params_text(own),
            )

    def _speed_limit_worker(self, speed_mps: float) -> None:
        command = mavlink_commands.change_speed(speed_mps)
        result = self._ask(mavlink.MAV_CMD_DO_CHANGE_SPEED, command, SPEED_ANSWER_S)
        new = False
        with self._cond:
            self._speed_busy = False
            if result == mavlink.MAV_RESULT_ACCEPTED:
                new = self._speed_limit_mps != speed_mps
                self.counters["speed_limits_set"] += new
                self._speed_limit_mps = speed_mps
                self._speed_set_at = time.monotonic()
            else:
                self.counters["speed_limit_failures"] += 1
        if new:
            log.info("the guided mode's speed is now the envelope's %g m/s", speed_mps)
        elif result != mavlink.MAV_RESULT_ACCEPTED:
            log.warning("the vehicle did not take the envelope's speed limit (%s)", result)

    # ------------------------------------------------------------------ the autopilot's fence

    def _fence_step(self, now: float) -> None:
        """Put the envelope on the autopilot as its fence once its local origin is known
        (GPS_GLOBAL_ORIGIN, the point local NED hangs off, in which the area frame sits) (in the I/O
        thread: the upload borrows the connection for a fraction of a second); on failure, say
        why and try again after ``FENCE_RETRY_S``."""
        with self._cond:
            if self._fence == "uploaded" or self._flavour is None:
                return
            flavour, origin, envelope = self._flavour, self._origin, self._fence_envelope
            if origin is None:
                self._fence = "waiting for the vehicle's origin (GPS_GLOBAL_ORIGIN)"
                self._fence_next_try = now + HOME_REQUEST_PERIOD_S
        if origin is None:
            self._request_origin()
            return
        try:
            plan = fence_plan(
                envelope, origin, self.config.frames, flavour, action=self.config.fence_action
            )
            report = self._upload_fence(plan)
        except (FenceError, MissionError) as exc:
            with self._cond:
                self._fence = f"failed: {exc}"
                self._fence_next_try = time.monotonic() + FENCE_RETRY_S
                self.counters["fence_failures"] += 1
            log.error("the autopilot's fence could not be put on the vehicle: %s", exc)
            return
        with self._cond:
            if self._fence_envelope is envelope:
                self._fence = "uploaded"
                self.counters["fence_uploads"] += 1
                self._cond.notify_all()
        log.info("the autopilot's fence is on the vehicle: %s", report)

    def _note_origin(self, origin: GeoPoint) -> None:
        """GPS_GLOBAL_ORIGIN (call under ``self._cond``): the local frame's origin, which the
        area frame hangs off and the fence is placed around. Not HOME_POSITION: a real PX4 SITL
        announced homes from its raw GNSS fix for its first seconds, 0.26-0.5 m from the origin
        its EKF then kept, and moves home at arming. An origin that moves after the fence is on
        the vehicle puts it on again."""
        previous = self._origin
        self._origin = origin
        if self._fence.startswith("waiting for the vehicle's origin"):
            self._fence_next_try = 0.0
        elif (
            previous is not None
            and self._fence == "uploaded"
            and _distance_m(previous, origin) > ORIGIN_MOVED_M
        ):
            self._fence = "uploading: the vehicle's origin moved"
            self._fence_next_try = 0.0
            log.warning("the vehicle's origin moved: its fence is put on again")

    # ------------------------------------------------------------------ the battery reserve

    def _note_battery(
        self, now: float, remaining_pct: float | None, voltage_v: float | None
    ) -> None:
        """A battery reading (call under ``self._cond``): ``remaining_pct`` None or negative when
        the vehicle does not know it. Readings while flying feed the drain estimate."""
        known = remaining_pct is not None and 0 <= remaining_pct <= 100
        self._battery_pct = float(remaining_pct) if known else None  # type: ignore[arg-type]
        self._battery_voltage_v = voltage_v
        if known and self._in_air():
            self._drain.add(now, float(remaining_pct))  # type: ignore[arg-type]

    def _home_leg_m(self) -> tuple[float, float] | None:
        """(horizontal distance, height) from home, metres (call under ``self._cond``)."""
        if self._ned is None:
            return None
        north_m, east_m, down_m = self._ned
        return math.hypot(north_m, east_m), max(0.0, -down_m)

    def _return_at_pct(self) -> float | None:
        """The charge at which the vehicle is sent home from here (under ``self._cond``)."""
        cfg = self.config.battery
        leg = self._home_leg_m()
        if cfg.reserve_pct is None or leg is None or not self._control.service_has_it:
            return None
        return cfg.reserve_pct + return_needs_pct(self._drain.pct_per_s, *leg, cfg)

    def _check_battery_reserve(self, now: float) -> None:
        """Send the vehicle home at its reserve (:mod:`service.battery`), in a worker
        (:meth:`_return_worker`)."""
        with self._cond:
            pct, leg = self._battery_pct, self._home_leg_m()
            if (
                pct is None
                or leg is None
                or self._return_pending is not None
                or not self._control.service_has_it
                or self._takeoff == "running"
                or not self._in_air()
            ):
                return
            why = reserve_reached(pct, self._drain.pct_per_s, *leg, self.config.battery)
            if why is None:
                return
            self._return_pending = why
            self.counters["battery_returns"] += 1
        log.warning("%s: sending the vehicle home", why)
        worker = threading.Thread(
            target=self._return_worker, args=(why,), name=f"{self._thread_name}-return", daemon=True
        )
        self._workers.append(worker)
        worker.start()

    def _return_worker(self, why: str) -> None:
        """Let go of the vehicle and command MAV_CMD_NAV_RETURN_TO_LAUNCH, unless the autopilot
        acts already. It first waits for a HEARTBEAT heard after the reserve was reached (the
        stream goes on meanwhile, so that PX4's offboard-loss hold does not start): if that
        shows a return or landing mode, or a failsafe (flagged, or announced in the last few
        seconds), the service only lets go, so that it never overrides the autopilot's own
        failsafe (its LAND, say, with an RTL). Otherwise it lets go (nothing streams) and asks
        for the return until accepted, :data:`RETURN_ATTEMPTS` times at most."""
        try:
            began = time.monotonic()
            with self._cond:
                heard = self._cond.wait_for(
                    lambda: self._stop.is_set() or (self._last_hb or -math.inf) > began,
                    timeout=STEP_TIMEOUT_S / 2,
                )
                if self._stop.is_set():
                    return
                texts = self._failsafe_text
                acting = heard and (
                    vehicle_control.is_return_or_land(self._flavour, self._mode_locked())
                    or self._failsafe_flagged()
                    or (
                        texts is not None and began - texts[0] < vehicle_control.FAILSAFE_EVIDENCE_S
                    )
                )
                if self._control.service_has_it:
                    action = "the autopilot acts already" if acting else "returning home (RTL)"
                    self._set_control(Control("autopilot", f"{why}: {action}", time.monotonic()))
            if acting:
                log.info("the autopilot returns or lands on its own: no return command sent")
                return
            for _ in range(RETURN_ATTEMPTS):
                result = self._ask(
                    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
                    mavlink_commands.return_to_launch(),
                    STEP_TIMEOUT_S / 2,
                )
                if result == mavlink.MAV_RESULT_ACCEPTED:
                    log.info("the vehicle accepted the return home")
                    return
                if self._stop.is_set():
                    return
                log.warning("return home not accepted (%s): asking again", result_name(result))
            with self._cond:
                self.counters["battery_return_failures"] += 1
            log.error("the vehicle did not accept the return home: its own failsafe must act")
        finally:
            with self._cond:
                self._return_pending = None


def _distance_m(a: GeoPoint, b: GeoPoint) -> float:
    """How far apart two origins are (m; flat-earth, as the frames are)."""
    north_m, east_m, down_m = global_to_ned(a, b)
    return math.hypot(north_m, east_m, down_m)


def _params_text(values: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:g}" for name, value in values.items())
