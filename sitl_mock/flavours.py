"""What makes the mock an ArduPilot Copter or a PX4 multicopter: mode numbers and flavour rules.

A :class:`Flavour` is plain data: the flight-mode table (custom mode numbers as each autopilot puts
them in HEARTBEAT.custom_mode), the COMMAND_ACK results and STATUSTEXT wording each autopilot uses
when it refuses something, its defaults (start-up time, return altitude, landing speed) and its
protocol habits (ArduPilot streams nothing until asked; PX4 streams by default). The state machine
in :mod:`sitl_mock.vehicle` reads these rules; it has no ``if flavour == ...`` of its own.

Mode numbers:

* ArduPilot Copter: ``custom_mode`` is the mode number (STABILIZE 0, ALT_HOLD 2, GUIDED 4, LOITER 5,
  RTL 6, LAND 9, POSHOLD 16, BRAKE 17).
* PX4: ``custom_mode = main_mode << 16 | sub_mode << 24`` (MANUAL 1, ALTCTL 2, POSCTL 3, AUTO 4
  with sub modes TAKEOFF 2, LOITER 3, RTL 5, LAND 6; OFFBOARD 6, STABILIZED 7).
  MAV_CMD_DO_SET_MODE carries main and sub mode separately, in param2 and param3.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from sitl_mock.geo import GeoPoint


class MavResult(enum.IntEnum):
    """MAV_RESULT values of COMMAND_ACK (same numbers as MAVLink's enum)."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


class Severity(enum.IntEnum):
    """MAV_SEVERITY values of STATUSTEXT."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class Behaviour(enum.Enum):
    """What the vehicle does in a flight mode (the mock has no RC: manual modes hold position)."""

    HOLD = "hold"
    """Hold the position where the mode was entered (LOITER, POSCTL, AUTO.LOITER, manual modes)."""
    GUIDED = "guided"
    """Follow external setpoints (ArduPilot GUIDED, PX4 OFFBOARD)."""
    TAKEOFF = "takeoff"
    """PX4 AUTO.TAKEOFF: climb to the takeoff altitude, then switch to the hold mode."""
    LAND = "land"
    """Descend where the mode was entered, touch down, disarm."""
    RTL = "rtl"
    """Climb to the return altitude, fly home, land, disarm."""


# MAV_MODE_FLAG bits for HEARTBEAT.base_mode.
MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MODE_FLAG_AUTO_ENABLED = 4
MODE_FLAG_GUIDED_ENABLED = 8
MODE_FLAG_STABILIZE_ENABLED = 16
MODE_FLAG_MANUAL_INPUT_ENABLED = 64
MODE_FLAG_SAFETY_ARMED = 128


@dataclass(frozen=True)
class ModeSpec:
    """One flight mode of a flavour."""

    name: str
    custom_mode: int
    behaviour: Behaviour
    needs_position: bool
    """Refused until the vehicle has a position estimate (GUIDED, LOITER, OFFBOARD, ...)."""
    allows_arming: bool
    """The vehicle may be armed in this mode (not in RTL or LAND, for instance)."""
    allows_user_takeoff: bool
    """ArduPilot's MAV_CMD_NAV_TAKEOFF is accepted in this mode (GUIDED, LOITER, ALT_HOLD...)."""
    base_mode_flags: int
    """MAV_MODE_FLAG bits this mode shows in HEARTBEAT.base_mode (besides CUSTOM and ARMED)."""


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4's HEARTBEAT.custom_mode for a main mode and (AUTO only) a sub mode."""
    return (main_mode & 0xFF) << 16 | (sub_mode & 0xFF) << 24


PX4_MAIN_AUTO = 4

_GUIDED_FLAGS = MODE_FLAG_STABILIZE_ENABLED | MODE_FLAG_GUIDED_ENABLED
_AP_ALWAYS = MODE_FLAG_STABILIZE_ENABLED | MODE_FLAG_MANUAL_INPUT_ENABLED
_PX4_AUTO = MODE_FLAG_AUTO_ENABLED | MODE_FLAG_STABILIZE_ENABLED | MODE_FLAG_GUIDED_ENABLED


def _ap(name: str, number: int, behaviour: Behaviour, pos: bool, arm: bool, takeoff: bool):
    flags = _AP_ALWAYS | (MODE_FLAG_GUIDED_ENABLED if pos else 0)
    return ModeSpec(name, number, behaviour, pos, arm, takeoff, flags)


ARDUPILOT_MODES: tuple[ModeSpec, ...] = (
    _ap("STABILIZE", 0, Behaviour.HOLD, pos=False, arm=True, takeoff=False),
    # MAV_CMD_NAV_TAKEOFF with param3 = 0 ("must navigate"): the navigating modes only.
    _ap("ALT_HOLD", 2, Behaviour.HOLD, pos=False, arm=True, takeoff=False),
    _ap("GUIDED", 4, Behaviour.GUIDED, pos=True, arm=True, takeoff=True),
    _ap("LOITER", 5, Behaviour.HOLD, pos=True, arm=True, takeoff=True),
    _ap("RTL", 6, Behaviour.RTL, pos=True, arm=False, takeoff=False),
    _ap("LAND", 9, Behaviour.LAND, pos=False, arm=False, takeoff=False),
    _ap("POSHOLD", 16, Behaviour.HOLD, pos=True, arm=True, takeoff=True),
    _ap("BRAKE", 17, Behaviour.HOLD, pos=True, arm=False, takeoff=False),
)

PX4_MODES: tuple[ModeSpec, ...] = (
    ModeSpec("MANUAL", px4_custom_mode(1), Behaviour.HOLD, False, True, False, 64),
    ModeSpec("ALTCTL", px4_custom_mode(2), Behaviour.HOLD, False, True, False, 64 | 16),
    ModeSpec("POSCTL", px4_custom_mode(3), Behaviour.HOLD, True, True, False, 64 | 16 | 8),
    ModeSpec(
        "AUTO.TAKEOFF", px4_custom_mode(4, 2), Behaviour.TAKEOFF, True, True, False, _PX4_AUTO
    ),
    ModeSpec("AUTO.LOITER", px4_custom_mode(4, 3), Behaviour.HOLD, True, True, False, _PX4_AUTO),
    ModeSpec("AUTO.RTL", px4_custom_mode(4, 5), Behaviour.RTL, True, False, False, _PX4_AUTO),
    ModeSpec("AUTO.LAND", px4_custom_mode(4, 6), Behaviour.LAND, False, False, False, _PX4_AUTO),
    ModeSpec("OFFBOARD", px4_custom_mode(6), Behaviour.GUIDED, True, True, False, _PX4_AUTO),
    ModeSpec("STABILIZED", px4_custom_mode(7), Behaviour.HOLD, False, True, False, 64 | 16),
)


@dataclass(frozen=True)
class Flavour:
    """The rules of one autopilot family. See the module docstring."""

    name: str
    autopilot_type: int
    """HEARTBEAT.autopilot: MAV_AUTOPILOT_ARDUPILOTMEGA (3) or MAV_AUTOPILOT_PX4 (12)."""
    modes: tuple[ModeSpec, ...]
    initial_mode: str
    guided_mode: str
    hold_mode: str
    land_mode: str
    rtl_mode: str
    takeoff_mode: str | None
    """PX4 switches to AUTO.TAKEOFF on MAV_CMD_NAV_TAKEOFF; ArduPilot takes off in the current
    mode."""

    # Protocol habits.
    streams_on_request_only: bool
    """ArduPilot sends no telemetry on a new link until SET_MESSAGE_INTERVAL/REQUEST_DATA_STREAM."""
    default_rates_hz: dict[str, float]
    """Rates of the telemetry streams (message name -> Hz): sent by default on PX4, and the rate a
    SET_MESSAGE_INTERVAL with interval 0 ("default rate") selects on both."""
    honours_request_data_stream: bool
    """ArduPilot still serves the old REQUEST_DATA_STREAM groups; PX4 ignores them."""
    params_bytewise: bool
    """PX4 sends integer parameters bit-for-bit in PARAM_VALUE's float; ArduPilot casts them."""

    # Setpoint rules.
    setpoints_buffered_outside_guided: bool
    """PX4 keeps setpoints received outside OFFBOARD (they make the offboard signal and the first
    offboard target); ArduPilot drops setpoints outside GUIDED."""
    guided_needs_setpoint_stream: bool
    """PX4: OFFBOARD is refused unless setpoints already stream at more than 2 Hz."""
    setpoint_cancels_ground_takeoff: bool
    """ArduPilot: a position target while the takeoff is still on the ground cancels the takeoff."""
    guided_lifts_off_from_setpoint: bool
    """PX4: an armed vehicle on the ground in OFFBOARD takes off towards a setpoint above it."""
    guided_setpoint_timeout_failsafe: bool
    """PX4: OFFBOARD without setpoints for longer than the timeout switches to the hold mode."""
    velocity_setpoint_timeout_s: float | None
    """ArduPilot GUIDED stops after 3 s without a new velocity target."""
    yaw_follows_course: bool
    """Without a yaw in the setpoint, ArduPilot turns to face its direction of travel."""
    target_echo_outside_guided: bool
    """PX4 reports its position setpoint (POSITION_TARGET_LOCAL_NED) in every mode while armed;
    ArduPilot only in GUIDED."""

    # Defaults.
    default_home: GeoPoint
    """Where each autopilot's own SITL starts (ArduPilot: CMAC, Canberra; PX4: Zurich)."""
    ready_delay_s: float
    """Time from boot until the position estimate is good (ArduPilot SITL's EKF needs ~40 s)."""
    origin_delay_s: float
    """Time from boot until the EKF has an origin: LOCAL_POSITION_NED is sent from then on
    (ArduCopter SITL ~19 s, "EKF3 IMU0 origin set")."""
    prearm_delay_s: float
    """Time from boot until the pre-arm checks pass: arming is allowed from then on in modes that
    need no position (ArduCopter SITL ~22 s, in STABILIZE)."""
    mode_switch_read_s: float | None
    """When the RC flight-mode switch is first read after boot and sets its mode (the initial
    mode), undoing a mode a ground station asked for before: a real ArduCopter SITL went from
    GUIDED back to STABILIZE 0.2 s after granting it, at ~2.2 s. None: no such read."""
    mode_position_check_armed_only: bool
    """ArduCopter checks a mode's need for a position only when armed (GUIDED is granted on the
    ground without one); PX4 checks it always."""
    takeoff_position_from_params: bool
    """PX4 reads MAV_CMD_NAV_TAKEOFF params 5/6 (latitude, longitude) as a take-off position when
    finite; ArduPilot ignores them."""
    sends_ekf_status: bool
    """ArduPilot sends EKF_STATUS_REPORT; PX4 does not."""
    arming_needs_position: bool
    """Arming is refused without a position estimate in every mode (as the mock's PX4 does);
    otherwise only in the modes that need one (ArduCopter arms in STABILIZE without it)."""
    rtl_alt_m: float
    land_speed_mps: float
    land_disarm_delay_s: float
    takeoff_spool_s: float
    """Time from the takeoff command until the vehicle leaves the ground."""
    default_takeoff_alt_m: float | None
    """Takeoff altitude when MAV_CMD_NAV_TAKEOFF gives none (NaN); None: such a takeoff fails."""
    takeoff_alt_is_amsl: bool
    """PX4 reads MAV_CMD_NAV_TAKEOFF param7 as AMSL altitude; ArduPilot as relative to home."""

    # How refusals are answered: (COMMAND_ACK result, STATUSTEXT or None).
    result_refused: MavResult
    """COMMAND_ACK result of a command the autopilot understood but refuses right now."""
    text_arm_not_ready: str
    text_prearm_failing: str
    """Arming refused before the pre-arm checks pass (any mode)."""
    text_arm_mode: str
    text_disarm_in_air: str
    text_mode_needs_position: str
    """Formatted with ``mode=``."""
    text_offboard_no_stream: str
    text_unknown_mode: str
    result_interval_refused: MavResult
    text_interval_refused: str
    """SET_MESSAGE_INTERVAL for a message the autopilot does not have (``{message_id}``)."""
    text_ready: tuple[str, ...]
    text_origin_set: str
    """When the EKF gets its origin ("" for nothing)."""
    text_auto_disarm: str
    text_offboard_lost: str
    text_gcs_lost: str
    """Formatted with ``action=``."""
    text_gcs_back: str
    text_battery_failsafe: str

    # The autopilot's own fence (sitl_mock.fence, sitl_mock.mission).
    fence_style: str
    """``ardupilot`` or ``px4``: whose fence parameters, checks and mission protocol habits."""
    fence_max_items: int
    """A fence upload of more items is refused (``MAV_MISSION_NO_SPACE``)."""
    text_fence_breach: str
    """A breach the vehicle acts on; formatted with ``fences=`` (ArduPilot's "Polygon fence")
    and ``action=`` (PX4's "Hold", "Return", "Land", "Terminate")."""
    text_fence_warning: str
    """A breach reported only (ArduPilot FENCE_ACTION 0, PX4 GF_ACTION 1)."""
    text_fence_cleared: str
    fence_recovery_s: float | None
    """ArduCopter: a mode change while a fence is breached (its own fence action's included)
    starts a "manual recovery" during which new breaches are ignored, this long; None: none."""
    text_fence_recovery: str

    def mode(self, name: str) -> ModeSpec:
        """The mode called ``name`` (KeyError for a name the flavour does not have)."""
        for spec in self.modes:
            if spec.name == name:
                return spec
        raise KeyError(f"{self.name} has no mode {name!r}")

    def mode_by_custom(self, custom_mode: int) -> ModeSpec | None:
        """The mode with HEARTBEAT.custom_mode ``custom_mode``, or None if there is none."""
        if self.autopilot_type == PX4.autopilot_type:
            main = (custom_mode >> 16) & 0xFF
            sub = (custom_mode >> 24) & 0xFF
            custom_mode = px4_custom_mode(main, sub if main == PX4_MAIN_AUTO else 0)
        for spec in self.modes:
            if spec.custom_mode == custom_mode:
                return spec
        return None

    def custom_mode_from_command(self, param2: float, param3: float) -> int | None:
        """The custom mode MAV_CMD_DO_SET_MODE asks for (param2, and on PX4 param3), or None."""
        if not math.isfinite(param2) or param2 < 0 or param2 > 0xFFFFFFFF:
            return None
        if self.autopilot_type == PX4.autopilot_type:
            sub = int(param3) if math.isfinite(param3) and 0 <= param3 <= 255 else 0
            return px4_custom_mode(int(param2), sub)
        return int(param2)


ARDUPILOT = Flavour(
    name="ardupilot",
    autopilot_type=3,
    modes=ARDUPILOT_MODES,
    initial_mode="STABILIZE",
    guided_mode="GUIDED",
    hold_mode="LOITER",
    land_mode="LAND",
    rtl_mode="RTL",
    takeoff_mode=None,
    streams_on_request_only=True,
    default_rates_hz={
        "SYS_STATUS": 2.0,
        "GPS_RAW_INT": 2.0,
        "EXTENDED_SYS_STATE": 2.0,
        "GLOBAL_POSITION_INT": 4.0,
        "LOCAL_POSITION_NED": 4.0,
        "ATTITUDE": 4.0,
        "VFR_HUD": 4.0,
        "BATTERY_STATUS": 1.0,
        "POSITION_TARGET_LOCAL_NED": 4.0,
        "POSITION_TARGET_GLOBAL_INT": 2.0,
        "HOME_POSITION": 0.5,
        "EKF_STATUS_REPORT": 2.0,
    },
    honours_request_data_stream=True,
    params_bytewise=False,
    setpoints_buffered_outside_guided=False,
    guided_needs_setpoint_stream=False,
    setpoint_cancels_ground_takeoff=True,
    guided_lifts_off_from_setpoint=False,
    guided_setpoint_timeout_failsafe=False,
    velocity_setpoint_timeout_s=3.0,
    yaw_follows_course=True,
    target_echo_outside_guided=False,
    default_home=GeoPoint(-35.363261, 149.165230, 584.0),
    ready_delay_s=40.0,
    origin_delay_s=19.0,
    prearm_delay_s=22.0,
    mode_switch_read_s=2.2,
    mode_position_check_armed_only=True,
    takeoff_position_from_params=False,
    sends_ekf_status=True,
    arming_needs_position=False,
    rtl_alt_m=15.0,
    land_speed_mps=0.5,
    land_disarm_delay_s=1.0,
    takeoff_spool_s=1.0,
    default_takeoff_alt_m=None,
    takeoff_alt_is_amsl=False,
    result_refused=MavResult.FAILED,
    text_arm_not_ready="Arm: Need Position Estimate",
    text_prearm_failing="PreArm: AHRS: waiting for home",
    text_arm_mode="Arm: Mode not armable",
    text_disarm_in_air="Disarm: not landed",
    text_mode_needs_position="Mode change to {mode} failed: requires position",
    text_offboard_no_stream="",
    text_unknown_mode="No such mode",
    result_interval_refused=MavResult.DENIED,
    text_interval_refused="Unknown message id {message_id}",
    text_ready=("EKF3 IMU0 is using GPS",),
    text_origin_set="EKF3 IMU0 origin set",
    text_auto_disarm="Disarming motors: no takeoff",
    text_offboard_lost="",
    text_gcs_lost="GCS Failsafe On: {action}",
    text_gcs_back="GCS Failsafe Cleared",
    text_battery_failsafe="Battery failsafe: LAND",
    fence_style="ardupilot",
    fence_max_items=70,
    text_fence_breach="{fences} breached",
    text_fence_warning="{fences} breached",
    text_fence_cleared="Fence breach cleared",
    fence_recovery_s=10.0,
    text_fence_recovery="Manual recovery started",
)

PX4 = Flavour(
    name="px4",
    autopilot_type=12,
    modes=PX4_MODES,
    initial_mode="AUTO.LOITER",
    guided_mode="OFFBOARD",
    hold_mode="AUTO.LOITER",
    land_mode="AUTO.LAND",
    rtl_mode="AUTO.RTL",
    takeoff_mode="AUTO.TAKEOFF",
    streams_on_request_only=False,
    default_rates_hz={
        "SYS_STATUS": 1.0,
        "GPS_RAW_INT": 1.0,
        "EXTENDED_SYS_STATE": 1.0,
        "GLOBAL_POSITION_INT": 5.0,
        "LOCAL_POSITION_NED": 5.0,
        "ATTITUDE": 10.0,
        "VFR_HUD": 4.0,
        "BATTERY_STATUS": 0.5,
        "POSITION_TARGET_LOCAL_NED": 2.0,
        "POSITION_TARGET_GLOBAL_INT": 1.0,
        "HOME_POSITION": 0.5,
    },
    honours_request_data_stream=False,
    params_bytewise=True,
    setpoints_buffered_outside_guided=True,
    guided_needs_setpoint_stream=True,
    setpoint_cancels_ground_takeoff=False,
    guided_lifts_off_from_setpoint=True,
    guided_setpoint_timeout_failsafe=True,
    velocity_setpoint_timeout_s=None,
    yaw_follows_course=False,
    target_echo_outside_guided=True,
    default_home=GeoPoint(47.397742, 8.545594, 488.0),
    ready_delay_s=10.0,
    origin_delay_s=10.0,
    prearm_delay_s=10.0,
    mode_switch_read_s=None,
    mode_position_check_armed_only=False,
    takeoff_position_from_params=True,
    sends_ekf_status=False,
    arming_needs_position=True,
    rtl_alt_m=30.0,
    land_speed_mps=0.7,
    land_disarm_delay_s=2.0,
    takeoff_spool_s=0.5,
    default_takeoff_alt_m=2.5,
    takeoff_alt_is_amsl=True,
    result_refused=MavResult.TEMPORARILY_REJECTED,
    text_arm_not_ready="Arming denied: no valid position estimate",
    text_prearm_failing="Arming denied: no valid position estimate",
    text_arm_mode="Arming denied: not possible in this flight mode",
    text_disarm_in_air="Disarming denied: not landed",
    text_mode_needs_position="Switching to {mode} is currently not possible: no position estimate",
    text_offboard_no_stream="Switching to Offboard is currently not possible: no offboard signal",
    text_unknown_mode="Unsupported flight mode",
    result_interval_refused=MavResult.TEMPORARILY_REJECTED,
    text_interval_refused="",
    text_ready=("Ready for takeoff!",),
    text_origin_set="",
    text_auto_disarm="Disarmed by auto preflight disarming",
    text_offboard_lost="Failsafe activated: no offboard signal, holding",
    text_gcs_lost="Connection to ground station lost: {action}",
    text_gcs_back="Connection to ground station regained",
    text_battery_failsafe="Failsafe activated: battery critical, landing",
    fence_style="px4",
    fence_max_items=256,
    text_fence_breach="Failsafe activated due to geofence violation, triggering {action}",
    text_fence_warning="Failsafe warning triggered due to geofence violation",
    text_fence_cleared="",
    fence_recovery_s=None,
    text_fence_recovery="",
)

FLAVOURS: dict[str, Flavour] = {ARDUPILOT.name: ARDUPILOT, PX4.name: PX4}


def get_flavour(name: str) -> Flavour:
    """The flavour called ``name`` ("ardupilot" or "px4"); ValueError for anything else."""
    try:
        return FLAVOURS[name]
    except KeyError:
        raise ValueError(f"unknown flavour {name!r}: choose one of {sorted(FLAVOURS)}") from None
