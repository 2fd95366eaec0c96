"""``tupa demo``: the closed loop for real: autopilot, service and network controller as processes.

1. ``tupa sitl-mock`` (PX4 flavour) on a free loopback port;
2. ``tupa serve`` against it with ``--arm-and-takeoff`` and the chosen policy (the service's
   default by default), on a free port, with a one-time random API token;
3. the network controller, played here by the embedded simulator
   (:mod:`closed_loop.controller`): every second it reads the vehicle's true position from the
   autopilot, computes every user's metrics there and POSTs them as a report.

It plays a few scenarios where placement matters (heterogeneous traffic) one after the other,
the last with walking users and changing demand (the ``closed-loop-moving`` world), the vehicle
flying on from wherever the previous scenario left it. It ends with a table: the utility the
served policy achieved in the loop against ``min-distance``, ``load-weighted`` and the tracking
oracle, each re-placed every step from the latest report and flown from the same start under
the ``closed-loop`` world's limits, with the same users (the same motion and demand) — the
protocol of ``tupa eval --world closed-loop``. A PNG shows each scenario's users and the track,
over a site's buildings (footprints shaded by height, :func:`draw_buildings`) when the demo flies
over one (``--environment site:PATH``).
"""

from __future__ import annotations

import os
import secrets
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from closed_loop.controller import SimulatedNetwork, StepRecord, TruePosition, run_scenario
from closed_loop.processes import start_service, start_sitl_mock
from service.frames import FrameConfig
from sim.config import AreaConfig, NetworkConfig
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import heterogeneity_index
from sim.world import World, get_world


@dataclass(frozen=True)
class DemoConfig:
    policy: str | None = None  # None: the service's default (the tracking oracle)
    scenario_file: Path | None = None
    """A ``tupa-scenarios/1`` file whose scenarios are played (the first ``n_scenarios`` when
    given); None: generated ones (:func:`pick_scenarios`)."""
    n_scenarios: int | None = None
    """How many scenarios (without a file: generated, default 3)."""
    steps: int = 40
    step_s: float = 1.0
    speed_mps: float = 10.0
    seed: int = 7
    flavour: str = "px4"
    out_dir: Path = Path("runs/demo")
    queueing: str = "fq-codel"
    world: str = "closed-loop"
    environment: str | None = None
    """The channel environment (None: the scenario file's, else ``open``)."""


COMPARED = ("min-distance", "load-weighted", "oracle", "planning-oracle")


def pick_scenarios(n: int, seed: int, area: AreaConfig) -> list[Scenario]:
    """``n`` heterogeneous scenarios (H quantiles 0.5 to 0.98 among 200 generated ones), where
    traffic-aware placement matters."""
    pool = generate_scenarios(200, 3, seed=seed, area=area)
    h = np.array([heterogeneity_index(s.users_xy_m, s.load_bps, area) for s in pool])
    order = np.argsort(h)
    quantiles = np.linspace(0.5, 0.98, n) if n > 1 else np.array([0.9])
    return [pool[order[int(q * (len(pool) - 1))]] for q in quantiles]


def demo_scenarios(cfg: DemoConfig) -> tuple[AreaConfig, list[Scenario]]:
    """The area the demo flies in and the scenarios it plays, in order.

    With ``cfg.scenario_file``: the file's scenarios (the first ``cfg.n_scenarios`` when
    given), in the file's channel environment unless ``cfg.environment`` names it too
    (``InputError`` when they differ, or when the file's area is not the demo's). Without:
    ``cfg.n_scenarios`` (default 3) generated heterogeneous ones (:func:`pick_scenarios`) in
    ``cfg.environment`` (default ``open``). ``InputError`` for a count that is not positive.
    """
    from sim.errors import InputError

    if cfg.n_scenarios is not None and cfg.n_scenarios < 1:
        raise InputError(f"--n-scenarios: must be positive, got {cfg.n_scenarios}")
    if cfg.scenario_file is None:
        area = AreaConfig(environment=cfg.environment or "open")
        return area, pick_scenarios(cfg.n_scenarios or 3, cfg.seed, area)
    from sim.files import load_scenarios

    area, scenarios = load_scenarios(cfg.scenario_file)
    if cfg.environment is not None and cfg.environment != area.environment:
        raise InputError(
            f"--environment: {cfg.environment}, but {cfg.scenario_file} is in {area.environment}"
            " (drop --environment to fly the file's)"
        )
    if replace(area, environment="open") != AreaConfig():
        raise InputError(
            f"--scenarios: {cfg.scenario_file}: the demo flies the default area "
            f"({AreaConfig().size_x_m:g} m x {AreaConfig().size_y_m:g} m, zones and altitudes as "
            "tupa scenarios generate writes them); this file's area differs"
        )
    if not scenarios:
        raise InputError(f"--scenarios: {cfg.scenario_file}: scenarios: empty (nothing to fly)")
    return area, scenarios[: cfg.n_scenarios]


