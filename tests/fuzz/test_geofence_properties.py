"""No policy output, NaN or extreme report, and no vehicle position can make the link stream a
setpoint outside the geofence (the area volume: x, y in [0, 500] m, z in [25, 100] m).

Three levels, all on real code (no fakes):

* :func:`sim.geometry.clamp_point` (the geofence) on any three floats;
* every policy kind (the baselines: ``placement``; the shipped DDQN checkpoint when it is there:
  ``moves``; a real, untrained DDPG network: ``coordinates``) deciding on
  any report from any vehicle position, its target handed to a real
  :class:`~service.mavlink_link.MavlinkLink` (to a closed port: it clamps without a vehicle),
  exactly as :meth:`PlacementService.decide_once` does: the target the link would stream is
  inside the volume, or the decision is refused with ValueError and the old target stays;
* :class:`PlacementService` itself against an in-process sitl_mock, fed reports the HTTP side
  would refuse (NaN, infinities, negative numbers, users outside the area): whatever it decides,
  the streamed target stays inside, and a refusal leaves the old one.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from policies.interface import Policy
from service.mavlink_link import MavlinkLink
from service.policy_runtime import SHIPPED_DDQN, load_policy
from service.vehicle_link import LinkConfig
from sim.config import AreaConfig
from sim.geometry import clamp_point
from sim.observation import UserReports
from sim.world import CLOSED_LOOP, PAPER

AREA = AreaConfig()
BOUNDS = ((0.0, AREA.size_x_m), (0.0, AREA.size_y_m), (AREA.z_min_m, AREA.z_max_m))
PROPERTY = settings(
    max_examples=40,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def inside(target: Any) -> bool:
    values = [float(v) for v in target]
    return len(values) == 3 and all(
        math.isfinite(v) and lo <= v <= hi for v, (lo, hi) in zip(values, BOUNDS, strict=True)
    )


def test_the_area_is_the_one_the_issue_names() -> None:
    assert BOUNDS == ((0.0, 500.0), (0.0, 500.0), (25.0, 100.0))


# --------------------------------------------------------------------------- strategies

any_float = st.floats(allow_nan=True, allow_infinity=True)
extreme = st.floats(min_value=-1e300, max_value=1e300, allow_nan=False, allow_infinity=False)
non_negative = st.one_of(
    st.floats(min_value=0.0, max_value=1e300, allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, 5e-324, 1e-300, 1.0, 40e6, 1e300]),
)
position = st.tuples(extreme, extreme, extreme)


@st.composite
def valid_reports(draw: Any, max_users: int = 300) -> UserReports:
    """What the HTTP side accepts: finite, non-negative, loss in [0, 1], users in the area,
    one to ``max_users`` users, magnitudes from 0 to 1e300."""
    n = draw(st.one_of(st.integers(1, 3), st.integers(1, max_users)))

    def column(elements: Any) -> np.ndarray:
        return np.array(draw(st.lists(elements, min_size=n, max_size=n)), dtype=float)

    x = st.floats(min_value=0.0, max_value=AREA.size_x_m)
    y = st.floats(min_value=0.0, max_value=AREA.size_y_m)
    return UserReports(
        x_m=column(x),
        y_m=column(y),
        offered_bps=column(non_negative),
        throughput_bps=column(non_negative),
        delay_s=column(non_negative),
        plr=column(st.floats(min_value=0.0, max_value=1.0)),
    )


@st.composite
def hostile_reports(draw: Any, max_users: int = 50) -> UserReports:
    """What only the service level can see: any float anywhere, NaN and infinities included."""
    n = draw(st.integers(1, max_users))

    def column() -> np.ndarray:
        return np.array(draw(st.lists(any_float, min_size=n, max_size=n)), dtype=float)

    return UserReports(
        x_m=column(),
        y_m=column(),
        offered_bps=column(),
        throughput_bps=column(),
        delay_s=column(),
        plr=column(),
    )


# --------------------------------------------------------------------------- clamp_point


@given(target=st.tuples(any_float, any_float, any_float))
@PROPERTY
def test_clamp_to_area_puts_every_finite_target_inside(target: tuple[float, ...]) -> None:
    if not all(math.isfinite(v) for v in target):
        with pytest.raises(ValueError, match="finite"):
            clamp_point(target, AREA)
        return
    clamped, was_clamped = clamp_point(target, AREA)
    assert inside(clamped)
    assert was_clamped == (not inside(target))
    if inside(target):
        assert clamped == tuple(float(v) for v in target)
    assert clamp_point(clamped, AREA) == (clamped, False)  # idempotent
    for value, got, (lo, hi) in zip(target, clamped, BOUNDS, strict=True):
        assert got == min(max(value, lo), hi)  # the nearest point: per-axis clamp


@given(target=st.lists(any_float, max_size=6).filter(lambda t: len(t) != 3))
@PROPERTY
def test_clamp_to_area_refuses_anything_but_three_numbers(target: list[float]) -> None:
    with pytest.raises(ValueError, match="target"):
        clamp_point(target, AREA)


# --------------------------------------------------------------------------- every policy kind


def _policy_specs() -> list[Any]:
    specs: list[Any] = [
        pytest.param("min-distance", id="min-distance"),
        pytest.param("load-weighted", id="load-weighted"),
        pytest.param("oracle", id="oracle"),
    ]
    # The "coordinates" kind: a real SB3 DDPG network, untrained (arbitrary actions).
    specs.append(pytest.param(DDPG_UNTRAINED, id="ddpg-untrained"))
    reason = f"the shipped DDQN checkpoint {SHIPPED_DDQN} is not in this checkout"
    specs.append(
        pytest.param(
            str(SHIPPED_DDQN),
            id="ddqn-dr",
            marks=pytest.mark.skipif(not SHIPPED_DDQN.is_file(), reason=reason),
        )
    )
    return specs


_POLICIES: dict[str, Policy] = {}
DDPG_UNTRAINED = "ddpg-untrained"


def _untrained_ddpg() -> Policy:
    """A DDPG policy (kind ``coordinates``) as the service serves one, with a freshly built
    (untrained, small) network: no DDPG checkpoint is shipped."""
    from dataclasses import replace

    from policies.adapters import CheckpointPolicy
    from policies.training.presets import NetworkPreset, get_preset
    from policies.training.training import build_model, make_env
    from sim.scenarios import generate_scenarios

    tiny = NetworkPreset(channels=(8,), hidden=32, features_dim=32, dropout=0.0)
    preset = replace(get_preset("fast", "ddpg"), network=tiny, buffer_size=1_000)
    env = make_env("ddpg", generate_scenarios(2, 3, seed=7), replace(PAPER, area=AREA))
    model = build_model("ddpg", env, preset, seed=0, tensorboard_log=None)
    metadata = {"algorithm": "ddpg", "strategy": "untrained"}
    return CheckpointPolicy(model, metadata, DDPG_UNTRAINED, world=replace(PAPER, area=AREA))


def _policy(spec: str) -> Policy:
    if spec not in _POLICIES:  # loading a checkpoint takes seconds: once per session
        _POLICIES[spec] = (
            _untrained_ddpg()
            if spec == DDPG_UNTRAINED
            else load_policy(spec, replace(CLOSED_LOOP, area=AREA))
        )
    return _POLICIES[spec]


@pytest.fixture(scope="module")
def link() -> Iterator[MavlinkLink]:
    """A real link to a closed port: no vehicle, but set_target clamps and keeps the target."""
    with MavlinkLink(LinkConfig("tcp:127.0.0.1:1", area=AREA, reconnect_max_s=1.0)) as real:
        yield real


def _decide_and_stream(
    link: MavlinkLink,
    policy: Policy,
    reports: UserReports,
    vehicle: np.ndarray,
) -> None:
    """What decide_once does with a decision, and the property about it."""
    before = link.state().target_m
    try:
        target = policy.decide(reports, vehicle)
        clamped = link.set_target(tuple(float(v) for v in np.asarray(target).ravel()))
    except ValueError:  # the one documented refusal (InputError is one)
        assert link.state().target_m == before  # refused: the old target stays
        return
    assert inside(clamped), clamped
    assert link.state().target_m == clamped
    assert link.state().target_m is None or inside(link.state().target_m)


@pytest.mark.parametrize("spec", _policy_specs())
@given(reports=valid_reports(), vehicle=position)
@PROPERTY
def test_any_valid_report_and_any_position_stream_inside_the_geofence(
    spec: str, link: MavlinkLink, reports: UserReports, vehicle: Any
) -> None:
    policy = _policy(spec)
    if spec == "oracle" and len(reports.x_m) > 40:  # the oracle searches the volume: keep it quick
        reports = UserReports(*(np.asarray(col)[:40] for col in _columns(reports)))
    with np.errstate(invalid="ignore"):  # a 1e300 m position cast to a zone index
        _decide_and_stream(link, policy, reports, np.array(vehicle))


@pytest.mark.parametrize("spec", _policy_specs())
@given(
    reports=hostile_reports(),
    vehicle=st.tuples(any_float, any_float, any_float),
)
@PROPERTY
def test_nan_and_hostile_numbers_never_stream_outside_the_geofence(
    spec: str, link: MavlinkLink, reports: UserReports, vehicle: Any
) -> None:
    policy = _policy(spec)
    with np.errstate(all="ignore"):
        _decide_and_stream(link, policy, reports, np.array(vehicle))


def _columns(reports: UserReports) -> list[np.ndarray]:
    return [
        reports.x_m,
        reports.y_m,
        reports.offered_bps,
        reports.throughput_bps,
        reports.delay_s,
        reports.plr,
    ]


# --------------------------------------------------------------------------- the service


@pytest.fixture(scope="module")
def placement() -> Iterator[Any]:
    """PlacementService (load-weighted, decides on every report) on an in-process sitl_mock."""
    from service.opening import open_service
    from service.settings import ServiceSettings
    from sitl_mock.config import VehicleConfig
    from sitl_mock.server import MockAutopilot
    from tests.helpers import wait_for

    mock = MockAutopilot("tcp:127.0.0.1:0", "px4", VehicleConfig(ready_delay_s=0.3))
    mock.start()
    try:
        settings_ = ServiceSettings(
            mavlink=f"tcp:127.0.0.1:{mock.port}",
            api_token="unused",
            policy="load-weighted",
            decision_mode="on-report",
        )
        service = open_service(settings_).start()
        try:
            wait_for(lambda: service.readiness()[0], 15.0, message="link up, position known")
            yield service
        finally:
            service.stop()
    finally:
        mock.stop()


def test_the_service_streams_inside_the_geofence_whatever_it_is_fed(placement: Any) -> None:
    from service.decisions import Report

    timestamps = itertools.count(1)

    @given(reports=st.one_of(hostile_reports(), valid_reports(max_users=100)))
    @PROPERTY
    def check(reports: UserReports) -> None:
        before = placement.vehicle().target_m
        ids = tuple(f"u{i}" for i in range(len(reports.x_m)))
        with np.errstate(all="ignore"):
            try:
                decision = placement.submit_report(Report(float(next(timestamps)), ids, reports))
            except ValueError:
                decision = None
        streamed = placement.vehicle().target_m
        if decision is not None and decision.source == "policy":
            assert inside(decision.target_m)
        if streamed != before:
            assert streamed is not None and inside(streamed)
        assert streamed is None or inside(streamed)

    check()
    counters = placement.snapshot_counters()
    # Both sides were exercised: decisions streamed, and hostile reports refused.
    assert counters.get("decisions", 0) > 0, counters
    assert counters.get("decisions_rejected", 0) > 0, counters
