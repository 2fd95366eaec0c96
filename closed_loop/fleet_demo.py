"""``tupa demo --uavs K``: the closed loop with a fleet, for real, policies side by side.

For every compared fleet policy (``kmeans-min-distance``, ``kmeans-load-weighted`` and
``kmeans-scored``; the ``fleet-oracle`` too when one of its decisions fits the decision period:
the demo measures one first) it starts

1. one ``tupa sitl-mock --vehicles K`` (PX4 flavour): K vehicles, system ids 1..K, one free
   loopback port each, vehicle i's home 15·i m east of vehicle 0's;
2. one ``tupa serve --fleet-file`` flying them with that policy (``--arm-and-takeoff``, a
   one-time random API token), the fleet file written beside the outputs: vehicle i's area
   origin lies 15·i m further west from its own home, so that every vehicle sees the same area,
   whose centre is vehicle 0's home;
3. the fleet's network controller played by the embedded simulator
   (:mod:`closed_loop.fleet_controller`): every second it reads each vehicle's true position
   from its autopilot, computes every user's metrics with the fleet model (K access points on
   distinct channels, association with hysteresis, handovers) and POSTs one report of all
   users.

The users stand in K + 1 hot spots around the area's centre, with different loads; one hot spot
walks as a group (random waypoint, 1.5–2.5 m/s, the same path in every loop). Every loop flies
the same users in real time from the same start. The demo ends with a table (per policy: mean
utility, served-user fraction, Jain fairness, minimum user throughput, handovers), ``demo.json``
and ``track.png`` (every vehicle's track, one colour per vehicle; users coloured by the vehicle
serving them at the end; the hot spots, and the walking one's path).
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any, cast

import httpx
import numpy as np

from closed_loop.controller import TruePosition
from closed_loop.demo import (
    _in_parallel,
    _jsonable,
    _say,
    _wait_airborne,
    draw_buildings,
    save_png,
)
from closed_loop.fleet_controller import (
    FleetStepRecord,
    GroupedUsers,
    SimulatedFleetNetwork,
    run_fleet_scenario,
    summarise,
)
from closed_loop.processes import (
    ProcessFailedError,
    TupaProcess,
    mock_fleet_file,
    start_service,
)
from policies.fleet_policy import FLEET_POLICIES
from service.frames import FrameConfig
from sim.channel import area_site
from sim.config import AreaConfig, NetworkConfig
from sim.errors import InputError
from sim.fleet import MAX_UAVS, FleetConfig
from sim.world import Demand, Mobility, get_world

__all__ = [
    "ALWAYS_FLOWN",
    "FleetDemoConfig",
    "HotSpotLayout",
    "format_fleet_table",
    "hot_spot_layout",
    "hot_spot_users",
    "plot_fleet_tracks",
    "run_fleet_demo",
]

ALWAYS_FLOWN: tuple[str, ...] = ("kmeans-min-distance", "kmeans-load-weighted", "kmeans-scored")
"""The fleet policies the demo always compares (the fleet oracle joins when it is fast enough)."""
SPACING_M = 15.0
"""East-west distance between neighbouring mock vehicles' homes (``tupa sitl-mock``'s default)."""
WALK = Mobility(model="group", speed_mps=(1.5, 2.5), pause_s=(0.0, 0.0))
"""How the walking hot spot moves: together, at a brisk walk, without pausing."""


@dataclass(frozen=True)
class FleetDemoConfig:
    """What ``tupa demo --uavs K`` flies; the defaults are the command's."""

    uavs: int = 3
    policies: tuple[str, ...] | None = None
    """None: both k-means baselines, and the fleet oracle when a decision fits ``step_s``."""
    steps: int = 60
    step_s: float = 1.0
    speed_mps: float = 10.0
    seed: int = 7
    flavour: str = "px4"
    out_dir: Path = Path("runs/demo-fleet")
    environment: str = "open"
    users_per_spot: int = 6
    load_per_uav_bps: float = 30e6
    separation_m: float = 10.0

    def __post_init__(self) -> None:
        k = self.uavs
        if isinstance(k, bool) or not isinstance(k, int) or not 2 <= k <= MAX_UAVS:
            raise InputError(f"--uavs: a fleet demo needs 2..{MAX_UAVS} vehicles, got {k!r}")
        if self.policies is not None:
            unknown = [p for p in self.policies if p not in FLEET_POLICIES and not Path(p).exists()]
            if unknown or not self.policies or len(set(self.policies)) != len(self.policies):
                raise InputError(
                    f"--policy: with --uavs, a comma-separated list of distinct fleet policies "
                    f"({', '.join(FLEET_POLICIES)}, or fleet checkpoints), got "
                    f"{','.join(self.policies)!r}"
                )
        for name in ("steps", "users_per_spot"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise InputError(f"{name}: must be a whole number >= 1, got {value!r}")
        for name in ("step_s", "speed_mps", "load_per_uav_bps", "separation_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{name}: must be > 0, got {value!r}")


# --------------------------------------------------------------------------------------------
# The users: hot spots, one walking


@dataclass(frozen=True)
class HotSpotLayout:
    """Users in hot spots at time 0: ``spot`` (U,) is each user's hot spot; ``moving_spot``
    walks (:data:`WALK`), the others stay."""

    centres_m: np.ndarray
    spread_m: float
    users_xy_m: np.ndarray
    load_bps: np.ndarray
    spot: np.ndarray
    moving_spot: int

    @property
    def n_spots(self) -> int:
        return len(self.centres_m)

    def spot_loads_bps(self) -> np.ndarray:
        return np.bincount(self.spot, weights=self.load_bps, minlength=self.n_spots)


def hot_spot_layout(
    n_uavs: int,
    seed: int,
    area: AreaConfig,
    users_per_spot: int = 6,
    load_per_uav_bps: float = 30e6,
    spread_m: float = 20.0,
) -> HotSpotLayout:
    """``n_uavs + 1`` hot spots of ``users_per_spot`` users each, around the area's centre.

    The centres lie on a ring 120–200 m from the centre (evenly spaced in angle from a random
    start, radii drawn), so no vehicle starts on one; users lie at Gaussian offsets
    (σ = ``spread_m``) from their centre, clipped 1 m inside the area. Loads total
    ``load_per_uav_bps`` per UAV, split between the hot spots by a Dirichlet(2) draw over
    what is left after 5 % each (some hot spots heavy, some light, none empty), and within a
    hot spot by Exp(1) weights with a floor of 3 % of the spot's mean. The walking hot spot
    is the one nearest the median load. On a site (``site:PATH``) a user drawn inside a
    building is drawn again from its hot spot (:func:`sim.sites.ground.place_on_walkable`; the
    nearest walkable cell after its tries), so every user stands on walkable ground; elsewhere
    the draws are what they always were. Deterministic given ``seed``."""
    rng = np.random.default_rng(seed)
    n_spots = n_uavs + 1
    middle = np.array([area.size_x_m / 2, area.size_y_m / 2])
    reach = min(area.size_x_m, area.size_y_m) / 2
    angles = rng.uniform(0.0, 2 * math.pi) + np.arange(n_spots) * 2 * math.pi / n_spots
    radii = rng.uniform(0.48, 0.8, n_spots) * reach  # 120-200 m in the paper's 500 m area
    centres = middle + radii[:, None] * np.c_[np.cos(angles), np.sin(angles)]
    shares = 0.05 + (1.0 - 0.05 * n_spots) * rng.dirichlet(np.full(n_spots, 2.0))
    total = load_per_uav_bps * n_uavs
    xy, load = [], []
    upper = np.array([area.size_x_m, area.size_y_m]) - 1.0
    site = area_site(area)
    for s in range(n_spots):
        spot_xy = np.clip(centres[s] + rng.normal(0.0, spread_m, (users_per_spot, 2)), 1.0, upper)
        if site is not None:
            from sim.sites.ground import place_on_walkable

            def redraw(which: np.ndarray, centre: np.ndarray = centres[s]) -> np.ndarray:
                return np.clip(centre + rng.normal(0.0, spread_m, (which.size, 2)), 1.0, upper)

            spot_xy = place_on_walkable(site, spot_xy, redraw, area.size_x_m, area.size_y_m)
        xy.append(spot_xy)
        weights = rng.exponential(1.0, users_per_spot)
        weights = np.maximum(weights / weights.sum(), 0.03 / users_per_spot)
        load.append(total * shares[s] * weights / weights.sum())
    spot = np.repeat(np.arange(n_spots), users_per_spot)
    moving = int(np.argmin(np.abs(shares - np.median(shares))))
    return HotSpotLayout(centres, spread_m, np.vstack(xy), np.concatenate(load), spot, moving)


def hot_spot_users(
    layout: HotSpotLayout, area: AreaConfig, rng: np.random.Generator
) -> GroupedUsers:
    """The layout's users as they move: one group per hot spot, the walking one under
    :data:`WALK`, demand steady. They draw from ``rng`` (here and as they advance): the same
    seed gives the same walk."""
    groups = []
    for s in range(layout.n_spots):
        mine = layout.spot == s
        mobility = WALK if s == layout.moving_spot else Mobility()
        groups.append((layout.users_xy_m[mine], layout.load_bps[mine], mobility, Demand()))
    return GroupedUsers(groups, area, rng)


# --------------------------------------------------------------------------------------------
# One loop per policy: a mock fleet, a service, a position reader per vehicle


@dataclass
class _FleetLoop:
    policy: str
    mock: TupaProcess
    service: TupaProcess
    vehicles: dict[str, TruePosition]
    client: httpx.Client
    fleet_file: Path

    def close(self) -> None:
        self.client.close()
        for vehicle in self.vehicles.values():
            vehicle.close()
        self.service.stop()
        self.mock.stop()


def start_sitl_fleet(
    n_vehicles: int, flavour: str, speed_mps: float, timeout_s: float = 30.0
) -> tuple[TupaProcess, list[int]]:
    """``tupa sitl-mock --vehicles N`` on free loopback ports: the process and each vehicle's
    port, in system id order (1..N)."""
    proc = TupaProcess(
        ["sitl-mock", "--vehicles", str(n_vehicles), "--listen", "tcp:127.0.0.1:0",
         "--flavour", flavour, "--ready-delay-s", "2", "--speed-mps", str(speed_mps),
         "--spacing-m", str(SPACING_M)],
        "sitl-mock-fleet",
    )  # fmt: skip
    try:
        ports = [
            int(proc.wait_for_line(rf"sysid {i + 1} listening on \S+:(\d+)\s*$", timeout_s)[1])
            for i in range(n_vehicles)
        ]
    except ProcessFailedError:
        proc.stop()
        raise
    return proc, ports


def fleet_file(
    ports: list[int], area: AreaConfig, separation_m: float
) -> tuple[dict[str, Any], dict[str, FrameConfig]]:
    """The ``--fleet-file`` for a mock fleet on ``ports`` (vehicle i: system id i + 1, home
    15·i m east of vehicle 0's; :func:`closed_loop.processes.mock_fleet_file`) whose area is
    centred on vehicle 0's home; and each vehicle's frames (the same origins, for its position
    reader)."""
    first = FrameConfig(-area.size_y_m / 2, -area.size_x_m / 2)
    spec = mock_fleet_file(ports, first, SPACING_M, separation_m)
    vehicles = cast(list[dict[str, Any]], spec["vehicles"])
    frames = {
        v["id"]: FrameConfig(
            v["area_origin_north_m"], v["area_origin_east_m"], v["area_origin_down_m"]
        )
        for v in vehicles
    }
    return spec, frames


def _start_loop(policy: str, cfg: FleetDemoConfig, area: AreaConfig) -> _FleetLoop:
    mock, ports = start_sitl_fleet(cfg.uavs, cfg.flavour, cfg.speed_mps)
    try:
        spec, frames = fleet_file(ports, area, cfg.separation_m)
        path = cfg.out_dir / f"fleet-{policy}.json"
        path.write_text(json.dumps(spec, indent=2) + "\n")
        token = secrets.token_urlsafe(24)
        serve_args = [
            *("--fleet-file", str(path), "--policy", policy, "--port", "0", "--arm-and-takeoff"),
            *("--step-s", str(cfg.step_s), "--log-level", "warning"),
            *("--environment", cfg.environment),
        ]
        service, api_port = start_service(serve_args, env={"TUPA_API_TOKEN": token})
    except BaseException:
        mock.stop()
        raise
    vehicles = {
        v["id"]: TruePosition(v["mavlink"], frames[v["id"]], system_id=v["system_id"]).start()
        for v in spec["vehicles"]
    }
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{api_port}",
        headers={"Authorization": f"Bearer {token}"},
        timeout=10.0,
    )
    return _FleetLoop(policy, mock, service, vehicles, client, path)


