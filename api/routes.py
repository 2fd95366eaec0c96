"""The routes: ``/v1`` (authenticated) for reports, setpoint, vehicle and policy; probes; metrics.

Handlers that only read the service's state (which it guards with short locks) are ``async``:
the probes, the metrics and ``GET /v1/policy`` among them, so that they answer from the event
loop and never wait for a worker thread. Those that may run a policy or load a checkpoint run in
the thread pool, so that they never stall the event loop; policy loads run one at a time (a
second concurrent ``PUT /v1/policy`` gets 409), so they hold at most one worker for long.
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from typing import Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CONTENT_TYPE_LATEST

from api.auth import require_token
from api.metrics import render_metrics
from api.schemas import (
    BatteryOut,
    ControlIn,
    ControlOut,
    DecisionOut,
    DecisionTimingOut,
    EnvelopeIn,
    ErrorOut,
    FleetOut,
    FleetVehicleOut,
    Health,
    PolicyIn,
    PolicyOut,
    Readiness,
    ReportIn,
    ReportOut,
    RouteOut,
    TakeoffOut,
    Target,
    ValidationErrorOut,
    VehicleOut,
)
from service.decisions import Decision, Report, VehicleView
from service.errors import InputError
from service.placement import (
    FutureReportError,
    OutOfOrderReportError,
    PlacementService,
    PolicyBusyError,
)
from service.vehicle_link import ControlRefused, LinkState, VehicleLink

_AUTH_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut, "description": "Missing or wrong bearer token"},
}
# Answered by the middlewares before any route runs (api.app, api.ratelimit).
RATE_LIMITED: dict[int | str, dict[str, Any]] = {
    429: {
        "model": ErrorOut,
        "description": "Over this client's request rate; retry after `Retry-After` seconds",
        "headers": {
            "Retry-After": {"description": "Seconds to wait", "schema": {"type": "integer"}}
        },
    },
}
_BODY_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorOut, "description": "Body that cannot be parsed (e.g. not UTF-8)"},
    413: {"model": ErrorOut, "description": "Body over the size limit"},
}

log = logging.getLogger(__name__)
v1 = APIRouter(prefix="/v1", dependencies=[Depends(require_token)], responses=_AUTH_RESPONSES)
probes = APIRouter()


def _service(request: Request) -> PlacementService:
    return request.app.state.service


def _single_vehicle(request: Request, fleet_route: str) -> PlacementService:
    """The service, when it drives one vehicle; 409 naming ``fleet_route`` when it drives more."""
    service = _service(request)
    if service.sole_vehicle_id() is None:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            detail=f"this service drives {len(service.links)} vehicles: {fleet_route}",
        )
    return service


def _unprocessable(loc: list[str | int], msg: str) -> HTTPException:
    """A 422 shaped like FastAPI's own validation errors, naming the field."""
    return HTTPException(
        status.HTTP_422_UNPROCESSABLE_CONTENT,
        detail=[{"loc": ["body", *loc], "msg": msg, "type": "value_error"}],
    )


def _target(xyz_m: tuple[float, float, float]) -> Target:
    x, y, z = xyz_m
    return Target(x_m=x, y_m=y, z_m=z)


def _setpoint_out(decisions: dict[str, Decision], sole_id: str | None) -> DecisionOut:
    """A setpoint, one shape for any number of vehicles: ``targets``, the target of each
    commanded vehicle it is about, by id; ``target``, vehicle ``sole_id``'s (the one vehicle
    of a single-vehicle service, or the one a per-vehicle route names; None for a fleet's);
    the decisions' source and policy, and the latest one's time."""
    if not decisions:
        return DecisionOut(target=None, source="none", policy=None, decided_at=None, targets={})
    first = next(iter(decisions.values()))
    sole = decisions.get(sole_id) if sole_id is not None else None
    return DecisionOut(
        target=None if sole is None else _target(sole.target_m),
        source=first.source,  # type: ignore[arg-type]
        policy=first.policy,
        decided_at=max(d.decided_at for d in decisions.values()),
        targets={vid: _target(d.target_m) for vid, d in decisions.items()},
    )


