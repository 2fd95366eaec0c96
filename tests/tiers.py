"""The test tiers, named by what a test needs rather than by how long it takes.

Every test that needs one of these resources carries its marker; a test with none of them is
pure logic run in process, and ``make test-fast`` runs exactly those (``-m`` with
:data:`FAST_SELECTION`). ``make test`` runs every tier.

A test gets a marker in one of two ways:

* through a fixture: a fixture function decorated with :func:`needs` (below ``@pytest.fixture``)
  gives its marker to every test that uses it, directly or through other fixtures
  (``tests/conftest.py``'s ``pytest_collection_modifyitems``, from the fixture that is in effect
  for that test, so two fixtures of one name in different modules are told apart);
* by hand, where the test itself starts the resource (``pytestmark`` of a module, or a mark on
  the function).

``xdist_group`` (pytest-xdist's ``--dist loadgroup``) keeps tests on one worker, one after the
other: :func:`needs` can name a group for the tests of its fixture (for a fixture wider than a
test, so that it is built once per run rather than once per worker, or for tests that must not
overlap each other).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable[..., object])

TIERS: dict[str, str] = {
    "process": "starts real processes (tupa serve, sitl-mock, a tupa command, a worker process)",
    "flying": "an in-process sitl_mock vehicle flies on the wall clock (take-offs, failsafes)",
    "training": "trains a policy for real (SB3, imitation, a sweep's trials)",
    "ns3": "runs ns-3 (a worker process that imports ns-3: ~15 s, paid once per test run)",
    "browser": "drives chromium through Playwright",
    "ray": "starts a private Ray instance",
}
"""Marker name -> what a test with it needs (registered in pyproject.toml's pytest markers)."""

FAST_SELECTION = "not (" + " or ".join(TIERS) + ")"
"""The ``-m`` expression of the in-process tier (``make test-fast``)."""

NEEDS_ATTRIBUTE = "tupa_needs"
GROUP_ATTRIBUTE = "tupa_xdist_group"


def needs(*markers: str, group: str | None = None) -> Callable[[F], F]:
    """Fixture decorator (placed below ``@pytest.fixture``): every test that uses the fixture
    gets ``markers`` (each a key of :data:`TIERS`) and, with ``group``, the ``xdist_group`` of
    that name. Returns the function unchanged otherwise."""
    unknown = [m for m in markers if m not in TIERS]
    if unknown:
        raise ValueError(f"unknown tier marker(s) {unknown}: expected one of {sorted(TIERS)}")

    def decorate(function: F) -> F:
        setattr(function, NEEDS_ATTRIBUTE, tuple(markers))
        if group is not None:
            setattr(function, GROUP_ATTRIBUTE, group)
        return function

    return decorate
