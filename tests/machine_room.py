"""While a test that measures timing under load runs, at most one other test runs beside it.

``make test`` runs more pytest-xdist workers than the machine has cores (most tests wait rather
than compute). The ``timing`` group's tests (:mod:`tests.tiers`: the fault tests, the hostile
clients, the MAVLink sprays) assert latencies — a ``/healthz`` p99 during a flood, a recovery
within seconds — written for a machine shared with one other test (one worker per core on two
cores), not with three. Their xdist group keeps them off each other; this keeps the rest of the
run to one test beside them:

* a worker running a ``timing`` test holds the *gate* (from its setup to its teardown, kept
  from one ``timing`` test to the next on the same worker, given back before any other test),
  and before its test starts it waits for the tests already *inside* to end;
* a worker about to run another test looks at the gate: free, it goes inside (a shared lock
  that the ``timing`` test waits on); held, it waits for the one *companion* seat, and holds
  that seat for its test.

So a ``timing`` test runs beside at most the one companion, whatever the number of workers. The
locks are ``flock`` locks on three files in a folder the xdist controller makes for the run
(:data:`ROOM_ENV` names it to the workers) and removes at its end; a worker that dies gives its
locks back with its process. Without xdist, or with one worker, nothing is locked.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Literal

ROOM_ENV = "TUPA_TEST_ROOM"
"""The environment variable that gives the workers the folder of the run's lock files."""

EXCLUSIVE_GROUP = "timing"
"""The xdist group whose tests keep the rest of the run to one companion."""

POLL_S = 0.05
"""How often a waiting worker looks at the gate and the companion seat again."""

MAX_WAIT_S = 3600.0
"""A worker that has waited this long for the gate or the seat gives up (RuntimeError)."""

Held = Literal["gate", "companion", "inside"]


class MachineRoom:
    """One worker's side: :meth:`enter_alone` or :meth:`enter` before a test, :meth:`leave`
    after."""

    def __init__(self, folder: Path, max_wait_s: float = MAX_WAIT_S) -> None:
        self.max_wait_s = max_wait_s
        self._gate: IO[str] = open(folder / "gate.lock", "a+")  # noqa: SIM115 (held open)
        self._inside: IO[str] = open(folder / "inside.lock", "a+")  # noqa: SIM115
        self._companion: IO[str] = open(folder / "companion.lock", "a+")  # noqa: SIM115
        self.held: Held | None = None

    def enter_alone(self) -> None:
        """Take the gate for a ``timing`` test (nothing if held already), then wait for the
        tests already inside to end (RuntimeError after ``max_wait_s``)."""
        if self.held == "gate":
            return
        self.leave()
        fcntl.flock(self._gate, fcntl.LOCK_EX)
        try:
            self._wait_for(lambda: _try_lock(self._inside, fcntl.LOCK_EX), "the tests inside")
        except BaseException:
            fcntl.flock(self._gate, fcntl.LOCK_UN)
            raise
        self.held = "gate"

    def enter(self) -> None:
        """Before any other test: go inside while the gate is free; while it is held, wait for
        the companion seat and hold it (RuntimeError after ``max_wait_s``)."""
        self.leave()
        self._wait_for(self._try_enter, "the machine room")

    def _try_enter(self) -> bool:
        if _try_lock(self._gate, fcntl.LOCK_SH):
            # No timing test holds the gate, so none holds the inside lock either (it is taken
            # only under the gate): the shared lock is free now.
            inside = _try_lock(self._inside, fcntl.LOCK_SH)
            fcntl.flock(self._gate, fcntl.LOCK_UN)  # only looked
            if inside:
                self.held = "inside"
                return True
            return False
        if _try_lock(self._companion, fcntl.LOCK_EX):
            self.held = "companion"
            return True
        return False

    def _wait_for(self, taken: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + self.max_wait_s
        while not taken():
            if time.monotonic() >= deadline:
                raise RuntimeError(f"waited {self.max_wait_s:.0f} s for {what}")
            time.sleep(POLL_S)

    def leave(self) -> None:
        """Give back the gate, the inside lock or the seat, if held."""
        if self.held == "gate":
            fcntl.flock(self._inside, fcntl.LOCK_UN)
            fcntl.flock(self._gate, fcntl.LOCK_UN)
        elif self.held == "inside":
            fcntl.flock(self._inside, fcntl.LOCK_UN)
        elif self.held == "companion":
            fcntl.flock(self._companion, fcntl.LOCK_UN)
        self.held = None

    def close(self) -> None:
        self.leave()
        self._gate.close()
        self._inside.close()
        self._companion.close()


def _try_lock(file: IO[str], operation: int) -> bool:
    """``flock(file, operation)`` without waiting; whether it was given."""
    try:
        fcntl.flock(file, operation | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def room_from_environment() -> MachineRoom | None:
    """This worker's room, when the run has one (:data:`ROOM_ENV` set by the controller and
    more than one worker); else None."""
    folder = os.environ.get(ROOM_ENV)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not folder or workers < 2 or "PYTEST_XDIST_WORKER" not in os.environ:
        return None
    return MachineRoom(Path(folder))