def time_fleet_oracle(layout: HotSpotLayout, cfg: FleetDemoConfig, area: AreaConfig) -> float:
    """Seconds one fleet-oracle decision takes on the demo's users here: the very policy
    ``tupa serve --policy fleet-oracle`` runs every decision period, in the closed-loop world
    with the demo's area and decision period."""
    from dataclasses import replace

    from policies.fleet_policy import FleetPlacementPolicy
    from sim.observation import UserReports

    world = replace(get_world("closed-loop"), area=area, step_s=cfg.step_s)
    policy = FleetPlacementPolicy("fleet-oracle", world, cfg.separation_m)
    xy, load = np.asarray(layout.users_xy_m), np.asarray(layout.load_bps)
    quiet = np.zeros(len(load))
    reports = UserReports(xy[:, 0], xy[:, 1], load, load, quiet, quiet)
    started = time.perf_counter()
    policy.decide_fleet(reports, np.zeros((cfg.uavs, 3)))
    return time.perf_counter() - started


def _fly(
    loop: _FleetLoop,
    layout: HotSpotLayout,
    cfg: FleetDemoConfig,
    area: AreaConfig,
    printing: bool,
) -> list[FleetStepRecord]:
    # The users draw from their own generator, seeded alike in every loop: the same walk.
    users_rng = np.random.default_rng(cfg.seed * 1000 + 1)
    network = SimulatedFleetNetwork(
        hot_spot_users(layout, area, users_rng),
        FleetConfig(n_uavs=cfg.uavs, separation_m=cfg.separation_m),
        NetworkConfig(),
        area,
        seed=cfg.seed,
        users_rng=users_rng,
    )
    return run_fleet_scenario(
        network, loop.vehicles, loop.client, cfg.steps, cfg.step_s,
        on_step=_print_step if printing else None,
    )  # fmt: skip


