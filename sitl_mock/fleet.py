"""A fleet of simulated vehicles in one process: one :class:`MockAutopilot` per vehicle.

Each vehicle is a complete, independent :class:`~sitl_mock.server.MockAutopilot` (its own
thread, socket, state machine and counters); :class:`MockFleet` only derives what differs
between them and starts and stops them together::

    with MockFleet(3, "tcp:127.0.0.1:0", flavour="px4") as fleet:
        for system_id, port in zip(fleet.system_ids, fleet.ports):
            connect_to(f"tcp:127.0.0.1:{port}")   # HEARTBEATs from system_id
        fleet[1].state()                           # the second vehicle's snapshot

What differs, vehicle ``i`` (0-based) of ``count``:

* MAVLink system id ``system_id_base + i`` (component id the same for all);
* its own port: ``tcp:HOST:P`` (or ``udp:``) gives ports ``P, P+1, …``; port 0 lets each pick a
  free one; ``udpout:HOST:P`` sends vehicle ``i`` to remote port ``P+i`` (as PX4's multi-vehicle
  SITL sends instance ``i`` to 14540+i). Alternatively one listen spec per vehicle;
* its own home: ``spacing_m`` metres east of the previous vehicle's home (the first keeps the
  configured home, or the flavour's SITL home), so no two vehicles start closer than
  ``spacing_m``. The geofence of each is centred on its own home.

Flavour, signing key, speeds, delays and every other setting are shared.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence

from sitl_mock.config import VehicleConfig
from sitl_mock.flavours import Flavour, get_flavour
from sitl_mock.geo import GeoPoint, ned_to_global
from sitl_mock.server import MockAutopilot, parse_listen

MAX_VEHICLES = 8
"""The most vehicles one fleet serves (the project's fleets have 1–8 UAVs)."""
DEFAULT_SPACING_M = 15.0
"""Default east-west distance between neighbouring homes: more than the fleet's default 10 m
separation between UAVs, so a fleet never starts in violation of it."""


def fleet_listens(listen: str | Sequence[str], count: int) -> list[str]:
    """One listen spec per vehicle (ValueError naming ``listen`` if impossible).

    A single spec is expanded to consecutive ports (port 0 stays 0: each vehicle picks a free
    one); a sequence must give exactly ``count`` specs, no explicit address twice.
    """
    if isinstance(listen, str):
        spec = parse_listen(listen)
        if spec.port != 0 and spec.port + count - 1 > 65535:
            raise ValueError(f"listen: {count} consecutive ports from {spec.port} go past 65535")
        step = 1 if spec.port else 0
        return [f"{spec.kind}:{spec.host}:{spec.port + i * step}" for i in range(count)]
    specs = [parse_listen(text) for text in listen]
    if len(specs) != count:
        raise ValueError(f"listen: {len(specs)} addresses given for {count} vehicles")
    seen: set[tuple[str, str, int]] = set()
    for spec in specs:
        # tcp and udp ports are separate namespaces; udpout names the remote side.
        key = (spec.kind, spec.host, spec.port)
        if spec.port != 0 and key in seen:
            raise ValueError(f"listen: {spec} is given to two vehicles")
        seen.add(key)
    return [str(spec) for spec in specs]


def fleet_homes(home: GeoPoint, count: int, spacing_m: float) -> list[GeoPoint]:
    """Homes in a row: vehicle ``i`` is ``i * spacing_m`` metres east of ``home``."""
    if not (isinstance(spacing_m, int | float) and math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m: must be a positive number, got {spacing_m!r}")
    return [ned_to_global(home, 0.0, i * spacing_m, 0.0) for i in range(count)]


class MockFleet:
    """``count`` independent :class:`MockAutopilot` vehicles, started and stopped together.

    Construction validates everything (ValueError whose message starts with the field's name:
    ``count``, ``system_id_base``, ``listen``, ``spacing_m``, or a :class:`VehicleConfig`
    field) and binds nothing; :meth:`start` binds every socket or none (OSError).
    """

    def __init__(
        self,
        count: int,
        listen: str | Sequence[str] = "tcp:127.0.0.1:0",
        flavour: str | Flavour = "ardupilot",
        config: VehicleConfig | None = None,
        signing_key: bytes | None = None,
        system_id_base: int = 1,
        component_id: int = 1,
        spacing_m: float = DEFAULT_SPACING_M,
        physics_rate_hz: float = 50.0,
        speedup: float = 1.0,
    ) -> None:
        if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_VEHICLES:
            raise ValueError(f"count: must be in 1..{MAX_VEHICLES}, got {count!r}")
        if not 1 <= system_id_base <= 255:
            raise ValueError(f"system_id_base: must be in 1..255, got {system_id_base}")
        if system_id_base + count - 1 > 255:
            raise ValueError(
                f"system_id_base: {count} vehicles from {system_id_base} need system ids up to "
                f"{system_id_base + count - 1}, above 255"
            )
        listens = fleet_listens(listen, count)
        flavour = get_flavour(flavour) if isinstance(flavour, str) else flavour
        base = config if config is not None else VehicleConfig()
        base.validate()
        home = base.home if base.home is not None else flavour.default_home
        homes = fleet_homes(home, count, spacing_m)
        self.flavour = flavour
        self.mocks: list[MockAutopilot] = [
            MockAutopilot(
                listens[i],
                flavour=flavour,
                # Vehicle 0 keeps the given config as is: a fleet of one is today's single mock.
                config=dataclasses.replace(base, home=homes[i]) if i else base,
                signing_key=signing_key,
                system_id=system_id_base + i,
                component_id=component_id,
                physics_rate_hz=physics_rate_hz,
                speedup=speedup,
            )
            for i in range(count)
        ]

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> MockFleet:
        """Start every vehicle; if one cannot bind, stop those already started and raise OSError
        (its ``strerror`` names the address: ``cannot open tcp:127.0.0.1:5761: ...``)."""
        started: list[MockAutopilot] = []
        try:
            for mock in self.mocks:
                try:
                    mock.start()
                except OSError as exc:
                    # Say which of the fleet's addresses failed; keep errno for callers.
                    raise OSError(
                        exc.errno, f"cannot open {mock.listen}: {exc.strerror or exc}"
                    ) from exc
                started.append(mock)
        except BaseException:
            for mock in started:
                mock.stop()
            raise
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop every vehicle (safe to call twice, and after a failed :meth:`start`)."""
        for mock in self.mocks:
            mock.stop(timeout_s)

    def __enter__(self) -> MockFleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ access

    def __len__(self) -> int:
        return len(self.mocks)

    def __iter__(self) -> Iterator[MockAutopilot]:
        return iter(self.mocks)

    def __getitem__(self, index: int) -> MockAutopilot:
        return self.mocks[index]

    @property
    def system_ids(self) -> list[int]:
        """Each vehicle's MAVLink system id, in order."""
        return [mock.protocol.system_id for mock in self.mocks]

    @property
    def ports(self) -> list[int]:
        """Each vehicle's bound local port (the real ones once started with port 0)."""
        return [mock.port for mock in self.mocks]

    @property
    def addresses(self) -> list[str]:
        """Each vehicle's address, as :attr:`MockAutopilot.address` gives it."""
        return [mock.address for mock in self.mocks]

    def by_system_id(self, system_id: int) -> MockAutopilot:
        """The vehicle with this MAVLink system id (KeyError if none)."""
        for mock in self.mocks:
            if mock.protocol.system_id == system_id:
                return mock
        raise KeyError(system_id)
