"""The test tiers (tests/tiers.py, tests/conftest.py): every tier is a registered marker, a
fixture decorated with ``needs`` marks the tests that use it, however indirectly, and
``--fast`` (make test-fast) is exactly the tests with no tier marker."""

from __future__ import annotations

import pytest

from tests.tiers import FAST_SELECTION, TIERS, needs


def test_every_tier_and_the_xdist_group_are_registered_markers(
    pytestconfig: pytest.Config,
) -> None:
    registered = {line.split(":", 1)[0].split("(", 1)[0] for line in pytestconfig.getini("markers")}
    assert set(TIERS) | {"xdist_group", "slow"} <= registered


def test_the_fast_selection_names_every_tier() -> None:
    assert FAST_SELECTION == "not (process or flying or training or ns3 or browser or ray)"
    assert all(tier in FAST_SELECTION for tier in TIERS)


def test_needs_refuses_a_tier_that_does_not_exist() -> None:
    with pytest.raises(ValueError, match="unknown tier marker"):
        needs("slowish")


@pytest.fixture
@needs("process", group="tiers-test")
def _a_process() -> str:
    return "no process is started: only the marker is checked"


@pytest.fixture
def _through_another(_a_process: str) -> str:
    return _a_process


def test_a_fixture_marks_the_tests_that_use_it_even_through_another(
    request: pytest.FixtureRequest, _through_another: str
) -> None:
    assert request.node.get_closest_marker("process") is not None
    assert request.node.get_closest_marker("flying") is None
    group = request.node.get_closest_marker("xdist_group")
    assert group is not None and group.args == ("tiers-test",)


def test_a_test_without_tier_fixtures_has_no_tier_marker(request: pytest.FixtureRequest) -> None:
    assert not [tier for tier in TIERS if request.node.get_closest_marker(tier)]


def test_the_ids_are_unique_so_a_parallel_run_runs_every_test(
    request: pytest.FixtureRequest,
) -> None:
    """schemathesis's cases of one test shared its id (tests/conftest.py renames them)."""
    ids = [item.nodeid for item in request.session.items]
    assert len(ids) == len(set(ids))
