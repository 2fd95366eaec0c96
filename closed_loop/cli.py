"""``tupa demo`` (the closed loop behind ``make run``) and ``tupa controller-sim``."""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sim.config import ENVIRONMENTS


def register(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo",
        allow_abbrev=False,
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
        "--scenarios",
        metavar="FILE",
        help="fly the scenarios of this tupa-scenarios/1 file, in its environment (default: "
        "heterogeneous ones generated with --seed); the last one with walking users",
    )
    demo.add_argument(
        "--n-scenarios",
        type=int,
        metavar="N",
        help="how many scenarios: generated ones (default 3), or the first N of --scenarios "
        "FILE (the fleet demo plays one)",
    )
    demo.add_argument(
        "--steps", type=int, help="1-s steps per scenario (default 40; the fleet demo's 60)"
    )
    demo.add_argument("--seed", type=int, default=7)
    demo.add_argument("--flavour", choices=("px4", "ardupilot"), default="px4")
    demo.add_argument(
        "--environment",
        default=None,
        metavar="ENV",
        help=f"what stands on the ground: {', '.join(ENVIRONMENTS)} or site:PATH (a site "
        "directory, docs/sites.md: users on its walkable ground, its buildings in track.png); "
        "the simulated network's channel and the service's (default: the --scenarios file's, "
        "else open, the paper's)",
    )
    demo.add_argument(
        "--out", type=Path, metavar="DIR", help="default runs/demo (the fleet's: runs/demo-fleet)"
    )
    demo.set_defaults(handler=_demo)

    ctl = subparsers.add_parser(
        "controller-sim",
        allow_abbrev=False,
        help="a network controller played by the simulator, POSTing reports to a service",
        description="Every step: read the vehicle's true position from the autopilot over "
        "MAVLink, compute each user's metrics there with the embedded network model, POST them "
        "to the service (token from TUPA_API_TOKEN). Plays the scenarios of --scenarios FILE, "
        "or generated ones, one after the other.",
    )
    ctl.add_argument("--api", default="http://127.0.0.1:8080", help="the service's base URL")
    ctl.add_argument(
        "--environment",
        default="open",
        metavar="ENV",
        help=f"the channel of generated scenarios: {', '.join(ENVIRONMENTS)} or site:PATH (a "
        "site directory: users on its walkable ground) (default open; a --scenarios file says "
        "its own)",
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
    ctl.add_argument(
        "--wait-s",
        type=float,
        default=30.0,
        metavar="S",
        help="how long to keep trying a service that is not answering yet at start (it may be "
        "starting beside this one; default 30); then one line and exit code 2",
    )
    ctl.add_argument("--seed", type=int, default=1)
    ctl.set_defaults(handler=_controller_sim)


def _positive(name: str, value: float) -> None:
    from sim.errors import InputError

    if not value > 0:
        raise InputError(f"{name}: must be positive, got {value}")


def _check_environment(value: str | None) -> str | None:
    """``--environment`` checked before anything starts (None stays None): a named environment,
    or ``site:PATH`` with a sound site there that covers the default area; otherwise one
    InputError line naming ``--environment`` (:func:`sim.config.check_environment`)."""
    if value is None:
        return None
    from sim.channel import area_site
    from sim.config import AreaConfig, check_environment
    from sim.errors import InputError

    environment = check_environment(value, "--environment", on_disk=True)
    try:
        area_site(AreaConfig(environment=environment))  # a site: sound and covering the area
    except InputError as exc:
        raise InputError(f"--environment: {str(exc).removeprefix('environment: ')}") from None
    return environment


def _demo(args: argparse.Namespace) -> int:
    from sim.errors import InputError
    from sim.fleet import MAX_UAVS

    if not 1 <= args.uavs <= MAX_UAVS:
        raise InputError(f"--uavs: must be in 1..{MAX_UAVS}, got {args.uavs}")
    args.environment = _check_environment(args.environment)
    if args.uavs > 1:
        return _fleet_demo(args)
    from dataclasses import replace

    import closed_loop.demo as demo

    steps = 40 if args.steps is None else args.steps
    _positive("steps", steps)
    cfg = demo.DemoConfig(
        policy=args.policy,
        scenario_file=None if args.scenarios is None else _scenario_file(args.scenarios),
        n_scenarios=args.n_scenarios,
        steps=steps,
        seed=args.seed,
        flavour=args.flavour,
        out_dir=Path("runs/demo") if args.out is None else args.out,
        environment=args.environment,
    )
    area, _ = demo.demo_scenarios(cfg)  # a bad file or count: one line before anything starts
    demo.run_demo(replace(cfg, environment=area.environment))
    return 0


def _scenario_file(text: str) -> Path:
    """``--scenarios``' file; a bare count (what ``--scenarios`` took before it took a file, as
    every other command's does) is refused naming ``--n-scenarios``."""
    from sim.errors import InputError

    path = Path(text)
    if text.strip().isdigit() and not path.exists():
        raise InputError(
            f"--scenarios: takes a scenario file (tupa-scenarios/1 JSON), as tupa eval's does; "
            f"for {text.strip()} generated scenarios use --n-scenarios {text.strip()}"
        )
    return path


def _fleet_demo(args: argparse.Namespace) -> int:
    """``tupa demo --uavs K`` with K >= 2: :mod:`closed_loop.fleet_demo`."""
    from closed_loop.fleet_demo import FleetDemoConfig, parse_policies, run_fleet_demo
    from sim.errors import InputError

    if args.scenarios is not None:
        raise InputError("--scenarios: the fleet demo (--uavs 2..8) plays its own hot spots")
    if args.n_scenarios is not None:
        raise InputError("--n-scenarios: the fleet demo (--uavs 2..8) plays one scenario")
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
            environment=args.environment or "open",
        )
    )
    return 0


