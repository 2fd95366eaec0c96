"""``tupa demo``: the closed loop for real: autopilot, service and network controller as processes.

1. ``tupa sitl-mock`` (PX4 flavour) on a free loopback port;
2. ``tupa serve`` against it with ``--arm-and-takeoff`` and the chosen policy (the shipped DDQN
   checkpoint by default), on a free port, with a one-time random API token;
3. the network controller, played here by the embedded simulator
   (:mod:`service.controller_sim`): every second it reads the vehicle's true position from the
   autopilot, computes every user's metrics there and POSTs them as a report.

It plays a few scenarios of increasing heterogeneity one after the other (the vehicle flies on
from wherever the previous scenario left it) and ends with a table: the utility achieved in the
loop against what ``min-distance`` and the oracle reach from the same start with the same speed
limit (the simulator's straight-line flight at the autopilot's maximum speed), and against the
policy's own final position held from the first step (what the flight cost). A PNG shows each
scenario's users and the vehicle's track.
"""

from __future__ import annotations

import secrets
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.controller_sim import SimulatedNetwork, StepRecord, TruePosition, run_scenario
from service.frames import FrameConfig
from service.processes import start_service, start_sitl_mock
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import heterogeneity_index


@dataclass(frozen=True)
class DemoConfig:
    policy: str | None = None  # None: the service's default (shipped DDQN checkpoint)
    scenarios: int = 3
    steps: int = 25
    step_s: float = 1.0
    speed_mps: float = 10.0
    seed: int = 7
    flavour: str = "px4"
    out_dir: Path = Path("runs/demo")
    queueing: str = "fq-codel"


def pick_scenarios(n: int, seed: int, area: AreaConfig) -> list[Scenario]:
    """``n`` scenarios spread over heterogeneity: quantiles of H among 200 generated ones."""
    pool = generate_scenarios(200, 3, seed=seed, area=area)
    h = np.array([heterogeneity_index(s.users_xy_m, s.load_bps, area) for s in pool])
    order = np.argsort(h)
    quantiles = np.linspace(0.2, 0.98, n) if n > 1 else np.array([0.9])
    return [pool[order[int(q * (len(pool) - 1))]] for q in quantiles]


def static_episode(
    target_m: np.ndarray,
    scenario: Scenario,
    start_m: np.ndarray,
    steps: int,
    speed_mps: float | None,
    network: NetworkConfig,
    seed: int,
) -> float:
    """Mean utility of flying from ``start_m`` to a fixed ``target_m`` and holding it."""
    from policies.evaluation import position_to_action_f64
    from sim.envs import EnvConfig, FapContinuousEnv

    area = AreaConfig()
    env = FapContinuousEnv(
        [scenario],
        EnvConfig(episode_steps=steps, max_speed_mps=speed_mps, network=network, area=area),
    )
    env.reset(seed=seed, options={"scenario": scenario, "uav_xyz_m": start_m})
    action = position_to_action_f64(np.asarray(target_m, dtype=float), area)
    return float(np.mean([env.step(action)[1] for _ in range(steps)]))


def compare(
    scenario: Scenario,
    start_m: np.ndarray,
    final_m: np.ndarray,
    cfg: DemoConfig,
    network: NetworkConfig,
    seed: int,
) -> dict[str, Any]:
    """min-distance and the oracle from the same start at the same speed; the policy's last
    target held from the first step (no flight)."""
    from policies.baselines import make_policy

    area = AreaConfig()
    out: dict[str, Any] = {}
    for name in ("min-distance", "oracle"):
        policy = make_policy(name, area, network, UtilityConfig(), episode_steps=cfg.steps)
        target = policy.place(scenario)
        out[f"{name}_target_m"] = [float(v) for v in target]
        out[name] = static_episode(
            target, scenario, start_m, cfg.steps, cfg.speed_mps, network, seed
        )
        out[f"{name}_no_flight"] = static_episode(
            target, scenario, target, cfg.steps, None, network, seed
        )
    out["policy_target_no_flight"] = static_episode(
        final_m, scenario, final_m, cfg.steps, None, network, seed
    )
    return out


