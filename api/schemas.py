"""Pydantic models at the HTTP boundary (and only here): what goes in and out of the API.

Numbers must be finite (``NaN`` and infinities are refused with 422) and within physical ranges
(rates up to :data:`MAX_BPS`, delays up to :data:`MAX_DELAY_S`, loss ratios in [0, 1],
positions up to :data:`MAX_POSITION_M`): a finite but absurd number such as 1e308 would
overflow the policies' arithmetic. Checks that depend on the service's settings (users inside
the area, unique ids, how many users, a timestamp not from the future) are made by the route or
the service, with the same 422 error shape.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

MAX_BPS = 1e12
"""1 Tbit/s: far above any Wi-Fi user's rate, far below where sums of them could overflow."""
MAX_DELAY_S = 3600.0
"""An hour: a packet delay beyond it is a measurement error, not a delay."""
MAX_POSITION_M = 1e6
"""1,000 km: a loose bound (the route checks the area itself)."""
MAX_TIMESTAMP_S = 1e10
"""The year 2286: a loose bound (the service refuses any timestamp ahead of its clock)."""


class _Strict(BaseModel):
    # strict: a number must be a JSON number (not "1.5", not true), a string a JSON string.
    model_config = ConfigDict(allow_inf_nan=False, extra="forbid", strict=True)


class UserReportIn(_Strict):
    """What the network controller measured for one user over the last period."""

    id: str = Field(min_length=1, max_length=64, description="The user's id, unique per report")
    x_m: float = Field(
        ge=0,
        le=MAX_POSITION_M,
        description="East position in the area frame, metres (at most the area's width)",
    )
    y_m: float = Field(
        ge=0,
        le=MAX_POSITION_M,
        description="North position in the area frame, metres (at most the area's depth)",
    )
    offered_bps: float = Field(ge=0, le=MAX_BPS, description="Offered (uplink) load, bit/s")
    throughput_bps: float = Field(ge=0, le=MAX_BPS, description="Received throughput, bit/s")
    delay_s: float = Field(ge=0, le=MAX_DELAY_S, description="Mean packet delay, seconds")
    plr: float = Field(ge=0, le=1, description="Packet loss ratio in [0, 1]")


class ReportIn(_Strict):
    """One report of all users the access point serves."""

    model_config = ConfigDict(
        allow_inf_nan=False,
        extra="forbid",
        strict=True,
        json_schema_extra={
            "examples": [
                {
                    "timestamp": 1_764_000_000.0,
                    "users": [
                        {
                            "id": "ue-1",
                            "x_m": 120.0,
                            "y_m": 80.0,
                            "offered_bps": 30e6,
                            "throughput_bps": 21.5e6,
                            "delay_s": 0.42,
                            "plr": 0.18,
                        },
                        {
                            "id": "ue-2",
                            "x_m": 400.0,
                            "y_m": 410.0,
                            "offered_bps": 5e6,
                            "throughput_bps": 5e6,
                            "delay_s": 0.004,
                            "plr": 0.0,
                        },
                    ],
                }
            ]
        },
    )

    timestamp: float = Field(
        ge=0,
        le=MAX_TIMESTAMP_S,
        description="When it was measured, Unix time in seconds; at most `report_max_future_s` "
        "(default 5 s) ahead of the service's clock",
    )
    users: list[UserReportIn] = Field(min_length=1, description="Every user, at least one")


class Target(_Strict):
    x_m: float
    y_m: float
    z_m: float


