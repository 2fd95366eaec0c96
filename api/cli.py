"""``tupa serve``: the placement service over HTTP (uvicorn), commanding a vehicle over MAVLink."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Serve the placement API and stream the chosen targets to the autopilot over MAVLink.

Every option can also come from a TUPA_* environment variable (TUPA_MAVLINK, TUPA_POLICY,
TUPA_API_TOKEN, TUPA_MAVLINK_SIGNING_KEY, TUPA_DECISION_MODE, ...); options win. Without an API
token (TUPA_API_TOKEN, or --api-token-file FILE) the service refuses to start unless --insecure
is given. A connection string pymavlink cannot open is refused at start, as in a fleet file.
The vehicle is never armed unless --arm-and-takeoff is given.

Examples:
  TUPA_API_TOKEN=secret tupa serve --mavlink tcp:127.0.0.1:5760          # ArduPilot SITL
  TUPA_API_TOKEN=secret tupa serve --mavlink udpin:0.0.0.0:14540          # PX4 SITL (offboard)
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve",
        allow_abbrev=False,
        help="run the placement service (HTTP API + MAVLink setpoint streaming)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--mavlink",
        metavar="CONN",
        action="append",
        help="pymavlink connection string: tcp:HOST:PORT, tcpin:, udp:, udpin:, udpout:, "
        "udpbcast:, or a serial device path (default tcp:127.0.0.1:5760); repeat it to drive a "
        "fleet whose vehicles share one frame (vehicles uav1, uav2, ...)",
    )
    parser.add_argument(
        "--fleet-file",
        type=Path,
        metavar="FILE",
        help="drive a fleet of 1-8 vehicles: YAML with one MAVLink connection, frame and "
        "optional system id per vehicle (service/fleet_spec.py); the policy is then a fleet "
        "one: kmeans-scored (default), kmeans-load-weighted, kmeans-min-distance, fleet-oracle",
    )
    parser.add_argument(
        "--envelope",
        type=Path,
        metavar="FILE",
        dest="envelope_file",
        help="the flight-safety envelope (tupa-envelope/1 JSON, sim/envelope/files.py): "
        "inclusion polygon, no-fly volumes, altitude band, clearance; targets are moved into it "
        "and flown to along legal routes (default: the area's box; a fleet file's vehicles may "
        "have their own)",
    )
    parser.add_argument(
        "--separation-m",
        type=float,
        metavar="M",
        help="a fleet's minimum 3-D distance between any two targets (default 10)",
    )
    parser.add_argument("--mavlink-backend", choices=("pymavlink", "mavsdk"))
    parser.add_argument(
        "--policy",
        metavar="PATH|NAME",
        help="checkpoint, or min-distance, load-weighted, min-distance-env, oracle (default: "
        "oracle, the tracking oracle; see service/policy_runtime.py)",
    )
    parser.add_argument(
        "--arm-and-takeoff",
        action="store_true",
        default=None,
        help="arm and take off to the minimum altitude before the first placement",
    )
    parser.add_argument(
        "--takeoff-timeout-s",
        type=float,
        metavar="S",
        help="how long the take-off sequence keeps trying, refusals retried with backoff "
        "(default 300: a real vehicle needs its GPS lock and pre-arm checks first)",
    )
    parser.add_argument(
        "--autopilot-fence",
        action="store_true",
        default=None,
        help="also put the envelope on the autopilot as its own fence (polygons, ceiling, breach "
        "action), read it back, and neither take off nor stream until it is there (pymavlink "
        "backend)",
    )
    parser.add_argument(
        "--fence-action",
        choices=("rtl", "hold", "land", "report"),
        help="what the autopilot does on a fence breach, with --autopilot-fence (default rtl)",
    )
    parser.add_argument(
        "--battery-reserve-pct",
        type=_reserve,
        metavar="PCT|off",
        help="charge to be left on landing: at what flying home takes plus this, the service "
        "ends the placement and commands the return (RTL) before the autopilot's own failsafe "
        "(default 20; off: never, the autopilot's failsafe still acts)",
    )
    parser.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to listen on (default 8080; 0: any free)")
    parser.add_argument(
        "--api-token-file",
        type=Path,
        metavar="FILE",
        help="read the API token from FILE (or set TUPA_API_TOKEN)",
    )
    parser.add_argument(
        "--insecure", action="store_true", default=None, help="allow serving without a token"
    )
    parser.add_argument("--decision-mode", choices=("paced", "on-report"))
    parser.add_argument(
        "--world",
        help="the world the policy was trained for (default closed-loop): its decision period",
    )
    parser.add_argument(
        "--environment",
        help="what stands on the ground: open (default, the paper's), suburban, urban, "
        "dense-urban, highrise-urban, or site:PATH, a ray-traced district (tupa site build) "
        "(the channel the policy and the oracle assume)",
    )
    parser.add_argument(
        "--step-s", type=float, help="decision period in seconds (default: the world's, 1)"
    )
    parser.add_argument("--report-max-age-s", type=float, help="older reports are stale")
    parser.add_argument("--state-file", type=Path, help="persist the last target and policy here")
    parser.add_argument(
        "--rate-limit-rps",
        type=float,
        metavar="N",
        help="requests/s each client may make on average, then 429 (default 200; 0: no limit)",
    )
    parser.add_argument(
        "--rate-limit-burst",
        type=int,
        metavar="N",
        help="requests a client may make at once above its rate (default 400)",
    )
    parser.add_argument(
        "--log-level", default="info", choices=("debug", "info", "warning", "error")
    )
    parser.set_defaults(handler=_serve)


_SETTING_ARGS = (
    "mavlink_backend",
    "fleet_file",
    "envelope_file",
    "separation_m",
    "policy",
    "arm_and_takeoff",
    "takeoff_timeout_s",
    "battery_reserve_pct",
    "autopilot_fence",
    "fence_action",
    "host",
    "port",
    "insecure",
    "decision_mode",
    "world",
    "environment",
    "step_s",
    "report_max_age_s",
    "state_file",
    "rate_limit_rps",
    "rate_limit_burst",
)


def _reserve(text: str) -> float | str:
    """``--battery-reserve-pct``: a number, or ``off``."""
    if text.strip().lower() == "off":
        return "off"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a percentage or 'off', got {text!r}") from None


def settings_from_args(args: argparse.Namespace):  # -> ServiceSettings (lazy import)
    """Options given on the command line over ``TUPA_*`` variables; ``InputError`` naming the
    field for a bad value."""
    from pydantic import ValidationError

    from service.errors import InputError
    from service.settings import ServiceSettings

    overrides = {name: getattr(args, name) for name in _SETTING_ARGS}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if overrides.get("battery_reserve_pct") == "off":
        overrides["battery_reserve_pct"] = None
    if args.mavlink and args.fleet_file is not None:
        raise InputError("fleet_file: give a fleet file or --mavlink, not both")
    if args.mavlink:  # one vehicle, or a fleet from repeated --mavlink
        if len(args.mavlink) == 1:
            overrides["mavlink"] = args.mavlink[0]
        else:
            overrides["fleet_mavlink"] = tuple(args.mavlink)
    if args.api_token_file is not None:
        try:
            overrides["api_token"] = args.api_token_file.read_text().strip()
        except OSError as exc:
            raise InputError(f"api-token-file: {exc}") from None
    try:
        return ServiceSettings(**overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(p) for p in first["loc"]) or "settings"
        message = str(first["msg"]).removeprefix("Value error, ")  # pydantic's own prefix
        raise InputError(f"{field}: {message}") from None


def _serve(args: argparse.Namespace) -> int:
    import logging

    from api.app import create_app
    from api.live import end_streams
    from api.server import server_config
    from service.errors import InputError
    from service.opening import open_service

    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    settings = settings_from_args(args)
    try:
        settings.check_startable()
    except ValueError as exc:
        raise InputError(str(exc)) from None
    service = open_service(settings)  # InputError for an unusable policy
    app = create_app(settings, service_factory=lambda _settings: service)

    import socket

    # Bind first, so that --port 0 gets a free port we can announce; uvicorn serves the socket.
    family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((settings.host, settings.port))
    except OSError as exc:
        service.close_links()
        raise InputError(f"port: cannot listen on {settings.host}:{settings.port}: {exc}") from None
    port = sock.getsockname()[1]
    # The server's limits (head size, read and keep-alive timeouts, connections, no proxy
    # headers unless trusted): api.server.
    config = server_config(
        app,
        settings,
        log_level=args.log_level,
        access_log=args.log_level == "debug",
        lifespan="on",
    )
    server = _announcing_server(config, f"http://{settings.host}:{port}")
    server.before_shutdown = lambda: end_streams(app)  # the live streams would hold it up
    server.run(sockets=[sock])
    return 0


def _announcing_server(config: Any, url: str) -> Any:
    """The server of :mod:`api.server`, printing where it listens on stdout once it accepts
    requests (scripts and tests read the first line to learn the port), and the operator view's
    address."""
    from api.server import Server

    class AnnouncingServer(Server):
        async def startup(self, sockets: list[Any] | None = None) -> None:
            await super().startup(sockets=sockets)
            if not self.should_exit:
                # One write, newline included: print() writes the text and the newline
                # separately, and a log line from another thread can land between them.
                sys.stdout.write(f"tupa serve listening on {url}\noperator view: {url}/\n")
                sys.stdout.flush()

    return AnnouncingServer(config)
