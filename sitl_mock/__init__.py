"""sitl_mock: a stand-in for an external autopilot (ArduPilot Copter or PX4) over MAVLink 2.

It imports pymavlink and nothing of this project's own packages, so that tests between the
service's MAVLink link and this mock catch real protocol mistakes on either side.

Modules, one job each:

* :mod:`sitl_mock.geo` — local NED <-> latitude/longitude around home.
* :mod:`sitl_mock.flavours` — mode numbers and the rules that differ between ArduPilot and PX4.
* :mod:`sitl_mock.config` — the vehicle's settings (:class:`VehicleConfig`).
* :mod:`sitl_mock.kinematics` — speed/acceleration limits, position controller, geofence shape.
* :mod:`sitl_mock.setpoints` — type_mask and frame decoding of position targets.
* :mod:`sitl_mock.battery` — charge drain.
* :mod:`sitl_mock.vehicle` — the state machine (modes, arming, failsafes), stepped with an
  explicit dt: no wall clock inside.
* :mod:`sitl_mock.params` — the parameter table clients may fetch (the fence's may be set).
* :mod:`sitl_mock.fence` — the fence a ground station uploads: zones, ceiling, breach actions.
* :mod:`sitl_mock.mission` — the MAVLink mission protocol for that fence (upload, download).
* :mod:`sitl_mock.protocol` — MAVLink in and out: commands, ACKs, setpoints, streams, signing.
* :mod:`sitl_mock.server` — TCP/UDP transport and :class:`MockAutopilot`, the entry point.
* :mod:`sitl_mock.fleet` — :class:`MockFleet`: several vehicles in one process, one
  :class:`MockAutopilot` each (own port, system id and home).
* :mod:`sitl_mock.cli` — ``tupa sitl-mock``.

This ``__init__`` stays import-light (``tupa --help`` imports the package); ``MockAutopilot``,
``MockFleet`` and ``VehicleConfig`` are loaded on first access.
"""

from __future__ import annotations

from typing import Any

__all__ = ["MockAutopilot", "MockFleet", "VehicleConfig"]


def __getattr__(name: str) -> Any:
    if name == "MockAutopilot":
        from sitl_mock.server import MockAutopilot

        return MockAutopilot
    if name == "MockFleet":
        from sitl_mock.fleet import MockFleet

        return MockFleet
    if name == "VehicleConfig":
        from sitl_mock.config import VehicleConfig

        return VehicleConfig
    raise AttributeError(f"module 'sitl_mock' has no attribute {name!r}")
