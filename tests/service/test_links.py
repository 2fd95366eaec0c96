"""Choosing the vehicle link backend (service.links)."""

from __future__ import annotations

import pytest

from service.links import LINK_BACKENDS, open_link
from service.mavlink_link import MavlinkLink
from service.mavsdk_link import MavsdkLink
from service.vehicle_link import LinkConfig, VehicleLink, signing_key_from_passphrase

CONFIG = LinkConfig("tcp:127.0.0.1:1")


def test_backends_are_listed_with_pymavlink_first():
    assert LINK_BACKENDS == ("pymavlink", "mavsdk")


@pytest.mark.parametrize(("backend", "cls"), [("pymavlink", MavlinkLink), ("mavsdk", MavsdkLink)])
def test_open_link_gives_an_unstarted_link_of_the_backend(backend, cls):
    link = open_link(backend, CONFIG)
    assert type(link) is cls
    assert isinstance(link, VehicleLink)
    assert link.config is CONFIG
    state = link.state()
    assert state.link == "connecting" and state.target_m is None and not state.streaming
    assert state.counters["setpoints_sent"] == 0 and state.counters["geofence_clamps"] == 0


@pytest.mark.parametrize("backend", ["", "MAVSDK", "grpc", "dronekit"])
def test_an_unknown_backend_is_refused_naming_the_setting(backend):
    with pytest.raises(ValueError, match=r"mavlink_backend.*pymavlink, mavsdk"):
        open_link(backend, CONFIG)


def test_signing_is_only_for_the_pymavlink_backend():
    config = LinkConfig("tcp:127.0.0.1:1", signing_key=signing_key_from_passphrase("tupa"))
    assert isinstance(open_link("pymavlink", config), MavlinkLink)
    with pytest.raises(ValueError, match="signing_key"):
        open_link("mavsdk", config)