def _controller_sim(args: argparse.Namespace) -> int:
    if args.fleet_file is not None:
        return _fleet_controller_sim(args)
    from closed_loop.controller import SimulatedNetwork, TruePosition, run_scenario
    from service.fleet_spec import check_connection
    from service.frames import FrameConfig
    from sim.config import AreaConfig
    from sim.errors import InputError
    from sim.scenarios import generate_scenarios

    _positive("steps", args.steps)
    _positive("step-s", args.step_s)
    if not args.wait_s >= 0:
        raise InputError(f"--wait-s: must be >= 0, got {args.wait_s}")
    area = AreaConfig(environment=_check_environment(args.environment) or "open")
    if args.scenarios is not None:
        from sim.files import load_scenarios

        area, scenarios = load_scenarios(args.scenarios)  # the file's environment
    else:
        _positive("count", args.count)
        scenarios = generate_scenarios(args.count, args.users, seed=args.seed, area=area)
    check_connection(args.mavlink, "--mavlink")
    frames = FrameConfig(args.area_origin_north_m, args.area_origin_east_m)
    with _service_client(args.api, args.wait_s) as client, _one_line_errors(args.api, "--mavlink"):
        vehicle = TruePosition(args.mavlink, frames).start()
        try:
            vehicle.wait(timeout_s=POSITION_TIMEOUT_S)
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
    import numpy as np

    from closed_loop.controller import TruePosition
    from closed_loop.fleet_controller import (
        SimulatedFleetNetwork,
        run_fleet_scenario,
        summarise,
    )
    from service.fleet_spec import load_fleet_file
    from sim.config import AreaConfig
    from sim.errors import InputError
    from sim.fleet import FleetConfig
    from sim.scenarios import generate_scenarios
    from sim.users import UserDynamics
    from sim.world import Demand, Mobility

    _positive("steps", args.steps)
    _positive("step-s", args.step_s)
    if not args.wait_s >= 0:
        raise InputError(f"--wait-s: must be >= 0, got {args.wait_s}")
    area = AreaConfig(environment=_check_environment(args.environment) or "open")
    spec = load_fleet_file(args.fleet_file)
    if args.scenarios is not None:
        from sim.files import load_scenarios

        area, scenarios = load_scenarios(args.scenarios)
    else:
        _positive("count", args.count)
        scenarios = generate_scenarios(
            args.count, args.users, seed=args.seed, area=area, family="hotspots"
        )
    fleet = FleetConfig(n_uavs=len(spec), separation_m=spec.separation_m)
    with (
        _service_client(args.api, args.wait_s) as client,
        _one_line_errors(args.api, "--fleet-file"),
    ):
        vehicles = {
            v.id: TruePosition(v.mavlink, v.frames, system_id=v.system_id).start()
            for v in spec.vehicles
        }
        try:
            for vehicle in vehicles.values():
                vehicle.wait(timeout_s=POSITION_TIMEOUT_S)
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