def _vehicle_setpoint_out(view: VehicleView) -> DecisionOut:
    """One vehicle's setpoint (``GET /v1/vehicles``, ``GET /v1/vehicles/ID/setpoint``)."""
    return _setpoint_out({} if view.decision is None else {view.id: view.decision}, view.id)


def _vehicle_out(state: LinkState) -> VehicleOut:
    return VehicleOut(
        position=None if state.position_m is None else _target(state.position_m),
        mode=state.mode,
        armed=state.armed,
        link=state.link,
        flavour=state.flavour,
        heartbeat_age_s=state.heartbeat_age_s,
        streaming=state.streaming,
        takeoff=TakeoffOut(
            state=state.takeoff,
            phase=state.takeoff_phase,
            attempts=state.takeoff_attempts,
            last_refusal=state.takeoff_last_refusal,
        ),
        status_texts=list(state.status_texts),
        control=ControlOut(
            holder=state.control, reason=state.control_reason, age_s=state.control_age_s
        ),
        route=None
        if state.route is None
        else RouteOut(
            kind=state.route.kind,  # type: ignore[arg-type]
            waypoints=[_target(w) for w in state.route.waypoints_m],
            hold_reason=state.route.hold_reason,
        ),
        fence=state.fence,
        battery=BatteryOut(
            remaining_pct=state.battery_pct,
            voltage_v=state.battery_voltage_v,
            drain_pct_per_min=None
            if state.battery_drain_pct_per_s is None
            else state.battery_drain_pct_per_s * 60.0,
            return_at_pct=state.battery_return_at_pct,
        ),
    )


def _fleet_vehicle_out(view: VehicleView) -> FleetVehicleOut:
    return FleetVehicleOut(
        id=view.id,
        system_id=view.state.system_id,
        commanded=view.problem is None and view.decision is not None,
        problem=view.problem,
        vehicle=_vehicle_out(view.state),
        setpoint=_vehicle_setpoint_out(view),
    )


def to_report(body: ReportIn, service: PlacementService) -> Report:
    """Check what the schema cannot (area, unique ids, user count) and build the service's
    :class:`~service.placement.Report`; 422 naming the first bad field."""
    area = service.area
    max_users = service.settings.max_users
    if len(body.users) > max_users:
        raise _unprocessable(["users"], f"at most {max_users} users per report")
    seen: set[str] = set()
    for i, user in enumerate(body.users):
        if user.id in seen:
            raise _unprocessable(["users", i, "id"], f"duplicate user id {user.id!r}")
        seen.add(user.id)
        if not 0.0 <= user.x_m <= area.size_x_m:
            raise _unprocessable(["users", i, "x_m"], f"outside the area [0, {area.size_x_m}] m")
        if not 0.0 <= user.y_m <= area.size_y_m:
            raise _unprocessable(["users", i, "y_m"], f"outside the area [0, {area.size_y_m}] m")
    columns = {
        name: np.array([getattr(u, name) for u in body.users], dtype=float)
        for name in ("x_m", "y_m", "offered_bps", "throughput_bps", "delay_s", "plr")
    }
    return Report.from_columns(body.timestamp, tuple(u.id for u in body.users), columns)


