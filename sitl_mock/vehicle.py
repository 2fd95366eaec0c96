"""The simulated multicopter: modes, arming, takeoff/land/RTL, setpoints, failsafes, kinematics.

:class:`Vehicle` is a pure state machine. It has no clock and no I/O: time moves only when the
caller calls :meth:`Vehicle.step` with an explicit ``dt_s``, which makes every behaviour
reproducible in a unit test. The transport (:mod:`sitl_mock.server`) steps it at 50 Hz of
wall-clock time and turns MAVLink messages into the method calls below; the answers come back as
:class:`CommandOutcome` (a MAV_RESULT for COMMAND_ACK) and as STATUSTEXT events drained with
:meth:`Vehicle.drain_events`.

Frames and units: positions are local NED around home (x north, y east, z down), metres; velocities
m/s; angles radians unless the name says ``_deg``. ``alt`` always means height above home, positive
up (``-down_m``).

Kinematics (:mod:`sitl_mock.kinematics`): a point mass whose velocity follows a commanded velocity
under acceleration limits; the commanded velocity towards a point comes from a square-root
controller (ArduPilot's ``sqrt_controller``): proportional near the target, constant-deceleration
braking further away, capped by the speed limits. With the defaults (10 m/s, 2.5 m/s²) a 60 m leg
takes about 11 s, as on ArduPilot's SITL, and the vehicle settles within centimetres of the target.

Everything the flavour decides (mode numbers, refusal results and texts, defaults) comes from
:class:`sitl_mock.flavours.Flavour`.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass

from sitl_mock.battery import Battery
from sitl_mock.config import VehicleConfig
from sitl_mock.fence import ALT_MAX, GIVE_UP_DISTANCE_M, POLYGON, AutopilotFence, Breach
from sitl_mock.flavours import Behaviour, Flavour, MavResult, ModeSpec, Severity
from sitl_mock.geo import GeoPoint, global_to_ned, ned_to_global
from sitl_mock.kinematics import (
    GRAVITY_MPS2,
    ZERO,
    Fence,
    Limits,
    Vec3,
    accelerate,
    clamp_velocity,
    stopping_point,
    velocity_towards,
    wrap_pi,
)
from sitl_mock.setpoints import (
    FRAME_GLOBAL_INT,
    FRAME_GLOBAL_RELATIVE_ALT_INT,
    FRAME_LOCAL_NED,
    FRAME_LOCAL_OFFSET_NED,
    POSITION_ONLY_MASK,
    Target,
    decode_global,
    decode_local,
)

log = logging.getLogger(__name__)

FORCE_MAGIC = 21196
"""MAV_CMD_COMPONENT_ARM_DISARM param2 value that forces arming/disarming past the checks."""

# MAV_LANDED_STATE values.
LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 1, 2, 3, 4

TAKEOFF_DONE_MARGIN_M = 0.25
LIFTOFF_MIN_ALT_M = 0.5
TOUCHDOWN_ALT_M = 0.05
LAND_SLOWDOWN_ALT_M = 10.0
RTL_ARRIVED_M = 1.0
TAKEOFF_MIN_ALT_M = 1.0
TAKEOFF_POSITION_MAX_M = 1000.0
"""PX4: a take-off position (params 5/6) farther than this from the vehicle is accepted and not
flown (a real PX4 SITL took latitude/longitude 0/0, thousands of km away, that way: AUTO.TAKEOFF,
no climb, auto-disarm ~10 s later). PX4's exact threshold is not modelled."""

# EKF_STATUS_REPORT flag sets (EKF_STATUS_FLAGS): attitude 1, horizontal velocity 2, vertical
# velocity 4, relative/absolute horizontal position 8/16, absolute vertical position 32, constant
# position mode 128, predicted relative/absolute horizontal position 256/512, uninitialised 1024.
EKF_HEALTHY = 1 | 2 | 4 | 8 | 16 | 32 | 256 | 512
EKF_NO_GPS = 1 | 4 | 32 | 128
EKF_UNINITIALIZED = 1024


@dataclass(frozen=True)
class StatusText:
    """A STATUSTEXT the vehicle wants every ground station to see."""

    severity: Severity
    text: str


@dataclass(frozen=True)
class CommandOutcome:
    """The answer to a command: the COMMAND_ACK result (and why, for logs and tests)."""

    result: MavResult
    reason: str = ""

    @property
    def accepted(self) -> bool:
        return self.result is MavResult.ACCEPTED


@dataclass(frozen=True)
class VehicleState:
    """A consistent copy of what the vehicle is doing, for tests and logs."""

    time_s: float
    ready: bool
    armed: bool
    landed: bool
    landed_state: int
    mode: str
    custom_mode: int
    position_ned_m: Vec3
    velocity_ned_mps: Vec3
    alt_m: float
    global_position: GeoPoint
    yaw_rad: float
    battery_remaining_pct: float
    target_ned_m: Vec3 | None
    gcs_failsafe_active: bool


@dataclass
class _Takeoff:
    """A climb to ``alt_m`` above home at (north_m, east_m); starts when ``start_s`` is set."""

    north_m: float
    east_m: float
    alt_m: float
    start_s: float | None
    then_ne: tuple[float, float] | None = None
    """PX4: where to fly and hold once at altitude (a take-off position), if given."""


