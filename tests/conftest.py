"""Fixtures shared by the test packages: sitl_mock autopilots on free loopback ports (port 0),
each stopped at teardown, also on failure."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from hypothesis import settings

from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot

# Property tests: a failure prints the blob that reproduces it (@reproduce_failure), and CI runs
# them derandomised, so a red CI run replays exactly (profile "ci": `.ci/run` sets
# HYPOTHESIS_PROFILE, and any CI that sets CI gets it too). pytest-randomly shuffles the test
# order and prints its seed in the header ("Using --randomly-seed=N": pass it back to replay).
settings.register_profile("dev", print_blob=True)
settings.register_profile("ci", print_blob=True, derandomize=True)
settings.load_profile(
    os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev")
)


@pytest.fixture
def start_mock() -> Iterator[Callable[..., MockAutopilot]]:
    """Factory: ``start_mock(flavour, listen=..., signing_key=..., **VehicleConfig fields)``."""
    mocks: list[MockAutopilot] = []

    def _start(
        flavour: str = "ardupilot",
        listen: str = "tcp:127.0.0.1:0",
        signing_key: bytes | None = None,
        **config: Any,
    ) -> MockAutopilot:
        config.setdefault("ready_delay_s", 0.3)
        mock = MockAutopilot(listen, flavour, VehicleConfig(**config), signing_key=signing_key)
        mocks.append(mock)
        return mock.start()

    yield _start
    for mock in mocks:
        mock.stop()
