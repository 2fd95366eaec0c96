"""Helpers shared by every test package: a bounded polling helper (no fixed sleeps: every wait is
on a condition, with a timeout) and loopback addresses for mocks and links.

Fixtures live in the ``conftest.py`` files (``start_mock`` in ``tests/conftest.py``); in-memory
stand-ins for the service's collaborators in ``tests/fakes.py``.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from sitl_mock.server import MockAutopilot

T = TypeVar("T")


def wait_for(
    condition: Callable[[], T],
    timeout_s: float = 5.0,
    interval_s: float = 0.02,
    message: str = "condition",
) -> T:
    """Poll ``condition`` until it returns something truthy (returned) or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {message}")
        time.sleep(interval_s)


def free_udp_port() -> int:
    """A loopback UDP port free right now (nothing listens on that TCP port either, almost
    surely)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def tcp_url(mock: MockAutopilot) -> str:
    """The pymavlink connection string of a mock listening on loopback TCP."""
    return f"tcp:127.0.0.1:{mock.port}"


def tiny_preset(algorithm: str = "ddpg", **overrides: Any) -> Any:
    """The ``fast`` preset of ``algorithm`` shrunk for tests that train for real in seconds:
    one 8-channel conv layer, a 32-unit head, a small buffer, 10-step training episodes
    (``overrides`` replace any field)."""
    from dataclasses import replace

    from policies.training.presets import NetworkPreset, get_preset

    fields: dict[str, Any] = {
        "network": NetworkPreset(channels=(8,), hidden=32, features_dim=32, dropout=0.0),
        "buffer_size": 5_000,
        "learning_starts": 64,
        "batch_size": 32,
        "train_episode_steps": 10,
        **overrides,
    }
    return replace(get_preset("fast", algorithm), **fields)
