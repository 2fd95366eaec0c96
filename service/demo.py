"""``tupa demo``: the closed loop for real: autopilot, service and network controller as processes.

1. ``tupa sitl-mock`` (PX4 flavour) on a free loopback port;
2. ``tupa serve`` against it with ``--arm-and-takeoff`` and the chosen policy (the shipped DDQN
   checkpoint by default), on a free port, with a one-time random API token;
3. the network controller, played here by the embedded simulator
   (:mod:`service.controller_sim`): every second it reads the vehicle's true position from the
   autopilot, computes every user's metrics there and POSTs them as a report.

It plays a few scenarios where placement matters (heterogeneous traffic) one after the other,
the last with walking users and changing demand (the ``closed-loop-moving`` world), the vehicle
flying on from wherever the previous scenario left it. It ends with a table: the utility the
served policy achieved in the loop against ``min-distance``, ``load-weighted`` and the tracking
oracle, each re-placed every step from the latest report and flown from the same start under
the ``closed-loop`` world's limits, with the same users (the same motion and demand) — the
protocol of ``tupa eval --world closed-loop``. A PNG shows each scenario's users and the track.
"""

from __future__ import annotations

import secrets
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.controller_sim import SimulatedNetwork, StepRecord, TruePosition, run_scenario
from service.frames import FrameConfig
from service.processes import start_service, start_sitl_mock
from sim.config import AreaConfig, NetworkConfig
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import heterogeneity_index
from sim.world import World, get_world


@dataclass(frozen=True)
class DemoConfig:
    policy: str | None = None  # None: the service's default (shipped DDQN checkpoint)
    scenarios: int = 3
    steps: int = 40
    step_s: float = 1.0
    speed_mps: float = 10.0
    seed: int = 7
    flavour: str = "px4"
    out_dir: Path = Path("runs/demo")
    queueing: str = "fq-codel"
    world: str = "closed-loop"


COMPARED = ("min-distance", "load-weighted", "oracle")


def pick_scenarios(n: int, seed: int, area: AreaConfig) -> list[Scenario]:
    """``n`` heterogeneous scenarios (H quantiles 0.5 to 0.98 among 200 generated ones), where
    traffic-aware placement matters."""
    pool = generate_scenarios(200, 3, seed=seed, area=area)
    h = np.array([heterogeneity_index(s.users_xy_m, s.load_bps, area) for s in pool])
    order = np.argsort(h)
    quantiles = np.linspace(0.5, 0.98, n) if n > 1 else np.array([0.9])
    return [pool[order[int(q * (len(pool) - 1))]] for q in quantiles]


def demo_world(index: int, cfg: DemoConfig) -> World:
    """The world scenario ``index`` plays in: the last one has moving users."""
    name = "closed-loop-moving" if index == cfg.scenarios - 1 and cfg.scenarios > 1 else cfg.world
    world = get_world(name)
    network = NetworkConfig().with_queueing(cfg.queueing)  # type: ignore[arg-type]
    return replace(
        world,
        network=network,
        episode_steps=cfg.steps,
        step_s=cfg.step_s,
        flight=replace(world.flight, horizontal_mps=cfg.speed_mps),
    )


def compare(
    scenario: Scenario, start_m: np.ndarray, world: World, seed: int, users_seed: int
) -> dict[str, Any]:
    """The baselines and the tracking oracle flown in ``world`` from ``start_m``, with the
    users the loop had (same motion and demand): mean utility, and each one's first target."""
    from policies.baselines import make_policy
    from policies.evaluation import StaticAgent
    from sim.envs import FapContinuousEnv

    out: dict[str, Any] = {}
    for name in COMPARED:
        agent = StaticAgent(make_policy(name, world=world))
        area = world.area
        home = np.clip(start_m, [0, 0, area.z_min_m], [area.size_x_m, area.size_y_m, area.z_max_m])
        env = FapContinuousEnv([scenario], world=replace(world, home=tuple(map(float, home))))
        agent.begin_episode(scenario, env.world)
        observation, info = env.reset(
            seed=seed, options={"scenario": scenario, "users_seed": users_seed}
        )
        rewards = []
        for _ in range(world.episode_steps):
            observation, reward, _, _, info = env.step(agent.act(observation, info))
            rewards.append(reward)
        out[name] = float(np.mean(rewards))
        out[f"{name}_target_m"] = [float(v) for v in info["target_xyz_m"]]
    return out


def run_demo(cfg: DemoConfig) -> dict[str, Any]:
    area = AreaConfig()
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
                world = demo_world(i, cfg)
                users_seed = cfg.seed * 1000 + i
                _say(f"world: {world.name}")
                sim_net = SimulatedNetwork(
                    scenario, world.network, area, seed=cfg.seed + i,
                    mobility=world.mobility, demand=world.demand, users_seed=users_seed,
                )  # fmt: skip
                records = run_scenario(
                    sim_net, vehicle, client, cfg.steps, cfg.step_s, on_step=_print_step
                )
                achieved = float(np.mean([r.utility for r in records]))
                others = compare(scenario, start, world, cfg.seed + i, users_seed)
                results.append(
                    {
                        "scenario": scenario.id,
                        "world": world.name,
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
    mine = f"{policy_name} (loop)"
    header = (
        f"{'scenario':>8} {'world':>18} {'H':>5} | {mine:>20} {'min-distance':>12} "
        f"{'load-weighted':>13} {'tracking oracle':>15}"
    )
    lines = [
        "Mean utility per step, all flown from the same start under the same limits:",
        header,
        "-" * len(header),
    ]
    for i, r in enumerate(results):
        verdict = "" if r["achieved"] >= r["min-distance"] else "  (below min-distance)"
        lines.append(
            f"{i + 1:>8} {r['world']:>18} {r['heterogeneity']:>5.2f} | {r['achieved']:>20.3f} "
            f"{r['min-distance']:>12.3f} {r['load-weighted']:>13.3f} {r['oracle']:>15.3f}"
            f"{verdict}"
        )
    lines.append(
        "min-distance, load-weighted and the tracking oracle are re-placed every step from the "
        "latest report (tupa eval --world closed-loop's protocol)"
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
        trails = np.array([s["users_xy_m"] for s in r["track"] if s.get("users_xy_m")])
        if trails.size and np.ptp(trails, axis=0).max() > 1.0:  # users that moved
            for u in range(trails.shape[1]):
                ax.plot(trails[:, u, 0], trails[:, u, 1], "-", c="tab:orange", lw=1, alpha=0.6)
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
            f"scenario {i + 1} ({r['world']}): H = {r['heterogeneity']:.2f}\n"
            f"loop {r['achieved']:.3f}, min-dist {r['min-distance']:.3f}, "
            f"oracle {r['oracle']:.3f}",
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