def run_fleet_demo(cfg: FleetDemoConfig) -> dict[str, Any]:
    """Fly the compared fleet policies side by side (a mock fleet and a service each) over the
    same users from the same start; write ``demo.json`` and ``track.png`` in ``cfg.out_dir``;
    print and return the summary."""
    area = AreaConfig(environment=cfg.environment)
    layout = hot_spot_layout(cfg.uavs, cfg.seed, area, cfg.users_per_spot, cfg.load_per_uav_bps)
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    oracle_s: float | None = None
    policies = list(cfg.policies or ALWAYS_FLOWN)
    if cfg.policies is None:
        _say("timing one fleet-oracle decision on the demo's users ...")
        oracle_s = time_fleet_oracle(layout, cfg, area)
        fits = oracle_s <= cfg.step_s
        if fits:
            policies.append("fleet-oracle")
        _say(
            f"fleet-oracle: one decision took {oracle_s:.2f} s "
            + (
                f"(fits the {cfg.step_s:g} s decision period: flown too)"
                if fits
                else f"(more than the {cfg.step_s:g} s decision period: not flown)"
            )
        )
    loads = ", ".join(f"{v / 1e6:.1f}" for v in layout.spot_loads_bps())
    _say(
        f"fleet of {cfg.uavs}: {len(layout.load_bps)} users in {layout.n_spots} hot spots "
        f"(loads [{loads}] Mbit/s; hot spot {layout.moving_spot + 1} walks); "
        f"policies side by side: {', '.join(policies)}"
    )
    loops: dict[str, _FleetLoop] = {}
    try:
        # One after the other, from this thread: the processes die with the thread that started
        # them (PR_SET_PDEATHSIG, closed_loop/processes.py).
        for policy in policies:
            loops[policy] = _start_loop(policy, cfg, area)
        first = loops[policies[0]]
        token_file = _write_token(first.client, cfg.out_dir / "api-token")
        _say(
            f"{policies[0]}: {str(first.client.base_url).rstrip('/')}/v1/vehicles "
            f"(token in {token_file}); waiting for take-off ..."
        )
        _in_parallel(
            {
                f"{p}/{vid}": partial(_wait_airborne, vehicle, area.z_min_m - 2.0, 90.0)
                for p, lp in loops.items()
                for vid, vehicle in lp.vehicles.items()
            }
        )
        _say(f"every vehicle airborne; flying {cfg.steps} steps of {cfg.step_s:g} s")
        records = _in_parallel(
            {p: partial(_fly, lp, layout, cfg, area, p == policies[0]) for p, lp in loops.items()}
        )
        final_state = {p: _vehicles(lp.client) for p, lp in loops.items()}
    finally:
        for lp in loops.values():
            lp.close()
    results = {
        p: {
            "metrics": summarise(records[p]),
            "fleet_file": str(loops[p].fleet_file),
            "vehicles_at_end": final_state[p],
            "steps": [asdict(r) for r in records[p]],
        }
        for p in policies
    }
    summary = {
        "uavs": cfg.uavs,
        "config": _jsonable(asdict(cfg)),
        "area_m": [area.size_x_m, area.size_y_m],
        "hot_spots": {
            "centres_m": layout.centres_m.tolist(),
            "spread_m": layout.spread_m,
            "moving": layout.moving_spot,
            "loads_bps": layout.spot_loads_bps().tolist(),
        },
        "users": {
            "xy_m": layout.users_xy_m.tolist(),
            "load_bps": layout.load_bps.tolist(),
            "spot": layout.spot.tolist(),
        },
        "fleet_oracle_decision_s": oracle_s,
        "policies": results,
    }
    from sim.atomic import atomic_write_json

    atomic_write_json(cfg.out_dir / "demo.json", summary)
    plot_fleet_tracks(summary, area, cfg.out_dir / "track.png")
    _say("\n" + format_fleet_table(summary))
    _say(f"\nwrote {cfg.out_dir / 'demo.json'} and {cfg.out_dir / 'track.png'}")
    return summary