class DecisionOut(BaseModel):
    """The vehicles' targets and where they came from (one shape for any number of vehicles)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "target": {"x_m": 187.5, "y_m": 162.5, "z_m": 25.0},
                    "source": "policy",
                    "policy": "oracle",
                    "decided_at": 1_764_000_001.2,
                    "targets": {"uav1": {"x_m": 187.5, "y_m": 162.5, "z_m": 25.0}},
                }
            ]
        }
    )

    target: Target | None = Field(
        description="The vehicle's target: the one vehicle of a single-vehicle service, or the "
        "vehicle a per-vehicle route names; None until it is decided, and always for a fleet's "
        "setpoint (see targets)"
    )
    source: Literal["policy", "restored", "none"]
    policy: str | None
    decided_at: float | None = Field(description="Unix time of the decision, seconds")
    targets: dict[str, Target] = Field(
        default_factory=dict,
        description="The target of each commanded vehicle, by vehicle id, for any number of "
        'vehicles (one vehicle: {"uav1": ...}; a vehicle that cannot be commanded now has '
        "none)",
    )


class ReportOut(DecisionOut):
    """The answer to a report: the target, and what became of the report."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "target": {"x_m": 187.5, "y_m": 162.5, "z_m": 25.0},
                    "source": "policy",
                    "policy": "oracle",
                    "decided_at": 1_764_000_001.2,
                    "targets": {"uav1": {"x_m": 187.5, "y_m": 162.5, "z_m": 25.0}},
                    "report_outcome": "decided",
                }
            ]
        }
    )

    report_outcome: Literal["decided", "held", "superseded", "pending", "stored"] = Field(
        description="decided: a decision was taken from this report, and this is it; held: a "
        "decision was attempted on it and the target is held (the MAVLink link is down: it is "
        "decided once the link is back, if still fresh; a refused target; a failing policy); "
        "superseded: a newer report replaced it before a decision read it (answered at once; "
        "the newer one is decided); pending: its decision had not ended 1.75 decision periods "
        "after it arrived (decisions are slower than the period; it follows unless a newer "
        "report replaces it: GET /v1/setpoint shows it); stored: paced mode, kept for the next "
        "period's decision. Except for decided, the target is the current one"
    )


class TakeoffOut(BaseModel):
    """Where the arm-and-takeoff sequence stands (``--arm-and-takeoff``)."""

    state: str = Field(description="idle, running, airborne, or 'failed: <reason>'")
    phase: str | None = Field(description="The step it is at while running")
    attempts: int = Field(description="How many times the sequence has started")
    last_refusal: str | None = Field(
        description="Why the last attempt failed, with the vehicle's STATUSTEXT about it"
    )


class ControlOut(BaseModel):
    """Who has the vehicle, and why (the pilot and the autopilot's failsafes always win)."""

    holder: Literal["service", "pilot", "autopilot", "operator"] = Field(
        description="service: it streams setpoints and may ask for the guided mode; pilot: the "
        "vehicle left the guided mode on someone's command; autopilot: a failsafe, a return or a "
        "landing; operator: released through PUT .../control. Only an operator hands it back."
    )
    reason: str = Field(description="What the vehicle did, or how the service got it")
    age_s: float | None = Field(description="Seconds since the control last changed hands")


class ControlIn(_Strict):
    """Hand the vehicle back to the service, or take it from the service."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        json_schema_extra={"examples": [{"holder": "service"}, {"holder": "operator"}]},
    )

    holder: Literal["service", "operator"] = Field(
        description="service: hand the vehicle back (refused while it is in a return or landing "
        "mode or flags a failsafe); operator: the service lets go and streams nothing"
    )
    reason: str | None = Field(
        default=None, max_length=200, description="Noted in the vehicle's control reason"
    )
    takeoff: bool = Field(
        default=False,
        description="With holder service: a vehicle handed back on the ground (returned home, "
        "recharged) is armed and takes off, as with --arm-and-takeoff. Never without it.",
    )


class RouteOut(BaseModel):
    """The way to the target inside the vehicle's envelope, or where it holds and why."""

    kind: Literal["direct", "over", "around", "recover", "hold"] = Field(
        description="direct; over (climbs over no-fly volumes); around (a detour at one height); "
        "recover (back into the envelope first); hold (no legal way: it keeps still)"
    )
    waypoints: list[Target] = Field(
        description="The remaining waypoints, the setpoint streamed now first (the hold point "
        "while holding); the last is the target"
    )
    hold_reason: str | None = Field(description="Why it holds (None while it flies)")