def run_demo(cfg: DemoConfig) -> dict[str, Any]:
    area = AreaConfig()
    network = NetworkConfig().with_queueing(cfg.queueing)  # type: ignore[arg-type]
    scenarios = pick_scenarios(cfg.scenarios, cfg.seed, area)
    token = secrets.token_urlsafe(24)
    mock, mock_port = start_sitl_mock(
        [
            "--listen",
            "tcp:127.0.0.1:0",
            "--flavour",
            cfg.flavour,
            "--ready-delay-s",
            "2",
            "--speed-mps",
            str(cfg.speed_mps),
        ]
    )
    service = vehicle = None
    try:
        serve_args = [
            "--mavlink",
            f"tcp:127.0.0.1:{mock_port}",
            "--port",
            "0",
            "--arm-and-takeoff",
            "--step-s",
            str(cfg.step_s),
            "--log-level",
            "warning",
        ]
        if cfg.policy:
            serve_args += ["--policy", cfg.policy]
        _say(f"autopilot (sitl-mock, {cfg.flavour}) on tcp:127.0.0.1:{mock_port}")
        # Home (where the vehicle boots and takes off) at the area's centre, as the paper's
        # episodes start there: the area's south-west corner lies 250 m south and west of it.
        origin = {
            "TUPA_AREA_ORIGIN_NORTH_M": str(-area.size_y_m / 2),
            "TUPA_AREA_ORIGIN_EAST_M": str(-area.size_x_m / 2),
        }
        service, api_port = start_service(serve_args, env={"TUPA_API_TOKEN": token, **origin})
        base = f"http://127.0.0.1:{api_port}"
        _say(f"placement service on {base}")
        frames = FrameConfig(-area.size_y_m / 2, -area.size_x_m / 2)
        vehicle = TruePosition(f"tcp:127.0.0.1:{mock_port}", frames).start()
        with httpx.Client(
            base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=10.0
        ) as client:
            policy_name = client.get("/v1/policy").json()["name"]
            _say(f"policy: {policy_name}; waiting for take-off ...")
            _wait_airborne(vehicle, area.z_min_m - 2.0, timeout_s=90.0)
            results = []
            for i, scenario in enumerate(scenarios):
                h = heterogeneity_index(scenario.users_xy_m, scenario.load_bps, area)
                loads = ", ".join(f"{v / 1e6:.1f}" for v in scenario.load_bps)
                _say(f"\nscenario {i + 1}/{len(scenarios)}: H = {h:.2f}, loads [{loads}] Mbit/s")
                start = np.asarray(vehicle.wait(5.0))
                sim_net = SimulatedNetwork(scenario, network, area, seed=cfg.seed + i)
                records = run_scenario(
                    sim_net, vehicle, client, cfg.steps, cfg.step_s, on_step=_print_step
                )
                targets = [r.target_m for r in records if r.target_m is not None]
                final = np.asarray(targets[-1] if targets else records[-1].position_m)
                achieved = float(np.mean([r.utility for r in records]))
                others = compare(scenario, start, final, cfg, network, cfg.seed + i)
                results.append(
                    {
                        "scenario": scenario.id,
                        "heterogeneity": h,
                        "users_xy_m": scenario.users_xy_m.tolist(),
                        "load_bps": scenario.load_bps.tolist(),
                        "achieved": achieved,
                        **others,
                        "track": [asdict(r) for r in records],
                    }
                )
    finally:
        if vehicle is not None:
            vehicle.close()
        if service is not None:
            service.stop()
        mock.stop()
    summary = {"policy": policy_name, "config": _jsonable(asdict(cfg)), "scenarios": results}
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    from sim.files import atomic_write_json

    atomic_write_json(cfg.out_dir / "demo.json", summary)
    plot_tracks(results, area, cfg.out_dir / "track.png", policy_name)
    _say("\n" + format_table(results, policy_name))
    _say(f"\nwrote {cfg.out_dir / 'demo.json'} and {cfg.out_dir / 'track.png'}")
    return summary