def format_fleet_table(summary: dict[str, Any]) -> str:
    """The per-policy table of a fleet demo's summary."""
    cfg = summary["config"]
    header = (
        f"{'policy':<22} {'utility':>7} {'served':>7} {'Jain':>6} "
        f"{'min thr (Mbit/s)':>16} {'handovers':>9}"
    )
    lines = [
        f"Fleet of {summary['uavs']} UAVs, {len(summary['users']['spot'])} users in "
        f"{len(summary['hot_spots']['centres_m'])} hot spots (one walking), "
        f"{cfg['steps']} steps of {cfg['step_s']:g} s, every policy flown from the same start "
        "with the same users (means over the steps; handovers in all):",
        header,
        "-" * len(header),
    ]
    for policy, r in summary["policies"].items():
        m = r["metrics"]
        lines.append(
            f"{policy:<22} {m['utility']:>7.3f} {m['served_fraction']:>7.2f} "
            f"{m['jain_fairness']:>6.2f} {m['min_throughput_bps'] / 1e6:>16.2f} "
            f"{m['handovers']:>9d}"
        )
    oracle_s = summary.get("fleet_oracle_decision_s")
    if oracle_s is not None and "fleet-oracle" not in summary["policies"]:
        lines.append(
            f"fleet-oracle: not flown, one decision took {oracle_s:.2f} s here, more than the "
            f"{cfg['step_s']:g} s decision period"
        )
    lines.append(
        "served: share of users receiving >= 90 % of their offered load; Jain: fairness of "
        "per-user throughput; min thr: the lowest user's throughput"
    )
    return "\n".join(lines)


