"""Degraded mode, flown: a fleet of K mock autopilots (one process each) under ``tupa serve
--fleet-file``; one vehicle's link is lost (its process frozen with SIGSTOP), later it returns.

Measures, from the service's own API (``GET /v1/vehicles``, polled at 10 Hz):

* how long until the service calls the link lost (its heartbeat timeout, 3 s), and until the
  fleet re-places for K - 1 vehicles (in decision periods after the loss was detected);
* the utility of where the K - 1 flying vehicles *are* (the fleet network model's episode
  utility, :meth:`policies.placements.fleet_oracle.FleetOracle.score`, with the decision period as
  the model's step, as the service's world has it) against the search oracle's for
  K - 1 vehicles over the same users, and when it comes within 0.02 of it; the same for where
  their targets are (what the policy chose, before flight time);
* how long until the returning vehicle is commanded again, and the utility with K once more.

Target (issue 16): after one vehicle of K is lost, utility back within 0.02 of the search
oracle for K - 1 within 3 decision periods. Flight time counts: a vehicle 150 m from its new
target needs 15 s at the mock's default 10 m/s, so with 1-s periods the flown utility cannot
meet it unless the others are near their new places; the JSON reports both clocks.

    python benchmarks/fleet_degraded.py                      # K = 3, 30 users, kmeans-load-weighted
    python benchmarks/fleet_degraded.py --policy fleet-oracle --step-s 8
Writes benchmarks/results/fleet_degraded_POLICY.json.
"""

from __future__ import annotations

import argparse
import json
import secrets
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
# First on the path: run as a script, this folder comes first, and its closed_loop.py (the
# closed-loop benchmark) would shadow the closed_loop package.
sys.path.insert(0, str(REPO))

from closed_loop.processes import (  # noqa: E402
    TupaProcess,
    mock_fleet_file,
    start_mock_fleet,
    start_service,
)
from policies.interface import ReportedUsers  # noqa: E402
from policies.placements.fleet_oracle import FleetOracle, FleetOracleConfig  # noqa: E402
from service.frames import FrameConfig, GeoPoint  # noqa: E402
from sim.fleet import FleetConfig  # noqa: E402
from sim.world import get_world  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
PX4_HOME = GeoPoint(47.397742, 8.545594, 488.0)  # the PX4 flavour's SITL home
FRAMES = FrameConfig(-250.0, -250.0)  # the first vehicle's home at the area's centre
WITHIN = 0.02