def demo_world(index: int, count: int, cfg: DemoConfig) -> World:
    """The world scenario ``index`` of ``count`` plays in: the last one has moving users."""
    name = "closed-loop-moving" if index == count - 1 and count > 1 else cfg.world
    world = get_world(name)
    network = NetworkConfig().with_queueing(cfg.queueing)  # type: ignore[arg-type]
    return replace(
        world,
        area=replace(world.area, environment=cfg.environment or "open"),
        network=network,
        episode_steps=cfg.steps,
        step_s=cfg.step_s,
        flight=replace(world.flight, horizontal_mps=cfg.speed_mps),
    )


def compare(
    scenario: Scenario, start_m: np.ndarray, world: World, seed: int, users_seed: int
) -> dict[str, Any]:
    """The baselines, the tracking and planning oracles and the shipped checkpoints, each flown
    in ``world`` from ``start_m`` by the simulator, with the users the loop had (same motion and
    demand): mean utility, and each one's last target."""
    from policies.evaluation.evaluation import run_episode
    from policies.registry import resolve_policy
    from service.policy_runtime import SHIPPED_CHECKPOINTS
    from sim.geometry import clip_to_volume

    home = clip_to_volume(start_m, world.area)
    flown = replace(world, home=tuple(map(float, home)))
    policies = [resolve_policy(name, world) for name in COMPARED]
    policies += [resolve_policy(p, world) for p in sorted(SHIPPED_CHECKPOINTS.glob("*.zip"))]
    out: dict[str, Any] = {"checkpoints": [p.name for p in policies if p.name not in COMPARED]}
    for policy in policies:
        episode = run_episode(policy, scenario, flown, seed, users_seed)
        out[policy.name] = float(np.mean(episode.utility[SCORED]))
        out[f"{policy.name}_target_m"] = [float(v) for v in episode.final_info["target_xyz_m"]]
    return out


LOOP_BASELINES = ("min-distance", "load-weighted")
"""Flown through loops of their own beside the served policy's, for a like-for-like table."""
SCORED = slice(None, -1)
"""The simulator's steps scored: its step k ends at the position the loop's report k + 1 is
measured at, and the loop's first report (at the start, before any decision) is not scored
(:data:`LOOP_SCORED`), so both score the same positions."""
LOOP_SCORED = slice(1, None)
"""The loop's reports scored: all but the first (taken at the start, before any decision)."""
START_TOLERANCE_M = 0.5
"""A scenario starts once every vehicle is this close to home: settled (its position
controller asks for 0.5 m/s there), so that it starts from rest as the simulator's does."""
DECISION_MODE = "on-report"
"""The demo's services decide on each report as it arrives (``tupa serve``'s
``TUPA_DECISION_MODE``): the controller reports once a period, so this is the loop with the least
latency, the one the ``closed-loop`` world flies (its ``flight.latency_s``)."""
TIE_TOLERANCE = 0.005
"""Loops side by side differ by milliseconds of timing: within this, the table calls it a tie
(``benchmarks/closed_loop.py``'s tolerance for "at least min-distance")."""