POSITION_TIMEOUT_S = 30.0
"""How long ``tupa controller-sim`` waits for each autopilot's first position."""
HTTP_TIMEOUT_S = 10.0
"""How long it waits for each answer of the service."""


@contextmanager
def _service_client(api: str, wait_s: float) -> Iterator[Any]:  # an httpx.Client (lazy import)
    """A client of the service at ``api`` carrying ``TUPA_API_TOKEN``, checked first by one
    authenticated request (``GET /v1/policy``), tried again every half second for ``wait_s``
    while nothing answers (a service starting beside this one): a service that is down, refuses
    the token or is not a TUPA service is an ``InputError`` naming ``--api`` or
    ``TUPA_API_TOKEN``."""
    import time

    import httpx

    from sim.errors import InputError

    token = os.environ.get("TUPA_API_TOKEN", "")
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    deadline = time.monotonic() + wait_s
    with httpx.Client(base_url=api, headers=headers, timeout=HTTP_TIMEOUT_S) as client:
        with _one_line_errors(api, "--mavlink"):
            while True:
                try:
                    response = client.get("/v1/policy")
                    break
                except (httpx.ConnectError, httpx.RemoteProtocolError):
                    if time.monotonic() >= deadline:
                        raise
                    time.sleep(0.5)
            if response.status_code == 401:
                raise InputError(
                    f"TUPA_API_TOKEN: the service at {api} refused TUPA_API_TOKEN "
                    "(401 Unauthorized): it is not the service's token"
                    if token
                    else f"TUPA_API_TOKEN: not set, and the service at {api} wants a token "
                    "(401 Unauthorized)"
                )
            response.raise_for_status()
        yield client


@contextmanager
def _one_line_errors(api: str, position_option: str) -> Iterator[None]:
    """What may end a controller's run, as one ``InputError`` line: the service refusing a
    request (``--api``: the request, the status and the service's reason), unreachable or not
    answering (``--api``), an autopilot giving no position (``position_option``)."""
    import httpx

    from sim.errors import InputError

    try:
        yield
    except httpx.HTTPStatusError as exc:
        request, response = exc.request, exc.response
        try:
            detail = response.json().get("detail")
        except (ValueError, AttributeError):
            detail = None
        reason = f": {' '.join(str(detail).split())[:200]}" if detail else ""
        raise InputError(
            f"--api: the service at {api} answered {request.method} {request.url.path} with "
            f"{response.status_code} {response.reason_phrase}{reason}"
        ) from None
    except httpx.TimeoutException:
        raise InputError(
            f"--api: the service at {api} did not answer within {HTTP_TIMEOUT_S:g} s"
        ) from None
    except httpx.TransportError as exc:
        raise InputError(
            f"--api: cannot reach the service at {api} ({' '.join(str(exc).split())}); is "
            "tupa serve running there?"
        ) from None
    except TimeoutError as exc:
        raise InputError(f"{position_option}: {exc}") from None
