"""The in-memory vehicle link (tests/fakes.py) behaves as the placement tests assume: it is a
:class:`~service.vehicle_link.VehicleLink`, flies at its speed, takes off only when asked, stops
streaming when the link drops, and moves on its own in real-time mode. (Its geofence is checked
with the real links' in ``test_link_contract.py``.)"""

from __future__ import annotations

import math

import pytest

from service.vehicle_link import LinkConfig, VehicleLink
from sim.config import AreaConfig
from tests.fakes import FakeLink
from tests.helpers import wait_for

CONFIG = LinkConfig("tcp:127.0.0.1:1", area=AreaConfig())


def test_it_is_a_vehicle_link_that_flies_at_its_speed_towards_the_target():
    link = FakeLink(CONFIG, position_m=(100.0, 100.0, 50.0), speed_mps=10.0)
    assert isinstance(link, VehicleLink)
    with link:
        state = link.state()
        assert state.link == "up" and state.armed and state.takeoff == "airborne"
        assert state.position_m == (100.0, 100.0, 50.0) and not state.streaming
        link.set_target((130.0, 140.0, 50.0))  # 50 m away
        assert link.state().streaming and link.state().mode == "OFFBOARD"
        link.advance(2.0)
        assert math.dist(link.state().position_m, (100.0, 100.0, 50.0)) == pytest.approx(20.0)
        link.advance(10.0)
        assert link.state().position_m == pytest.approx((130.0, 140.0, 50.0))
        link.clear_target()
        link.advance(1.0)
        assert link.state().position_m == pytest.approx((130.0, 140.0, 50.0))
    assert link.closed


def test_a_vehicle_on_the_ground_ignores_targets_until_it_has_taken_off():
    link = FakeLink(CONFIG, climb_mps=5.0).start()
    assert not link.state().armed and link.state().takeoff == "idle"
    link.set_target((50.0, 50.0, 30.0))
    link.advance(5.0)
    assert link.state().position_m == (0.0, 0.0, 0.0) and link.arms == 0
    future = link.arm_and_takeoff(z_m=30.0)
    assert link.arms == 1 and link.state().takeoff == "running" and not link.state().streaming
    link.advance(3.0)
    assert not future.done() and link.state().position_m[2] == pytest.approx(15.0)
    link.advance(3.0)
    assert future.result(timeout=0) is None and link.state().takeoff == "airborne"
    assert link.state().streaming
    link.advance(1.0)
    assert link.state().position_m[0] > 0.0
    assert link.arm_and_takeoff().result(timeout=0) is None  # flying: taken over, not armed
    assert link.arms == 1


def test_a_take_off_without_the_vehicle_times_out():
    link = FakeLink(CONFIG, up=False)
    future = link.arm_and_takeoff(timeout_s=2.0)
    link.advance(2.5)
    assert isinstance(future.exception(timeout=0), TimeoutError)
    assert link.state().takeoff.startswith("failed") and link.arms == 0


def test_a_lost_link_stops_the_stream_and_its_return_resumes_it():
    link = FakeLink(CONFIG, position_m=(100.0, 100.0, 50.0))
    link.set_target((200.0, 100.0, 50.0))
    link.set_link(False)
    state = link.state()
    assert state.link == "link_lost" and not state.streaming
    link.advance(1.0)
    assert link.state().position_m == (100.0, 100.0, 50.0)
    link.set_link(True)
    link.advance(1.0)
    assert link.state().position_m == pytest.approx((110.0, 100.0, 50.0))
    assert link.counters["reconnects"] == 1


def test_in_real_time_it_moves_on_its_own():
    link = FakeLink(CONFIG, position_m=(100.0, 100.0, 50.0), speed_mps=50.0, realtime=True)
    with link:
        link.set_target((110.0, 100.0, 50.0))
        wait_for(
            lambda: link.state().position_m == pytest.approx((110.0, 100.0, 50.0)),
            5.0,
            message="the vehicle at its target",
        )
