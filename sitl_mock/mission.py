"""The MAVLink mission protocol for the fence (``mission_type`` = ``MAV_MISSION_TYPE_FENCE``), as
the autopilots serve it: upload (MISSION_COUNT, then one request per item, then MISSION_ACK) and
download (MISSION_REQUEST_LIST -> MISSION_COUNT, MISSION_REQUEST_INT -> MISSION_ITEM_INT), one
upload at a time, the request repeated after 1 s without an item and the upload cancelled after
8 s (ArduPilot's ``MissionItemProtocol``).

What differs between the flavours (from ArduPilot's source; PX4's as its mavlink_mission does):

* ArduPilot asks for items with MISSION_REQUEST, answers an item out of sequence with
  MISSION_ACK ``MAV_MISSION_INVALID_SEQUENCE`` (and keeps the upload going), says why it refuses
  in STATUSTEXT ("Only 70 items are supported", "Invalid vertex count (2)", "Fence upload
  timeout"), and sends items back in ``MAV_FRAME_GLOBAL`` with z = 0.
* PX4 asks with MISSION_REQUEST_INT, ignores a repeated item, and sends items back as stored.

Missions and rally points (other ``mission_type``) are not served: MISSION_ACK
``MAV_MISSION_UNSUPPORTED``.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.fence import (
    CMD_POLYGON_EXCLUSION,
    CMD_POLYGON_INCLUSION,
    FENCE_COMMANDS,
    GLOBAL_FRAMES,
    MISSION_ACCEPTED,
    MISSION_INVALID_PARAM1,
    MISSION_UNSUPPORTED,
    MISSION_UNSUPPORTED_FRAME,
    AutopilotFence,
    FenceItem,
    check_items,
)
from sitl_mock.flavours import Severity

log = logging.getLogger(__name__)

MAV = mavlink
FENCE = MAV.MAV_MISSION_TYPE_FENCE
REQUEST_REPEAT_S = 1.0
UPLOAD_TIMEOUT_S = 8.0
MISSION_MESSAGES = frozenset(
    {
        "MISSION_COUNT",
        "MISSION_ITEM",
        "MISSION_ITEM_INT",
        "MISSION_REQUEST",
        "MISSION_REQUEST_INT",
        "MISSION_REQUEST_LIST",
        "MISSION_ACK",
        "MISSION_CLEAR_ALL",
    }
)


@dataclass
class _Upload:
    link: Any
    peer: tuple[int, int]
    count: int
    next_seq: int = 0
    items: list[FenceItem] = field(default_factory=list)
    last_request_s: float = 0.0
    last_receive_s: float = 0.0


class FenceMissionServer:
    """The fence's mission protocol for one vehicle. ``say(severity, text)`` queues a
    STATUSTEXT; ``encoder`` builds the messages (the protocol's own); ``link.send`` sends one.
    ``max_items``: more in a MISSION_COUNT is refused with ``MAV_MISSION_NO_SPACE``. Counts go to
    ``stats``: ``fence_uploads``, ``fence_uploads_refused``, ``fence_downloads``,
    ``fence_requests_repeated``."""

    def __init__(
        self,
        fence: AutopilotFence,
        ardupilot: bool,
        max_items: int,
        encoder: mavlink.MAVLink,
        say: Callable[[Severity, str], None],
        stats: Counter[str] | None = None,
    ) -> None:
        self.fence = fence
        self.ardupilot = ardupilot
        self.max_items = max_items
        self._enc = encoder
        self._say = say
        self._upload: _Upload | None = None
        self.stats: Counter[str] = stats if stats is not None else Counter()

    @property
    def receiving(self) -> bool:
        return self._upload is not None

    def handle(self, link: Any, message: Any, now_s: float) -> None:
        """One mission message from ``link`` (addressed to this vehicle)."""
        kind = message.get_type()
        header = message.get_header()
        peer = (header.srcSystem, header.srcComponent)
        mission_type = getattr(message, "mission_type", 0)
        if mission_type != FENCE:
            if kind in ("MISSION_COUNT", "MISSION_REQUEST_LIST", "MISSION_CLEAR_ALL"):
                self._ack(link, peer, MISSION_UNSUPPORTED, mission_type)
            return
        if kind == "MISSION_COUNT":
            self._on_count(link, peer, message.count, now_s)
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            self._on_item(link, peer, message, now_s)
        elif kind == "MISSION_REQUEST_LIST":
            if self._upload is not None:
                self._ack(link, peer, MAV.MAV_MISSION_DENIED)
                return
            self.stats["fence_downloads"] += 1
            link.send(self._enc.mission_count_encode(*peer, len(self.fence.items), FENCE))
        elif kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            self._on_request(link, peer, message.seq, kind == "MISSION_REQUEST_INT")
        elif kind == "MISSION_ACK":
            upload = self._upload
            if upload is not None and upload.peer == peer:
                log.info("fence upload cancelled by the ground station (%d)", message.type)
                self._upload = None
        elif kind == "MISSION_CLEAR_ALL":
            if self._upload is not None and self._upload.peer != peer:
                self._ack(link, peer, MAV.MAV_MISSION_DENIED)
                return
            self._upload = None
            self.fence.store(())
            self._ack(link, peer, MISSION_ACCEPTED)

    def tick(self, now_s: float) -> None:
        """Repeat the request after 1 s without an item; cancel the upload after 8 s."""
        upload = self._upload
        if upload is None:
            return
        if now_s - upload.last_receive_s > UPLOAD_TIMEOUT_S:
            self._upload = None
            self.stats["fence_uploads_refused"] += 1
            if self.ardupilot:
                self._say(Severity.WARNING, "Fence upload timeout")
            self._ack(upload.link, upload.peer, MAV.MAV_MISSION_OPERATION_CANCELLED)
        elif now_s - upload.last_request_s > REQUEST_REPEAT_S:
            self.stats["fence_requests_repeated"] += 1
            self._request(upload, now_s)

    # ------------------------------------------------------------------ upload

    def _on_count(self, link: Any, peer: tuple[int, int], count: int, now_s: float) -> None:
        if self._upload is not None and self._upload.peer != peer:
            self._ack(link, peer, MAV.MAV_MISSION_DENIED)
            return
        self._upload = None
        if count > self.max_items:
            self.stats["fence_uploads_refused"] += 1
            if self.ardupilot:
                self._say(Severity.WARNING, f"Only {self.max_items} items are supported")
            self._ack(link, peer, MAV.MAV_MISSION_NO_SPACE)
            return
        if count == 0:
            self.fence.store(())
            self.stats["fence_uploads"] += 1
            self._ack(link, peer, MISSION_ACCEPTED)
            return
        upload = _Upload(link, peer, count, last_receive_s=now_s)
        self._upload = upload
        self._request(upload, now_s)

    def _request(self, upload: _Upload, now_s: float) -> None:
        upload.last_request_s = now_s
        encode = self._enc.mission_request_encode
        if not self.ardupilot:
            encode = self._enc.mission_request_int_encode
        upload.link.send(encode(*upload.peer, upload.next_seq, FENCE))

    def _on_item(self, link: Any, peer: tuple[int, int], message: Any, now_s: float) -> None:
        upload = self._upload
        if upload is None or upload.peer != peer:
            self._ack(link, peer, MAV.MAV_MISSION_DENIED if upload else MAV.MAV_MISSION_ERROR)
            return
        if message.seq != upload.next_seq:
            if self.ardupilot:
                self._ack(link, peer, MAV.MAV_MISSION_INVALID_SEQUENCE)
            return
        if message.get_type() == "MISSION_ITEM":
            x, y = round(message.x * 1e7), round(message.y * 1e7)
            if self.ardupilot and upload.next_seq == 0:
                self._say(Severity.WARNING, "got MISSION_ITEM; GCS should send MISSION_ITEM_INT")
        else:
            x, y = message.x, message.y
        item = FenceItem(message.command, message.frame, message.param1, x, y)
        result = _item_result(item)
        if result != MISSION_ACCEPTED:
            self._refuse(upload, result, "")
            return
        upload.items.append(item)
        upload.next_seq += 1
        upload.last_receive_s = now_s
        if upload.next_seq < upload.count:
            self._request(upload, now_s)
            return
        result, why = check_items(upload.items, self.ardupilot)
        if result != MISSION_ACCEPTED:
            self._refuse(upload, result, why)
            return
        self._upload = None
        self.fence.store(upload.items)
        self.stats["fence_uploads"] += 1
        log.info("fence uploaded: %d items, %d zones", len(upload.items), len(self.fence.zones))
        self._ack(link, peer, MISSION_ACCEPTED)

    def _refuse(self, upload: _Upload, result: int, why: str) -> None:
        self._upload = None
        self.stats["fence_uploads_refused"] += 1
        if why and self.ardupilot:
            self._say(Severity.WARNING if "count (" in why else Severity.INFO, why)
            self._say(Severity.WARNING, "Fence validation failed")
        log.info("fence upload refused: %d %s", result, why)
        self._ack(upload.link, upload.peer, result)

    # ------------------------------------------------------------------ download

    def _on_request(self, link: Any, peer: tuple[int, int], seq: int, as_int: bool) -> None:
        if self._upload is not None:
            self._ack(link, peer, MAV.MAV_MISSION_DENIED)
            return
        items = self.fence.items
        if not 0 <= seq < len(items):
            if self.ardupilot:
                link.send(self._enc.mission_count_encode(*peer, len(items), FENCE))
            self._ack(link, peer, MAV.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = items[seq]
        frame = MAV.MAV_FRAME_GLOBAL if self.ardupilot else item.frame
        param1 = float(int(item.param1)) if _is_polygon(item) else item.param1
        if as_int:
            message = self._enc.mission_item_int_encode(
                *peer, seq, frame, item.command, 0, 1, param1, 0, 0, 0, item.x, item.y, 0, FENCE
            )
        else:
            if self.ardupilot and seq == 0:
                self._say(Severity.WARNING, "got MISSION_REQUEST; use MISSION_REQUEST_INT!")
            message = self._enc.mission_item_encode(
                *peer, seq, frame, item.command, 0, 1, param1, 0, 0, 0,
                item.x / 1e7, item.y / 1e7, 0, FENCE,
            )  # fmt: skip
        link.send(message)

    def _ack(
        self, link: Any, peer: tuple[int, int], result: int, mission_type: int = FENCE
    ) -> None:
        link.send(self._enc.mission_ack_encode(*peer, result, mission_type))


def _is_polygon(item: FenceItem) -> bool:
    return item.command in (CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION)


def _item_result(item: FenceItem) -> int:
    """ArduPilot's per-item conversion checks (frame, command, vertex count field)."""
    if item.frame not in GLOBAL_FRAMES:
        return MISSION_UNSUPPORTED_FRAME
    if item.command not in FENCE_COMMANDS:
        return MISSION_UNSUPPORTED
    if _is_polygon(item) and item.param1 > 255:
        return MISSION_INVALID_PARAM1
    return MISSION_ACCEPTED
