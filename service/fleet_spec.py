"""Which vehicles ``tupa serve`` drives: one, or a fleet of 1–8 from a fleet file or repeated
``--mavlink`` options.

A fleet file is YAML (JSON is YAML too)::

    separation_m: 10            # optional (default 10): the minimum 3-D distance between targets
    envelope: site.json         # optional: every vehicle's flight envelope (tupa-envelope/1,
                                #   sim/envelope/files.py; a path relative to this file)
    vehicles:                   # 1..8, in priority order (the first keeps its target in a conflict)
      - id: uav1                # letters, digits, '-' and '_'; unique
        mavlink: tcp:127.0.0.1:5760
        system_id: 1            # optional: the MAVLink system id this vehicle must have
        area_origin_north_m: 0  # optional: where the area's south-west corner at z = 0 lies
        area_origin_east_m: 0   #   from THIS vehicle's home, local NED (homes differ)
        area_origin_down_m: 0
        envelope: north.json    # optional: this vehicle's own envelope (else the fleet's)

Every problem is one :class:`~service.errors.InputError` naming the field
(``vehicles[1].mavlink: ...``): a fleet outside 1–8 vehicles, two vehicles with the same id,
connection or system id, a connection string pymavlink would not know, a separation that is not
a positive number, an unknown key, an envelope file that cannot be flown (or that puts a
vehicle's home inside a no-fly volume: :meth:`VehicleSpec.envelope`).
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from service.errors import InputError
from service.frames import FrameConfig, ned_to_area
from sim.config import AreaConfig
from sim.envelope import (
    Envelope,
    area_envelope,
    envelope_from_document,
    home_violation,
    load_envelope,
)
from sim.fleet import MAX_UAVS

SOLE_VEHICLE_ID = "uav1"
"""The id of a service's one vehicle where no fleet file names it (``tupa serve --mavlink``):
the key of its entry in every answer that lists vehicles."""

DEFAULT_SEPARATION_M = 10.0
"""The fleet's default minimum distance between any two targets, metres (3-D)."""

_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
_NETWORK_SCHEMES = ("tcp", "tcpin", "udp", "udpin", "udpout", "udpbcast")
_MAVSDK_SCHEMES = (
    "udp",
    "udpin",
    "udpout",
    "tcp",
    "tcpin",
    "tcpout",
    "serial",
    "serialflowcontrol",
)
_VEHICLE_KEYS = frozenset(
    {
        "id",
        "mavlink",
        "system_id",
        "area_origin_north_m",
        "area_origin_east_m",
        "area_origin_down_m",
        "envelope",
    }
)
_FLEET_KEYS = frozenset({"separation_m", "vehicles", "envelope"})


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of the fleet: its name in the API, its connection and its frame."""

    id: str
    mavlink: str
    system_id: int | None = None
    frames: FrameConfig = FrameConfig()  # noqa: RUF009 (frozen, so sharing it is safe)
    envelope_file: Path | None = None
    """Its flight envelope (``tupa-envelope/1``); None: the area's box."""

    def envelope(self, area: AreaConfig, field: str = "envelope") -> Envelope:
        """The vehicle's envelope over ``area`` (the area's box without a file); InputError
        naming ``field`` for a file that cannot be flown or that puts the vehicle's home (its
        take-off column) inside a no-fly volume."""
        if self.envelope_file is None:
            return area_envelope(area)
        envelope = load_envelope(self.envelope_file, area)
        check_home(envelope, self.frames, f"{field}: {self.envelope_file}")
        return envelope


def check_home(envelope: Envelope, frames: FrameConfig, field: str = "envelope") -> Envelope:
    """``envelope`` when a vehicle whose home the ``frames`` place can take off in it; else
    InputError naming ``field`` (its take-off would climb through a no-fly volume)."""
    home_x_m, home_y_m, _ = ned_to_area(0.0, 0.0, 0.0, frames)
    why = home_violation(envelope, (home_x_m, home_y_m))
    if why is not None:
        raise InputError(f"{field}: {why}")
    return envelope