@dataclass
class _Loop:
    """One closed loop: an autopilot simulator, a placement service, its vehicle's position."""

    policy: str
    mock: Any
    service: Any
    vehicle: TruePosition
    client: httpx.Client
    name: str = ""

    def close(self) -> None:
        self.client.close()
        self.vehicle.close()
        self.service.stop()
        self.mock.stop()


def _start_loop(policy: str | None, cfg: DemoConfig, area: AreaConfig) -> _Loop:
    token = secrets.token_urlsafe(24)
    mock, mock_port = start_sitl_mock(
        ["--listen", "tcp:127.0.0.1:0", "--flavour", cfg.flavour, "--ready-delay-s", "2",
         "--speed-mps", str(cfg.speed_mps)]
    )  # fmt: skip
    try:
        serve_args = [
            *("--mavlink", f"tcp:127.0.0.1:{mock_port}", "--port", "0", "--arm-and-takeoff"),
            *("--step-s", str(cfg.step_s), "--log-level", "warning"),
            *("--environment", cfg.environment),
        ]
        if policy:
            serve_args += ["--policy", policy]
        # Home (where the vehicle boots and takes off) at the area's centre, as the worlds'
        # episodes start there: the area's south-west corner lies 250 m south and west of it.
        origin = {
            "TUPA_AREA_ORIGIN_NORTH_M": str(-area.size_y_m / 2),
            "TUPA_AREA_ORIGIN_EAST_M": str(-area.size_x_m / 2),
            "TUPA_DECISION_MODE": DECISION_MODE,
        }
        service, api_port = start_service(serve_args, env={"TUPA_API_TOKEN": token, **origin})
    except BaseException:
        mock.stop()
        raise
    frames = FrameConfig(-area.size_y_m / 2, -area.size_x_m / 2)
    vehicle = TruePosition(f"tcp:127.0.0.1:{mock_port}", frames).start()
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{api_port}",
        headers={"Authorization": f"Bearer {token}"},
        timeout=10.0,
    )
    loop = _Loop(policy or "", mock, service, vehicle, client)
    loop.name = client.get("/v1/policy").json()["name"]
    loop.policy = loop.policy or client.get("/v1/policy").json()["spec"]
    return loop


def _fly_to(loop: _Loop, xy_m: tuple[float, float], area: AreaConfig, timeout_s: float) -> None:
    """Bring the vehicle to ``xy_m`` at the lowest altitude through the service itself: serve
    ``min-distance`` and report one user there until the vehicle arrives, then serve the loop's
    policy again."""
    loop.client.put("/v1/policy", json={"policy": "min-distance"}).raise_for_status()
    user = {"id": "home", "x_m": xy_m[0], "y_m": xy_m[1], "offered_bps": 1e6,
            "throughput_bps": 1e6, "delay_s": 0.01, "plr": 0.0}  # fmt: skip
    goal = np.array([xy_m[0], xy_m[1], area.z_min_m])
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            report = {"timestamp": time.time(), "users": [user]}
            loop.client.post("/v1/reports", json=report).raise_for_status()
            position = np.asarray(loop.vehicle.wait(5.0))
            if float(np.linalg.norm(position - goal)) <= START_TOLERANCE_M:
                return
            if time.monotonic() > deadline:
                route = loop.client.get("/v1/vehicle").json().get("route")
                raise TimeoutError(
                    f"{loop.name}: the vehicle did not reach the start {goal} within "
                    f"{timeout_s:g} s: it is at {np.round(position, 1).tolist()}, its route "
                    f"{route}; the service's last lines:\n{loop.service.tail(15)}"
                )
            time.sleep(0.5)  # the next report: the service decides once per report here
    finally:
        loop.client.put("/v1/policy", json={"policy": loop.policy}).raise_for_status()


def _fly_scenario(
    loop: _Loop, scenario: Scenario, world: World, cfg: DemoConfig, index: int, printing: bool
) -> list[StepRecord]:
    """One loop plays scenario ``index`` in real time (the same users in every loop)."""
    network = SimulatedNetwork(
        scenario, world.network, world.area, seed=cfg.seed + index,
        mobility=world.mobility, demand=world.demand, users_seed=cfg.seed * 1000 + index,
    )  # fmt: skip
    return run_scenario(
        network, loop.vehicle, loop.client, cfg.steps, cfg.step_s,
        on_step=_print_step if printing else None,
    )  # fmt: skip