def hot_spot_users(k: int, n_users: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_users`` around ``k`` hot spots on a circle of radius 160 m about the centre, loads
    1–8 Mbit/s (the first spot's users four times heavier)."""
    rng = np.random.default_rng(seed)
    angles = 2 * np.pi * (np.arange(k) / k + 0.125)
    centres = 250.0 + 160.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    spot = np.arange(n_users) % k
    xy = np.clip(centres[spot] + rng.normal(0.0, 20.0, (n_users, 2)), 0.0, 500.0)
    load = rng.uniform(1e6, 8e6, n_users) * np.where(spot == 0, 4.0, 1.0)
    return xy, load


def report(xy: np.ndarray, load: np.ndarray) -> dict[str, Any]:
    users = [
        {"id": f"u{i}", "x_m": float(x), "y_m": float(y), "offered_bps": float(b),
         "throughput_bps": float(b), "delay_s": 0.01, "plr": 0.0}
        for i, ((x, y), b) in enumerate(zip(xy, load, strict=True))
    ]  # fmt: skip
    return {"timestamp": time.time(), "users": users}


class Reporter:
    """POSTs the users' report every ``period_s`` on a thread, as a network controller would."""

    def __init__(self, client: httpx.Client, xy: np.ndarray, load: np.ndarray, period_s: float):
        self.client, self.xy, self.load, self.period_s = client, xy, load, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Reporter:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.client.post("/v1/reports", json=report(self.xy, self.load))
            self._stop.wait(self.period_s)


def poll(client: httpx.Client) -> dict[str, dict[str, Any]]:
    return {v["id"]: v for v in client.get("/v1/vehicles").json()["vehicles"]}


def positions(vehicles: dict[str, dict[str, Any]], ids: list[str], key: str) -> np.ndarray | None:
    """(len(ids), 3) of each vehicle's position (``key="position"``) or target; None if any
    is missing."""
    rows = []
    for vid in ids:
        v = vehicles[vid]
        point = v["vehicle"]["position"] if key == "position" else v["setpoint"]["target"]
        if point is None:
            return None
        rows.append((point["x_m"], point["y_m"], point["z_m"]))
    return np.array(rows)


def settled(vehicles: dict[str, dict[str, Any]], ids: list[str], tol_m: float = 3.0) -> bool:
    here, there = positions(vehicles, ids, "position"), positions(vehicles, ids, "target")
    return (
        here is not None
        and there is not None
        and all(vehicles[v]["commanded"] for v in ids)
        and bool(np.all(np.linalg.norm(here - there, axis=1) < tol_m))
    )


def wait(
    predicate: Any, client: httpx.Client, timeout_s: float, what: str
) -> tuple[float, dict[str, dict[str, Any]]]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        vehicles = poll(client)
        if predicate(vehicles):
            return time.monotonic(), vehicles
        time.sleep(0.1)
    raise TimeoutError(f"{what}: not within {timeout_s:.0f} s")


def run(args: argparse.Namespace) -> dict[str, Any]:
    k = args.uavs
    world = get_world("closed-loop")
    xy, load = hot_spot_users(k, args.users, args.seed)
    users = ReportedUsers(xy, load)
    # Scored in the service's world: its decision period is the model's step.
    config = FleetOracleConfig(step_s=args.step_s)
    oracles = {
        n: FleetOracle(FleetConfig(n_uavs=n), world.area, world.network, world.utility, config)
        for n in (k - 1, k)
    }
    started = time.perf_counter()
    best = {n: oracle.search(users).utility for n, oracle in oracles.items()}
    oracle_s = time.perf_counter() - started
    ids = [f"uav{i + 1}" for i in range(k)]
    lost_id = ids[1]
    flying = [v for v in ids if v != lost_id]
    token = secrets.token_urlsafe(16)
    processes: list[TupaProcess] = []
    with tempfile.TemporaryDirectory() as tmp:
        try:
            mocks = start_mock_fleet(
                k,
                PX4_HOME,
                ["--flavour", "px4", "--ready-delay-s", "1", "--speed-mps", str(args.speed_mps)],
            )
            processes += [p for p, _ in mocks]
            fleet_file = Path(tmp) / "fleet.yaml"
            fleet_file.write_text(yaml.safe_dump(mock_fleet_file([p for _, p in mocks], FRAMES)))
            service, port = start_service(
                ["--fleet-file", str(fleet_file), "--policy", args.policy, "--port", "0",
                 "--arm-and-takeoff", "--step-s", str(args.step_s)],
                env={"TUPA_API_TOKEN": token},
            )  # fmt: skip
            processes.append(service)
            with (
                httpx.Client(
                    base_url=f"http://127.0.0.1:{port}",
                    headers={"Authorization": f"Bearer {token}"},
                    timeout=30.0,
                ) as client,
                Reporter(client, xy, load, args.step_s),
            ):
                _, full = wait(lambda v: settled(v, ids), client, 240.0, "the fleet in place")
                full_utility = float(
                    oracles[k].score(positions(full, ids, "position")[None], users)[0]
                )
                print(f"{k} vehicles in place: utility {full_utility:.4f} "
                      f"(oracle for {k}: {best[k]:.4f})")  # fmt: skip

                frozen = mocks[1][0]
                frozen.proc.send_signal(signal.SIGSTOP)
                t_freeze = time.monotonic()
                t_lost, _ = wait(
                    lambda v: v[lost_id]["vehicle"]["link"] == "link_lost", client, 30.0, "loss"
                )
                # Re-placed: the first decision without it (its id leaves the targets).
                deadline = time.monotonic() + 30.0
                while lost_id in client.get("/v1/setpoint").json()["targets"]:
                    if time.monotonic() > deadline:
                        raise TimeoutError("re-placed: not within 30 s")
                    time.sleep(0.05)
                t_replaced, replaced = time.monotonic(), poll(client)
                target_utility = float(
                    oracles[k - 1].score(positions(replaced, flying, "target")[None], users)[0]
                )
                trace = []
                t_within = None
                deadline = time.monotonic() + args.degraded_s
                while time.monotonic() < deadline:
                    vehicles = poll(client)
                    here = positions(vehicles, flying, "position")
                    now = time.monotonic()
                    if here is not None:
                        value = float(oracles[k - 1].score(here[None], users)[0])
                        trace.append((round(now - t_lost, 2), round(value, 4)))
                        if t_within is None and value >= best[k - 1] - WITHIN:
                            t_within = now
                    if t_within is not None and settled(vehicles, flying):
                        break
                    time.sleep(0.2)
                _, degraded = wait(lambda v: settled(v, flying), client, 120.0, "K-1 in place")
                degraded_utility = float(
                    oracles[k - 1].score(positions(degraded, flying, "position")[None], users)[0]
                )
                frozen.proc.send_signal(signal.SIGCONT)
                t_resume = time.monotonic()
                t_rejoin, _ = wait(lambda v: v[lost_id]["commanded"], client, 60.0, "rejoin")
                _, back = wait(lambda v: settled(v, ids), client, 120.0, "K in place again")
                back_utility = float(
                    oracles[k].score(positions(back, ids, "position")[None], users)[0]
                )
        finally:
            for process in reversed(processes):
                process.stop()
    period = args.step_s

    def periods(seconds: float | None) -> float | None:
        return None if seconds is None else round(seconds / period, 2)

    return {
        "command": " ".join(sys.argv),
        "uavs": k,
        "users": args.users,
        "policy": args.policy,
        "decision_period_s": period,
        "speed_mps": args.speed_mps,
        "oracle_search_s": round(oracle_s, 2),
        "utility": {
            "oracle_k": round(best[k], 4),
            "oracle_k_minus_1": round(best[k - 1], 4),
            "flown_k_before_loss": round(full_utility, 4),
            "targets_k_minus_1_at_replacement": round(target_utility, 4),
            "flown_k_minus_1_settled": round(degraded_utility, 4),
            "flown_k_after_rejoin": round(back_utility, 4),
        },
        "seconds": {
            "freeze_to_link_lost": round(t_lost - t_freeze, 2),
            "link_lost_to_replaced": round(t_replaced - t_lost, 2),
            "link_lost_to_within_0_02": None if t_within is None else round(t_within - t_lost, 2),
            "resume_to_rejoined": round(t_rejoin - t_resume, 2),
        },
        "decision_periods_after_link_lost": {
            "replaced": periods(t_replaced - t_lost),
            "within_0_02_flown": periods(None if t_within is None else t_within - t_lost),
            "targets_within_0_02": target_utility >= best[k - 1] - WITHIN,
        },
        "trace_k_minus_1": trace,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uavs", type=int, default=3)
    parser.add_argument("--users", type=int, default=30)
    parser.add_argument("--policy", default="kmeans-load-weighted")
    parser.add_argument("--step-s", type=float, default=1.0, help="decision period (default 1)")
    parser.add_argument("--speed-mps", type=float, default=10.0, help="the mocks' top speed")
    parser.add_argument("--degraded-s", type=float, default=60.0, help="longest wait with K-1")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument(
        "--out", type=Path, help="default: benchmarks/results/fleet_degraded_POLICY.json"
    )
    args = parser.parse_args()
    if not 2 <= args.uavs <= 8:
        parser.error("--uavs: must be in 2..8 (one of them is lost)")
    out = args.out or RESULTS / f"fleet_degraded_{args.policy}.json"
    result = run(args)
    print(json.dumps({k: v for k, v in result.items() if k != "trace_k_minus_1"}, indent=2))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