Corner = Annotated[list[float], Field(min_length=2, max_length=2, description="[x, y], metres")]


class ExclusionIn(_Strict):
    """A no-fly volume: a footprint between two heights (area frame)."""

    name: str = Field(default="", max_length=100)
    polygon: list[Corner] = Field(min_length=3, max_length=200)
    floor_m: float = 0.0
    ceiling_m: float


class EnvelopeIn(_Strict):
    """A ``tupa-envelope/1`` document (sim/envelope/files.py): where the vehicle may fly. The
    geometry is checked beyond this schema (a simple polygon, a ceiling above the floor, room
    left to fly, the vehicle's home outside every no-fly volume): 422 naming the field."""

    model_config = ConfigDict(
        allow_inf_nan=False,
        extra="forbid",
        strict=True,
        json_schema_extra={
            "examples": [
                {
                    "format": "tupa-envelope/1",
                    "ceiling_m": 90,
                    "clearance_m": 5,
                    "exclusions": [
                        {
                            "name": "helipad",
                            "polygon": [[100, 100], [160, 100], [160, 150], [100, 150]],
                            "floor_m": 0,
                            "ceiling_m": 60,
                        }
                    ],
                }
            ]
        },
    )

    format: Literal["tupa-envelope/1"]
    inclusion: list[Corner] | None = Field(
        default=None, min_length=3, max_length=1000, description="Default: the area"
    )
    floor_m: float | None = Field(default=None, description="Default: the area's lowest altitude")
    ceiling_m: float | None = Field(default=None, description="Default: the area's highest")
    clearance_m: float | None = Field(default=None, ge=0, description="Default: 0")
    max_speed_mps: float | None = Field(default=None, gt=0, description="Default: 10")
    exclusions: list[ExclusionIn] = Field(
        default_factory=list,
        max_length=200,
        description="At most 200, of at most 200 corners each and 1000 corners in all (routes "
        "are planned round every corner); a district's buildings are added by the service",
    )


class BatteryOut(BaseModel):
    """The vehicle's battery, and when the service sends it home (service/battery.py)."""

    remaining_pct: float | None = Field(description="Remaining charge, % (None: not reported)")
    voltage_v: float | None = Field(description="Pack voltage (None: not reported)")
    drain_pct_per_min: float | None = Field(
        description="The drain measured while flying (None before 20 s of it)"
    )
    return_at_pct: float | None = Field(
        description="The charge at which the service ends the placement and commands the return "
        "home from where the vehicle is now: the reserve plus what flying home takes (None while "
        "it does not fly in the service's hands, or without a reserve)"
    )


