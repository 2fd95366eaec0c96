"""Fixtures for the sitl_mock tests: raw-pymavlink clients to mocks (``start_mock`` is in
tests/conftest.py). Every client a test starts is stopped at teardown, also on failure."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from sitl_mock.server import MockAutopilot
from tests.sitl_mock.helpers import MavClient


@pytest.fixture
def connect() -> Iterator[Callable[..., MavClient]]:
    """Factory: ``connect(mock, **MavClient options)``: a raw-pymavlink client to the mock."""
    clients: list[MavClient] = []

    def _connect(mock: MockAutopilot, **options: Any) -> MavClient:
        kind = "tcp" if mock.listen.kind == "tcp" else "udp"
        client = MavClient(("127.0.0.1", mock.port), kind=kind, **options)
        clients.append(client)
        return client

    yield _connect
    for client in clients:
        client.close()
