"""Fixtures of the fault-injection suite: a :class:`~tests.faults.harness.Harness` per test,
closed at teardown so that every process and proxy it started is stopped, also on failure. When
a test fails, the output of every process it started (service, mock) and the proxies' counters
are printed before they stop, and pytest shows them with the failure."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.faults.harness import Harness
from tests.tiers import needs


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    report = yield
    setattr(item, f"report_{report.when}", report)  # read by the harness fixture's teardown
    return report


@pytest.fixture
@needs("process", group="timing")
def harness(request: pytest.FixtureRequest) -> Iterator[Harness]:
    h = Harness()
    try:
        yield h
    finally:
        call = getattr(request.node, "report_call", None)
        if call is not None and call.failed:
            print(h.describe())
        h.close()
