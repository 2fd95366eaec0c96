"""The MAVLink mission protocol for the fence (``mission_type`` = ``MAV_MISSION_TYPE_FENCE``), and
parameters set with confirmation, on pymavlink: what puts a :class:`service.fence.FencePlan` on
the autopilot and reads it back.

The contract (:class:`MavPort`): the caller owns the connection and lends it for the transfer.

* ``send(message)``: send one pymavlink message object (``MAVLink_*_message``, built here with the
  dialect's ``*_encode``, not packed); the caller packs it on its connection (sequence number,
  signing), e.g. ``conn.mav.send``. It may raise OSError, which ends the transfer.
* ``receive(timeout_s)``: the next message from the connection (any type), or None when nothing
  came within ``timeout_s``; e.g. ``conn.recv_match(blocking=True, timeout=timeout_s)``.
* ``on_other(message)``: every message this transfer does not consume (telemetry, HEARTBEATs,
  STATUSTEXTs included) is handed back here, so that the link's own handling goes on during a
  transfer (optional).
* ``on_idle()``: called before every wait (at least every 0.1 s): the link sends its own
  HEARTBEAT from here, so that a long transfer does not trigger the autopilot's ground-station
  failsafe (optional).

Everything runs in the calling thread and blocks; nothing else may read the connection meanwhile
(the link's I/O thread calls it between two polls, before streaming starts). Every wait is
bounded: a transfer takes at most ``(retries + 1) × timeout`` per step.

The protocol, as the MAVLink specification prescribes and ArduPilot and PX4 implement it:

* upload (:func:`upload_fence`): MISSION_COUNT; the autopilot asks for each item with
  MISSION_REQUEST_INT (PX4) or MISSION_REQUEST (ArduPilot), answered with MISSION_ITEM_INT; it
  ends with MISSION_ACK (``MAV_MISSION_ACCEPTED``, or the reason for refusing). A request that
  does not come within ``timeout_s`` makes us send the last message again (the count, or the
  item), at most ``retries`` times in a row; then the transfer is cancelled (MISSION_ACK
  ``MAV_MISSION_OPERATION_CANCELLED``) and :class:`MissionTimeoutError` raised. ArduPilot answers an
  item sent again with MISSION_ACK ``MAV_MISSION_INVALID_SEQUENCE`` and asks again itself: that
  ACK does not end the upload; any other error does.
* download (:func:`download_fence`): MISSION_REQUEST_LIST -> MISSION_COUNT, then
  MISSION_REQUEST_INT per item -> MISSION_ITEM_INT (a MISSION_ITEM, from an old autopilot, is
  accepted), each retried the same way, then our MISSION_ACK ``MAV_MISSION_ACCEPTED``.
* parameters (:func:`set_params`): PARAM_SET, then the PARAM_VALUE that echoes it; retried when
  none comes; :class:`ParamError` when the autopilot keeps another value or never answers (an
  unknown name). Integers travel as the autopilot wants them: cast to the float (ArduPilot) or
  bit for bit in it (PX4, ``bytewise``).

A refusal raises :class:`MissionRefusedError` naming the MAV_MISSION_RESULT and what the autopilot
said meanwhile and just after (STATUSTEXTs of severity WARNING or worse: ArduPilot says why, after
its MISSION_ACK: "Only 70 items are supported", "Invalid vertex count (2)", "Fence validation
failed"). No MAVSDK variant yet: MAVSDK's geofence plugin is the way on that backend.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from service.fence import (
    FenceItem,
    FenceParam,
    FencePlan,
    compare_items,
    compare_params,
)

FENCE = mavlink.MAV_MISSION_TYPE_FENCE
ACCEPTED = mavlink.MAV_MISSION_ACCEPTED
CANCELLED = mavlink.MAV_MISSION_OPERATION_CANCELLED
INVALID_SEQUENCE = mavlink.MAV_MISSION_INVALID_SEQUENCE
POLL_S = 0.1
REASON_SEVERITY = mavlink.MAV_SEVERITY_WARNING
"""STATUSTEXTs kept as reasons: WARNING or worse (ArduPilot's fence refusals are WARNINGs)."""
REASON_LINGER_S = 0.5
"""After a refusal, how long to keep listening for the STATUSTEXTs that say why (ArduPilot
sends them just after its MISSION_ACK)."""
_ENCODER = mavlink.MAVLink(None, 0, 0)  # builds message objects; the caller's connection packs
_INT_TYPES = {
    mavlink.MAV_PARAM_TYPE_UINT8,
    mavlink.MAV_PARAM_TYPE_INT8,
    mavlink.MAV_PARAM_TYPE_UINT16,
    mavlink.MAV_PARAM_TYPE_INT16,
    mavlink.MAV_PARAM_TYPE_UINT32,
    mavlink.MAV_PARAM_TYPE_INT32,
}


class MissionError(RuntimeError):
    """A fence transfer or parameter set that did not complete. ``statustexts``: what the
    autopilot said meanwhile (its reasons); ``result``: the MAV_MISSION_RESULT, if one came."""

    def __init__(self, what: str, result: int | None = None, statustexts: Sequence[str] = ()):
        said = f" (autopilot said: {'; '.join(statustexts)})" if statustexts else ""
        super().__init__(what + said)
        self.result = result
        self.statustexts = tuple(statustexts)


class MissionTimeoutError(MissionError):
    """The autopilot stopped answering (after every retry)."""


class MissionRefusedError(MissionError):
    """The autopilot answered MISSION_ACK with an error."""


class ParamError(MissionError):
    """A parameter the autopilot did not take, or did not answer for."""


class FenceMismatchError(MissionError):
    """What was read back is not what was sent."""


@dataclass(frozen=True)
class Timing:
    """Timeouts and retries (the mission protocol's defaults: 1.5 s, 5 retries)."""

    timeout_s: float = 1.5
    retries: int = 5
    param_timeout_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.timeout_s > 0 or not self.param_timeout_s > 0:
            raise ValueError("timeout_s, param_timeout_s: must be positive")
        if self.retries < 0:
            raise ValueError(f"retries: must be >= 0, got {self.retries}")


@dataclass
class MavPort:
    """A borrowed MAVLink connection to one autopilot (see the module docstring)."""

    send: Callable[[Any], None]
    receive: Callable[[float], Any | None]
    target_system: int = 1
    target_component: int = 1
    on_other: Callable[[Any], None] | None = None
    on_idle: Callable[[], None] | None = None
    own_system: int | None = None
    """Our system id: answers addressed to another system are passed on, not taken (None: take
    them whatever their target)."""
    resends: int = 0
    """Messages sent again after a timeout or a repeated request (a count, for reports)."""
    statustexts: list[str] = field(default_factory=list)
    """The vehicle's STATUSTEXTs of severity WARNING or worse seen during the current step
    (cleared as each step starts), and just after a refusal."""

    @classmethod
    def for_connection(
        cls, conn: Any, target_system: int = 1, target_component: int = 1, **options: Any
    ) -> MavPort:
        """A port on a ``mavutil.mavlink_connection`` that nothing else reads meanwhile."""
        return cls(
            send=conn.mav.send,
            receive=lambda timeout_s: conn.recv_match(blocking=True, timeout=timeout_s),
            target_system=target_system,
            target_component=target_component,
            own_system=conn.mav.srcSystem,
            **options,
        )


@dataclass(frozen=True)
class FenceReport:
    """What :func:`apply_fence_plan` did: items sent and read back (identical), parameters set
    and read back, how long it took, how many messages were sent again."""

    items_sent: int
    items_read_back: int
    params: dict[str, float]
    upload_s: float
    download_s: float
    params_s: float
    resends: int
    statustexts: tuple[str, ...]


# ---------------------------------------------------------------------- the fence


def upload_fence(port: MavPort, items: Sequence[FenceItem], timing: Timing = Timing()) -> None:
    """Replace the autopilot's fence with ``items`` (see the module docstring); returns once it
    answered MISSION_ACK accepted. MissionRefusedError, MissionTimeoutError, or OSError from
    ``send``."""
    port.statustexts.clear()
    count = len(items)
    what = "fence upload"
    port.send(
        _ENCODER.mission_count_encode(port.target_system, port.target_component, count, FENCE)
    )
    last_sent: int | None = None  # None: the count
    highest = -1
    tries_left = timing.retries
    while True:
        message = _await(
            port, ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"), timing.timeout_s
        )
        if message is None:
            if tries_left == 0:
                _cancel(port)
                waiting = "MISSION_COUNT" if last_sent is None else f"item {last_sent}"
                raise MissionTimeoutError(
                    f"{what}: no answer to {waiting} after {timing.retries + 1} tries "
                    f"({timing.timeout_s:g} s each)",
                    statustexts=port.statustexts,
                )
            tries_left -= 1
            port.resends += 1
            if last_sent is None:
                port.send(
                    _ENCODER.mission_count_encode(
                        port.target_system, port.target_component, count, FENCE
                    )
                )
            else:
                port.send(_item_message(port, items[last_sent], last_sent))
            continue
        if message.get_type() == "MISSION_ACK":
            if message.type == INVALID_SEQUENCE:
                continue  # ArduPilot's answer to an item sent again: it asks again itself
            if message.type == ACCEPTED and (count == 0 or highest == count - 1):
                return
            if message.type == ACCEPTED:
                raise MissionError(
                    f"{what}: accepted after item {highest} of {count}", ACCEPTED, port.statustexts
                )
            _linger(port)
            raise MissionRefusedError(
                f"{what} of {count} items refused: {_result_name(message.type)}",
                message.type,
                port.statustexts,
            )
        seq = message.seq
        if not 0 <= seq < count:
            _cancel(port)
            raise MissionError(
                f"{what}: the autopilot asked for item {seq} of {count}", None, port.statustexts
            )
        if seq > highest:
            highest = seq
            tries_left = timing.retries
        else:
            port.resends += 1  # asked again: our item was lost
        port.send(_item_message(port, items[seq], seq))
        last_sent = seq


def download_fence(port: MavPort, timing: Timing = Timing()) -> list[FenceItem]:
    """The autopilot's fence items, in order (see the module docstring). MissionRefusedError,
    MissionTimeoutError, or OSError from ``send``."""
    port.statustexts.clear()
    what = "fence download"
    request_list = _ENCODER.mission_request_list_encode(
        port.target_system, port.target_component, FENCE
    )
    reply = _exchange(port, request_list, ("MISSION_COUNT",), timing, f"{what}: count")
    count = reply.count
    items: list[FenceItem] = []
    for seq in range(count):
        request = _ENCODER.mission_request_int_encode(
            port.target_system, port.target_component, seq, FENCE
        )
        message = _exchange(
            port,
            request,
            ("MISSION_ITEM_INT", "MISSION_ITEM"),
            timing,
            f"{what}: item {seq} of {count}",
            lambda m, seq=seq: m.seq == seq,
        )
        items.append(_fence_item(message))
    if count:
        port.send(
            _ENCODER.mission_ack_encode(port.target_system, port.target_component, ACCEPTED, FENCE)
        )
    return items


def clear_fence(port: MavPort, timing: Timing = Timing()) -> None:
    """MISSION_CLEAR_ALL for the fence; returns once the autopilot acknowledged it."""
    port.statustexts.clear()
    message = _ENCODER.mission_clear_all_encode(port.target_system, port.target_component, FENCE)
    ack = _exchange(port, message, ("MISSION_ACK",), timing, "fence clear", accept_ack=True)
    if ack.type != ACCEPTED:
        _linger(port)
        raise MissionRefusedError(
            f"fence clear refused: {_result_name(ack.type)}", ack.type, port.statustexts
        )


# ---------------------------------------------------------------------- parameters


def set_params(
    port: MavPort, params: Iterable[FenceParam], bytewise: bool, timing: Timing = Timing()
) -> dict[str, float]:
    """Set each parameter in order and wait for the PARAM_VALUE that confirms it; the values
    the autopilot reports. ``bytewise``: integers travel bit for bit in the float (PX4).
    ParamError naming the parameter when it keeps another value or never answers."""
    values: dict[str, float] = {}
    for param in params:
        port.statustexts.clear()
        message = _ENCODER.param_set_encode(
            port.target_system,
            port.target_component,
            param.name.encode(),
            _param_field(param.value, param.is_int, bytewise),
            param.param_type,
        )
        reply = _exchange(
            port,
            message,
            ("PARAM_VALUE",),
            Timing(timing.param_timeout_s, timing.retries, timing.param_timeout_s),
            f"{param.name}: PARAM_SET",
            lambda m, name=param.name: param_name(m) == name,
            error=ParamError,
        )
        value = _param_value(reply, bytewise)
        tolerance = 0.0 if param.is_int else 0.01
        if abs(value - param.value) > tolerance:
            _linger(port)
            raise ParamError(
                f"{param.name}: set {param.value:g}, the autopilot kept {value:g}",
                statustexts=port.statustexts,
            )
        values[param.name] = value
    return values


def read_params(
    port: MavPort, names: Iterable[str], bytewise: bool, timing: Timing = Timing()
) -> dict[str, float]:
    """Each parameter's value (PARAM_REQUEST_READ by name); ParamError for one with no
    answer."""
    values: dict[str, float] = {}
    for name in names:
        port.statustexts.clear()
        request = _ENCODER.param_request_read_encode(
            port.target_system, port.target_component, name.encode(), -1
        )
        reply = _exchange(
            port,
            request,
            ("PARAM_VALUE",),
            Timing(timing.param_timeout_s, timing.retries, timing.param_timeout_s),
            f"{name}: PARAM_REQUEST_READ",
            lambda m, name=name: param_name(m) == name,
            error=ParamError,
        )
        values[name] = _param_value(reply, bytewise)
    return values


# ---------------------------------------------------------------------- the whole plan


def apply_fence_plan(port: MavPort, plan: FencePlan, timing: Timing = Timing()) -> FenceReport:
    """Put ``plan`` on the autopilot: upload the items, read them back and compare, set the
    parameters (the enabling one last) and read them back and compare. Raises MissionError (a
    subclass saying which) at the first step that fails; the link must not stream then."""
    bytewise = plan.autopilot == "px4"
    port.resends = 0
    texts: list[str] = []
    t0 = time.monotonic()
    upload_fence(port, plan.items, timing)
    texts += port.statustexts
    t1 = time.monotonic()
    got = download_fence(port, timing)
    texts += port.statustexts
    t2 = time.monotonic()
    if differences := compare_items(plan.items, got):
        raise FenceMismatchError("fence read back differs: " + "; ".join(differences))
    set_params(port, plan.params, bytewise, timing)
    values = read_params(port, [p.name for p in plan.params], bytewise, timing)
    texts += port.statustexts
    if differences := compare_params(plan.params, values):
        raise FenceMismatchError("fence parameters read back differ: " + "; ".join(differences))
    t3 = time.monotonic()
    return FenceReport(
        len(plan.items),
        len(got),
        values,
        round(t1 - t0, 3),
        round(t2 - t1, 3),
        round(t3 - t2, 3),
        port.resends,
        tuple(texts),
    )


# ---------------------------------------------------------------------- internals


def _exchange(
    port: MavPort,
    message: Any,
    reply_types: tuple[str, ...],
    timing: Timing,
    what: str,
    match: Callable[[Any], bool] = lambda _m: True,
    accept_ack: bool = False,
    error: type[MissionError] = MissionTimeoutError,
) -> Any:
    """Send ``message`` and wait for a reply of ``reply_types`` satisfying ``match``, sending
    it again after each timeout (``timing.retries`` times). A MISSION_ACK (unless it is the
    reply) refuses: MissionRefusedError."""
    waited = (*reply_types, "MISSION_ACK") if not accept_ack else reply_types
    for attempt in range(timing.retries + 1):
        if attempt:
            port.resends += 1
        port.send(message)
        deadline = time.monotonic() + timing.timeout_s
        while (left := deadline - time.monotonic()) > 0:
            reply = _await(port, waited, left)
            if reply is None:
                break
            if reply.get_type() == "MISSION_ACK" and not accept_ack:
                _linger(port)
                raise MissionRefusedError(
                    f"{what}: refused, {_result_name(reply.type)}", reply.type, port.statustexts
                )
            if match(reply):
                return reply
            if port.on_other is not None:
                port.on_other(reply)  # a stale answer (an earlier item, another parameter)
    raise error(
        f"{what}: no answer after {timing.retries + 1} tries ({timing.timeout_s:g} s each)",
        statustexts=port.statustexts,
    )


def _await(port: MavPort, types: tuple[str, ...], timeout_s: float) -> Any | None:
    """The next message from the target of one of ``types`` (the mission ones for the fence
    only), within ``timeout_s``; everything else goes to ``on_other``. STATUSTEXTs from the
    target are also kept in ``port.statustexts``."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        if port.on_idle is not None:
            port.on_idle()
        message = port.receive(min(left, POLL_S))
        if message is None:
            continue
        kind = message.get_type()
        from_target = (message.get_srcSystem(), message.get_srcComponent()) == (
            port.target_system,
            port.target_component,
        )
        if from_target and kind == "STATUSTEXT" and message.severity <= REASON_SEVERITY:
            port.statustexts.append(message.text)
        if from_target and kind in types and _for_us(port, message):
            return message
        if port.on_other is not None:
            port.on_other(message)
    return None


def _linger(port: MavPort) -> None:
    """Listen a little longer, for the STATUSTEXTs that explain a refusal."""
    _await(port, (), REASON_LINGER_S)


def _for_us(port: MavPort, message: Any) -> bool:
    """Addressed to us (when we know who we are), and of the fence for mission messages."""
    target = getattr(message, "target_system", None)
    if port.own_system is not None and target not in (None, 0, port.own_system):
        return False
    mission_type = getattr(message, "mission_type", None)
    return mission_type is None or mission_type == FENCE


def _cancel(port: MavPort) -> None:
    port.send(
        _ENCODER.mission_ack_encode(port.target_system, port.target_component, CANCELLED, FENCE)
    )


def _item_message(port: MavPort, item: FenceItem, seq: int) -> Any:
    return _ENCODER.mission_item_int_encode(
        port.target_system,
        port.target_component,
        seq,
        item.frame,
        item.command,
        0,
        1,
        float(item.vertex_count),
        0.0,
        0.0,
        0.0,
        item.lat_e7,
        item.lon_e7,
        0.0,
        FENCE,
    )


def _fence_item(message: Any) -> FenceItem:
    """A MISSION_ITEM_INT (or MISSION_ITEM, latitude/longitude in degrees) as a FenceItem."""
    if message.get_type() == "MISSION_ITEM":
        lat_e7, lon_e7 = round(message.x * 1e7), round(message.y * 1e7)
    else:
        lat_e7, lon_e7 = message.x, message.y
    return FenceItem(message.command, round(message.param1), lat_e7, lon_e7, message.frame)


def _result_name(result: int) -> str:
    entry = mavlink.enums["MAV_MISSION_RESULT"].get(result)
    if entry is None:
        return f"MAV_MISSION_RESULT {result}"
    return f"{entry.name} ({entry.description.rstrip('.')})"


def param_name(message: Any) -> str:
    """A PARAM_VALUE's ``param_id`` as text."""
    name = message.param_id
    return name.decode(errors="replace") if isinstance(name, bytes) else str(name)


def _param_field(value: float, is_int: bool, bytewise: bool) -> float:
    if is_int and bytewise:
        return struct.unpack("<f", struct.pack("<i", round(value)))[0]
    return float(value)


def _param_value(message: Any, bytewise: bool) -> float:
    if bytewise and message.param_type in _INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", message.param_value))[0])
    return float(message.param_value)