class VehicleOut(BaseModel):
    """The vehicle as the service sees it over MAVLink (area frame)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "position": {"x_m": 180.2, "y_m": 160.9, "z_m": 25.1},
                    "mode": "OFFBOARD",
                    "armed": True,
                    "link": "up",
                    "flavour": "px4",
                    "heartbeat_age_s": 0.31,
                    "streaming": True,
                    "takeoff": {
                        "state": "airborne",
                        "phase": None,
                        "attempts": 1,
                        "last_refusal": None,
                    },
                    "status_texts": ["INFO: Takeoff detected"],
                    "control": {
                        "holder": "service",
                        "reason": "its take-off sequence",
                        "age_s": 42.0,
                    },
                }
            ]
        }
    )

    position: Target | None
    mode: str | None
    armed: bool
    link: Literal["connecting", "up", "link_lost"]
    flavour: str | None
    heartbeat_age_s: float | None
    streaming: bool
    takeoff: TakeoffOut
    status_texts: list[str] = Field(
        description="The vehicle's latest STATUSTEXT messages, oldest first ('SEVERITY: text')"
    )
    control: ControlOut
    route: RouteOut | None = Field(
        default=None, description="The route flown to the target (None before the first one)"
    )
    battery: BatteryOut | None = Field(default=None, description="The vehicle's battery")
    fence: str = Field(
        default="off",
        description="The autopilot's own fence (--autopilot-fence): off, uploaded, what it waits "
        "for, or failed: why (nothing streams until it is uploaded)",
    )


class DecisionTimingOut(BaseModel):
    """How long the service's decisions take, against the decision period. A decision is timed
    from the policy's call until its target is ready for the link."""

    mode: Literal["paced", "on-report"] = Field(description="The decision mode")
    period_s: float = Field(description="The decision period, seconds")
    timed: int = Field(description="Decisions timed since the service started")
    last_s: float | None = Field(description="The last decision's duration (None before one)")
    max_s: float | None = Field(description="The longest decision so far (None before one)")
    overruns: int = Field(
        description="Decisions longer than the period: while they happen, decisions come once "
        "per decision rather than once per period, and on-report answers may be `pending`"
    )


class PolicyOut(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "name": "ddpg-residual-dr",
                    "kind": "coordinates",
                    "spec": "policies/checkpoints/ddpg-residual-dr.zip",
                    "metadata": {"algorithm": "ddpg", "strategy": "gen10k", "episodes": 2000},
                    "decisions": {
                        "mode": "on-report",
                        "period_s": 1.0,
                        "timed": 1200,
                        "last_s": 0.004,
                        "max_s": 0.041,
                        "overruns": 0,
                    },
                }
            ]
        }
    )

    name: str
    kind: Literal["moves", "coordinates", "placement"]
    spec: str
    metadata: dict[str, object] | None
    decisions: DecisionTimingOut | None = Field(
        default=None, description="How long the service's decisions take (GET /v1/policy)"
    )


class PolicyIn(_Strict):
    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        json_schema_extra={"examples": [{"policy": "load-weighted"}]},
    )

    policy: str = Field(
        min_length=1,
        max_length=4096,
        description="A checkpoint path on the service's machine, or min-distance, "
        "load-weighted, min-distance-env, oracle",
    )


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    ready: bool
    reasons: list[str]
    policy: str
    link: str = Field(description="The (first) vehicle's MAVLink link")
    vehicles: dict[str, str] = Field(
        description="Each vehicle's MAVLink link, by id (one vehicle: uav1)"
    )


class FleetVehicleOut(BaseModel):
    """One vehicle of the service's fleet (a single-vehicle service has one: ``uav1``)."""

    id: str
    system_id: int | None = Field(
        description="The MAVLink system id heard from it (None before its first HEARTBEAT)"
    )
    commanded: bool = Field(description="Whether the service streams it a target now")
    problem: str | None = Field(description="Why it is not commanded now")
    vehicle: VehicleOut
    setpoint: DecisionOut


class FleetOut(BaseModel):
    """The vehicles the service drives, in the fleet's priority order."""

    separation_m: float | None = Field(
        description="The minimum 3-D distance between any two targets (None: one vehicle)"
    )
    vehicles: list[FleetVehicleOut]


class ErrorOut(BaseModel):
    """An error in one line: 401, 409, 413, 429."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"detail": "authorization: a valid 'Bearer <token>' header is required"}]
        }
    )

    detail: str


class FieldError(BaseModel):
    loc: list[str | int] = Field(description='Where: ["body", "users", 2, "plr"]')
    msg: str
    type: str | None


class ValidationErrorOut(BaseModel):
    """422: each bad field named (the offending value is not echoed)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "detail": [
                        {
                            "loc": ["body", "users", 0, "plr"],
                            "msg": "Input should be less than or equal to 1",
                            "type": "less_than_equal",
                        }
                    ]
                }
            ]
        }
    )

    detail: list[FieldError]
