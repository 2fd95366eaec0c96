"""The fence on the autopilot through service/mission_protocol.py, against the mock on both
flavours: upload and read back identical, parameters confirmed, refusals named, lost messages
retried, silence timed out."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from shapely.geometry import Polygon

from service.fence import FenceItem, FenceParam, fence_plan
from service.frames import FrameConfig, GeoPoint
from service.mission_protocol import (
    MavPort,
    MissionRefusedError,
    MissionTimeoutError,
    ParamError,
    Timing,
    apply_fence_plan,
    clear_fence,
    download_fence,
    read_params,
    set_params,
    upload_fence,
)
from sim.config import AreaConfig
from sim.envelope import Envelope, Exclusion

FRAME = FrameConfig(area_origin_north_m=-100.0, area_origin_east_m=-100.0)
ENVELOPE = Envelope.for_area(
    AreaConfig(),
    [
        Exclusion(Polygon([(150, 150), (200, 150), (200, 220), (150, 220)]), 0.0, 60.0, "pad"),
        Exclusion(Polygon([(300, 300), (340, 300), (320, 360)]), 0.0, 90.0, "tower"),
    ],
    clearance_m=5.0,
)
FAST = Timing(timeout_s=0.3, retries=2, param_timeout_s=0.3)


@pytest.fixture
def port(start_mock: Any, request: Any) -> Iterator[tuple[MavPort, Any]]:
    """A MavPort on a pymavlink connection to a fresh mock of the parametrised flavour."""
    mock = start_mock(request.param)
    conn = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{mock.port}",
        source_system=255,
        source_component=190,
        dialect="ardupilotmega",
        retries=5,
    )
    others: list[Any] = []
    port = MavPort.for_connection(conn, on_other=others.append)
    yield port, mock
    conn.close()


def home_of(mock: Any) -> GeoPoint:
    home = mock.vehicle.home
    return GeoPoint(home.lat_deg, home.lon_deg, home.alt_amsl_m)


@pytest.mark.parametrize("port", ["ardupilot", "px4"], indirect=True)
def test_the_plan_goes_up_and_comes_back_identical(port):
    port, mock = port
    autopilot = mock.flavour.name
    plan = fence_plan(ENVELOPE, home_of(mock), FRAME, autopilot)
    report = apply_fence_plan(port, plan)
    assert report.items_sent == report.items_read_back == 4 + 4 + 3
    assert report.params == {p.name: float(p.value) for p in plan.params}
    assert download_fence(port) == list(plan.items)
    fence = mock.vehicle.autopilot_fence
    assert [zone.inclusion for zone in fence.zones] == [True, False, False]
    assert fence.enabled
    assert fence.params[("FENCE_ALT_MAX" if autopilot == "ardupilot" else "GF_MAX_VER_DIST")] == (
        102.0
    )
    assert report.resends == 0
    # Cleared: nothing comes back.
    clear_fence(port)
    assert download_fence(port) == []


@pytest.mark.parametrize("port", ["ardupilot"], indirect=True)
def test_refusals_are_named_with_the_autopilots_reasons(port):
    port, mock = port
    plan = fence_plan(ENVELOPE, home_of(mock), FRAME)
    with pytest.raises(MissionRefusedError) as too_many:
        upload_fence(port, list(plan.items) * 10)
    assert str(too_many.value) == (
        "fence upload of 110 items refused: MAV_MISSION_NO_SPACE (Mission items exceed "
        "storage space) (autopilot said: Only 70 items are supported)"
    )
    assert too_many.value.result == 4
    two = [FenceItem(i.command, 2, i.lat_e7, i.lon_e7) for i in plan.items[:2]]
    with pytest.raises(MissionRefusedError, match="MAV_MISSION_ERROR") as bad:
        upload_fence(port, two)
    assert bad.value.statustexts == ("Invalid vertex count (2)", "Fence validation failed")
    with pytest.raises(ParamError, match=r"^FENCE_ALT_MAX: set 5000, the autopilot kept 150$"):
        set_params(port, [FenceParam("FENCE_ALT_MAX", 5000.0)], bytewise=False, timing=FAST)
    with pytest.raises(ParamError, match=r"^NO_SUCH_PARAM: PARAM_SET: no answer after 3 tries"):
        set_params(port, [FenceParam("NO_SUCH_PARAM", 1.0)], bytewise=False, timing=FAST)
    assert mock.vehicle.autopilot_fence.items == ()  # nothing was stored


@pytest.mark.parametrize("port", ["px4"], indirect=True)
def test_px4_integers_travel_bit_for_bit(port):
    port, mock = port
    values = set_params(port, [FenceParam("GF_ACTION", 3, 6)], bytewise=True)
    assert values == {"GF_ACTION": 3.0}
    assert mock.vehicle.autopilot_fence.params["GF_ACTION"] == 3.0
    assert read_params(port, ["GF_ACTION", "GF_MAX_VER_DIST"], bytewise=True) == {
        "GF_ACTION": 3.0,
        "GF_MAX_VER_DIST": 150.0,
    }


@pytest.mark.parametrize("port", ["ardupilot", "px4"], indirect=True)
def test_a_lost_item_is_sent_again(port):
    """Item 1 is lost once on the way: the upload still completes, identical."""
    port, mock = port
    plan = fence_plan(ENVELOPE, home_of(mock), FRAME, mock.flavour.name)
    send = port.send
    dropped: list[int] = []

    def lossy(message: Any) -> None:
        if message.get_type() == "MISSION_ITEM_INT" and message.seq == 1 and not dropped:
            dropped.append(1)
            return
        send(message)

    port.send = lossy
    upload_fence(port, plan.items, Timing(timeout_s=0.5, retries=3))
    assert dropped == [1]
    assert port.resends >= 1
    port.send = send
    assert download_fence(port) == list(plan.items)


@pytest.mark.parametrize("port", ["ardupilot"], indirect=True)
def test_silence_times_out_and_cancels(port):
    port, mock = port
    send = port.send
    sent: list[str] = []

    def only_the_cancel(message: Any) -> None:
        sent.append(message.get_type())
        if message.get_type() == "MISSION_ACK":
            send(message)

    port.send = only_the_cancel
    with pytest.raises(
        MissionTimeoutError, match=r"^fence upload: no answer to MISSION_COUNT after 3 tries"
    ):
        upload_fence(port, fence_plan(ENVELOPE, home_of(mock), FRAME).items, FAST)
    assert sent == ["MISSION_COUNT"] * 3 + ["MISSION_ACK"]
    with pytest.raises(MissionTimeoutError, match=r"^fence download: count: no answer after 3"):
        download_fence(port, FAST)
