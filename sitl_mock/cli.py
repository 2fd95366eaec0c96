"""``tupa sitl-mock``: registered by the sitl_mock package (filled in by the MAVLink work)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Nothing yet: the MAVLink autopilot simulator is issue 5."""
