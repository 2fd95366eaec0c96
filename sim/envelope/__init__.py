"""The flight-safety envelope: where one vehicle may be and how it gets there.

* :mod:`sim.envelope.volume`: :class:`Envelope` (inclusion polygon, exclusion volumes, altitude
  band, clearance, speed limit) and its exact point and segment checks.
* :mod:`sim.envelope.paths`: :func:`legal_target` and :func:`plan_path` (direct, over, around,
  or :class:`Hold`).
* :mod:`sim.envelope.route`: :class:`Route`, what is streamed leg by leg (planned from where
  the vehicle is, advanced as it flies, or a hold that says why).
* :mod:`sim.envelope.files`: the ``tupa-envelope/1`` JSON format and its checks.
* :mod:`sim.envelope.buildings`: a site's buildings as exclusions (every envelope over a site
  holds them).

Pure geometry on shapely, shared by whatever flies a vehicle (the service's link, the world's
flight model), so that what is trained, evaluated and flown keeps to the same envelope.
"""

from sim.envelope.files import (
    ENVELOPE_FORMAT,
    area_envelope,
    envelope_from_document,
    load_envelope,
)
from sim.envelope.paths import FlightPath, Hold, legal_target, plan_path
from sim.envelope.volume import Envelope, Exclusion, home_violation

__all__ = [
    "ENVELOPE_FORMAT",
    "Envelope",
    "Exclusion",
    "FlightPath",
    "Hold",
    "area_envelope",
    "envelope_from_document",
    "home_violation",
    "legal_target",
    "load_envelope",
    "plan_path",
]
