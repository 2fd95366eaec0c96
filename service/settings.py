"""The placement service's settings: command-line options, else ``TUPA_*`` environment variables.

Every field can be set as an environment variable with the ``TUPA_`` prefix (``TUPA_MAVLINK``,
``TUPA_API_TOKEN``, ``TUPA_POLICY``, ...); ``tupa serve`` options override them. Secrets
(``api_token``, ``mavlink_signing_key``) are :class:`pydantic.SecretStr`, so they never show in
a ``repr`` or a log line.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, SecretStr, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.policy_runtime import SHIPPED_CHECKPOINTS, default_policy_spec

if TYPE_CHECKING:
    from service.battery import BatteryConfig
    from service.fleet_spec import FleetSpec
    from service.frames import FrameConfig
    from sim.world import World

DecisionMode = Literal["paced", "on-report"]
MavlinkBackend = Literal["pymavlink", "mavsdk"]


class ServiceSettings(BaseSettings):
    """Everything ``tupa serve`` needs; the defaults suit a local PX4 or ArduPilot SITL."""

    model_config = SettingsConfigDict(env_prefix="TUPA_", extra="ignore", frozen=True)

    mavlink: str = "tcp:127.0.0.1:5760"
    """pymavlink connection string of the autopilot (``tcp:``, ``udpin:``, ``udpout:``, serial)."""
    fleet_mavlink: tuple[str, ...] = ()
    """A fleet from repeated ``--mavlink`` (two or more): vehicles ``uav1``, ``uav2``, ... in one
    frame (JSON list in ``TUPA_FLEET_MAVLINK``). Vehicles with different homes: ``fleet_file``."""
    fleet_file: Path | None = None
    """A fleet of 1–8 vehicles (:mod:`service.fleet_spec` has the format): one MAVLink link
    each, with its own frame; the policy is a fleet policy (``kmeans-load-weighted``, ...)."""
    envelope_file: Path | None = None
    """The flight-safety envelope (``tupa-envelope/1`` JSON, :mod:`sim.envelope.files`): where
    the vehicle may fly, and every vehicle of a fleet without its own (the fleet file's
    ``envelope``). None: the area's box."""
    separation_m: float = Field(default=10.0, gt=0, le=1000, allow_inf_nan=False)
    """A fleet's minimum 3-D distance between any two targets (a fleet file may set its own)."""
    mavlink_backend: MavlinkBackend = "pymavlink"
    mavlink_signing_key: SecretStr | None = None
    """MAVLink 2 signing key, 64 hex characters (32 bytes), the same as the vehicle's."""
    policy: str = Field(default_factory=default_policy_spec)
    """A checkpoint path or a policy's name (``oracle``, ``planning-oracle``, ``min-distance``,
    ...). Not given: the served default for ``environment`` (:meth:`served_policy_spec`)."""
    arm_and_takeoff: bool = False
    """Arm and take off to the minimum altitude before the first placement (never by default)."""
    autopilot_fence: bool = False
    """Also put each vehicle's envelope on its autopilot as its own fence (polygons, ceiling,
    breach action; :mod:`service.fence`), read it back, and neither take off nor stream until it
    is there (pymavlink backend). Routes then keep out of every exclusion at every height."""
    fence_action: Literal["rtl", "hold", "land", "report"] = "rtl"
    """What the autopilot does on a fence breach (with ``autopilot_fence``)."""
    battery_reserve_pct: float | None = Field(default=20.0, ge=0, lt=100, allow_inf_nan=False)
    """Charge to be left on landing, %: at what flying home from where the vehicle is takes plus
    this, the service ends the placement and commands the return (:mod:`service.battery`);
    None: never (the autopilot's own failsafe still acts)."""
    takeoff_timeout_s: float = Field(default=300.0, gt=0, le=86400, allow_inf_nan=False)
    """How long the take-off sequence keeps trying (a real vehicle needs its GPS lock first)."""
    host: str = "127.0.0.1"
    port: int = Field(default=8080, ge=0, le=65535)
    api_token: SecretStr | None = None
    """Bearer token every ``/v1`` route requires."""
    insecure: bool = False
    """Allow serving without ``api_token`` (local experiments only)."""
    decision_mode: DecisionMode = "paced"
    """``paced``: one decision every ``step_s`` from the latest report; ``on-report``: a
    decision for each report as it arrives, one at a time, the latest report winning (reports
    that arrive during a decision replace each other: one pending decision at most)."""
    world: str = "closed-loop"
    """The world the policy was trained for (:mod:`sim.world`): its decision period is the
    service's, unless ``step_s`` is given."""
    environment: str = "open"
    """What stands on the ground (:data:`sim.config.ENVIRONMENTS`): the channel the policy's
    observations come from and the oracle optimises for; the network controller reports
    measured metrics whatever it is."""
    step_s: float | None = Field(default=None, gt=0, le=3600)
    """The decision period (the paper's time step S); default: the world's."""
    report_max_age_s: float = Field(default=5.0, gt=0)
    """A report older than this (since it arrived) is stale: the target is held."""
    setpoint_rate_hz: float = Field(default=10.0, gt=2.0, le=100.0)
    area_origin_north_m: float = 0.0
    area_origin_east_m: float = 0.0
    area_origin_down_m: float = 0.0
    """Where the area's south-west corner at z = 0 lies from the vehicle's home (local NED)."""
    max_users: int = Field(default=1000, ge=1)
    max_body_bytes: int = Field(default=1_000_000, ge=1024)
    rate_limit_rps: float = Field(default=200.0, ge=0, allow_inf_nan=False)
    """Requests per second each client (peer address) may make on average; 0: no limit. Over
    it: 429 with ``Retry-After``. The probes (``/healthz``, ``/readyz``) are never limited.
    The default is well under what the service serves on one core (about 700-1,000 simple
    requests a second), so that no one client can take all of it, and far above what a
    network controller needs (a report per vehicle per decision period)."""
    rate_limit_burst: int = Field(default=400, ge=1)
    """How many requests a client may make at once above its rate (the token bucket's size)."""
    queueing: Literal["fq-codel", "mac-only"] = "fq-codel"
    """The network model variant the ``oracle`` baseline optimises for."""
    policy_dirs: tuple[Path, ...] = (SHIPPED_CHECKPOINTS, Path("runs"))
    """Where ``PUT /v1/policy`` may load checkpoints from (JSON list in ``TUPA_POLICY_DIRS``):
    a checkpoint is a pickle, so a client must not make the service load an arbitrary file."""
    state_file: Path | None = None
    """Where the last target and policy are persisted (none: not persisted). Its policy is
    restored only from ``policy_dirs`` (else the configured ``policy`` serves)."""
    checkpoint_max_bytes: int = Field(default=64 * 1024 * 1024, ge=1024 * 1024)
    """The largest checkpoint the service loads: the zip file, and what its members expand to
    (a small zip can expand to gigabytes). The shipped ones expand to 7 and 14 MB."""
    report_max_future_s: float = Field(default=5.0, ge=0, le=3600, allow_inf_nan=False)
    """How far ahead of the service's clock a report's ``timestamp`` may be (clock skew); a
    report further ahead is refused (422): accepted, it would make every later report old."""
    trusted_proxies: tuple[str, ...] = ()
    """Peer addresses whose ``X-Forwarded-For`` names the client (JSON list in
    ``TUPA_TRUSTED_PROXIES``, e.g. ``["127.0.0.1"]`` behind a local reverse proxy). Empty: the
    header is ignored from everyone, so no client can pick the address it is rate-limited by."""
    http_max_header_bytes: int = Field(default=32 * 1024, ge=4096, le=1024 * 1024)
    """The largest request head (request line and headers) accepted; larger: 400, closed."""
    http_max_headers: int = Field(default=100, ge=10, le=10_000)
    """The most header lines a request may have; more: 431."""
    http_request_timeout_s: float = Field(default=10.0, gt=0, le=3600, allow_inf_nan=False)
    """How long a client has to send a whole request, from its first byte (or from connecting);
    a connection still sending after that (slow, stalled, or lying about its length) is closed."""
    http_keep_alive_s: int = Field(default=5, ge=1, le=3600)
    """How long an idle keep-alive connection is kept open between requests."""
    http_max_connections: int = Field(default=512, ge=8)
    """Connections at once, all clients together (each carries one request at a time). At the
    cap, a new connection takes the place of one held by the client holding the most, if it
    holds more than the newcomer; else the newcomer is closed at once (:mod:`api.server`)."""
    http_max_connections_per_client: int = Field(default=32, ge=1, le=100_000)
    """Connections one client (peer address) may hold at once; beyond: closed at once, nothing
    answered. ``trusted_proxies`` are exempt (they speak for many clients)."""
    http_write_timeout_s: float = Field(default=30.0, gt=0, le=3600, allow_inf_nan=False)
    """How long a connection may hold unsent bytes without taking any (its client reads
    nothing: a response, pipelined answers, a close waiting to flush); then it is reset."""
    live_max_streams: int = Field(default=16, ge=1, le=1000)
    """Operator-view streams (``GET /v1/live/events``, one per open page) at once; beyond: 503
    with ``Retry-After``. Each holds one of the ``http_max_connections`` for as long as it is
    open, so this keeps most of them for the network controller."""
    live_stall_s: float = Field(default=30.0, gt=0, le=3600, allow_inf_nan=False)
    """A stream whose client has not taken a frame for this long (it stopped reading, and the
    connection's buffers are full) is closed, freeing its place."""

    @field_validator("world", "environment")
    @classmethod
    def _known_name(cls, value: str, info: ValidationInfo) -> str:
        from sim.config import environment_problem
        from sim.world import WORLDS

        if info.field_name == "environment":
            problem = environment_problem(value, on_disk=True)  # a named one, or site:PATH
            if problem is not None:
                raise ValueError(problem)
        elif value not in WORLDS:
            raise ValueError(f"must be one of {', '.join(WORLDS)}, got {value!r}")
        return value

    @property
    def decision_period_s(self) -> float:
        """``step_s``, or the world's decision period."""
        if self.step_s is not None:
            return self.step_s
        from sim.world import get_world

        return get_world(self.world).step_s

    def served_policy_spec(self) -> str:
        """The single vehicle's policy: :attr:`policy` when it was given (option or
        ``TUPA_POLICY``), else the served default for :attr:`environment`, the policy the
        closed-loop benchmark ranks first there (:func:`policies.defaults.served_default`)."""
        if "policy" in self.model_fields_set:
            return self.policy
        from policies.defaults import served_default

        return served_default(self.environment).policy

    def policy_world(self) -> World:
        """The world the served policy decides in: :attr:`world` with the service's queueing
        and decision period (what the oracle optimises for and the observation is built with)."""
        from dataclasses import replace

        from sim.config import NetworkConfig
        from sim.world import get_world

        world = get_world(self.world)
        return replace(
            world,
            area=replace(world.area, environment=self.environment),
            network=NetworkConfig().with_queueing(self.queueing),
            step_s=self.decision_period_s,
        )

    @field_validator("area_origin_north_m", "area_origin_east_m", "area_origin_down_m")
    @classmethod
    def _finite(cls, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @field_validator("mavlink_signing_key")
    @classmethod
    def _hex_key(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None or not value.get_secret_value():
            return None
        try:
            key = bytes.fromhex(value.get_secret_value())
        except ValueError:
            raise ValueError("must be 64 hexadecimal characters") from None
        if len(key) != 32:
            raise ValueError(f"must be 32 bytes (64 hex characters), got {len(key)} bytes")
        return value

    @property
    def is_fleet(self) -> bool:
        """Whether the service drives a fleet (a fleet file, or several ``--mavlink``)."""
        return self.fleet_file is not None or len(self.fleet_mavlink) > 1

    def fleet_spec(self) -> FleetSpec:
        """The vehicles to drive (``InputError`` naming the field for a bad fleet): the fleet
        file's, the repeated ``--mavlink`` ones, or the one ``mavlink`` vehicle (``uav1``)."""
        from service.fleet_spec import fleet_from_urls, load_fleet_file, single_vehicle

        if self.fleet_file is not None:
            return load_fleet_file(self.fleet_file, self.separation_m, self.envelope_file)
        if len(self.fleet_mavlink) > 1:
            return fleet_from_urls(
                self.fleet_mavlink, self.frames(), self.separation_m, self.envelope_file
            )
        return single_vehicle(self.mavlink, self.frames(), self.envelope_file)

    def frames(self) -> FrameConfig:
        """Where the area lies from the (single) vehicle's home."""
        from service.frames import FrameConfig

        return FrameConfig(
            self.area_origin_north_m, self.area_origin_east_m, self.area_origin_down_m
        )

    def battery(self) -> BatteryConfig:
        """The battery reserve each vehicle link keeps (:mod:`service.battery`)."""
        from service.battery import BatteryConfig

        return BatteryConfig(reserve_pct=self.battery_reserve_pct)

    def signing_key_bytes(self) -> bytes | None:
        key = self.mavlink_signing_key
        return bytes.fromhex(key.get_secret_value()) if key is not None else None

    def check_startable(self) -> None:
        """Refuse to serve what cannot be served (ValueError naming the option or field): a
        MAVLink connection string the link could not open (``--mavlink``, checked as a fleet
        file's are: :func:`service.fleet_spec.check_connection`), a fleet file beside repeated
        ``--mavlink``, no token unless ``insecure``."""
        from service.fleet_spec import check_connection

        if self.fleet_file is not None and self.fleet_mavlink:
            raise ValueError("fleet_file: give a fleet file or repeated --mavlink, not both")
        if self.fleet_file is None:
            for url in self.fleet_mavlink or (self.mavlink,):
                check_connection(url, "--mavlink", self.mavlink_backend)
        token = self.api_token.get_secret_value() if self.api_token else ""
        if not token and not self.insecure:
            raise ValueError(
                "api_token: no token configured; set TUPA_API_TOKEN or pass --api-token-file "
                "FILE, or --insecure for a local experiment"
            )
