"""Fixtures of the API tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from tests.api.fleet_helpers import fleet_app, single_app
from tests.fakes import FakeLink


@pytest.fixture
def fleet() -> Iterator[tuple[TestClient, dict[str, FakeLink]]]:
    """A started fleet service of three FakeLinks (kmeans-load-weighted, on-report) behind a
    TestClient; stopped at teardown."""
    yield from fleet_app()


@pytest.fixture
def single() -> Iterator[tuple[TestClient, FakeLink]]:
    """A started one-vehicle service over a FakeLink flying at (250, 250, 30) behind a
    TestClient; stopped at teardown."""
    yield from single_app()
