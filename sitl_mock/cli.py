"""``tupa sitl-mock``: run the MAVLink autopilot simulator from the shell.

Only argparse at module level: pymavlink and the simulator are imported inside the handler, so
``tupa --help`` stays fast. Bad arguments print one line naming the option and return 2.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sitl_mock.geo import GeoPoint


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sitl-mock`` subcommand."""
    parser = subparsers.add_parser(
        "sitl-mock",
        allow_abbrev=False,
        help="run a MAVLink autopilot simulator (ArduPilot Copter or PX4 flavour)",
        description=(
            "Serve one simulated multicopter over MAVLink 2, behaving like ArduPilot Copter "
            "(GUIDED) or PX4 (OFFBOARD): modes, arming checks, takeoff/land/RTL, position "
            "setpoints, geofence, failsafes, battery. With --vehicles N, a fleet of N independent "
            "vehicles: system ids --system-id, +1, ...; one port each; homes --spacing-m apart. "
            "Runs until interrupted (Ctrl-C or SIGTERM)."
        ),
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=None,
        help="tcp:HOST:PORT (server, several clients), udp:HOST:PORT (bind and answer senders) "
        "or udpout:HOST:PORT (send to a client listening there, as PX4 SITL does); port 0 picks "
        "a free one (default tcp:127.0.0.1:5760). With --vehicles N: vehicle i uses PORT+i "
        "(port 0: each a free one), or repeat --listen once per vehicle",
    )
    parser.add_argument(
        "--vehicles",
        type=int,
        default=None,
        metavar="N",
        help="serve a fleet of N vehicles (1..8) in this process, one port and one system id "
        "each, printing one line per vehicle (default: 1, or one per repeated --listen)",
    )
    parser.add_argument(
        "--spacing-m",
        type=float,
        default=15.0,
        help="fleet: each vehicle's home this far east of the previous one's (default 15, more "
        "than the fleet's 10 m separation)",
    )
    parser.add_argument(
        "--flavour", choices=("ardupilot", "px4"), default="ardupilot", help="default ardupilot"
    )
    parser.add_argument(
        "--home",
        default=None,
        metavar="LAT,LON,ALT",
        help="home position: degrees, degrees, metres AMSL (default: the flavour's SITL home)",
    )
    parser.add_argument(
        "--speed-mps", type=float, default=10.0, help="max horizontal speed (default 10)"
    )
    parser.add_argument(
        "--climb-speed-mps", type=float, default=3.0, help="max vertical speed (default 3)"
    )
    parser.add_argument(
        "--accel-mps2",
        type=float,
        default=2.5,
        help="max horizontal acceleration (default 2.5, ArduPilot's WPNAV_ACCEL)",
    )
    parser.add_argument(
        "--signing-key",
        default=None,
        metavar="HEX",
        help="MAVLink 2 signing key, 64 hex digits (32 bytes): unsigned or wrongly signed "
        "commands and setpoints are then ignored",
    )
    parser.add_argument(
        "--ready-delay-s",
        type=float,
        default=None,
        help="seconds until the position estimate is ready; arming in GUIDED/OFFBOARD is "
        "refused before (default: 40 for ardupilot, 10 for px4)",
    )
    parser.add_argument(
        "--origin-delay-s",
        type=float,
        default=None,
        help="seconds until the EKF origin is set; no LOCAL_POSITION_NED before (default: 19 "
        "for ardupilot, 10 for px4; never later than --ready-delay-s)",
    )
    parser.add_argument(
        "--prearm-delay-s",
        type=float,
        default=None,
        help="seconds until the pre-arm checks pass: arming in modes that need no position "
        "(default: 22 for ardupilot, 10 for px4; never later than --ready-delay-s)",
    )
    parser.add_argument(
        "--mode-switch-read-s",
        type=float,
        default=None,
        help="ardupilot: when the RC mode switch is first read and sets STABILIZE, undoing an "
        "earlier GUIDED, as a real ArduCopter SITL did (default 2.2; never later than "
        "--ready-delay-s; negative: never)",
    )
    parser.add_argument(
        "--offboard-timeout-s",
        type=float,
        default=1.0,
        help="PX4 OFFBOARD: hold when setpoints stop for this long (default 1, COM_OF_LOSS_T)",
    )
    parser.add_argument(
        "--offboard-stream-min-s",
        type=float,
        default=1.0,
        help="PX4: setpoints must stream (> 2 Hz) this long before OFFBOARD is accepted "
        "(default 1)",
    )
    parser.add_argument(
        "--auto-disarm-s",
        type=float,
        default=10.0,
        help="disarm when armed on the ground without takeoff for this long (default 10)",
    )
    parser.add_argument(
        "--gcs-failsafe-s",
        type=float,
        default=5.0,
        help="armed and no ground-station heartbeat for this long: failsafe (default 5)",
    )
    parser.add_argument(
        "--gcs-failsafe-action",
        choices=("rtl", "land", "none"),
        default="rtl",
        help="what the ground-station failsafe does in the air (default rtl)",
    )
    parser.add_argument(
        "--fence-radius-m",
        type=float,
        default=1000.0,
        help="horizontal geofence radius around home, 0 for none (default 1000)",
    )
    parser.add_argument(
        "--fence-alt-max-m",
        type=float,
        default=150.0,
        help="geofence ceiling above home, 0 for none (default 150)",
    )
    parser.add_argument(
        "--fence-action",
        choices=("reject", "clamp"),
        default="reject",
        help="setpoints outside the fence: ignore them, or go to the nearest fence point",
    )
    parser.add_argument("--battery-capacity-mah", type=float, default=5000.0, help="default 5000")
    parser.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="run the vehicles' clock this many times faster than the wall clock (their flight, "
        "boot, telemetry and timers, as ArduPilot SITL's --speedup; at most 10; default 1: "
        "real time)",
    )
    parser.add_argument(
        "--system-id",
        "--sysid-base",
        dest="system_id",
        type=int,
        default=1,
        help="MAVLink system id of the vehicle; in a fleet, of the first one, vehicle i having "
        "this + i (default 1)",
    )
    parser.add_argument(
        "--log-level",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        default="INFO",
        help="default INFO",
    )
    parser.set_defaults(handler=run)


