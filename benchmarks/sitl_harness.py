"""Pieces the real-SITL benchmark drivers share (first used by ``real_px4_sitl.py``; the
ArduCopter drivers ``real_sitl_*.py`` keep their own copies of the older forms).

* :func:`ensure_private_namespace`: SITLs bind every interface, so a driver runs in a private
  network namespace with only ``lo`` up. Outside one it replaces itself (``execvp``, same pid, so
  signals still reach it) with ``unshare -n`` running the same command line plus
  ``--no-unshare``; inside one it brings ``lo`` up.
* :func:`start_child` / :func:`stop`: child processes in their own session (so that the whole
  group can be signalled) that the kernel kills if this driver dies (``PR_SET_PDEATHSIG``), and
  their orderly stop (SIGTERM to the group, SIGKILL after a grace period).
* :func:`start_serve`: ``tupa serve ... --port 0`` with a fresh token in ``TUPA_API_TOKEN``;
  the port it chose, read from its log.
* :class:`ApiPoller`: ``GET /v1/vehicle`` at 5 Hz and ``GET /metrics`` at 1 Hz in a thread: the
  latest answer, each change of who has the vehicle / mode / streaming / fence / take-off /
  route, the battery every 2 s, the counters.
* :class:`ReportPoster`: a report of fixed users every ``period_s``, answer codes counted.
* :func:`parse_serve_log`: the service's log lines that matter, timed from the run's start.
* :func:`append_run`: append one run to a JSON list under an exclusive lock.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime
import fcntl
import json
import os
import re
import secrets
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx

TUPA = Path(sys.executable).with_name("tupa")
PR_SET_PDEATHSIG = 1

METRICS_WANTED = {
    "tupa_setpoints_sent_total": "setpoints_sent",
    "tupa_vehicle_mode_requests_total": "mode_requests",
    "tupa_vehicle_battery_returns_total": "battery_returns",
    "tupa_vehicle_battery_remaining_percent": "battery_pct",
    "tupa_vehicle_control_released_total": "control_released",
}
SERVE_LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) (\w+) ([\w.]+): (.*)$")
SERVE_LOG_KEYS = re.compile(
    r"battery|reserve|return|fence|route|autopilot has|pilot has|control|GUIDED|OFFBOARD|"
    r"take-off|airborne|failsafe|link lost|link up|stream|WARNING|ERROR",
    re.I,
)


# ---------------------------------------------------------------------- the namespace


def only_loopback() -> str | None:
    """Why this is not a private network namespace with ``lo`` up, or None when it is."""
    names = [name for _, name in socket.if_nameindex()]
    if names != ["lo"]:
        return f"network interfaces {names}: run inside `unshare -n` (only lo)"
    if not _lo_up():
        return "lo is down: `ip link set lo up` first"
    return None


def _lo_up() -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        flags = struct.unpack("16sH", fcntl.ioctl(s, 0x8913, struct.pack("16sH", b"lo", 0)))[1]
    return bool(flags & 1)  # IFF_UP


def ensure_private_namespace(no_unshare: bool) -> str | None:
    """Make sure this process runs in a private network namespace with only ``lo``, up.

    Outside one: with ``no_unshare`` return why not (the caller refuses); else replace this
    process with ``unshare -n`` running the same command line plus ``--no-unshare`` (never
    returns). Inside one: bring ``lo`` up if it is down; None."""
    names = [name for _, name in socket.if_nameindex()]
    if names != ["lo"]:
        if no_unshare or not shutil.which("unshare"):
            return f"network interfaces {names}: run inside `unshare -n` (only lo)"
        sys.stdout.flush()
        sys.stderr.flush()
        argv = ["unshare", "-n", sys.executable, *sys.argv, "--no-unshare"]
        os.execvp("unshare", argv)
    if not _lo_up():
        subprocess.run(["ip", "link", "set", "lo", "up"], check=True, timeout=10)
    return only_loopback()


# ---------------------------------------------------------------------- processes


def _child_setup() -> None:
    """In the child, before exec: its own session, and SIGKILL when this driver dies."""
    os.setsid()
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def start_child(
    cmd: Sequence[str], log: Any, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.Popen:
    """Start ``cmd`` (stdout and stderr to the open file ``log``) in its own session, killed by
    the kernel if this process dies. Call from the main thread (the death signal follows the
    thread that forked)."""
    return subprocess.Popen(
        list(cmd),
        cwd=cwd,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        preexec_fn=_child_setup,  # called from the main thread (see above)
    )


def stop(proc: subprocess.Popen | None, grace_s: float = 15.0) -> int | None:
    """SIGCONT + SIGTERM to the process's group, SIGKILL after ``grace_s``; its exit status."""
    if proc is None:
        return None
    if proc.poll() is not None:
        return proc.returncode
    try:
        os.killpg(proc.pid, signal.SIGCONT)
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return proc.wait(5)
    try:
        return proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        return proc.wait(5)


