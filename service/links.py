"""Choosing the vehicle link: ``pymavlink`` (:class:`~service.mavlink_link.MavlinkLink`, the
default) or ``mavsdk`` (:class:`~service.mavsdk_link.MavsdkLink`, on the native MAVSDK binding).

Both take the same :class:`~service.mavlink_link.LinkConfig` and answer the same
:class:`VehicleLink` interface, so the placement loop does not know which one it drives::

    link = open_link(settings.mavlink_backend, LinkConfig(url, area=area, frames=frames))
    link.start()

Differences a user can see: the ``mavsdk`` backend cannot sign MAVLink 2 (a ``signing_key``
raises ValueError), and MAVSDK re-sends the latest setpoint at 20 Hz on its own, so the vehicle
gets at least 20 setpoints a second whatever ``setpoint_rate_hz`` says. Each backend's module
docstring has the details.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Future
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from service.mavlink_link import TAKEOFF_TIMEOUT_S, LinkConfig, LinkState

if TYPE_CHECKING:
    from service.mavlink_link import MavlinkLink
    from service.mavsdk_link import MavsdkLink

LINK_BACKENDS = ("pymavlink", "mavsdk")
"""The values ``--mavlink-backend`` accepts; the first is the default."""


@runtime_checkable
class VehicleLink(Protocol):
    """What the service needs from a vehicle link (both backends implement it)."""

    config: LinkConfig

    def start(self) -> VehicleLink:
        """Start the background I/O; returns at once."""
        ...

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop everything (idempotent)."""
        ...

    def state(self) -> LinkState:
        """A snapshot of the link and the vehicle; never blocks on I/O."""
        ...

    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        """Stream an area-frame target from now on; returns it clamped to the geofence."""
        ...

    def clear_target(self) -> None:
        """Stop streaming (the vehicle's own failsafe for a lost stream then acts)."""
        ...

    def arm_and_takeoff(
        self, z_m: float | None = None, timeout_s: float = TAKEOFF_TIMEOUT_S
    ) -> Future[None]:
        """Arm and climb (only when asked), retrying refusals until ``timeout_s``; the Future
        completes when airborne."""
        ...


def open_link(backend: str, config: LinkConfig) -> MavlinkLink | MavsdkLink:
    """A link (not started) on ``backend``, one of :data:`LINK_BACKENDS`.

    ValueError naming ``mavlink_backend`` for an unknown backend, and from the backend for a
    config it cannot serve (the ``mavsdk`` backend with a signing key, or a URL it cannot use).
    """
    if backend == "pymavlink":
        from service.mavlink_link import MavlinkLink

        return MavlinkLink(config)
    if backend == "mavsdk":
        from service.mavsdk_link import MavsdkLink

        return MavsdkLink(config)
    raise ValueError(f"mavlink_backend: must be one of {', '.join(LINK_BACKENDS)}, got {backend!r}")
