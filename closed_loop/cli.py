"""``tupa demo`` (the closed loop behind ``make run``) and ``tupa controller-sim``."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from sim.config import ENVIRONMENTS


def register(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="closed loop: sitl-mock + tupa serve + a simulated network controller",
        description="Start the autopilot simulator, the placement service and a network "
        "controller played by the embedded simulator; fly a few heterogeneous scenarios in real "
        "time (the last with walking users); print the utility achieved against min-distance, "
        "load-weighted and the tracking oracle, all flown from the same start under the same "
        "limits; write demo.json and track.png.",
    )
    demo.add_argument(
        "--uavs",
        type=int,
        default=1,
        metavar="K",
        help="vehicles (1..8, default 1). K >= 2: the fleet demo, one mock fleet and one tupa "
        "serve --fleet-file per fleet policy, users in K + 1 hot spots (one walking), "
        "written to runs/demo-fleet unless --out says otherwise",
    )
    demo.add_argument(
        "--policy",
        help="checkpoint or baseline (default: the service's, the tracking oracle); with "
        "--uavs K >= 2, a comma-separated list of fleet policies (default: kmeans-min-distance, "
        "kmeans-load-weighted and kmeans-scored, and fleet-oracle when one decision fits the "
        "period)",
    )
    demo.add_argument(
        "--scenarios", type=int, help="how many (default 3; the fleet demo plays one)"
    )
    demo.add_argument(
        "--steps", type=int, help="1-s steps per scenario (default 40; the fleet demo's 60)"
    )
    demo.add_argument("--seed", type=int, default=7)
    demo.add_argument("--flavour", choices=("px4", "ardupilot"), default="px4")
    demo.add_argument(
        "--environment",
        choices=ENVIRONMENTS,
        default="open",
        help="what stands on the ground: the simulated network's channel and the service's "
        "(default open, the paper's)",
    )
    demo.add_argument(
        "--out", type=Path, metavar="DIR", help="default runs/demo (the fleet's: runs/demo-fleet)"
    )
    demo.set_defaults(handler=_demo)

    ctl = subparsers.add_parser(
        "controller-sim",
        help="a network controller played by the simulator, POSTing reports to a service",
        description="Every step: read the vehicle's true position from the autopilot over "
        "MAVLink, compute each user's metrics there with the embedded network model, POST them "
        "to the service (token from TUPA_API_TOKEN). Plays the scenarios of --scenarios FILE, "
        "or generated ones, one after the other.",
    )
    ctl.add_argument("--api", default="http://127.0.0.1:8080", help="the service's base URL")
    ctl.add_argument(
        "--environment",
        choices=ENVIRONMENTS,
        default="open",
        help="the channel of generated scenarios (a --scenarios file says its own)",
    )
    ctl.add_argument(
        "--mavlink", default="tcp:127.0.0.1:5760", help="the autopilot (true position)"
    )
    ctl.add_argument(
        "--area-origin-north-m",
        type=float,
        default=float(os.environ.get("TUPA_AREA_ORIGIN_NORTH_M", 0.0)),
        help="north offset of the area's south-west corner from home (as tupa serve's)",
    )
    ctl.add_argument(
        "--area-origin-east-m",
        type=float,
        default=float(os.environ.get("TUPA_AREA_ORIGIN_EAST_M", 0.0)),
        help="east offset of the area's south-west corner from home (as tupa serve's)",
    )
    ctl.add_argument(
        "--fleet-file",
        type=Path,
        metavar="FILE",
        help="a fleet: tupa serve's fleet file (each vehicle's connection, system id and area "
        "origin; --mavlink and --area-origin-* unused); the fleet model (one AP per vehicle) "
        "measures the users, generated in hot spots unless --scenarios says otherwise",
    )
    ctl.add_argument("--scenarios", type=Path, metavar="FILE", help="tupa-scenarios/1 JSON")
    ctl.add_argument("--users", type=int, default=3, help="users per generated scenario")
    ctl.add_argument("--count", type=int, default=5, help="generated scenarios (default 5)")
    ctl.add_argument("--steps", type=int, default=60, help="steps per scenario (default 60)")
    ctl.add_argument("--step-s", type=float, default=1.0)
    ctl.add_argument("--seed", type=int, default=1)
    ctl.set_defaults(handler=_controller_sim)


def _positive(name: str, value: float) -> None:
    from sim.errors import InputError

    if not value > 0:
        raise InputError(f"{name}: must be positive, got {value}")


def _demo(args: argparse.Namespace) -> int:
    from sim.errors import InputError
    from sim.fleet import MAX_UAVS

    if not 1 <= args.uavs <= MAX_UAVS:
        raise InputError(f"--uavs: must be in 1..{MAX_UAVS}, got {args.uavs}")
    if args.uavs > 1:
        return _fleet_demo(args)
    from closed_loop.demo import DemoConfig, run_demo

    scenarios = 3 if args.scenarios is None else args.scenarios
    steps = 40 if args.steps is None else args.steps
    _positive("scenarios", scenarios)
    _positive("steps", steps)
    run_demo(
        DemoConfig(
            policy=args.policy,
            scenarios=scenarios,
            steps=steps,
            seed=args.seed,
            flavour=args.flavour,
            out_dir=Path("runs/demo") if args.out is None else args.out,
            environment=args.environment,
        )
    )
    return 0


def _fleet_demo(args: argparse.Namespace) -> int:
    """``tupa demo --uavs K`` with K >= 2: :mod:`closed_loop.fleet_demo`."""
    from closed_loop.fleet_demo import FleetDemoConfig, parse_policies, run_fleet_demo
    from sim.errors import InputError

    if args.scenarios is not None:
        raise InputError("--scenarios: the fleet demo (--uavs 2..8) plays one scenario")
    steps = 60 if args.steps is None else args.steps
    _positive("steps", steps)
    run_fleet_demo(
        FleetDemoConfig(
            uavs=args.uavs,
            policies=parse_policies(args.policy),
            steps=steps,
            seed=args.seed,
            flavour=args.flavour,
            out_dir=Path("runs/demo-fleet") if args.out is None else args.out,
            environment=args.environment,
        )
    )
    return 0


def _controller_sim(args: argparse.Namespace) -> int:
    if args.fleet_file is not None:
        return _fleet_controller_sim(args)
    import httpx

    from closed_loop.controller import SimulatedNetwork, TruePosition, run_scenario
    from service.frames import FrameConfig
    from sim.config import AreaConfig
    from sim.scenarios import generate_scenarios

    _positive("steps", args.steps)
    _positive("step-s", args.step_s)
    area = AreaConfig(environment=args.environment)
    if args.scenarios is not None:
        from sim.files import load_scenarios

        area, scenarios = load_scenarios(args.scenarios)  # the file's environment
    else:
        _positive("count", args.count)
        scenarios = generate_scenarios(args.count, args.users, seed=args.seed)
    token = os.environ.get("TUPA_API_TOKEN", "")
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    frames = FrameConfig(args.area_origin_north_m, args.area_origin_east_m)
    vehicle = TruePosition(args.mavlink, frames).start()
    try:
        with httpx.Client(base_url=args.api, headers=headers, timeout=10.0) as client:
            for i, scenario in enumerate(scenarios):
                network = SimulatedNetwork(scenario, area=area, seed=args.seed + i)
                records = run_scenario(network, vehicle, client, args.steps, args.step_s)
                mean = sum(r.utility for r in records) / len(records)
                print(f"scenario {scenario.id}: mean utility {mean:.3f}", flush=True)
    finally:
        vehicle.close()
    return 0


def _fleet_controller_sim(args: argparse.Namespace) -> int:
    """``tupa controller-sim --fleet-file FILE``: :mod:`closed_loop.fleet_controller` driving
    the fleet the file names, one report of all users per step."""
    import httpx
    import numpy as np

    from closed_loop.controller import TruePosition
    from closed_loop.fleet_controller import (
        SimulatedFleetNetwork,
        run_fleet_scenario,
        summarise,
    )
    from service.fleet_spec import load_fleet_file
    from sim.config import AreaConfig
    from sim.fleet import FleetConfig
    from sim.scenarios import generate_scenarios
    from sim.users import UserDynamics
    from sim.world import Demand, Mobility

    _positive("steps", args.steps)
    _positive("step-s", args.step_s)
    spec = load_fleet_file(args.fleet_file)
    area = AreaConfig(environment=args.environment)
    if args.scenarios is not None:
        from sim.files import load_scenarios

        area, scenarios = load_scenarios(args.scenarios)
    else:
        _positive("count", args.count)
        scenarios = generate_scenarios(
            args.count, args.users, seed=args.seed, area=area, family="hotspots"
        )
    fleet = FleetConfig(n_uavs=len(spec), separation_m=spec.separation_m)
    token = os.environ.get("TUPA_API_TOKEN", "")
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    vehicles = {
        v.id: TruePosition(v.mavlink, v.frames, system_id=v.system_id).start()
        for v in spec.vehicles
    }
    try:
        with httpx.Client(base_url=args.api, headers=headers, timeout=10.0) as client:
            for i, scenario in enumerate(scenarios):
                rng = np.random.default_rng(args.seed * 1000 + i)
                users = UserDynamics(
                    scenario.users_xy_m, scenario.load_bps, Mobility(), Demand(), area, rng
                )
                network = SimulatedFleetNetwork(
                    users, fleet, area=area, seed=args.seed + i, users_rng=rng
                )
                records = run_fleet_scenario(network, vehicles, client, args.steps, args.step_s)
                m = summarise(records)
                print(
                    f"scenario {scenario.id}: mean utility {m['utility']:.3f}, served "
                    f"{m['served_fraction']:.2f}, Jain {m['jain_fairness']:.2f}, min throughput "
                    f"{m['min_throughput_bps'] / 1e6:.2f} Mbit/s, handovers {m['handovers']}",
                    flush=True,
                )
    finally:
        for vehicle in vehicles.values():
            vehicle.close()
    return 0
