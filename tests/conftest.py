"""Fixtures shared by the test packages: sitl_mock autopilots on free loopback ports (port 0),
each stopped at teardown, also on failure; the ns-3 worker, started once per test run; and the
hook that marks each test with the tiers it needs (:mod:`tests.tiers`: a test is marked by the
fixtures it uses)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from hypothesis import settings

from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from tests.machine_room import EXCLUSIVE_GROUP, ROOM_ENV, MachineRoom, room_from_environment
from tests.tiers import GROUP_ATTRIBUTE, NEEDS_ATTRIBUTE, TIERS, needs

# Property tests: a failure prints the blob that reproduces it (@reproduce_failure), and CI runs
# them derandomised, so a red CI run replays exactly (profile "ci": `.ci/run` sets
# HYPOTHESIS_PROFILE, and any CI that sets CI gets it too). pytest-randomly shuffles the test
# order and prints its seed in the header ("Using --randomly-seed=N": pass it back to replay).
settings.register_profile("dev", print_blob=True)
settings.register_profile("ci", print_blob=True, derandomize=True)
settings.load_profile(
    os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev")
)


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_the_test_tmp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Stable-Baselines3 makes a ``SB3-<date>`` folder in the system's temporary directory for
    every model that learns without a log folder; the test run's own temporary directory holds
    them instead (``SB3_LOGDIR``, inherited by the processes the tests start)."""
    before = os.environ.get("SB3_LOGDIR")
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3"))
    yield
    if before is None:
        os.environ.pop("SB3_LOGDIR", None)
    else:
        os.environ["SB3_LOGDIR"] = before


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--fast",
        action="store_true",
        help="run only the in-process tier: deselect the tests marked "
        + ", ".join(TIERS)
        + " (tests/tiers.py; make test-fast)",
    )


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist and pytest-randomly see the items
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test by the fixtures it uses, give it its xdist group, then (with ``--fast``)
    deselect every test that has a tier marker.

    * Tiers: the markers of each fixture decorated with :func:`tests.tiers.needs` that the test
      uses, directly or through other fixtures (the definition in effect for that test).
    * ``xdist_group``, unless the test has one of its own: the group of the first such fixture
      that names one; else, for a test that uses a fixture of its module's scope (or its
      class's), one group per module, so that a parallel run builds that fixture once, on one
      worker, rather than once on each.
    * Unique test ids: schemathesis gives every operation's case of a test the test's own id
      (tests/fuzz/test_openapi.py), and a parallel run keeps one test per id (it would run one
      operation of each). Such a test's id becomes its name, which names the operation
      (``test_with_the_token[GET /v1/vehicle]``); any id still shared is an error.
    * Under ``--dist loadgroup``, each grouped test's id ends in ``@GROUP``, which is how
      pytest-xdist's scheduler finds the group. pytest-xdist 3.8 writes that suffix where pytest
      8 kept the id (``_nodeid``); pytest 9 keeps it elsewhere, so without this, groups would be
      silently ignored (:func:`_set_nodeid`).
    """
    counts = Counter(item.nodeid for item in items)
    for item in items:
        if counts[item.nodeid] > 1 and "::" in item.nodeid:
            _set_nodeid(item, f"{item.nodeid.rsplit('::', 1)[0]}::{item.name}")
    shared = sorted(nodeid for nodeid, n in Counter(i.nodeid for i in items).items() if n > 1)
    if shared:
        raise pytest.UsageError(f"tests share an id (a parallel run would drop some): {shared}")
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        named = module = None
        for name in item.fixturenames:
            definitions = info.name2fixturedefs.get(name)
            if not definitions:
                continue
            definition = definitions[-1]
            for marker in getattr(definition.func, NEEDS_ATTRIBUTE, ()):
                if item.get_closest_marker(marker) is None:
                    item.add_marker(marker)
            named = named or getattr(definition.func, GROUP_ATTRIBUTE, None)
            if definition.scope in ("module", "class"):
                module = f"module:{item.nodeid.split('::', 1)[0]}"
        group = named or module
        if group is not None and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(group))
    if getattr(config.option, "loadgroup", False):
        for item in items:
            group = _xdist_group(item)
            if group is not None:
                _set_nodeid(item, f"{item.nodeid}@{group}")
    if config.getoption("fast"):
        keep = [i for i in items if not any(i.get_closest_marker(t) for t in TIERS)]
        dropped = [i for i in items if any(i.get_closest_marker(t) for t in TIERS)]
        if dropped:
            config.hook.pytest_deselected(items=dropped)
            items[:] = keep


def _xdist_group(item: pytest.Item) -> str | None:
    """The name of the test's ``xdist_group`` (``default`` when the mark names none), or None."""
    mark = item.get_closest_marker("xdist_group")
    if mark is None:
        return None
    return mark.args[0] if mark.args else mark.kwargs.get("name", "default")


