"""Choosing the vehicle link: ``pymavlink`` (:class:`~service.mavlink_link.MavlinkLink`, the
default) or ``mavsdk`` (:class:`~service.mavsdk_link.MavsdkLink`, on the native MAVSDK binding).

Both take the same :class:`~service.vehicle_link.LinkConfig` and implement the same
:class:`~service.vehicle_link.VehicleLink` interface, so the placement loop does not know which
one it drives::

    link = open_link(settings.mavlink_backend, LinkConfig(url, area=area, frames=frames))
    link.start()

Differences a user can see: the ``mavsdk`` backend cannot sign MAVLink 2 (a ``signing_key``
raises ValueError), and MAVSDK re-sends the latest setpoint at 20 Hz on its own, so the vehicle
gets at least 20 setpoints a second whatever ``setpoint_rate_hz`` says. Each backend's module
docstring has the details. A backend module is imported only when it is chosen.
"""

from __future__ import annotations

from service.vehicle_link import LinkConfig, VehicleLink

LINK_BACKENDS = ("pymavlink", "mavsdk")
"""The values ``--mavlink-backend`` accepts; the first is the default."""


def open_link(backend: str, config: LinkConfig) -> VehicleLink:
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