def format_table(results: Sequence[dict[str, Any]], policy_name: str) -> str:
    header = (
        f"{'scenario':>8} {'H':>5} | {policy_name + ' (loop)':>20} {'min-distance':>12} "
        f"{'oracle':>7} | {'flight cost':>11} {'oracle no-flight':>16}"
    )
    lines = [
        "Mean utility per step, with flight (same start, same speed limit):",
        header,
        "-" * len(header),
    ]
    for i, r in enumerate(results):
        cost = r["policy_target_no_flight"] - r["achieved"]
        lines.append(
            f"{i + 1:>8} {r['heterogeneity']:>5.2f} | {r['achieved']:>20.3f} "
            f"{r['min-distance']:>12.3f} {r['oracle']:>7.3f} | {cost:>11.3f} "
            f"{r['oracle_no_flight']:>16.3f}"
        )
    lines.append(
        "flight cost: the policy's last target held from the first step, minus what the loop "
        "achieved while flying (and deciding) there"
    )
    return "\n".join(lines)


def plot_tracks(
    results: Sequence[dict[str, Any]], area: AreaConfig, path: Path, policy_name: str
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4.4), squeeze=False)
    for ax, (i, r) in zip(axes[0], enumerate(results), strict=True):
        users = np.asarray(r["users_xy_m"])
        loads = np.asarray(r["load_bps"])
        ax.scatter(
            users[:, 0], users[:, 1], s=40 + 400 * loads / loads.max(), c="tab:orange",
            alpha=0.7, label="users (size: load)", zorder=3,
        )  # fmt: skip
        track = np.array([s["position_m"] for s in r["track"]])
        ax.plot(track[:, 0], track[:, 1], "-o", ms=2.5, c="tab:blue", label=f"{policy_name} track")
        ax.plot(*track[0, :2], "s", c="tab:blue", ms=7, label="start")
        ax.plot(*track[-1, :2], "*", c="tab:blue", ms=12, label="end")
        ax.plot(*r["min-distance_target_m"][:2], "x", c="k", ms=9, mew=2, label="min-distance")
        ax.plot(*r["oracle_target_m"][:2], "D", c="tab:green", ms=7, mfc="none", mew=2,
                label="oracle")  # fmt: skip
        ax.set_xlim(0, area.size_x_m)
        ax.set_ylim(0, area.size_y_m)
        ax.set_aspect("equal")
        ax.set_title(
            f"scenario {i + 1}: H = {r['heterogeneity']:.2f}\nloop {r['achieved']:.3f}, "
            f"min-dist {r['min-distance']:.3f}, oracle {r['oracle']:.3f}",
            fontsize=9,
        )
        ax.set_xlabel("x (m, east)")
        ax.set_ylabel("y (m, north)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def _wait_airborne(vehicle: TruePosition, z_m: float, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        position = vehicle.latest()
        if position is not None and position[2] >= z_m:
            return
        time.sleep(0.2)
    raise TimeoutError(f"the vehicle did not climb to {z_m} m within {timeout_s} s")


def _print_step(record: StepRecord) -> None:
    x, y, z = record.position_m
    target = (
        "(none yet)"
        if record.target_m is None
        else "({:.0f}, {:.0f}, {:.0f})".format(*record.target_m)
    )
    _say(
        f"  step {record.step + 1:>3}  utility {record.utility:.3f}  "
        f"vehicle ({x:6.1f}, {y:6.1f}, {z:5.1f})  target {target}"
    )


def _say(text: str) -> None:
    print(text, flush=True)


def _jsonable(obj: dict[str, Any]) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in obj.items()}


if __name__ == "__main__":
    sys.exit(0 if run_demo(DemoConfig()) else 1)