def envelope_for(document: Any, area: AreaConfig, frames: FrameConfig) -> Envelope:
    """The envelope a ``tupa-envelope/1`` document (parsed JSON) describes, for a vehicle whose
    home the ``frames`` place; InputError naming the field (``envelope.<field>``)."""
    try:
        envelope = envelope_from_document(document, area)
    except InputError as exc:
        raise InputError(f"envelope.{exc}") from None
    return check_home(envelope, frames)


@dataclass(frozen=True)
class FleetSpec:
    """The vehicles, in priority order, and the separation every set of targets keeps."""

    vehicles: tuple[VehicleSpec, ...]
    separation_m: float = DEFAULT_SEPARATION_M

    def __post_init__(self) -> None:
        check_fleet(self)

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(v.id for v in self.vehicles)

    def __len__(self) -> int:
        return len(self.vehicles)


def check_connection(url: str, field: str, backend: str | None = None) -> str:
    """``url`` if the link can open it (``tcp:HOST:PORT``, ``udpin:``, ``udpout:``, ``udp:``,
    ``tcpin:``, ``udpbcast:``, or a serial device path with an optional ``,BAUD``; and, unless
    ``backend`` is ``"pymavlink"``, a MAVSDK URL such as ``udpin://HOST:PORT``, which the
    ``mavsdk`` backend passes through); otherwise InputError naming ``field`` and the problem
    (with the known scheme closest to a mistyped one). The one check of a connection string: a
    fleet file's, ``--mavlink``'s, and ``TUPA_MAVLINK``'s."""
    text = url.strip() if isinstance(url, str) else ""
    if not text:
        raise InputError(f"{field}: must be a MAVLink connection string, got {url!r}")
    if "://" in text and text.partition("://")[0] in _MAVSDK_SCHEMES:
        if backend == "pymavlink":
            raise InputError(
                f"{field}: {text!r} is a MAVSDK URL, which only --mavlink-backend mavsdk opens; "
                "pymavlink takes SCHEME:HOST:PORT (udpin:0.0.0.0:14540)"
            )
        return text
    if text.startswith(("/", "COM")):  # a serial device (optionally ",BAUD")
        baud = text.partition(",")[2]
        if baud and not baud.isdigit():
            raise InputError(f"{field}: serial baud rate {baud!r} is not a number")
        return text
    scheme, sep, rest = text.partition(":")
    if not sep or scheme not in _NETWORK_SCHEMES:
        close = difflib.get_close_matches(scheme, _NETWORK_SCHEMES, n=1) if sep else []
        hint = f"did you mean {close[0]}:{rest}? " if close else ""
        raise InputError(
            f"{field}: unknown connection {text!r}: {hint}expected one of "
            f"{', '.join(s + ':HOST:PORT' for s in _NETWORK_SCHEMES)} or a serial device path"
        )
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise InputError(f"{field}: {text!r} needs {scheme}:HOST:PORT with a port in 1..65535")
    return text


def check_fleet(fleet: FleetSpec) -> None:
    """InputError naming the field for a fleet the service cannot drive (module doc)."""
    k = len(fleet.vehicles)
    if not 1 <= k <= MAX_UAVS:
        raise InputError(f"vehicles: a fleet has 1..{MAX_UAVS} vehicles, got {k}")
    sep = fleet.separation_m
    if isinstance(sep, bool) or not isinstance(sep, int | float) or not math.isfinite(sep):
        raise InputError(f"separation_m: must be a number, got {sep!r}")
    if sep <= 0:
        raise InputError(f"separation_m: must be > 0, got {sep!r}")
    seen: dict[str, dict[object, int]] = {"id": {}, "mavlink": {}, "system_id": {}}
    for i, vehicle in enumerate(fleet.vehicles):
        if not isinstance(vehicle.id, str) or not _ID.match(vehicle.id):
            raise InputError(
                f"vehicles[{i}].id: 1-32 letters, digits, '-' or '_', got {vehicle.id!r}"
            )
        check_connection(vehicle.mavlink, f"vehicles[{i}].mavlink")
        sid = vehicle.system_id
        if sid is not None and (
            isinstance(sid, bool) or not isinstance(sid, int) or not 1 <= sid <= 255
        ):
            raise InputError(f"vehicles[{i}].system_id: must be an integer in 1..255, got {sid!r}")
        unique = (("id", vehicle.id), ("mavlink", vehicle.mavlink.strip()), ("system_id", sid))
        for key, value in unique:
            if value is None:
                continue
            if value in seen[key]:
                raise InputError(
                    f"vehicles[{i}].{key}: {value!r} is also vehicles[{seen[key][value]}]'s"
                )
            seen[key][value] = i