def plot_fleet_tracks(summary: dict[str, Any], area: AreaConfig, path: Path) -> None:
    """One panel per policy: the hot spots (the walking one's path dashed), the users at the
    end coloured by the vehicle serving them, every vehicle's track in its own colour (start
    square, end star, last target cross); on a site, under it all, the buildings' footprints
    shaded by height (:func:`closed_loop.demo.draw_buildings`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    policies = summary["policies"]
    n = len(policies)
    colours = plt.get_cmap("tab10").colors
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 4.9), squeeze=False)
    spots = summary["hot_spots"]
    spot = np.asarray(summary["users"]["spot"])
    for ax, (policy, r) in zip(axes[0], policies.items(), strict=True):
        draw_buildings(ax, area)
        steps = r["steps"]
        trails = np.array([s["users_xy_m"] for s in steps])  # (T, U, 2)
        for s, centre in enumerate(spots["centres_m"]):
            ax.add_patch(
                Circle(centre, 2 * spots["spread_m"], color="0.6", alpha=0.18, lw=0, zorder=1)
            )
            label = f"hot spot {s + 1}" + (" (walks)" if s == spots["moving"] else "")
            top = centre[1] + 2 * spots["spread_m"] + 3
            ax.text(centre[0], top, label, ha="center", va="bottom", fontsize=7, color="0.3")
        walk = trails[:, spot == spots["moving"]].mean(axis=1)
        ax.plot(walk[:, 0], walk[:, 1], "--", c="0.35", lw=1.2, zorder=2,
                label="walking hot spot's centre")  # fmt: skip
        if np.linalg.norm(walk[-1] - walk[0]) > 1.0:  # where it went: an arrow, its circle
            ax.annotate("", xy=walk[-1], xytext=walk[max(len(walk) - 4, 0)], zorder=2,
                        arrowprops={"arrowstyle": "-|>", "color": "0.35", "lw": 1.2})  # fmt: skip
            ax.add_patch(Circle(walk[-1], 2 * spots["spread_m"], fill=False, ls=":",
                                ec="0.5", lw=1.0, zorder=1))  # fmt: skip
        last = steps[-1]
        association = np.asarray(last["association"])
        loads = np.asarray(last["load_bps"])
        users_colour = [colours[a % 10] if a >= 0 else "0.5" for a in association]
        ax.scatter(
            trails[-1, :, 0],
            trails[-1, :, 1],
            s=12 + 120 * loads / max(loads.max(), 1),
            c=users_colour,
            edgecolors="k",
            linewidths=0.4,
            alpha=0.85,
            zorder=3,
        )
        for k, vid in enumerate(last["positions_m"]):
            track = np.array([s["positions_m"][vid] for s in steps])
            c = colours[k % 10]
            ax.plot(track[:, 0], track[:, 1], "-", c=c, lw=1.6, zorder=4, label=vid)
            ax.plot(*track[0, :2], "s", c=c, ms=6, zorder=5)
            ax.plot(*track[-1, :2], "*", c=c, ms=13, mec="k", mew=0.5, zorder=5)
            target = last["targets_m"].get(vid)
            if target is not None:
                ax.plot(*target[:2], "x", c=c, ms=9, mew=2, zorder=5)
        m = r["metrics"]
        ax.set_title(
            f"{policy}\nutility {m['utility']:.3f}, served {m['served_fraction']:.2f}, "
            f"Jain {m['jain_fairness']:.2f}, handovers {m['handovers']}",
            fontsize=9,
        )
        ax.set_xlim(0, area.size_x_m)
        ax.set_ylim(0, area.size_y_m)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m, east)")
        ax.set_ylabel("y (m, north)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.text(
        0.5, 0.005,
        "square: start, star: end, cross: last target; users at the end, coloured by the "
        "vehicle serving them (size: load)",
        ha="center", fontsize=7, color="0.3",
    )  # fmt: skip
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_png(fig, path, 100)


def _vehicles(client: httpx.Client) -> dict[str, Any]:
    """``GET /v1/vehicles``: every vehicle as the service sees it (link, mode, target)."""
    response = client.get("/v1/vehicles")
    response.raise_for_status()
    return dict(response.json())


def _write_token(client: httpx.Client, path: Path) -> Path:
    """The service's one-time token in a file only its owner may read (not on the terminal,
    which may be logged)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # also when the file was there before
    with os.fdopen(fd, "w") as f:
        f.write(str(client.headers["Authorization"]).removeprefix("Bearer ") + "\n")
    return path


def _print_step(record: FleetStepRecord) -> None:
    where = "  ".join(
        f"{vid} ({x:5.0f},{y:5.0f},{z:4.0f})" for vid, (x, y, z) in record.positions_m.items()
    )
    _say(
        f"  step {record.step + 1:>3}  utility {record.utility:.3f}  served "
        f"{record.served_fraction:.2f}  Jain {record.jain_fairness:.2f}  "
        f"handovers {record.handovers_total:>3}  {where}"
    )


def parse_policies(text: str | None) -> tuple[str, ...] | None:
    """``--policy`` with ``--uavs``: a comma-separated list of fleet policies (None: the
    default set)."""
    if text is None:
        return None
    return tuple(p for p in re.split(r"\s*,\s*", text.strip()) if p)
