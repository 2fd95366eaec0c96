"""A placement service with no autopilot, for tests of the HTTP side."""

from __future__ import annotations

from service.mavlink_link import MavlinkLink
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig


def offline_service(settings: ServiceSettings) -> PlacementService:
    """A placement service whose link points at a closed port (no autopilot): the HTTP side
    must work all the same (reports are accepted, decisions wait for the link)."""
    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:1", reconnect_max_s=0.5))
    return PlacementService(settings, link, load_policy(settings.policy))
