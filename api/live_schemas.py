"""The operator view's frame (``GET /v1/live``, and each event of ``GET /v1/live/events``) as
pydantic models: the documented shape of what :mod:`service.live_view` writes. The service
encodes each frame once for every reader, so the routes send its bytes as they are; the tests
check them against these models."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Point = list[float | None]
"""``[x_m, y_m, z_m]`` in the area frame (x east, y north, z up)."""


class _Frame(BaseModel):
    model_config = ConfigDict(extra="forbid")


class LiveArea(_Frame):
    size_x_m: float
    size_y_m: float
    zone_m: float = Field(description="The side of a zone of the grid")
    z_min_m: float
    z_max_m: float


class LiveGeofence(_Frame):
    """The volume every target is clamped into, ``[low, high]`` per axis."""

    x_m: list[float]
    y_m: list[float]
    z_m: list[float]


class LivePolicy(_Frame):
    name: str
    spec: str


class LiveDecision(_Frame):
    source: str = Field(description="`policy` (decided from a report) or `restored`")
    policy: str
    decided_at: float = Field(description="Unix time, seconds")
    age_s: float | None


class LiveControl(_Frame):
    """Who has the vehicle (``service``, ``pilot``, ``autopilot``, ``operator``) and why."""

    holder: Literal["service", "pilot", "autopilot", "operator"]
    reason: str


class LiveExclusion(_Frame):
    name: str
    polygon: list[list[float]] = Field(description="Footprint corners [x, y], metres")
    floor_m: float
    ceiling_m: float


class LiveEnvelope(_Frame):
    """Where a vehicle may fly (``sim/envelope``): it never leaves the inclusion, never enters
    an exclusion volume, keeps within the altitude band and the clearance."""

    inclusion: list[list[float]] = Field(description="Polygon corners [x, y], metres")
    exclusions: list[LiveExclusion]
    floor_m: float
    ceiling_m: float
    clearance_m: float


class LiveRoute(_Frame):
    """The way to the target, or where the vehicle holds and why."""

    kind: Literal["direct", "over", "around", "recover", "hold"]
    waypoints_m: list[list[float]] = Field(description="The setpoint streamed now first")
    hold_reason: str | None


class LiveBattery(_Frame):
    remaining_pct: float | None
    return_at_pct: float | None = Field(
        description="The charge at which the service sends the vehicle home from here"
    )


class LiveSite(_Frame):
    """The district's buildings (on a site): the tallest building in each square."""

    cell_m: float
    nx: int
    ny: int
    heights_m: list[float] = Field(
        description="`nx` × `ny` heights, row by row from the south-west corner; 0: no building"
    )


class LiveCoverage(_Frame):
    """What a vehicle covers from where it is (on a site): the mean path loss to each square."""

    cell_m: float
    nx: int
    ny: int
    loss_db: list[float | None] = Field(
        description="`nx` × `ny` path losses (dB), row by row from the south-west corner; "
        "null: no path"
    )


class LiveVehicle(_Frame):
    id: str
    link: Literal["connecting", "up", "link_lost"]
    mode: str | None
    armed: bool
    flavour: str | None
    streaming: bool
    control: LiveControl
    heartbeat_age_s: float | None
    position_m: Point | None
    heading_deg: float | None = Field(
        description="Degrees clockwise from north, from telemetry; null when not reported"
    )
    target_m: Point | None
    track_m: list[list[float]] = Field(description="Recent positions, oldest first")
    decision: LiveDecision | None
    envelope: int = Field(description="Its envelope: an index into the frame's `envelopes`")
    route: LiveRoute | None
    battery: LiveBattery
    coverage: LiveCoverage | None = Field(description="On a site; null elsewhere")


class LiveUser(_Frame):
    id: str
    x_m: float
    y_m: float
    offered_bps: float
    throughput_bps: float
    delay_s: float
    plr: float
    served: float = Field(description="throughput / offered, in [0, 1]")


class LiveReport(_Frame):
    timestamp: float
    age_s: float | None = Field(description="Seconds since the service received it")
    stale: bool


class LiveUtility(_Frame):
    """The latest report's utility and its weighted parts (they add up to ``value``)."""

    t_s: float
    value: float
    throughput: float
    delay: float
    loss: float
    delay_ref_s: float


class LiveFrameOut(_Frame):
    """What the operator view shows at one instant (format ``tupa-live/1``)."""

    format: Literal["tupa-live/1"]
    seq: int
    time_s: float
    decision_period_s: float
    area: LiveArea
    geofence: LiveGeofence
    envelopes: list[LiveEnvelope] = Field(
        description="The vehicles' envelopes, each once (vehicles share one unless given their own)"
    )
    site: LiveSite | None = Field(description="The buildings, on a site; null elsewhere")
    policy: LivePolicy
    vehicles: list[LiveVehicle] = Field(
        description="The vehicle (id uav1), or a fleet's vehicles in the fleet's order"
    )
    users: list[LiveUser]
    report: LiveReport | None
    utility: LiveUtility | None
    utility_history: list[list[float]] = Field(
        description="`[t_s, value, throughput, delay, loss]`, oldest first"
    )