# ---------------------------------------------------------------------- tupa serve


def start_serve(
    args: Sequence[str], log_path: Path, extra_env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, str, dict[str, str], str]:
    """``tupa serve ARGS --port 0`` with a fresh token (``TUPA_API_TOKEN``), its output in
    ``log_path``: (process, the token, the auth headers, the command line as run, from
    ``tupa``). Use :func:`wait_for_port` for its port."""
    token = secrets.token_urlsafe(24)
    env = {**os.environ, "TUPA_API_TOKEN": token, **(extra_env or {})}
    cmd = [str(TUPA), "serve", *args, "--port", "0"]
    log = open(log_path, "w")  # noqa: SIM115 (the child keeps it)
    try:
        proc = start_child(cmd, log, env=env)
    finally:
        log.close()
    shown = " ".join(["tupa", *cmd[1:]])
    return proc, token, {"Authorization": f"Bearer {token}"}, shown


def wait_for_port(proc: subprocess.Popen, log_path: Path, timeout_s: float = 60.0) -> int | None:
    """The port ``tupa serve`` says it listens on (its log), or None if it ended or never said."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = re.search(
            r"listening on http://127\.0\.0\.1:(\d+)", log_path.read_text(errors="replace")
        )
        if found:
            return int(found.group(1))
        if proc.poll() is not None:
            return None
        time.sleep(0.2)
    return None


def parse_serve_log(
    path: Path, t0_wall: float, keys: re.Pattern[str] = SERVE_LOG_KEYS
) -> list[dict[str, Any]]:
    """The service's log lines that match ``keys`` (HTTP access lines and the vehicle's own
    ``vehicle says`` echo left out), with their time from ``t0_wall``."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        if "HTTP/1.1" in line:
            continue
        found = SERVE_LOG_TIME.match(line)
        if found is None:
            continue
        stamp, level, logger, text = found.groups()
        if not keys.search(text):
            continue
        wall = datetime.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()
        out.append({"t": round(wall - t0_wall, 2), "level": level, "logger": logger, "text": text})
    return out


# ---------------------------------------------------------------------- the API


