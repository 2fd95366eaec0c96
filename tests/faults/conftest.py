"""Fixtures of the fault-injection suite: a :class:`~tests.faults.harness.Harness` per test,
closed at teardown so that every process and proxy it started is stopped, also on failure."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.faults.harness import Harness


@pytest.fixture
def harness() -> Iterator[Harness]:
    h = Harness()
    try:
        yield h
    finally:
        h.close()