def _in_parallel(jobs: dict[str, Any]) -> dict[str, Any]:
    """Run each callable in its own thread; their results by key (the first error raised)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=len(jobs)) as pool:
        futures = {key: pool.submit(job) for key, job in jobs.items()}
        return {key: future.result() for key, future in futures.items()}


def run_demo(cfg: DemoConfig) -> dict[str, Any]:
    """Fly the served policy and the loop baselines side by side (one autopilot simulator and
    one service each), every scenario from home, and compare them with the simulator-flown
    tracking oracle and shipped checkpoints."""
    area, scenarios = demo_scenarios(cfg)
    cfg = replace(cfg, environment=area.environment)
    home_xy = (area.size_x_m / 2, area.size_y_m / 2)
    specs = {"served": cfg.policy, **{name: name for name in LOOP_BASELINES}}
    loops: dict[str, _Loop] = {}
    try:
        # One after the other, from this thread: the processes die with the thread that started
        # them (PR_SET_PDEATHSIG, closed_loop/processes.py), so not from a worker thread.
        for key, spec in specs.items():
            loops[key] = _start_loop(spec, cfg, area)
        served = loops["served"]
        _announce_operator_view(served, cfg.out_dir)
        policy_name = served.name
        for key in LOOP_BASELINES:
            if loops[key].name == policy_name:  # the served policy is one of the baselines
                loops.pop(key).close()
        beside = ", ".join(k for k in loops if k != "served")
        _say(
            f"policy: {policy_name}, with {beside} flown beside it (a vehicle and a service "
            "each); waiting for take-off ..."
        )
        _in_parallel(
            {k: (lambda lp=lp: _wait_airborne(lp.vehicle, area.z_min_m - 2.0, 90.0))
             for k, lp in loops.items()}
        )  # fmt: skip
        results = []
        for i, scenario in enumerate(scenarios):
            h = heterogeneity_index(scenario.users_xy_m, scenario.load_bps, area)
            loads = ", ".join(f"{v / 1e6:.1f}" for v in scenario.load_bps)
            _in_parallel({k: (lambda lp=lp: _fly_to(lp, home_xy, area, 120.0))
                          for k, lp in loops.items()})  # fmt: skip
            world = demo_world(i, len(scenarios), cfg)
            users_seed = cfg.seed * 1000 + i
            _say(
                f"\nscenario {i + 1}/{len(scenarios)} ({world.name}): H = {h:.2f}, loads "
                f"[{loads}] Mbit/s; every vehicle starts at home"
            )
            start = np.asarray(served.vehicle.wait(5.0))
            records = _in_parallel(
                {
                    k: partial(_fly_scenario, lp, scenario, world, cfg, i, k == "served")
                    for k, lp in loops.items()
                }
            )
            achieved = {
                k: float(np.mean([r.utility for r in rs[LOOP_SCORED]])) for k, rs in records.items()
            }
            others = compare(scenario, start, world, cfg.seed + i, users_seed)
            # The same policy in the loop and in the simulator (the target: within 0.01).
            loop_minus_sim = {
                name: achieved[key] - others[name]
                for key, name in (("served", policy_name), *((k, k) for k in LOOP_BASELINES))
                if key in achieved and name in others
            }
            for key in LOOP_BASELINES:  # flown for real where it had a loop of its own
                others[f"{key} (sim)"] = others[key]
                others[key] = achieved.get(key, achieved["served"])
            results.append(
                {
                    "scenario": scenario.id,
                    "world": world.name,
                    "heterogeneity": h,
                    "users_xy_m": scenario.users_xy_m.tolist(),
                    "load_bps": scenario.load_bps.tolist(),
                    "achieved": achieved["served"],
                    **others,
                    "loop_minus_sim": loop_minus_sim,
                    # Every loop's utility per step, as flown (the served one under its name).
                    "loop_utilities": {
                        (policy_name if k == "served" else k): [r.utility for r in rs]
                        for k, rs in records.items()
                    },
                    "track": [asdict(r) for r in records["served"]],
                }
            )
    finally:
        for lp in loops.values():
            lp.close()
    summary = {"policy": policy_name, "config": _jsonable(asdict(cfg)), "scenarios": results}
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    from sim.atomic import atomic_write_json

    atomic_write_json(cfg.out_dir / "demo.json", summary)
    plot_tracks(results, area, cfg.out_dir / "track.png", policy_name)
    plot_utilities(results, cfg.out_dir / "utility.png")
    _say("\n" + format_table(results, policy_name))
    _say(
        f"\nwrote {cfg.out_dir / 'demo.json'}, {cfg.out_dir / 'track.png'} and "
        f"{cfg.out_dir / 'utility.png'}"
    )
    return summary


def format_table(results: Sequence[dict[str, Any]], policy_name: str) -> str:
    mine = f"{policy_name} (loop)"
    checkpoints = list(results[0].get("checkpoints", [])) if results else []
    columns = [
        ("min-distance", "min-distance (loop)"),
        ("load-weighted", "load-weighted (loop)"),
        ("oracle", "tracking oracle (sim)"),
        ("planning-oracle", "planning oracle (sim)"),
        *((c, f"{c} (sim)") for c in checkpoints),
    ]
    header = f"{'scenario':>8} {'world':>18} {'H':>5} | {mine:>22} " + " ".join(
        f"{title:>{max(len(title), 7)}}" for _, title in columns
    )
    lines = [
        "Mean utility per step, all flown from the same start under the same limits:",
        header,
        "-" * len(header),
    ]
    for i, r in enumerate(results):
        gap = r["min-distance"] - r["achieved"]
        verdict = f"  ({mine} {gap:.3f} below min-distance (loop))" if gap > TIE_TOLERANCE else ""
        cells = " ".join(_cell(r.get(key), max(len(title), 7)) for key, title in columns)
        lines.append(
            f"{i + 1:>8} {r['world']:>18} {r['heterogeneity']:>5.2f} | {r['achieved']:>22.3f} "
            f"{cells}{verdict}"
        )
    lines.append("Loop minus simulator, the same policy on the same scenario:")
    for i, r in enumerate(results):
        gaps = ", ".join(f"{k} {v:+.3f}" for k, v in r.get("loop_minus_sim", {}).items())
        lines.append(f"{i + 1:>8} {gaps}")
    lines.append(
        "(loop): served by tupa serve and flown by an autopilot simulator of its own, side by "
        "side, from the same start, with the same users; (sim): flown by the embedded simulator "
        "(tupa eval --world closed-loop's protocol: the world's acceleration and latency); "
        "both score the steps after the first decision; "
        f"'{mine} ... below min-distance (loop)': its mean utility per step is below the "
        f"min-distance (loop) column's by more than {TIE_TOLERANCE}"
    )
    return "\n".join(lines)


def _cell(value: float | None, width: int) -> str:
    """A table cell: the mean to three decimals, or ``-`` where the row has none (a demo.json
    written before that column existed)."""
    return f"{'-':>{width}}" if value is None else f"{value:>{width}.3f}"


BUILDINGS_CMAP = "Greys"
"""The colour map of the buildings' heights in the track figures (light: low, dark: tall)."""
BUILDINGS_LIGHTEST = 0.2
"""Where on :data:`BUILDINGS_CMAP` a roof at 0 m starts, so that the lowest roofs still show
against the blank ground."""


