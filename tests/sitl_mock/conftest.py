"""Fixtures for the sitl_mock tests: raw-pymavlink clients to mocks (``start_mock`` is in
tests/conftest.py). Every client a test starts is stopped at teardown, also on failure."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from sitl_mock.server import MockAutopilot
from tests.sitl_mock.helpers import MavClient, stop_process
from tests.tiers import needs

REPO_ROOT = Path(__file__).resolve().parents[2]


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


@pytest.fixture
@needs("process")
def spawn() -> Iterator[Callable[..., subprocess.Popen]]:
    """Factory: ``spawn(*args)``: ``tupa sitl-mock ARGS`` as a process (stdout and stderr
    piped, text); every process is stopped at teardown (SIGTERM, then SIGKILL)."""
    processes: list[subprocess.Popen] = []

    def _spawn(*args: str) -> subprocess.Popen:
        process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "sitl-mock", *args],
            cwd=REPO_ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        processes.append(process)
        return process

    yield _spawn
    for process in processes:
        stop_process(process)
