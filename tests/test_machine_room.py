"""The machine room (tests/machine_room.py): while a ``timing`` test holds the gate, one other
test at a time runs beside it, and it starts only once the tests already inside have ended; with
the gate free, every test goes on."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from tests.machine_room import MachineRoom

WAIT_S = 10.0


def test_beside_a_timing_test_one_other_test_at_a_time(tmp_path: Path) -> None:
    timing, first, second = (MachineRoom(tmp_path) for _ in range(3))
    second_in = threading.Event()
    try:
        timing.enter_alone()
        first.enter()  # the companion seat is free: in at once
        assert first.held == "companion"

        def come_in() -> None:
            second.enter()
            second_in.set()

        threading.Thread(target=come_in, daemon=True).start()
        assert not second_in.wait(0.5)  # the seat is taken
        first.leave()
        assert second_in.wait(WAIT_S)  # the seat, given back, is the next one's
        assert second.held == "companion"
        second.leave()
        timing.leave()
        for room in (first, second):  # the gate free: no seat needed
            room.enter()
            assert room.held == "inside"
    finally:
        for room in (timing, first, second):
            room.close()


def test_without_a_timing_test_every_test_goes_on(tmp_path: Path) -> None:
    rooms = [MachineRoom(tmp_path) for _ in range(4)]
    entered = threading.Event()

    def enter_all() -> None:
        for room in rooms:
            room.enter()
        entered.set()

    try:
        threading.Thread(target=enter_all, daemon=True).start()
        assert entered.wait(WAIT_S), "a test waited with no timing test running"
        assert [room.held for room in rooms] == ["inside"] * 4
    finally:
        for room in rooms:
            room.close()


def test_a_timing_test_keeps_its_gate_and_a_worker_waits_no_longer_than_its_limit(
    tmp_path: Path,
) -> None:
    timing, seated, waiting = MachineRoom(tmp_path), MachineRoom(tmp_path), MachineRoom(tmp_path)
    waiting.max_wait_s = 0.2
    try:
        timing.enter_alone()
        timing.enter_alone()  # the next timing test on the same worker: held already
        seated.enter()
        with pytest.raises(RuntimeError, match="machine room"):
            waiting.enter()  # the gate and the seat taken
        assert waiting.held is None
    finally:
        for room in (timing, seated, waiting):
            room.close()


def test_a_timing_test_starts_once_the_tests_already_inside_have_ended(tmp_path: Path) -> None:
    inside, timing, newcomer = MachineRoom(tmp_path), MachineRoom(tmp_path), MachineRoom(tmp_path)
    started = threading.Event()

    def start_timing() -> None:
        timing.enter_alone()
        started.set()

    try:
        inside.enter()
        assert inside.held == "inside"
        threading.Thread(target=start_timing, daemon=True).start()
        assert not started.wait(0.5)  # a test is still inside
        newcomer.enter()  # the gate is taken: the newcomer gets the companion seat
        assert newcomer.held == "companion"
        inside.leave()
        assert started.wait(WAIT_S)  # the one inside ended: the timing test goes on
        assert timing.held == "gate"
    finally:
        for room in (inside, timing, newcomer):
            room.close()


def test_a_timing_test_waits_for_the_tests_inside_no_longer_than_its_limit(
    tmp_path: Path,
) -> None:
    inside, timing, later = MachineRoom(tmp_path), MachineRoom(tmp_path), MachineRoom(tmp_path)
    timing.max_wait_s = 0.2
    try:
        inside.enter()
        with pytest.raises(RuntimeError, match="the tests inside"):
            timing.enter_alone()
        assert timing.held is None
        later.enter()  # the gate was given back: in as usual
        assert later.held == "inside"
    finally:
        for room in (inside, timing, later):
            room.close()
