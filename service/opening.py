"""Which placement service a configuration asks for, opened: :func:`open_service`.

One vehicle: :class:`~service.placement.PlacementService`; a fleet file:
:class:`~service.fleet_placement.FleetPlacementService` (a subclass). Kept apart from both so
that the base class never imports its subclass.
"""

from __future__ import annotations

from service.fleet_placement import FleetPlacementService
from service.placement import PlacementService
from service.settings import ServiceSettings


def open_service(settings: ServiceSettings) -> PlacementService:
    """Load the policy and open the link(s) for ``settings`` (``InputError`` naming the field
    for an unusable policy or fleet); the links retry on their own. Not started."""
    if settings.is_fleet:
        return FleetPlacementService.from_settings(settings)
    return PlacementService.from_settings(settings)
