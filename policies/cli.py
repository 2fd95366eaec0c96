"""``tupa eval`` and friends (policies package)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Filled in below as the policies land."""
