"""A network controller played by the embedded simulator, for the demo and end-to-end tests.

Every step it reads the vehicle's *true* position from the autopilot over MAVLink (a second
client beside the service: the autopilot, not the service, says where the vehicle is), computes
every user's throughput, delay and loss there with :class:`sim.network.NetworkModel` (queues
carry over from step to step, as in the environments), and POSTs them to the service as one
report. ``tupa controller-sim`` runs it on its own (docker-compose's ``controller-sim``).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np

from service.frames import FrameConfig, ned_to_area
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.network import NetworkModel, QueueState
from sim.scenarios import Scenario
from sim.users import UserDynamics
from sim.utility import network_utility
from sim.world import Demand, Mobility

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil


class TruePosition:
    """The vehicle's position as the autopilot reports it (LOCAL_POSITION_NED), area frame.

    Asks system ``system_id`` for LOCAL_POSITION_NED at ``rate_hz`` (ArduPilot sends nothing
    until asked) and keeps the latest one it sends; :meth:`wait` blocks until a position is
    known or the time is up (``TimeoutError`` naming the autopilot, and why it could not be
    reached when it refused the connection). A fleet's vehicles have system ids 1..K, each read
    by its own instance with its own ``frames`` (every vehicle has its own home);
    ``system_id=None`` asks every system (broadcast) and keeps any system's position.
    """

    def __init__(
        self,
        url: str,
        frames: FrameConfig | None = None,
        rate_hz: float = 10.0,
        *,
        system_id: int | None = 1,
    ) -> None:
        if system_id is not None and not 1 <= system_id <= 255:
            raise InputError(f"system_id: must be in 1..255, got {system_id}")
        self.url = url
        self.frames = frames or FrameConfig()
        self.rate_hz = rate_hz
        self.system_id = system_id
        self._conn: Any = None
        self._position: tuple[float, float, float] | None = None
        self._refusal: str | None = None  # why the last try to connect failed
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"true-position-{system_id or url}", daemon=True
        )

    def start(self) -> TruePosition:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        if self._conn is not None:
            self._conn.close()

    def latest(self) -> tuple[float, float, float] | None:
        with self._cond:
            return self._position

    def wait(self, timeout_s: float) -> tuple[float, float, float]:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._position is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    why = f" ({self._refusal.lower()})" if self._refusal else ""
                    raise TimeoutError(f"no position from the autopilot at {self.url}{why}")
                self._cond.wait(remaining)
            return self._position

    def _connect(self) -> bool:
        """Open the connection, trying again every second while the autopilot refuses it (it
        may still be starting); False once closed before it opened."""
        while not self._stop.is_set():
            try:
                self._conn = mavutil.mavlink_connection(
                    self.url, source_system=254, source_component=190, autoreconnect=True
                )
                return True
            except OSError as exc:  # refused, unreachable: the reason goes into wait()'s error
                self._refusal = exc.strerror or str(exc)
                self._stop.wait(1.0)
        return False

    def _run(self) -> None:
        if not self._connect():
            return
        interval_us = int(1e6 / self.rate_hz)
        asked_at = -1e9
        while not self._stop.is_set():
            now = time.monotonic()
            if (now - asked_at > 2.0 and self._position is None) or now - asked_at > 10.0:
                self._conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, 8, 0, 0, 0)
                self._conn.mav.command_long_send(
                    self.system_id or 0,
                    1,
                    mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    0,
                    mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                    interval_us,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
                asked_at = now
            message = self._conn.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=0.2)
            if message is not None and self.system_id in (None, message.get_srcSystem()):
                position = ned_to_area(message.x, message.y, message.z, self.frames)
                with self._cond:
                    self._position = position
                    self._cond.notify_all()


@dataclass
class SimulatedNetwork:
    """One scenario's users, measured wherever the vehicle is (queues carry over)."""

    scenario: Scenario
    network: NetworkConfig = field(default_factory=NetworkConfig)
    area: AreaConfig = field(default_factory=AreaConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    seed: int = 0
    mobility: Mobility = field(default_factory=Mobility)
    """How the users move (static by default); a world's ``mobility``."""
    demand: Demand = field(default_factory=Demand)
    users_seed: int = 0
    """Seeds the users' motion and demand: the environment's ``options["users_seed"]``."""

    def __post_init__(self) -> None:
        self.model = NetworkModel(self.network, self.area)
        self.rng = np.random.default_rng(self.seed)
        self._users_rng = np.random.default_rng(self.users_seed)
        self.users = UserDynamics(
            self.scenario.users_xy_m, self.scenario.load_bps, self.mobility, self.demand,
            self.area, self._users_rng,
        )  # fmt: skip
        self._queues: QueueState | None = None
        self._steps = 0

    def measure(self, uav_xyz_m: np.ndarray, step_s: float = 1.0) -> dict[str, Any]:
        """Simulate ``step_s`` with the UAV at ``uav_xyz_m``: per-user metrics and the utility.
        The users move (and change their demand) by one step first, except on the first call."""
        if self._steps:
            self.users.advance(step_s, self._users_rng)
        self._steps += 1
        load = self.users.load_bps
        result = self.model.step(
            np.asarray(uav_xyz_m, dtype=float)[None, :],
            self.users.xy_m,
            load,
            self._queues,
            self.rng,
            step_s,
        )
        self._queues = result.state
        throughput, delay, plr = result.throughput_bps[0], result.delay_s[0], result.plr[0]
        utility = float(network_utility(throughput, delay, plr, load, self.utility))
        return {"throughput_bps": throughput, "delay_s": delay, "plr": plr, "utility": utility}

    def report(self, metrics: dict[str, Any], timestamp_s: float) -> dict[str, Any]:
        """The ``POST /v1/reports`` body for ``metrics``."""
        return report_body(
            self.users.xy_m,
            self.users.load_bps,
            metrics["throughput_bps"],
            metrics["delay_s"],
            metrics["plr"],
            timestamp_s,
        )


def report_body(
    xy_m: np.ndarray,
    offered_bps: np.ndarray,
    throughput_bps: np.ndarray,
    delay_s: np.ndarray,
    plr: np.ndarray,
    timestamp_s: float,
) -> dict[str, Any]:
    """A ``POST /v1/reports`` body: user ``i`` is ``ue-{i + 1}`` (the same ids every step)."""
    users = [
        {
            "id": f"ue-{i + 1}",
            "x_m": float(xy[0]),
            "y_m": float(xy[1]),
            "offered_bps": float(offered_bps[i]),
            "throughput_bps": float(throughput_bps[i]),
            "delay_s": float(delay_s[i]),
            "plr": float(plr[i]),
        }
        for i, xy in enumerate(xy_m)
    ]
    return {"timestamp": timestamp_s, "users": users}


@dataclass
class StepRecord:
    step: int
    position_m: tuple[float, float, float]
    target_m: tuple[float, float, float] | None
    utility: float
    users_xy_m: list[list[float]] = field(default_factory=list)


def run_scenario(
    network: SimulatedNetwork,
    vehicle: TruePosition,
    client: httpx.Client,
    steps: int,
    step_s: float = 1.0,
    on_step: Any = None,
) -> list[StepRecord]:
    """Play ``steps`` steps in real time: measure at the true position, POST, wait for the tick.

    ``client`` carries the service's base URL and token. Raises ``httpx.HTTPStatusError`` when
    the service refuses a report.
    """
    records: list[StepRecord] = []
    next_at = time.monotonic()
    for step in range(steps):
        position = vehicle.wait(timeout_s=30.0)
        metrics = network.measure(np.asarray(position), step_s)
        response = client.post("/v1/reports", json=network.report(metrics, time.time()))
        response.raise_for_status()
        target = response.json()["target"]
        target_m = (target["x_m"], target["y_m"], target["z_m"]) if target else None
        users = network.users.xy_m.tolist()
        record = StepRecord(step, position, target_m, metrics["utility"], users)
        records.append(record)
        if on_step is not None:
            on_step(record)
        next_at += step_s
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # the controller's reporting period (real time), not a wait-and-hope
        else:
            next_at = time.monotonic()
    return records