class Vehicle:
    """The simulated multicopter. See the module docstring; every method is non-blocking."""

    def __init__(self, flavour: Flavour, config: VehicleConfig | None = None) -> None:
        self.flavour = flavour
        self.config = config if config is not None else VehicleConfig()
        self.config.validate()
        cfg = self.config
        self.home: GeoPoint = cfg.home if cfg.home is not None else flavour.default_home
        self.ready_delay_s = (
            cfg.ready_delay_s if cfg.ready_delay_s is not None else flavour.ready_delay_s
        )
        # The earlier start-up milestones keep their share of a shortened start-up (a flavour's
        # default scaled like the position estimate), and never come after it.
        scale = self.ready_delay_s / flavour.ready_delay_s

        def milestone_s(configured: float | None, default: float) -> float:
            return min(default * scale if configured is None else configured, self.ready_delay_s)

        self.origin_delay_s = milestone_s(cfg.origin_delay_s, flavour.origin_delay_s)
        self.prearm_delay_s = milestone_s(cfg.prearm_delay_s, flavour.prearm_delay_s)
        self.mode_switch_read_s: float | None = None  # negative, or no default: never
        if cfg.mode_switch_read_s is not None or flavour.mode_switch_read_s is not None:
            switch_s = milestone_s(cfg.mode_switch_read_s, flavour.mode_switch_read_s or 0.0)
            self.mode_switch_read_s = switch_s if switch_s >= 0 else None
        self.rtl_alt_m = cfg.rtl_alt_m if cfg.rtl_alt_m is not None else flavour.rtl_alt_m
        self.land_speed_mps = cfg.land_speed_mps or flavour.land_speed_mps
        self.default_takeoff_alt_m = (
            cfg.takeoff_alt_m if cfg.takeoff_alt_m is not None else flavour.default_takeoff_alt_m
        )
        self.max_speed_h_mps = cfg.max_speed_h_mps
        # PX4's speeds that its horizontal limit caps (sitl_mock/params.py): cruise (missions,
        # returns) and the pilot's, PX4's defaults under the limit.
        self.px4_capped_speeds_mps = {
            "MPC_XY_CRUISE": min(5.0, cfg.max_speed_h_mps),
            "MPC_VEL_MANUAL": cfg.max_speed_h_mps,
        }
        # The pilot's backward and sideways speeds: PX4's -1, "MPC_VEL_MANUAL's".
        self.px4_manual_sides_mps = {"MPC_VEL_MAN_BACK": -1.0, "MPC_VEL_MAN_SIDE": -1.0}
        self.max_speed_up_mps = cfg.max_speed_up_mps
        self.max_speed_down_mps = cfg.max_speed_down_mps

        self.time_s = 0.0
        self.origin_set = False
        self.prearm_ok = False
        self._mode_switch_read = False
        self.ready = False
        self.armed = False
        self.landed = True
        self.mode: ModeSpec = flavour.mode(flavour.initial_mode)
        self.position = ZERO
        self.velocity = ZERO
        self.acceleration = ZERO
        self.yaw_rad = 0.0
        self.yaw_rate_rps = 0.0
        self.gcs_failsafe_active = False
        self.counters: Counter[str] = Counter()

        self._hold = ZERO
        self._target: Target | None = None
        self._pending_target: Target | None = None
        self._takeoff: _Takeoff | None = None
        self._rtl_phase = ""
        self._rtl_alt_m = 0.0
        self._armed_at_s = 0.0
        self._landed_at_s = 0.0
        self._stream_started_s: float | None = None
        self._last_setpoint_s: float | None = None
        self._last_gcs_heartbeat_s: float | None = None
        self._battery = Battery(cfg.battery_capacity_mah)
        self._fence = Fence(cfg.fence_radius_m, cfg.fence_alt_max_m)
        self.autopilot_fence = AutopilotFence(
            flavour.fence_style == "ardupilot", self.home, cfg.fence_alt_max_m
        )
        """The fence a ground station uploads and sets (zones, ceiling, action): breaches are
        acted on as the flavour's autopilot does (:meth:`_update_autopilot_fence`)."""
        self._fence_breaches = 0
        self._fence_recovery_until_s: float | None = None
        self._battery_failsafe_done = False
        self._at_fence = False
        self._events: list[StatusText] = []

    # ------------------------------------------------------------------ read-only views

    @property
    def alt_m(self) -> float:
        """Height above home, m (positive up)."""
        return -self.position.d

    @property
    def global_position(self) -> GeoPoint:
        return ned_to_global(self.home, *self.position)

    @property
    def battery_remaining_pct(self) -> float:
        return self._battery.remaining_pct

    @property
    def battery_voltage_v(self) -> float:
        return self._battery.voltage_v

    @property
    def battery_current_a(self) -> float:
        return self._battery.current_a

    @property
    def battery_consumed_mah(self) -> float:
        return self._battery.consumed_mah

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE: ON_GROUND, TAKEOFF, IN_AIR or LANDING."""
        if self._takeoff is not None and self._takeoff.start_s is not None:
            return LANDED_TAKEOFF
        if self.landed:
            return LANDED_ON_GROUND
        behaviour = self.mode.behaviour
        if behaviour is Behaviour.LAND or (
            behaviour is Behaviour.RTL and self._rtl_phase == "land"
        ):
            return LANDED_LANDING
        return LANDED_IN_AIR

    @property
    def failsafe_active(self) -> bool:
        return self.gcs_failsafe_active or self._battery_failsafe_done

    @property
    def ekf_flags(self) -> int:
        """EKF_STATUS_REPORT.flags as ArduPilot's EKF3 reports them: attitude, vertical velocity
        and position, in constant-position mode until it uses GPS; then every position and
        velocity flag (831, what a healthy ArduCopter SITL sends)."""
        if self.ready:
            return EKF_HEALTHY
        return EKF_NO_GPS if self.origin_set else EKF_NO_GPS | EKF_UNINITIALIZED

    def attitude_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw): the tilt that produces the current horizontal acceleration."""
        a_n, a_e, _ = self.acceleration
        cos_y, sin_y = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        a_forward = a_n * cos_y + a_e * sin_y
        a_right = -a_n * sin_y + a_e * cos_y
        pitch = -math.atan2(a_forward, GRAVITY_MPS2)
        roll = math.atan2(a_right, GRAVITY_MPS2)
        return roll, pitch, self.yaw_rad

    def echo_target(self) -> Target | None:
        """The setpoint the vehicle is following now (for POSITION_TARGET_LOCAL_NED), if any."""
        behaviour = self.mode.behaviour
        if behaviour is not Behaviour.GUIDED and not (
            self.flavour.target_echo_outside_guided and self.armed
        ):
            return None
        if behaviour is Behaviour.GUIDED and self._target is not None:
            return self._target
        if self._takeoff is not None:
            tk = self._takeoff
            return Target(
                Vec3(tk.north_m, tk.east_m, -tk.alt_m), None, None, POSITION_ONLY_MASK, 0.0
            )
        return Target(self._hold, None, None, POSITION_ONLY_MASK, 0.0)

    def snapshot(self) -> VehicleState:
        target = self.echo_target()
        return VehicleState(
            time_s=self.time_s,
            ready=self.ready,
            armed=self.armed,
            landed=self.landed,
            landed_state=self.landed_state,
            mode=self.mode.name,
            custom_mode=self.mode.custom_mode,
            position_ned_m=self.position,
            velocity_ned_mps=self.velocity,
            alt_m=self.alt_m,
            global_position=self.global_position,
            yaw_rad=self.yaw_rad,
            battery_remaining_pct=self.battery_remaining_pct,
            target_ned_m=target.position if target is not None else None,
            gcs_failsafe_active=self.gcs_failsafe_active,
        )

    def drain_events(self) -> list[StatusText]:
        """The STATUSTEXTs produced since the last call (oldest first)."""
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------ commands

    def arm(self, force: bool = False) -> CommandOutcome:
        """MAV_CMD_COMPONENT_ARM_DISARM with param1 = 1 (``force``: param2 = 21196)."""
        if self.armed:
            return CommandOutcome(MavResult.ACCEPTED, "already armed")
        if not force:
            refusal = self._arming_refusal()
            if refusal:
                self._emit(Severity.CRITICAL, refusal)
                return CommandOutcome(self.flavour.result_refused, refusal)
        self.armed = True
        self._armed_at_s = self.time_s
        self.counters["arms"] += 1
        self.counters[f"arms_in_{self.mode.name}"] += 1
        log.info("armed in %s", self.mode.name)
        if self._takeoff is not None and self._takeoff.start_s is None:
            self._takeoff.start_s = self.time_s
        return CommandOutcome(MavResult.ACCEPTED)

    def disarm(self, force: bool = False) -> CommandOutcome:
        """MAV_CMD_COMPONENT_ARM_DISARM with param1 = 0. In the air only when forced."""
        if not self.armed:
            return CommandOutcome(MavResult.ACCEPTED, "already disarmed")
        if not self.landed and not force:
            self._emit(Severity.CRITICAL, self.flavour.text_disarm_in_air)
            return CommandOutcome(self.flavour.result_refused, self.flavour.text_disarm_in_air)
        self._disarm("command" + (" (forced)" if force else ""))
        return CommandOutcome(MavResult.ACCEPTED)

    def set_mode(self, custom_mode: int) -> CommandOutcome:
        """Switch to the mode with HEARTBEAT.custom_mode ``custom_mode``."""
        spec = self.flavour.mode_by_custom(custom_mode)
        if spec is None:
            self._emit(Severity.WARNING, self.flavour.text_unknown_mode)
            return CommandOutcome(self.flavour.result_refused, f"unknown mode {custom_mode}")
        return self.set_mode_spec(spec)

    def set_mode_by_name(self, name: str) -> CommandOutcome:
        """Switch to the flavour's mode called ``name`` (e.g. "GUIDED", "OFFBOARD")."""
        return self.set_mode_spec(self.flavour.mode(name))

    def set_mode_spec(self, spec: ModeSpec) -> CommandOutcome:
        """A mode command (counted per mode asked for, as ``mode_commands_<NAME>``)."""
        self.counters[f"mode_commands_{spec.name}"] += 1
        if spec == self.mode:
            return CommandOutcome(MavResult.ACCEPTED, "already in mode")
        position_checked = self.armed or not self.flavour.mode_position_check_armed_only
        if spec.needs_position and not self.ready and position_checked:
            text = self.flavour.text_mode_needs_position.format(mode=spec.name)
            self._emit(Severity.WARNING, text)
            return CommandOutcome(self.flavour.result_refused, text)
        if (
            spec.behaviour is Behaviour.GUIDED
            and self.flavour.guided_needs_setpoint_stream
            and not self._setpoint_stream_ok()
        ):
            text = self.flavour.text_offboard_no_stream
            self._emit(Severity.WARNING, text)
            return CommandOutcome(self.flavour.result_refused, text)
        if spec.behaviour is Behaviour.TAKEOFF:
            if self.default_takeoff_alt_m is None:
                return CommandOutcome(self.flavour.result_refused, "no default takeoff altitude")
            return self._start_takeoff_mode(spec, self.default_takeoff_alt_m)
        self._enter_mode(spec, "command")
        return CommandOutcome(MavResult.ACCEPTED)

    def rc_mode_switch(self, name: str) -> None:
        """The pilot's RC flight-mode switch (or anything else outside MAVLink) sets mode
        ``name``: no checks, no answer, as on the real vehicle."""
        spec = self.flavour.mode(name)
        if spec != self.mode:
            self.counters["rc_mode_switches"] += 1
            self._enter_mode(spec, "RC mode switch")

    def takeoff(
        self, alt_param: float, lat_deg: float = math.nan, lon_deg: float = math.nan
    ) -> CommandOutcome:
        """MAV_CMD_NAV_TAKEOFF; ``alt_param`` is param7 as sent (its meaning is the flavour's),
        ``lat_deg``/``lon_deg`` params 5/6 (PX4: a take-off position when finite, which is not
        flown when farther than ``TAKEOFF_POSITION_MAX_M``; ArduPilot ignores them)."""
        flavour = self.flavour
        if not self.ready:
            return CommandOutcome(flavour.result_refused, "no position estimate")
        if math.isfinite(alt_param):
            alt_m = alt_param - self.home.alt_amsl_m if flavour.takeoff_alt_is_amsl else alt_param
        elif self.default_takeoff_alt_m is not None:
            alt_m = self.default_takeoff_alt_m
        else:
            return CommandOutcome(flavour.result_refused, "takeoff altitude missing")
        if alt_m < TAKEOFF_MIN_ALT_M or alt_m <= self.alt_m:
            return CommandOutcome(flavour.result_refused, f"takeoff altitude {alt_m:.1f} m too low")
        fence_alt = self.config.fence_alt_max_m
        if fence_alt and alt_m > fence_alt:
            return CommandOutcome(flavour.result_refused, "takeoff altitude outside the fence")
        if flavour.takeoff_mode is not None:
            spec = flavour.mode(flavour.takeoff_mode)
            then_ne: tuple[float, float] | None = None
            if flavour.takeoff_position_from_params and (
                math.isfinite(lat_deg) and math.isfinite(lon_deg)
            ):
                north_m, east_m, _ = global_to_ned(self.home, lat_deg, lon_deg, 0.0)
                if math.hypot(north_m - self.position.n, east_m - self.position.e) > (
                    TAKEOFF_POSITION_MAX_M
                ):
                    # Accepted, and the vehicle stays where it is (and auto-disarms).
                    self._enter_mode(spec, "takeoff")
                    self.counters["takeoffs_not_flown"] += 1
                    log.info("take-off position %.5f, %.5f too far: not flown", lat_deg, lon_deg)
                    return CommandOutcome(MavResult.ACCEPTED, "take-off position too far")
                then_ne = (north_m, east_m)
            return self._start_takeoff_mode(spec, alt_m, then_ne)
        # ArduPilot: a "user takeoff" in the current mode, armed and on the ground only.
        if not self.armed:
            return CommandOutcome(flavour.result_refused, "not armed")
        if not self.landed:
            return CommandOutcome(flavour.result_refused, "already flying")
        if not self.mode.allows_user_takeoff:
            return CommandOutcome(flavour.result_refused, f"no takeoff in {self.mode.name}")
        self._target = None
        self._takeoff = _Takeoff(self.position.n, self.position.e, alt_m, self.time_s)
        self.counters["takeoffs"] += 1
        log.info("takeoff to %.1f m in %s", alt_m, self.mode.name)
        return CommandOutcome(MavResult.ACCEPTED)

    def land(self) -> CommandOutcome:
        """MAV_CMD_NAV_LAND: switch to the flavour's land mode."""
        return self.set_mode_by_name(self.flavour.land_mode)

    def return_to_launch(self) -> CommandOutcome:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH: switch to the flavour's RTL mode."""
        return self.set_mode_by_name(self.flavour.rtl_mode)

    def change_speed(self, speed_type: float, speed_mps: float) -> CommandOutcome:
        """MAV_CMD_DO_CHANGE_SPEED: 0/1 horizontal, 2 climb, 3 descent; -1 leaves it unchanged."""
        if not math.isfinite(speed_mps) or speed_mps == -1:
            return CommandOutcome(MavResult.ACCEPTED, "unchanged")
        if speed_mps <= 0:
            return CommandOutcome(MavResult.DENIED, "speed must be positive")
        if speed_type in (0, 1):
            self.max_speed_h_mps = speed_mps
        elif speed_type == 2:
            self.max_speed_up_mps = speed_mps
        elif speed_type == 3:
            self.max_speed_down_mps = speed_mps
        else:
            return CommandOutcome(MavResult.DENIED, f"speed type {speed_type}")
        return CommandOutcome(MavResult.ACCEPTED)

    def set_battery_remaining(self, remaining_pct: float) -> None:
        """The simulator's battery knob (as ``SIM_BATT_VOLTAGE`` on ArduPilot SITL): the pack
        holds ``remaining_pct`` of its capacity from now on, and drains from there; the battery
        failsafe acts at its next check if that is at or below its threshold."""
        if not 0.0 <= remaining_pct <= 100.0:
            raise ValueError(f"remaining_pct: must be in [0, 100], got {remaining_pct!r}")
        battery = self._battery
        battery.consumed_mah = battery.capacity_mah * (1.0 - remaining_pct / 100.0)

    def note_gcs_heartbeat(self) -> None:
        """A ground station (or companion computer) HEARTBEAT arrived."""
        self._last_gcs_heartbeat_s = self.time_s
        if self.gcs_failsafe_active:
            self.gcs_failsafe_active = False
            self._emit(Severity.INFO, self.flavour.text_gcs_back)
            log.info("ground station back")

    # ------------------------------------------------------------------ setpoints

    def set_position_target_local(
        self,
        frame: int,
        type_mask: int,
        x: float,
        y: float,
        z: float,
        vx: float,
        vy: float,
        vz: float,
        yaw_rad: float,
    ) -> str:
        """SET_POSITION_TARGET_LOCAL_NED. Returns what became of it (also counted in ``counters``):
        accepted, buffered, cancelled_takeoff, ignored_mode, ignored_landed, rejected_invalid,
        rejected_frame, rejected_fence, unsupported."""
        self.counters["setpoints_received"] += 1
        decoded = decode_local(
            frame,
            type_mask,
            (x, y, z),
            (vx, vy, vz),
            yaw_rad,
            self.position,
            self.yaw_rad,
            self.time_s,
        )
        if isinstance(decoded, str):
            return self._count(decoded)
        return self._accept_target(decoded)

    def set_position_target_global(
        self,
        frame: int,
        type_mask: int,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vx: float,
        vy: float,
        vz: float,
        yaw_rad: float,
    ) -> str:
        """SET_POSITION_TARGET_GLOBAL_INT (lat/lon in degrees). Same results as the local one."""
        self.counters["setpoints_received"] += 1
        decoded = decode_global(
            frame,
            type_mask,
            (lat_deg, lon_deg, alt_m),
            (vx, vy, vz),
            yaw_rad,
            self.home,
            self.time_s,
        )
        if isinstance(decoded, str):
            return self._count(decoded)
        return self._accept_target(decoded)

    # ------------------------------------------------------------------ time

    def step(self, dt_s: float) -> None:
        """Advance the simulation by ``dt_s`` seconds (call with small steps, e.g. 0.02 s)."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            return
        self.time_s += dt_s
        self._update_readiness()
        self._update_failsafes()
        self._fly(dt_s)
        self._update_autopilot_fence()
        self._update_battery(dt_s)
        self._update_ground_disarm()

    # ------------------------------------------------------------------ internals: rules

    def say(self, severity: Severity, text: str) -> None:
        """Queue a STATUSTEXT for every ground station (the protocol's own refusals use it)."""
        self._emit(severity, text)

    def _emit(self, severity: Severity, text: str) -> None:
        if text:
            self._events.append(StatusText(severity, text))

    def _count(self, outcome: str) -> str:
        self.counters[f"setpoints_{outcome}"] += 1
        return outcome

    def _arming_refusal(self) -> str:
        """Why arming is refused now, or "" if it is allowed."""
        if not self.prearm_ok:
            return self.flavour.text_prearm_failing
        if not self.ready and (self.mode.needs_position or self.flavour.arming_needs_position):
            return self.flavour.text_arm_not_ready
        if not self.mode.allows_arming:
            return self.flavour.text_arm_mode
        if (
            self.mode.behaviour is Behaviour.GUIDED
            and self.flavour.guided_needs_setpoint_stream
            and not self._setpoint_stream_ok()
        ):
            return self.flavour.text_offboard_no_stream
        failsafe_pct = self.config.battery_failsafe_pct
        if failsafe_pct and self.battery_remaining_pct <= failsafe_pct:
            return "Arming denied: battery below failsafe level"
        fence = self.autopilot_fence
        if fence.ardupilot and fence.enabled:
            breach = fence.breach(self.position)
            if breach.fences:
                return f"PreArm: Vehicle breaching {breach.names}"
        return ""

    def _setpoint_stream_ok(self) -> bool:
        """PX4's offboard signal: setpoints at > 2 Hz, for at least ``offboard_stream_min_s``."""
        if self._last_setpoint_s is None or self._stream_started_s is None:
            return False
        if self.time_s - self._last_setpoint_s > self.config.offboard_stream_max_gap_s:
            return False
        return self.time_s - self._stream_started_s >= self.config.offboard_stream_min_s

    def _note_setpoint(self) -> None:
        last = self._last_setpoint_s
        if last is None or self.time_s - last > self.config.offboard_stream_max_gap_s:
            self._stream_started_s = self.time_s
        self._last_setpoint_s = self.time_s

    def _limits(self) -> Limits:
        cfg = self.config
        return Limits(
            self.max_speed_h_mps,
            self.max_speed_up_mps,
            self.max_speed_down_mps,
            cfg.accel_h_mps2,
            cfg.accel_v_mps2,
        )

    def _fence_check(self, position: Vec3) -> Vec3 | None:
        """``position`` if inside the fence, its clamped version (fence_action clamp) or None."""
        clamped = self._fence.clamp(position)
        if clamped == position:
            return position
        if self.config.fence_action == "clamp":
            self.counters["setpoints_clamped_fence"] += 1
            return clamped
        return None

    def _accept_target(self, target: Target) -> str:
        if target.position is not None:
            checked = self._fence_check(target.position)
            if checked is None:
                log.debug("setpoint outside the fence ignored: %s", target.position)
                return self._count("rejected_fence")
            if checked != target.position:
                target = Target(
                    checked, target.velocity, target.yaw_rad, target.type_mask, target.received_s
                )
            if not self.autopilot_fence.destination_ok(target.position):
                log.debug("setpoint outside the uploaded fence refused: %s", target.position)
                return self._count("rejected_fence")
        flavour = self.flavour
        if self.mode.behaviour is not Behaviour.GUIDED:
            if flavour.setpoints_buffered_outside_guided:
                self._note_setpoint()
                self._pending_target = target
                return self._count("buffered")
            return self._count("ignored_mode")
        self._note_setpoint()
        if self.landed and not flavour.guided_lifts_off_from_setpoint:
            if self._takeoff is not None and flavour.setpoint_cancels_ground_takeoff:
                self._takeoff = None
                self.counters["takeoffs_cancelled"] += 1
                log.info("position target while the takeoff is on the ground: takeoff cancelled")
                return self._count("cancelled_takeoff")
            return self._count("ignored_landed")
        self._target = target
        self._pending_target = target
        self._takeoff = None
        return self._count("accepted")

    def _enter_mode(self, spec: ModeSpec, reason: str) -> None:
        old = self.mode
        self.mode = spec
        self._hold = self._stopping_point()
        self._takeoff = None
        self._target = None
        pending = self._pending_target
        if (
            spec.behaviour is Behaviour.GUIDED
            and self.flavour.setpoints_buffered_outside_guided
            and pending is not None
            and self.time_s - pending.received_s <= self.config.offboard_timeout_s
        ):
            self._target = pending  # PX4 enters OFFBOARD with the setpoint being streamed
        if spec.behaviour is Behaviour.RTL:
            self._rtl_phase = "climb"
            self._rtl_alt_m = max(self.alt_m, self.rtl_alt_m)
        log.info("mode %s -> %s (%s)", old.name, spec.name, reason)
        recovery_s = self.flavour.fence_recovery_s
        fence = self.autopilot_fence
        if recovery_s is not None and self._fence_breaches and fence.enabled and fence.action:
            # ArduCopter: any mode change while breached, its own fence action's included.
            self._fence_recovery_until_s = self.time_s + recovery_s
            self._emit(Severity.INFO, self.flavour.text_fence_recovery)

    def _stopping_point(self) -> Vec3:
        """Where the vehicle comes to rest if it brakes now (what a new hold mode holds)."""
        return stopping_point(self.position, self.velocity, self._limits())

    def _start_takeoff_mode(
        self, spec: ModeSpec, alt_m: float, then_ne: tuple[float, float] | None = None
    ) -> CommandOutcome:
        """PX4: enter AUTO.TAKEOFF; the climb starts now if armed, else when armed, straight up;
        with a take-off position the vehicle then flies there and holds."""
        self._enter_mode(spec, "takeoff")
        start = self.time_s if self.armed else None
        self._takeoff = _Takeoff(self.position.n, self.position.e, alt_m, start, then_ne)
        self.counters["takeoffs"] += 1
        log.info("takeoff to %.1f m", alt_m)
        return CommandOutcome(MavResult.ACCEPTED)

    def _finish_takeoff(self) -> None:
        assert self._takeoff is not None
        tk = self._takeoff
        self._takeoff = None
        north_m, east_m = tk.then_ne if tk.then_ne is not None else (tk.north_m, tk.east_m)
        self._hold = Vec3(north_m, east_m, -tk.alt_m)
        log.info("takeoff complete at %.1f m", self.alt_m)
        if self.mode.behaviour is Behaviour.TAKEOFF:
            self._enter_mode(self.flavour.mode(self.flavour.hold_mode), "takeoff complete")
            self._hold = Vec3(north_m, east_m, -tk.alt_m)

    def _disarm(self, reason: str) -> None:
        self.armed = False
        self._takeoff = None
        self.counters["disarms"] += 1
        log.info("disarmed: %s", reason)

    def _update_readiness(self) -> None:
        now = self.time_s
        if not self.origin_set and now >= self.origin_delay_s:
            self.origin_set = True
            self._emit(Severity.INFO, self.flavour.text_origin_set)
        if not self.prearm_ok and now >= self.prearm_delay_s:
            self.prearm_ok = True
        switch_s = self.mode_switch_read_s
        if not self._mode_switch_read and switch_s is not None and now >= switch_s:
            self._mode_switch_read = True
            self.rc_mode_switch(self.flavour.initial_mode)
        if not self.ready and self.time_s >= self.ready_delay_s:
            self.ready = True
            for text in self.flavour.text_ready:
                self._emit(Severity.INFO, text)
            log.info("position estimate ready (home %s)", self.home)

    def _update_failsafes(self) -> None:
        flavour, cfg, now = self.flavour, self.config, self.time_s
        if (
            self.mode.behaviour is Behaviour.GUIDED
            and flavour.guided_setpoint_timeout_failsafe
            and (
                self._last_setpoint_s is None
                or now - self._last_setpoint_s > cfg.offboard_timeout_s
            )
        ):
            self.counters["failsafe_offboard"] += 1
            self._emit(Severity.CRITICAL, flavour.text_offboard_lost)
            self._enter_mode(flavour.mode(flavour.hold_mode), "offboard setpoints lost")
        last_gcs = self._last_gcs_heartbeat_s
        if (
            cfg.gcs_failsafe_action != "none"
            and self.armed
            and not self.gcs_failsafe_active
            and last_gcs is not None
            and now - last_gcs > cfg.gcs_failsafe_s
        ):
            self.gcs_failsafe_active = True
            self.counters["failsafe_gcs"] += 1
            if self.landed:
                action = "disarm"
                self._disarm("ground station lost")
            elif cfg.gcs_failsafe_action == "rtl":
                action = "RTL"
                self._failsafe_mode(flavour.rtl_mode)
            else:
                action = "LAND"
                self._failsafe_mode(flavour.land_mode)
            self._emit(Severity.CRITICAL, flavour.text_gcs_lost.format(action=action))
        failsafe_pct = cfg.battery_failsafe_pct
        if (
            failsafe_pct
            and not self._battery_failsafe_done
            and self.armed
            and not self.landed
            and self.battery_remaining_pct <= failsafe_pct
        ):
            self._battery_failsafe_done = True
            self.counters["failsafe_battery"] += 1
            self._emit(Severity.CRITICAL, flavour.text_battery_failsafe)
            self._failsafe_mode(flavour.land_mode)

    def _failsafe_mode(self, name: str, reason: str = "failsafe") -> None:
        spec = self.flavour.mode(name)
        if self.mode != spec:
            self._enter_mode(spec, reason)

    def _update_autopilot_fence(self) -> None:
        """Act on a new breach of the uploaded fence (zones, ceiling) by the vehicle itself, as
        the flavour's autopilot does: ArduCopter says "Polygon fence breached" (NOTICE) and
        switches by FENCE_ACTION (RTL, LAND, BRAKE; LAND when more than 100 m outside; disarms
        when armed on the ground), and "Fence breach cleared" once back inside; PX4 acts by
        GF_ACTION (hold, return, land, terminate) in the air. Armed only."""
        fence = self.autopilot_fence
        if not (fence.enabled and self.armed):
            self._fence_breaches = 0
            return
        breach = fence.breach(self.position)
        new = breach.fences & ~self._fence_breaches
        if self._fence_breaches and not breach.fences and not self.landed:
            self._emit(Severity.NOTICE, self.flavour.text_fence_cleared)
        self._fence_breaches = breach.fences
        recovery_until = self._fence_recovery_until_s
        if recovery_until is not None and self.time_s < recovery_until:
            new = 0  # a manual recovery: new breaches are ignored for a while
        if new:
            self.counters["fence_breaches"] += 1
            log.info("fence breached (%s, %.1f m outside)", breach.names, breach.distance_m)
            self._fence_action(Breach(new, breach.distance_m))

    def _fence_action(self, breach: Breach) -> None:
        flavour, action = self.flavour, self.autopilot_fence.action
        if self.autopilot_fence.ardupilot:
            if self.landed:
                self._disarm("fence breach on the ground")
                return
            names = breach.names
            if action == 0:
                self._emit(Severity.NOTICE, flavour.text_fence_warning.format(fences=names))
                return
            self._emit(Severity.NOTICE, flavour.text_fence_breach.format(fences=names, action=""))
            if breach.distance_m > GIVE_UP_DISTANCE_M or action in (2, 5):
                mode = flavour.land_mode  # SmartRTL (5) is not modelled: its fallback, LAND
            elif action == 4:
                mode = "BRAKE"
            else:
                mode = flavour.rtl_mode  # 1, and 3 (SmartRTL, not modelled: its fallback, RTL)
            self.counters["failsafe_fence"] += 1
            self._failsafe_mode(mode, "fence breach")
            return
        if self.landed or action == 0:
            return
        if action == 1:
            self._emit(Severity.WARNING, flavour.text_fence_warning)
            return
        name, mode = {
            2: ("Hold", flavour.hold_mode),
            3: ("Return", flavour.rtl_mode),
            4: ("Terminate", None),
            5: ("Land", flavour.land_mode),
        }[action]
        self._emit(Severity.CRITICAL, flavour.text_fence_breach.format(fences="", action=name))
        self.counters["failsafe_fence"] += 1
        if mode is None:
            self._disarm("flight termination (geofence)")
        else:
            self._failsafe_mode(mode, "geofence breach")

    def _update_ground_disarm(self) -> None:
        if not (self.armed and self.landed):
            return
        if self._takeoff is not None:
            return
        behaviour = self.mode.behaviour
        landing = behaviour is Behaviour.LAND or behaviour is Behaviour.RTL
        since_s = self.time_s - max(self._armed_at_s, self._landed_at_s)
        if landing and self.time_s - self._landed_at_s >= self.flavour.land_disarm_delay_s:
            self._disarm("landed")
        elif since_s >= self.config.auto_disarm_s:
            self.counters["auto_disarms"] += 1
            self._emit(Severity.INFO, self.flavour.text_auto_disarm)
            self._disarm(f"on the ground for {since_s:.1f} s without taking off")

    def _update_battery(self, dt_s: float) -> None:
        speed_mps = math.sqrt(sum(c * c for c in self.velocity))
        self._battery.drain(dt_s, self.armed, not self.landed, speed_mps)

    # ------------------------------------------------------------------ internals: kinematics

    def _wants_liftoff(self) -> bool:
        tk = self._takeoff
        if tk is not None and tk.start_s is not None:
            return self.time_s - tk.start_s >= self.flavour.takeoff_spool_s
        target = self._target
        if (
            self.mode.behaviour is Behaviour.GUIDED
            and self.flavour.guided_lifts_off_from_setpoint
            and target is not None
        ):
            if target.position is not None:
                return -target.position.d > LIFTOFF_MIN_ALT_M
            if target.velocity is not None:
                return target.velocity.d < -0.1
        return False

    def _velocity_to(self, target: Vec3) -> Vec3:
        return velocity_towards(self.position, target, self._limits())

    def _landing_velocity(self, over: Vec3) -> Vec3:
        vn, ve, _ = self._velocity_to(Vec3(over.n, over.e, self.position.d))
        fast = self.alt_m > LAND_SLOWDOWN_ALT_M
        return Vec3(vn, ve, self.max_speed_down_mps if fast else self.land_speed_mps)

    def _desired_velocity(self) -> Vec3:
        tk = self._takeoff
        if tk is not None and tk.start_s is not None:
            if self.alt_m >= tk.alt_m - TAKEOFF_DONE_MARGIN_M:
                self._finish_takeoff()
            else:
                return self._velocity_to(Vec3(tk.north_m, tk.east_m, -tk.alt_m))
        behaviour = self.mode.behaviour
        if behaviour is Behaviour.GUIDED and self._target is not None:
            target = self._target
            if target.position is not None:
                return self._velocity_to(target.position)
            assert target.velocity is not None
            timeout_s = self.flavour.velocity_setpoint_timeout_s
            if timeout_s is not None and self.time_s - target.received_s > timeout_s:
                return ZERO  # ArduPilot: a stale velocity target becomes "stop"
            return clamp_velocity(target.velocity, self._limits())
        if behaviour is Behaviour.LAND:
            return self._landing_velocity(self._hold)
        if behaviour is Behaviour.RTL:
            return self._rtl_velocity()
        return self._velocity_to(self._hold)

    def _rtl_velocity(self) -> Vec3:
        if self._rtl_phase == "climb":
            if self.alt_m < self._rtl_alt_m - TAKEOFF_DONE_MARGIN_M:
                return self._velocity_to(Vec3(self._hold.n, self._hold.e, -self._rtl_alt_m))
            self._rtl_phase = "return"
        if self._rtl_phase == "return":
            home_at_alt = Vec3(0.0, 0.0, -self._rtl_alt_m)
            speed_h = math.hypot(self.velocity.n, self.velocity.e)
            if math.hypot(*self.position[:2]) > RTL_ARRIVED_M or speed_h > 0.5:
                return self._velocity_to(home_at_alt)
            self._rtl_phase = "land"
        return self._landing_velocity(ZERO)

    def _fly(self, dt_s: float) -> None:
        if not self.armed:
            if self.landed:
                self.velocity = self.acceleration = ZERO
                return
            # Motors off in the air: it falls.
            v = self.velocity
            self._integrate(Vec3(v.n, v.e, v.d + GRAVITY_MPS2 * dt_s), dt_s)
            if self.position.d >= 0.0:
                self._touch_down()
            return
        if self.landed:
            if not self._wants_liftoff():
                self.velocity = self.acceleration = ZERO
                return
            self.landed = False
            self.counters["liftoffs"] += 1
            log.info("lift-off in %s", self.mode.name)
        desired = self._desired_velocity()
        target = self._target
        avoid = (
            self.autopilot_fence.avoidance
            and self.mode.behaviour is Behaviour.GUIDED
            and target is not None
            and target.position is None
        )
        self._integrate(accelerate(self.velocity, desired, self._limits(), dt_s), dt_s, avoid)
        self._update_yaw(dt_s)
        if self.position.d >= -TOUCHDOWN_ALT_M and desired.d >= 0.0 and self.velocity.d >= -0.05:
            self._touch_down()

    def _integrate(self, new_velocity: Vec3, dt_s: float, avoid: bool = False) -> None:
        """Move by ``dt_s`` towards ``new_velocity``, held at the cylinder fence; with ``avoid``
        (ArduPilot's AC_Avoid under GUIDED velocity control) also stopped FENCE_MARGIN short of
        the uploaded fence (its zones and ceiling) rather than crossing it."""
        v = self.velocity
        p = self.position
        position = Vec3(
            p.n + 0.5 * (v.n + new_velocity.n) * dt_s,
            p.e + 0.5 * (v.e + new_velocity.e) * dt_s,
            min(0.0, p.d + 0.5 * (v.d + new_velocity.d) * dt_s),
        )
        if avoid:
            crossing = self.autopilot_fence.near(position) & ~self.autopilot_fence.near(p)
            if crossing:
                stop_h, stop_v = crossing & POLYGON, crossing & ALT_MAX
                position = Vec3(
                    p.n if stop_h else position.n,
                    p.e if stop_h else position.e,
                    p.d if stop_v else position.d,
                )
                new_velocity = Vec3(
                    0.0 if stop_h else new_velocity.n,
                    0.0 if stop_h else new_velocity.e,
                    max(0.0, new_velocity.d) if stop_v else new_velocity.d,
                )
                self.counters["fence_avoid_stops"] += 1
        held = self._fence.clamp(position)
        at_fence = held != position
        if at_fence:
            # Held at the fence: no velocity through it.
            stopped_h = held.n != position.n or held.e != position.e
            new_velocity = Vec3(
                0.0 if stopped_h else new_velocity.n,
                0.0 if stopped_h else new_velocity.e,
                max(0.0, new_velocity.d) if held.d != position.d else new_velocity.d,
            )
            if not self._at_fence:
                self.counters["fence_holds"] += 1
                log.info("held at the fence at (%.1f, %.1f, %.1f)", *held)
        self._at_fence = at_fence
        self.acceleration = Vec3(
            *((nv - ov) / dt_s for nv, ov in zip(new_velocity, v, strict=True))
        )
        self.velocity = new_velocity
        self.position = held

    def _touch_down(self) -> None:
        self.position = Vec3(self.position.n, self.position.e, 0.0)
        self.velocity = self.acceleration = ZERO
        self.landed = True
        self._landed_at_s = self.time_s
        self._target = None
        self._hold = self.position
        self.counters["touchdowns"] += 1
        log.info(
            "touch-down at (%.1f, %.1f) in %s", self.position.n, self.position.e, self.mode.name
        )

    def _update_yaw(self, dt_s: float) -> None:
        wanted: float | None = None
        target = self._target if self.mode.behaviour is Behaviour.GUIDED else None
        if target is not None and target.yaw_rad is not None:
            wanted = target.yaw_rad
        elif self.flavour.yaw_follows_course and math.hypot(self.velocity.n, self.velocity.e) > 1.0:
            wanted = math.atan2(self.velocity.e, self.velocity.n)
        if wanted is None:
            self.yaw_rate_rps = 0.0
            return
        error = wrap_pi(wanted - self.yaw_rad)
        max_step = math.radians(self.config.yaw_rate_max_dps) * dt_s
        step = max(-max_step, min(max_step, error))
        self.yaw_rad = wrap_pi(self.yaw_rad + step)
        self.yaw_rate_rps = step / dt_s


__all__ = [
    "FORCE_MAGIC",
    "FRAME_GLOBAL_INT",
    "FRAME_GLOBAL_RELATIVE_ALT_INT",
    "FRAME_LOCAL_NED",
    "FRAME_LOCAL_OFFSET_NED",
    "POSITION_ONLY_MASK",
    "CommandOutcome",
    "StatusText",
    "Target",
    "Vec3",
    "Vehicle",
    "VehicleConfig",
    "VehicleState",
]