def draw_buildings(ax: Any, area: AreaConfig) -> Any | None:
    """On a site (``area.environment`` ``site:PATH``), draw its buildings under everything else
    on the axes ``ax`` (area frame, metres): every ground cell with something standing on it
    (``building_height_m`` > 0) as a footprint shaded by its height (:data:`BUILDINGS_CMAP`
    from :data:`BUILDINGS_LIGHTEST` at 0 m to black at the tallest roof of the area), with a
    colour bar "building height (m)".
    Walkable and open ground stays blank. Returns the image (None off a site, where nothing is
    drawn). The site is the one the channel loads (:func:`sim.channel.area_site`)."""
    from sim.channel import area_site

    site = area_site(area)
    if site is None:
        return None
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    height_m = np.asarray(site.building_height_m, dtype=float)
    cells_x = min(site.cells_x, int(np.ceil(area.size_x_m / site.cell_m - 1e-9)))
    cells_y = min(site.cells_y, int(np.ceil(area.size_y_m / site.cell_m - 1e-9)))
    height_m = height_m[:cells_y, :cells_x]
    shown = np.ma.masked_less_equal(height_m, 0.0)
    top_m = float(height_m.max()) if height_m.size and height_m.max() > 0 else 1.0
    shades = plt.get_cmap(BUILDINGS_CMAP)(np.linspace(BUILDINGS_LIGHTEST, 1.0, 256))
    image = ax.imshow(
        shown,
        origin="lower",
        extent=(0.0, cells_x * site.cell_m, 0.0, cells_y * site.cell_m),
        cmap=ListedColormap(shades, name=f"{BUILDINGS_CMAP}-buildings"),
        vmin=0.0,
        vmax=top_m,
        interpolation="nearest",
        zorder=0,
    )
    bar = plt.colorbar(image, ax=ax, fraction=0.046, pad=0.02)
    bar.set_label("building height (m)", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    return image


def plot_tracks(
    results: Sequence[dict[str, Any]], area: AreaConfig, path: Path, policy_name: str
) -> None:
    """One panel per scenario: the users (size: load; a walking user's trail), the served
    policy's track (start, end), min-distance's and the oracle's last targets; on a site, the
    buildings under them (:func:`draw_buildings`). Written atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 4.4), squeeze=False)
    for ax, (i, r) in zip(axes[0], enumerate(results), strict=True):
        draw_buildings(ax, area)
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
    save_png(fig, path, 110)


def plot_utilities(results: Sequence[dict[str, Any]], path: Path) -> None:
    """One panel per scenario: the utility of every loop, step by step, as flown through its
    service and autopilot simulator (``loop_utilities``). Written atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), squeeze=False, sharey=True)
    for ax, (i, r) in zip(axes[0], enumerate(results), strict=True):
        for name, utilities in r["loop_utilities"].items():
            steps = np.arange(1, len(utilities) + 1)
            mean = float(np.mean(utilities[LOOP_SCORED])) if len(utilities) > 1 else 0.0
            ax.plot(steps, utilities, lw=1.5, label=f"{name} ({mean:.3f})")
        ax.set_title(f"scenario {i + 1} ({r['world']}): H = {r['heterogeneity']:.2f}", fontsize=9)
        ax.set_xlabel("step (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, title="loop (mean from step 2)", title_fontsize=7)
    axes[0][0].set_ylabel("utility, flown")
    fig.tight_layout()
    save_png(fig, path, 110)


def save_png(fig: Any, path: Path, dpi: int) -> None:
    """Write the matplotlib figure ``fig`` to ``path`` as PNG (through a temporary file renamed
    over it: a reader never sees half a figure) and close it."""
    import matplotlib.pyplot as plt

    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=dpi)
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


def _announce_operator_view(loop: _Loop, out_dir: Path) -> None:
    """Print the served policy's operator view (``tupa serve``'s page, live while the demo
    runs) and where its one-time token is: in a file only its owner may read, not on the
    terminal (which may be logged) and never in the address."""
    out_dir.mkdir(parents=True, exist_ok=True)
    token_file = out_dir / "api-token"
    token = str(loop.client.headers["Authorization"]).removeprefix("Bearer ")
    fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # also when the file was there before
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    url = str(loop.client.base_url).rstrip("/") + "/"
    _say(f"operator view: {url} (the page asks for the token: it is in {token_file})")


def _say(text: str) -> None:
    print(text, flush=True)


def _jsonable(obj: dict[str, Any]) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in obj.items()}


if __name__ == "__main__":
    sys.exit(0 if run_demo(DemoConfig()) else 1)