@v1.post(
    "/reports",
    response_model=ReportOut,
    summary="Submit one report of all users",
    responses={
        409: {
            "model": ErrorOut,
            "description": "Older than the last accepted report (reports are ordered by "
            "min(timestamp, arrival time)): ignored",
        },
        **_BODY_RESPONSES,
        422: {
            "model": ValidationErrorOut,
            "description": "A field is invalid (named in it), more users than `max_users` "
            "(`users`), or the timestamp is ahead of the service's clock by more than "
            "`report_max_future_s`",
        },
    },
)
async def post_report(body: ReportIn, request: Request) -> ReportOut:
    """Accept the users' latest metrics; ``report_outcome`` says what became of the report.

    ``decision_mode=on-report``: decisions never queue. The answer comes when the decision
    taken from this report ends (``decided``: the answer is that decision; ``held``: the target
    is held, e.g. the MAVLink link is down: the report is kept and decided once the link is
    back, if still fresh), at once when a newer report replaces this one before a decision
    reads it (``superseded``: the newer one is decided instead), or, when decisions are slower
    than the decision period, 1.75 decision periods after it arrived (``pending``: its decision
    follows unless a newer report replaces it; ``GET /v1/setpoint`` shows it). The last three
    answer with the current target. ``paced``: the report is stored for the next period's
    decision (``stored``), answered at once with the current target. ``target`` is null before
    the first decision."""
    service = _service(request)
    report = to_report(body, service)
    try:
        # On the event loop, so that reports are taken in the order they came (a lock held for
        # microseconds); a worker thread could take a later report first under load.
        accepted = service.accept(report)
    except OutOfOrderReportError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    except FutureReportError as exc:
        raise _unprocessable(["timestamp"], str(exc)) from None
    if service.submit_waits:  # off the event loop (waits for a decision, bounded)
        receipt = await run_in_threadpool(service.receipt, accepted)
    else:
        receipt = service.receipt(accepted)
    out = _setpoint_out(service.receipt_decisions(receipt), service.sole_vehicle_id())
    return ReportOut(**dict(out), report_outcome=receipt.outcome)


@v1.get("/setpoint", response_model=DecisionOut, summary="The current target(s)")
async def get_setpoint(request: Request) -> DecisionOut:
    """The target being streamed to the vehicle and when it was decided; ``targets`` has each
    commanded vehicle's, by id (one vehicle: ``uav1``'s)."""
    service = _service(request)
    return _setpoint_out(service.decisions(), service.sole_vehicle_id())


_FLEET_CONFLICT: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorOut, "description": "This service drives a fleet: see /v1/vehicles"},
}


@v1.get(
    "/vehicle", response_model=VehicleOut, summary="The vehicle's state", responses=_FLEET_CONFLICT
)
async def get_vehicle(request: Request) -> VehicleOut:
    """Position in the area frame (x east, y north, z up, metres), mode, armed, link health."""
    service = _single_vehicle(request, "GET /v1/vehicles")
    return _vehicle_out(service.vehicle())


@v1.get("/vehicles", response_model=FleetOut, summary="Every vehicle the service drives")
async def get_vehicles(request: Request) -> FleetOut:
    """Each vehicle's state, current target and, when it is not commanded now, why (link lost,
    no position yet, a system id that is not its own). A single-vehicle service lists one,
    ``uav1``. While a vehicle is lost the others cover its users (degraded mode)."""
    service = _service(request)
    return FleetOut(
        separation_m=service.separation_m,
        vehicles=[_fleet_vehicle_out(view) for view in service.vehicles()],
    )


_NO_SUCH_VEHICLE: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorOut, "description": "No vehicle with this id"},
}


def _one_vehicle(service: PlacementService, vehicle_id: str) -> VehicleView:
    for view in service.vehicles():
        if view.id == vehicle_id:
            return view
    raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"vehicle_id: no vehicle {vehicle_id!r}")


@v1.get(
    "/vehicles/{vehicle_id}",
    response_model=FleetVehicleOut,
    summary="One vehicle of the fleet",
    responses=_NO_SUCH_VEHICLE,
)
async def get_fleet_vehicle(vehicle_id: str, request: Request) -> FleetVehicleOut:
    return _fleet_vehicle_out(_one_vehicle(_service(request), vehicle_id))


@v1.get(
    "/vehicles/{vehicle_id}/setpoint",
    response_model=DecisionOut,
    summary="One vehicle's current target",
    responses=_NO_SUCH_VEHICLE,
)
async def get_fleet_setpoint(vehicle_id: str, request: Request) -> DecisionOut:
    return _vehicle_setpoint_out(_one_vehicle(_service(request), vehicle_id))