def single_vehicle(
    mavlink: str, frames: FrameConfig, envelope_file: Path | None = None
) -> FleetSpec:
    """The one-vehicle fleet of a plain ``tupa serve --mavlink URL`` (id
    :data:`SOLE_VEHICLE_ID`)."""
    return FleetSpec((VehicleSpec(SOLE_VEHICLE_ID, mavlink, None, frames, envelope_file),))


def fleet_from_urls(
    urls: list[str] | tuple[str, ...],
    frames: FrameConfig,
    separation_m: float,
    envelope_file: Path | None = None,
) -> FleetSpec:
    """A fleet from repeated ``--mavlink`` options: ids ``uav1``, ``uav2``, ..., all in the same
    frame (vehicles that share a home or an EKF origin; otherwise use a fleet file) and the same
    envelope."""
    vehicles = tuple(
        VehicleSpec(f"uav{i + 1}", url, None, frames, envelope_file) for i, url in enumerate(urls)
    )
    return FleetSpec(vehicles, separation_m)


def parse_fleet(
    data: Any,
    default_separation_m: float = DEFAULT_SEPARATION_M,
    base_dir: Path | None = None,
    default_envelope: Path | None = None,
) -> FleetSpec:
    """A :class:`FleetSpec` from a fleet file's parsed content (module doc); envelope paths are
    relative to ``base_dir`` (the fleet file's folder); a vehicle with none gets the fleet's,
    else ``default_envelope``."""
    if not isinstance(data, dict):
        raise InputError("fleet file: must be a mapping with a 'vehicles' list")
    unknown = sorted(set(map(str, data)) - _FLEET_KEYS)
    if unknown:
        raise InputError(f"{unknown[0]}: unknown key (expected {', '.join(sorted(_FLEET_KEYS))})")
    fleet_envelope = _envelope_path(data, "envelope", base_dir) or default_envelope
    items = data.get("vehicles")
    if not isinstance(items, list):
        raise InputError("vehicles: must be a list of vehicles")
    vehicles = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise InputError(f"vehicles[{i}]: must be a mapping with 'id' and 'mavlink'")
        extra = sorted(set(map(str, item)) - _VEHICLE_KEYS)
        if extra:
            raise InputError(f"vehicles[{i}].{extra[0]}: unknown key")
        for key in ("id", "mavlink"):
            if not isinstance(item.get(key), str):
                raise InputError(f"vehicles[{i}].{key}: required, a string")
        origin = []
        for axis in ("north", "east", "down"):
            key = f"area_origin_{axis}_m"
            value = item.get(key, 0.0)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InputError(f"vehicles[{i}].{key}: must be a number, got {value!r}")
            if not math.isfinite(value):
                raise InputError(f"vehicles[{i}].{key}: must be finite, got {value!r}")
            origin.append(float(value))
        envelope = _envelope_path(item, "envelope", base_dir, f"vehicles[{i}].")
        vehicles.append(
            VehicleSpec(
                item["id"],
                item["mavlink"],
                item.get("system_id"),
                FrameConfig(*origin),
                envelope or fleet_envelope,
            )
        )
    return FleetSpec(tuple(vehicles), data.get("separation_m", default_separation_m))


def load_fleet_file(
    path: Path | str,
    default_separation_m: float = DEFAULT_SEPARATION_M,
    default_envelope: Path | None = None,
) -> FleetSpec:
    """Read and check a fleet file (InputError naming the file or the field)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"fleet_file: cannot read {path}: {exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise InputError(f"fleet_file: {path} is not valid YAML{where}") from None
    return parse_fleet(data, default_separation_m, Path(path).parent, default_envelope)


def _envelope_path(
    data: dict[str, Any], key: str, base_dir: Path | None, prefix: str = ""
) -> Path | None:
    value = data.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{prefix}{key}: must be the path of an envelope file, got {value!r}")
    path = Path(value)
    return path if path.is_absolute() or base_dir is None else base_dir / path