class ApiPoller:
    """``GET /v1/vehicle`` at 5 Hz and ``GET /metrics`` at 1 Hz, in a thread (times from
    ``t0``, a ``time.monotonic()``): the latest answer, each change of who has the vehicle /
    mode / armed / streaming / fence / take-off / route kind (``timeline``), each new route
    (``routes``), the battery every 2 s, the metrics' counters (``metrics``)."""

    def __init__(self, base: str, headers: dict[str, str], t0: float, echo: bool = True) -> None:
        self.t0 = t0
        self.echo = echo
        self.client = httpx.Client(base_url=base, headers=headers, timeout=5.0)
        self.halt = threading.Event()
        self.lock = threading.Lock()
        self.latest: dict[str, Any] | None = None
        self.latest_t = 0.0
        self.timeline: list[dict[str, Any]] = []
        self.battery: list[dict[str, Any]] = []
        self.routes: list[dict[str, Any]] = []
        self.metrics: list[dict[str, Any]] = []
        self.errors = 0
        self.thread = threading.Thread(target=self._run, name="api-poller", daemon=True)
        self.thread.start()

    def _now(self) -> float:
        return round(time.monotonic() - self.t0, 2)

    def _run(self) -> None:
        last_key = last_route = None
        next_metrics = next_battery = 0.0
        while not self.halt.is_set():
            t = self._now()
            try:
                v = self.client.get("/v1/vehicle").json()
                if not isinstance(v.get("control"), dict):  # a 401/503 body
                    raise ValueError("not a vehicle")
            except (httpx.HTTPError, ValueError, KeyError, TypeError):
                self.errors += 1
                self.halt.wait(0.2)
                continue
            route = v.get("route") or {}
            key = (
                v["control"]["holder"],
                v["control"]["reason"],
                v.get("mode"),
                v.get("armed"),
                v.get("streaming"),
                v.get("fence"),
                v["takeoff"]["state"],
                route.get("kind"),
            )
            with self.lock:
                self.latest, self.latest_t = v, t
                if key != last_key:
                    last_key = key
                    self.timeline.append(
                        {
                            "t": t,
                            "holder": key[0],
                            "reason": key[1],
                            "mode": key[2],
                            "armed": key[3],
                            "streaming": key[4],
                            "fence": key[5],
                            "takeoff": key[6],
                            "route_kind": key[7],
                            "position": v.get("position"),
                            "battery": v.get("battery"),
                        }
                    )
                    if self.echo:
                        print(
                            f"{t:7.2f} service: {key[0]} ({key[1]}) mode {key[2]} armed {key[3]} "
                            f"streaming {key[4]} fence {key[5]!r} take-off {key[6]} "
                            f"route {key[7]}",
                            flush=True,
                        )
                route_key = (
                    route.get("kind"),
                    route.get("hold_reason"),
                    len(route.get("waypoints") or []),
                )
                if route and route_key != last_route:
                    last_route = route_key
                    self.routes.append({"t": t, **route})
                if t >= next_battery and v.get("battery"):
                    self.battery.append({"t": t, "control": key[0], **v["battery"]})
                    next_battery = t + 2.0
            if t >= next_metrics:
                sample = self._metrics(t)
                with self.lock:
                    self.metrics.append(sample)
                next_metrics = t + 1.0
            self.halt.wait(0.2)
        self.client.close()

    def _metrics(self, t: float) -> dict[str, Any]:
        sample: dict[str, Any] = {"t": t}
        try:
            text = self.client.get("/metrics").text
        except httpx.HTTPError:
            return sample
        for line in text.splitlines():
            if line.startswith("#") or " " not in line:
                continue
            name, _, value = line.rpartition(" ")
            base = name.split("{", 1)[0]
            if base in METRICS_WANTED:
                with contextlib.suppress(ValueError):
                    key = METRICS_WANTED[base]
                    sample[key] = sample.get(key, 0.0) + float(value)
        return sample

    def snapshot(self) -> tuple[dict[str, Any] | None, float]:
        with self.lock:
            return self.latest, self.latest_t

    def close(self) -> None:
        self.halt.set()
        self.thread.join(5)


class ReportPoster:
    """POST /v1/reports of ``users`` (id, x_m, y_m, offered_bps) every ``period_s``, in a
    thread; each answer's status code counted (``codes``)."""

    def __init__(
        self, base: str, headers: dict[str, str], users: Sequence[dict[str, Any]], period_s: float
    ) -> None:
        self.base, self.headers, self.users, self.period_s = base, headers, users, period_s
        self.halt = threading.Event()
        self.codes: dict[str, int] = {}
        self.thread = threading.Thread(target=self._run, name="reports", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        client = httpx.Client(base_url=self.base, headers=self.headers, timeout=5.0)
        while not self.halt.is_set():
            users = [
                {**u, "throughput_bps": u["offered_bps"] * 0.8, "delay_s": 0.05, "plr": 0.01}
                for u in self.users
            ]
            try:
                r = client.post("/v1/reports", json={"timestamp": time.time(), "users": users})
                code = str(r.status_code)
            except httpx.HTTPError as exc:
                code = type(exc).__name__
            self.codes[code] = self.codes.get(code, 0) + 1
            self.halt.wait(self.period_s)
        client.close()

    def close(self) -> None:
        self.halt.set()
        self.thread.join(5)


# ---------------------------------------------------------------------- results


def append_run(path: Path, run: dict[str, Any]) -> None:
    """Append to the JSON list at ``path`` under an exclusive lock (runs may end together)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.seek(0)
        text = f.read()
        runs = json.loads(text) if text.strip() else []
        runs.append(run)
        f.seek(0)
        f.truncate()
        f.write(json.dumps(runs, indent=1))