_CONTROL_RESPONSES: dict[int | str, dict[str, Any]] = {
    409: {
        "model": ErrorOut,
        "description": "The vehicle cannot be handed back now (its link is down, it is in a "
        "return or landing mode, or it flags a failsafe): the reason is named",
    },
    **_BODY_RESPONSES,
    422: {"model": ValidationErrorOut, "description": "A field is invalid (named in it)"},
}


def _change_control(service: PlacementService, link: VehicleLink, body: ControlIn) -> None:
    """Hand ``link``'s vehicle back to the service or take it from it; 409 naming the reason
    when the vehicle cannot be handed back now. A vehicle handed back on the ground (returned
    home, recharged) takes off only when the operator asks for it (``takeoff``)."""
    if body.takeoff and body.holder != "service":
        raise _unprocessable(["takeoff"], "takeoff: only with holder service (a hand-back)")
    try:
        if body.holder == "service":
            link.hand_back(body.reason or "handed back by an operator")
        else:
            link.release(body.reason or "released by an operator")
    except ControlRefused as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=f"control: {exc}") from None
    log.warning("an operator set the vehicle's control to %s", body.holder)
    if body.holder == "service" and body.takeoff and not link.state().armed:
        log.warning("an operator asked the vehicle handed back to arm and take off")
        link.arm_and_takeoff(timeout_s=service.settings.takeoff_timeout_s)


@v1.put(
    "/vehicle/control",
    response_model=VehicleOut,
    summary="Hand the vehicle back to the service, or take it from the service",
    responses={**_CONTROL_RESPONSES, **_FLEET_CONFLICT},
)
async def put_vehicle_control(body: ControlIn, request: Request) -> VehicleOut:
    """Once a pilot or a failsafe took the vehicle out of the guided mode, the service streams
    nothing and asks for nothing until an operator hands it back here (``holder: service``);
    it then streams its next decision and asks for the guided mode during the request window.
    ``holder: operator`` makes the service let go. The answer is the vehicle's state."""
    service = _single_vehicle(request, "PUT /v1/vehicles/{vehicle_id}/control")
    _change_control(service, service.link, body)
    return _vehicle_out(service.vehicle())


@v1.put(
    "/vehicles/{vehicle_id}/control",
    response_model=FleetVehicleOut,
    summary="Hand one vehicle back to the service, or take it from the service",
    responses={**_CONTROL_RESPONSES, **_NO_SUCH_VEHICLE},
)
async def put_fleet_vehicle_control(
    vehicle_id: str, body: ControlIn, request: Request
) -> FleetVehicleOut:
    """As ``PUT /v1/vehicle/control``, for one vehicle of the fleet (a single-vehicle service
    names its vehicle ``uav1``); the fleet re-places the others while one is not commanded."""
    service = _service(request)
    _one_vehicle(service, vehicle_id)  # 404 for an unknown id
    _change_control(service, service.links[vehicle_id], body)
    return _fleet_vehicle_out(_one_vehicle(service, vehicle_id))


_ENVELOPE_RESPONSES: dict[int | str, dict[str, Any]] = {
    **_AUTH_RESPONSES,
    **_BODY_RESPONSES,
    422: {
        "model": ValidationErrorOut,
        "description": "The envelope cannot be flown, or puts the vehicle's home inside a no-fly "
        "volume (the field is named)",
    },
}


def _change_envelope(service: PlacementService, vid: str, body: EnvelopeIn) -> None:
    """Give vehicle ``vid`` the envelope ``body`` describes (422 naming the field)."""
    document = body.model_dump(mode="json", exclude_none=True)
    try:
        envelope = service.set_envelope(vid, document)
    except InputError as exc:
        field = str(exc).split(":", 1)[0].removeprefix("envelope").strip(".")
        raise _unprocessable(field.split(".") if field else [], str(exc)) from None
    log.warning(
        "an operator gave %s a new envelope: %d no-fly volumes, %g-%g m",
        vid,
        len(envelope.exclusions),
        envelope.floor_m,
        envelope.ceiling_m,
    )