def _error(message: str) -> int:
    print(f"tupa sitl-mock: error: {message}", file=sys.stderr)
    return 2


def _parse_home(text: str) -> GeoPoint:
    from sitl_mock.geo import GeoPoint

    parts = text.split(",")
    if len(parts) != 3:
        raise ValueError(f"expected LAT,LON,ALT, got {text!r}")
    lat, lon, alt = (float(part) for part in parts)
    return GeoPoint(lat, lon, alt)


def run(args: argparse.Namespace) -> int:
    """Start the simulator with ``args`` and serve until SIGINT or SIGTERM."""
    import logging
    import math
    import signal
    import threading

    from sitl_mock.config import VehicleConfig
    from sitl_mock.fleet import MAX_VEHICLES, MockFleet, fleet_listens
    from sitl_mock.server import MAX_SPEEDUP, parse_listen

    listens: list[str] = args.listen or ["tcp:127.0.0.1:5760"]
    for listen in listens:
        try:
            parse_listen(listen)
        except ValueError as exc:
            return _error(f"--listen: {exc}")
    count = args.vehicles if args.vehicles is not None else len(listens)
    if not 1 <= count <= MAX_VEHICLES:
        return _error(f"--vehicles: must be in 1..{MAX_VEHICLES}, got {count}")
    try:
        fleet_listens(listens[0] if len(listens) == 1 else listens, count)
    except ValueError as exc:
        return _error(f"--listen: {str(exc).split(': ', 1)[-1]}")
    home = None
    if args.home is not None:
        try:
            home = _parse_home(args.home)
        except ValueError as exc:
            return _error(f"--home: {exc}")
    signing_key = None
    if args.signing_key is not None:
        try:
            signing_key = bytes.fromhex(args.signing_key)
        except ValueError:
            return _error("--signing-key: not hexadecimal")
        if len(signing_key) != 32:
            return _error(
                f"--signing-key: must be 32 bytes (64 hex digits), got {len(signing_key)}"
            )
    if not 1 <= args.system_id <= 255:
        return _error(f"--system-id: must be in 1..255, got {args.system_id}")
    if args.system_id + count - 1 > 255:
        return _error(
            f"--system-id/--sysid-base: {count} vehicles from system id {args.system_id} "
            "would go past 255"
        )
    if not (math.isfinite(args.speedup) and 0 < args.speedup <= MAX_SPEEDUP):
        return _error(f"--speedup: must be in (0, {MAX_SPEEDUP:g}], got {args.speedup}")
    if not (math.isfinite(args.spacing_m) and args.spacing_m > 0):
        return _error(f"--spacing-m: must be a positive number, got {args.spacing_m}")
    config = VehicleConfig(
        home=home,
        max_speed_h_mps=args.speed_mps,
        max_speed_up_mps=args.climb_speed_mps,
        max_speed_down_mps=args.climb_speed_mps,
        ready_delay_s=args.ready_delay_s,
        origin_delay_s=args.origin_delay_s,
        prearm_delay_s=args.prearm_delay_s,
        mode_switch_read_s=args.mode_switch_read_s,
        accel_h_mps2=args.accel_mps2,
        offboard_timeout_s=args.offboard_timeout_s,
        offboard_stream_min_s=args.offboard_stream_min_s,
        auto_disarm_s=args.auto_disarm_s,
        gcs_failsafe_s=args.gcs_failsafe_s,
        gcs_failsafe_action=args.gcs_failsafe_action,
        fence_radius_m=args.fence_radius_m or None,
        fence_alt_max_m=args.fence_alt_max_m or None,
        fence_action=args.fence_action,
        battery_capacity_mah=args.battery_capacity_mah,
    )
    try:
        config.validate()
    except ValueError as exc:
        option = {
            "home": "--home",
            "max_speed_h_mps": "--speed-mps",
            "max_speed_up_mps": "--climb-speed-mps",
            "max_speed_down_mps": "--climb-speed-mps",
            "ready_delay_s": "--ready-delay-s",
            "origin_delay_s": "--origin-delay-s",
            "prearm_delay_s": "--prearm-delay-s",
            "mode_switch_read_s": "--mode-switch-read-s",
            "offboard_timeout_s": "--offboard-timeout-s",
            "offboard_stream_min_s": "--offboard-stream-min-s",
            "accel_h_mps2": "--accel-mps2",
            "auto_disarm_s": "--auto-disarm-s",
            "gcs_failsafe_s": "--gcs-failsafe-s",
            "fence_radius_m": "--fence-radius-m",
            "fence_alt_max_m": "--fence-alt-max-m",
            "battery_capacity_mah": "--battery-capacity-mah",
        }.get(str(exc).split(":", 1)[0], "argument")
        return _error(f"{option}: {str(exc).split(': ', 1)[-1]}")

    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    fleet = MockFleet(
        count,
        listens[0] if len(listens) == 1 else listens,
        flavour=args.flavour,
        config=config,
        signing_key=signing_key,
        system_id_base=args.system_id,
        spacing_m=args.spacing_m,
        speedup=args.speedup,
    )
    try:
        fleet.start()
    except OSError as exc:
        print(f"tupa sitl-mock: error: --listen: {exc.strerror}", file=sys.stderr)
        return 1
    stop = threading.Event()

    def _on_signal(signum: int, _frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    # One line on stdout that scripts (and tests using port 0) can read.
    # One write, newline included (print() writes the newline separately; a log line from the
    # server thread could land in between and hide the line from scripts reading it).
    # A fleet: one line per vehicle, "sitl-mock FLAVOUR sysid ID listening on ADDRESS", all in
    # that one write.
    if count == 1:
        lines = [f"sitl-mock {args.flavour} listening on {fleet[0].address}\n"]
    else:
        lines = [
            f"sitl-mock {args.flavour} sysid {system_id} listening on {address}\n"
            for system_id, address in zip(fleet.system_ids, fleet.addresses, strict=True)
        ]
    sys.stdout.write("".join(lines))
    sys.stdout.flush()
    try:
        while not stop.wait(0.5):
            pass
    finally:
        fleet.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for mock in fleet:
            logging.getLogger(__name__).info(
                "stopped sysid %d; counters: %s", mock.protocol.system_id, mock.stats
            )
    return 0