def _set_nodeid(item: pytest.Item, nodeid: str) -> None:
    """Give ``item`` the id ``nodeid``: pytest 9 keeps it as ``_id`` (a NodeId), pytest 8 as
    ``_nodeid`` (a string)."""
    if hasattr(item, "_id"):
        from _pytest.nodeid import coerce_node_id

        item._id = coerce_node_id(nodeid)
    else:
        item._nodeid = nodeid
    assert item.nodeid == nodeid, (item.nodeid, nodeid)


_ROOM_FOLDER = pytest.StashKey[str]()
_room: MachineRoom | None = None


def pytest_configure(config: pytest.Config) -> None:
    """The xdist controller makes the folder of the run's machine room (:mod:`tests.machine_room`:
    one test at a time beside a ``timing`` test); its workers, started after this, inherit its
    name."""
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    folder = tempfile.mkdtemp(prefix="tupa-test-room-")
    config.stash[_ROOM_FOLDER] = folder
    os.environ[ROOM_ENV] = folder


def pytest_unconfigure(config: pytest.Config) -> None:
    folder = config.stash.get(_ROOM_FOLDER, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(ROOM_ENV, None)


def _runs_alone(item: pytest.Item) -> bool:
    return _xdist_group(item) == EXCLUSIVE_GROUP


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    """A ``timing`` test takes the machine room's gate (setup, call, teardown; kept while its
    next test is one too) and waits for the tests already running to end; any other test waits
    while the gate is held, but one at a time may run beside it (:mod:`tests.machine_room`)."""
    global _room
    if _room is None:
        _room = room_from_environment()
    if _room is None:
        return (yield)
    alone = _runs_alone(item)
    if alone:
        _room.enter_alone()
    else:
        _room.enter()
    try:
        return (yield)
    finally:
        if not (alone and nextitem is not None and _runs_alone(nextitem)):
            _room.leave()


MOCK_SPEEDUP = 3.0
"""How much faster than the wall clock a :func:`start_mock` vehicle's clock runs by default
(``MockAutopilot``'s ``speedup``: its flight, its boot, its telemetry); a test that times the
vehicle against the wall clock passes ``speedup=1.0``."""
GROUND_STATION_TIMERS = (
    "offboard_timeout_s",
    "offboard_stream_max_gap_s",
    "gcs_failsafe_s",
    "auto_disarm_s",
)
"""The vehicle's timers that judge the ground station's wall-clock rates (its setpoint stream,
its heartbeats, its commands after arming): :func:`start_mock` multiplies their defaults by the
speedup (a test's own value is kept), so that the service under test has as many wall-clock
seconds as in real time before one of them fires."""
_DEFAULT_VEHICLE = VehicleConfig()

NO_NS3 = "ns-3 is not installed (pip install 'tupa[ns3]'): the ns-3 backend is optional"


@pytest.fixture(scope="session")
@needs("ns3", group="ns3")
def ns3_runner() -> Iterator[Any]:
    """One ns-3 worker (:class:`sim.ns3_backend.Ns3Runner`, niceness 10) for the whole test run:
    it imports ns-3 and compiles the scenario once (~15 s), then simulates the cases of every
    module one at a time; the tests that use it share the ``ns3`` xdist group, so that a
    parallel run starts it on one worker only. Skipped when ns-3 is not installed (checked with
    ``importorskip("ns3")``, the installed package's cheap namespace: ``import ns`` would load
    all of ns-3 into the test process)."""
    pytest.importorskip("ns3", reason=NO_NS3)
    from sim.ns3_backend import Ns3Runner

    with Ns3Runner(niceness=10) as runner:
        yield runner


@pytest.fixture
@needs("flying")
def start_mock() -> Iterator[Callable[..., MockAutopilot]]:
    """Factory: ``start_mock(flavour, listen=..., signing_key=..., **VehicleConfig fields)``."""
    mocks: list[MockAutopilot] = []

    def _start(
        flavour: str = "ardupilot",
        listen: str = "tcp:127.0.0.1:0",
        signing_key: bytes | None = None,
        speedup: float = MOCK_SPEEDUP,
        **config: Any,
    ) -> MockAutopilot:
        config.setdefault("ready_delay_s", 0.3)
        for name in GROUND_STATION_TIMERS:
            config.setdefault(name, getattr(_DEFAULT_VEHICLE, name) * speedup)
        mock = MockAutopilot(
            listen, flavour, VehicleConfig(**config), signing_key=signing_key, speedup=speedup
        )
        mocks.append(mock)
        return mock.start()

    yield _start
    for mock in mocks:
        mock.stop()