@v1.put(
    "/vehicle/envelope",
    response_model=VehicleOut,
    summary="Give the vehicle a new flight envelope",
    responses={**_ENVELOPE_RESPONSES, **_FLEET_CONFLICT},
)
def put_vehicle_envelope(body: EnvelopeIn, request: Request) -> VehicleOut:
    """From now on the vehicle flies inside this envelope: its route is planned again from where
    it is; a vehicle the new envelope finds outside holds where it is and says why (``route``),
    it never jumps. The answer is the vehicle's state. (A plain function: the envelope is built
    and checked, and the state file written, on the server's thread pool, not its event loop.)"""
    service = _single_vehicle(request, "PUT /v1/vehicles/{vehicle_id}/envelope")
    _change_envelope(service, next(iter(service.links)), body)
    return _vehicle_out(service.vehicle())


@v1.put(
    "/vehicles/{vehicle_id}/envelope",
    response_model=FleetVehicleOut,
    summary="Give one vehicle a new flight envelope",
    responses={**_ENVELOPE_RESPONSES, **_NO_SUCH_VEHICLE},
)
def put_fleet_vehicle_envelope(
    vehicle_id: str, body: EnvelopeIn, request: Request
) -> FleetVehicleOut:
    """As ``PUT /v1/vehicle/envelope``, for one vehicle of the fleet."""
    service = _service(request)
    _one_vehicle(service, vehicle_id)  # 404 for an unknown id
    _change_envelope(service, vehicle_id, body)
    return _fleet_vehicle_out(_one_vehicle(service, vehicle_id))


def _policy_out(service: PlacementService, policy: Any) -> PolicyOut:
    """``policy`` as ``/v1/policy`` shows it, with how long the service's decisions take."""
    timing = service.decision_timing()
    return PolicyOut(**policy.describe(), decisions=DecisionTimingOut(**asdict(timing)))


@v1.get("/policy", response_model=PolicyOut, summary="The serving policy")
async def get_policy(request: Request) -> PolicyOut:
    """The serving policy, and how long decisions take against the decision period
    (``decisions``: a decision slower than the period is an overrun)."""
    service = _service(request)
    return _policy_out(service, service.policy)


@v1.put(
    "/policy",
    response_model=PolicyOut,
    summary="Switch to another checkpoint or baseline",
    responses={
        409: {"model": ErrorOut, "description": "Another policy is being loaded: retry later"},
        **_BODY_RESPONSES,
        422: {"model": ValidationErrorOut, "description": "Unusable policy: the serving one stays"},
    },
)
def put_policy(body: PolicyIn, request: Request) -> PolicyOut:
    """Load and check the new policy fully, then swap it in atomically. A missing, corrupt,
    oversized or mismatched checkpoint, or one outside the service's checkpoint directories, is
    refused with 422 (naming the problem; the service log has the detail) and the serving
    policy stays in place. One load at a time: 409 while another is in progress."""
    service = _service(request)
    try:
        policy = service.swap_policy(body.policy)
    except PolicyBusyError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    except InputError as exc:
        raise _unprocessable(["policy"], str(exc)) from None
    except (OSError, ValueError) as exc:  # a name the OS refuses (too long, NUL byte, ...)
        log.warning("policy %r: not a usable path: %s", body.policy, exc)
        raise _unprocessable(["policy"], "policy: not a usable path") from None
    return _policy_out(service, policy)


@probes.get("/healthz", response_model=Health, summary="Liveness")
async def healthz() -> Health:
    return Health(status="ok")


@probes.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness: a policy is loaded and the MAVLink link is up",
    responses={503: {"model": Readiness, "description": "Not ready; reasons listed"}},
)
async def readyz(request: Request, response: Response) -> Readiness:
    service = _service(request)
    ready, reasons = service.readiness()
    if not ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    views = service.vehicles()
    return Readiness(
        ready=ready,
        reasons=reasons,
        policy=service.policy.name,
        link=views[0].state.link,
        vehicles={v.id: v.state.link for v in views},
    )


@probes.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}, **RATE_LIMITED},
)
async def metrics(request: Request) -> Response:
    body = await render_metrics(request.app.state.registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
