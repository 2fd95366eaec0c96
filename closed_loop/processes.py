"""Child ``tupa`` processes for the demo and the end-to-end tests: start, wait for a line, stop.

A :class:`TupaProcess` runs ``python -m service.cli ARGS`` (the ``tupa`` command of the running
interpreter), collects its output in a background thread, and lets the caller wait for a line
matching a pattern (how a process says it is listening, and on which port) with a time limit.
``stop()`` sends SIGTERM, then SIGKILL after a grace period; it is safe to call twice.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence

from service.frames import FrameConfig, GeoPoint, ned_to_global


def _detach_and_die_with_parent() -> None:
    """In the child before exec: its own session (Ctrl-C in the parent's terminal does not hit
    it twice), and SIGTERM when the parent dies, however it dies (Linux ``PR_SET_PDEATHSIG``),
    so that no child outlives a killed demo or test run."""
    os.setsid()
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1


class ProcessFailedError(RuntimeError):
    """The child exited, or did not say what was awaited in time; carries its last output."""


class TupaProcess:
    """``python -m MODULE ARGS`` (by default ``service.cli``, the ``tupa`` command) as a child.

    ``cwd`` is where it runs (default: the caller's directory); a module outside the installed
    packages, such as a test helper, needs the repository root.
    """

    def __init__(
        self,
        args: Sequence[str],
        name: str,
        env: dict[str, str] | None = None,
        module: str = "service.cli",
        cwd: str | os.PathLike[str] | None = None,
    ) -> None:
        self.name = name
        self.args = [sys.executable, "-m", module, *args]
        self._lines: deque[str] = deque(maxlen=2000)
        self._cond = threading.Condition()
        child_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.proc = subprocess.Popen(
            self.args,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            cwd=cwd,
            env=child_env,
            preexec_fn=_detach_and_die_with_parent,
        )
        self._reader = threading.Thread(target=self._read, name=f"{name}-output", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self._lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def wait_for_line(self, pattern: str, timeout_s: float) -> re.Match[str]:
        """The first output line matching ``pattern`` (searched), waiting up to ``timeout_s``."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._cond:
            while True:
                lines = list(self._lines)
                for line in lines[seen:]:
                    match = regex.search(line)
                    if match:
                        return match
                seen = len(lines)
                if self.proc.poll() is not None and not self._reader.is_alive():
                    raise ProcessFailedError(
                        f"{self.name} exited with {self.proc.returncode}:\n{self.tail()}"
                    )
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ProcessFailedError(
                        f"{self.name}: no line matching {pattern!r}:\n{self.tail()}"
                    )
                self._cond.wait(min(remaining, 0.5))

    def tail(self, n: int = 30) -> str:
        with self._cond:
            return "\n".join(list(self._lines)[-n:])

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, grace_s: float = 5.0) -> int | None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(grace_s)
        self._reader.join(grace_s)
        return self.proc.returncode

    def __enter__(self) -> TupaProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_sitl_mock(args: Sequence[str], timeout_s: float = 30.0) -> tuple[TupaProcess, int]:
    """``tupa sitl-mock ARGS`` (give ``--listen tcp:127.0.0.1:0``); returns it and its port."""
    proc = TupaProcess(["sitl-mock", *args], "sitl-mock")
    try:
        match = proc.wait_for_line(r"listening on \S+:(\d+)\s*$", timeout_s)
    except ProcessFailedError:
        proc.stop()
        raise
    return proc, int(match.group(1))


def start_service(
    args: Sequence[str], env: dict[str, str] | None = None, timeout_s: float = 90.0
) -> tuple[TupaProcess, int]:
    """``tupa serve ARGS`` (give ``--port 0``); returns it once uvicorn listens, and its port."""
    proc = TupaProcess(["serve", *args], "tupa-serve", env)
    try:
        match = proc.wait_for_line(r"tupa serve listening on http://\S+:(\d+)\s*$", timeout_s)
    except ProcessFailedError:
        proc.stop()
        raise
    return proc, int(match.group(1))


def start_mock_fleet(
    count: int,
    home: GeoPoint,
    args: Sequence[str] = (),
    spacing_m: float = 15.0,
    timeout_s: float = 30.0,
) -> list[tuple[TupaProcess, int]]:
    """``count`` ``tupa sitl-mock`` processes, one per vehicle, so that one vehicle alone can be
    frozen (SIGSTOP: its link is lost) or stopped, as a real fleet loses one vehicle's link.

    Vehicle ``i`` (0-based) has system id ``i + 1``, its home ``spacing_m * i`` metres east of
    ``home`` (as ``tupa sitl-mock --vehicles`` spaces them) and a free loopback TCP port; every
    one gets ``args`` too. Returns (process, port) per vehicle; if one fails, the ones started
    are stopped. :func:`mock_fleet_file` writes the matching fleet file."""
    started: list[tuple[TupaProcess, int]] = []
    try:
        for i in range(count):
            at = ned_to_global(home, 0.0, spacing_m * i, 0.0)
            started.append(
                start_sitl_mock(
                    [
                        "--listen", "tcp:127.0.0.1:0",
                        "--system-id", str(i + 1),
                        "--home", f"{at.lat_deg:.9f},{at.lon_deg:.9f},{at.alt_amsl_m:.3f}",
                        *args,
                    ],
                    timeout_s,
                )
            )  # fmt: skip
    except BaseException:
        for process, _ in started:
            process.stop()
        raise
    return started


def mock_fleet_file(
    ports: Sequence[int], frames: FrameConfig, spacing_m: float = 15.0, separation_m: float = 10.0
) -> dict[str, object]:
    """The fleet file (as a mapping to dump as YAML or JSON) for vehicles on loopback ``ports``
    spaced as :func:`start_mock_fleet` spaces them: ``frames`` is the first vehicle's, each next
    home lies ``spacing_m`` further east, so the area's corner lies that much further west of it."""
    return {
        "separation_m": separation_m,
        "vehicles": [
            {
                "id": f"uav{i + 1}",
                "mavlink": f"tcp:127.0.0.1:{port}",
                "system_id": i + 1,
                "area_origin_north_m": frames.area_origin_north_m,
                "area_origin_east_m": frames.area_origin_east_m - spacing_m * i,
                "area_origin_down_m": frames.area_origin_down_m,
            }
            for i, port in enumerate(ports)
        ],
    }
