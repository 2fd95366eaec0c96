"""The fleet model: K = 1 is the single-UAV model, cells on distinct channels are independent,
a shared channel costs airtime, association holds with hysteresis, handovers are counted and
cost an outage, the separation rule holds, bad input is a one-line error naming the field."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.association import associate, received_power_dbm
from sim.config import AreaConfig, RadioConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel, jain_index
from sim.flight import Flight, fly_many
from sim.geometry import (
    enforce_separation,
    hold_separation,
    min_pairwise_distance_m,
    volume_bounds,
)
from sim.network import NetworkModel
from sim.scenarios import generate_scenarios


@pytest.mark.parametrize("environment", ["open", "urban"])
@pytest.mark.parametrize("stochastic", [False, True])
def test_one_uav_is_the_single_model_bit_for_bit(environment: str, stochastic: bool) -> None:
    area = AreaConfig(environment=environment)
    single = NetworkModel(area=area)
    fleet = FleetModel(FleetConfig(n_uavs=1), area=area)
    scenario = generate_scenarios(1, 20, seed=3, family="mixture")[0]
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    state_a = state_b = None
    for step, xyz in enumerate(([250.0, 250.0, 25.0], [300.0, 120.0, 50.0], [40.0, 60.0, 100.0])):
        a = single.step(
            np.array([xyz]), scenario.users_xy_m, scenario.load_bps, state_a,
            rng_a if stochastic else None,
        )  # fmt: skip
        b = fleet.step(
            np.array([xyz]), scenario.users_xy_m, scenario.load_bps, state_b,
            rng_b if stochastic else None,
        )  # fmt: skip
        state_a, state_b = a.state, b.state
        for name in ("throughput_bps", "delay_s", "plr", "snr_db", "connected"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        np.testing.assert_array_equal(a.state.backlog_pkts, b.state.queues.backlog_pkts)
        assert b.handovers[0] == 0 and np.all(b.association == 0), step


def _two_cells(heavy_load_bps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """AP 0 at x = 100 m with one light user under it; AP 1 at x = 400 m with four users."""
    uavs = np.array([[100.0, 250.0, 25.0], [400.0, 250.0, 25.0]])
    users = np.array(
        [[100.0, 250.0], [380.0, 250.0], [420.0, 250.0], [400.0, 230.0], [400.0, 270.0]]
    )
    load = np.array([2e6] + [heavy_load_bps] * 4)
    return uavs, users, load


def test_distinct_channels_are_independent_cells() -> None:
    """The user of AP 0 sees exactly the same network whatever AP 1's users offer."""
    model = FleetModel(FleetConfig(n_uavs=2))
    results = []
    for heavy in (1e5, 30e6):
        uavs, users, load = _two_cells(heavy)
        state = None
        for _ in range(3):
            result = model.step(uavs, users, load, state)
            state = result.state
        results.append(result)
    light, loaded = results
    assert list(light.association[0]) == [0, 1, 1, 1, 1]
    for name in ("throughput_bps", "delay_s", "plr", "snr_db"):
        assert getattr(light, name)[0, 0] == getattr(loaded, name)[0, 0], name
    assert loaded.delay_s[0, 1:].min() > light.delay_s[0, 1:].max()  # AP 1's cell did change
    # And the user of AP 0 fares as it would alone under a single UAV.
    alone = NetworkModel().step(uavs[:1], users[:1], load[:1])
    alone = NetworkModel().step(uavs[:1], users[:1], load[:1], alone.state)
    alone = NetworkModel().step(uavs[:1], users[:1], load[:1], alone.state)
    assert light.throughput_bps[0, 0] == pytest.approx(alone.throughput_bps[0, 0], rel=1e-12)
    assert light.delay_s[0, 0] == pytest.approx(alone.delay_s[0, 0], rel=1e-12)


def test_a_shared_channel_within_carrier_sense_range_costs_throughput() -> None:
    uavs = np.array([[200.0, 250.0, 25.0], [300.0, 250.0, 25.0]])
    rng = np.random.default_rng(0)
    users = np.concatenate(
        [rng.uniform([150, 200], [190, 300], (6, 2)), rng.uniform([310, 200], [350, 300], (6, 2))]
    )
    load = np.full(12, 6e6)  # 72 Mbit/s: more than one channel carries
    totals = {}
    for mode in ("distinct", "shared"):
        model = FleetModel(FleetConfig(n_uavs=2, channel_mode=mode))
        state = None
        for _ in range(3):
            result = model.step(uavs, users, load, state)
            state = result.state
        totals[mode] = result.throughput_bps.sum()
        if mode == "shared":
            assert list(result.domain[0]) == [0, 0]  # 100 m apart: one contention domain
            assert np.all(np.isneginf(result.interference_dbm))
    assert totals["shared"] < 0.75 * totals["distinct"]


def test_out_of_carrier_sense_range_the_other_cell_interferes() -> None:
    area = AreaConfig(size_x_m=1500.0, size_y_m=500.0)
    uavs = np.array([[100.0, 250.0, 25.0], [1400.0, 250.0, 25.0]])
    users = np.array([[60.0, 250.0], [1440.0, 250.0]])
    load = np.array([5e6, 5e6])
    distinct = FleetModel(FleetConfig(n_uavs=2), area=area).step(uavs, users, load)
    shared = FleetModel(FleetConfig(n_uavs=2, channel_mode="shared"), area=area).step(
        uavs, users, load
    )
    assert list(shared.domain[0]) == [0, 1]  # 1.3 km apart: below -82 dBm, no deferral
    assert np.all(np.isfinite(shared.interference_dbm)) and shared.interference_dbm.max() < -82
    assert np.all(shared.snr_db < distinct.snr_db)  # SINR below SNR
    # Nobody offering traffic in the other cell: no interference.
    quiet = FleetModel(FleetConfig(n_uavs=2, channel_mode="shared"), area=area).step(
        uavs, users, np.array([5e6, 0.0])
    )
    assert np.isneginf(quiet.interference_dbm[0, 0]) and np.isfinite(quiet.interference_dbm[0, 1])


def test_association_picks_the_strongest_and_hysteresis_stops_flapping() -> None:
    area, radio = AreaConfig(), RadioConfig()
    uavs = np.array([[[150.0, 250.0, 25.0], [350.0, 250.0, 25.0]]])
    near_left = np.array([[170.0, 250.0]])
    rx = received_power_dbm(uavs, near_left, area, radio)
    first, handover = associate(rx, None, 3.0, radio.min_rssi_dbm)
    assert first[0, 0] == 0 and not handover.any()
    # A user wandering ±5 m around the midpoint: no handover either way, from either AP.
    for start in (0, 1):
        current = np.array([[start]])
        for x in (245.0, 255.0, 247.0, 253.0, 250.0):
            rx = received_power_dbm(uavs, np.array([[x, 250.0]]), area, radio)
            current, handover = associate(rx, current, 3.0, radio.min_rssi_dbm)
            assert current[0, 0] == start and not handover.any()
    # Far past the midpoint the other AP is more than 3 dB stronger: one handover.
    rx = received_power_dbm(uavs, np.array([[330.0, 250.0]]), area, radio)
    moved, handover = associate(rx, np.array([[0]]), 3.0, radio.min_rssi_dbm)
    assert moved[0, 0] == 1 and handover[0, 0]
    # Without hysteresis the same wander flaps.
    current, flaps = np.array([[0]]), 0
    for x in (255.0, 245.0, 255.0, 245.0):
        rx = received_power_dbm(uavs, np.array([[x, 250.0]]), area, radio)
        current, handover = associate(rx, current, 0.0, radio.min_rssi_dbm)
        flaps += int(handover.sum())
    assert flaps == 4


def test_handovers_are_counted_and_cost_an_outage() -> None:
    users = np.array([[120.0, 250.0], [380.0, 250.0]])
    load = np.array([4e6, 4e6])
    here = np.array([[100.0, 250.0, 25.0], [400.0, 250.0, 25.0]])
    swapped = here[::-1].copy()  # the UAVs trade places: both users hand over
    counts = {}
    for outage in (0.0, 0.2):
        model = FleetModel(FleetConfig(n_uavs=2, handover_outage_s=outage))
        state = model.step(here, users, load).state
        state = model.step(here, users, load, state).state
        result = model.step(swapped, users, load, state)
        assert result.handover[0].all() and result.handovers[0] == 2
        assert list(result.association[0]) == [1, 0]
        after = model.step(swapped, users, load, result.state)
        assert not after.handover.any() and after.handovers[0] == 2
        counts[outage] = result
    lossless, costly = counts[0.0], counts[0.2]
    np.testing.assert_allclose(costly.throughput_bps, 0.8 * lossless.throughput_bps)
    assert np.all(costly.plr >= 0.2 - 1e-12)


def test_fleet_metrics() -> None:
    uavs, users, load = _two_cells(1e6)
    result = FleetModel(FleetConfig(n_uavs=2)).step(uavs, users, load)
    assert result.served_fraction[0] == 1.0  # light load: everybody gets what it offers
    assert result.min_throughput_bps[0] == result.throughput_bps[0].min()
    assert 0.0 < result.jain_fairness[0] <= 1.0
    assert result.uav_utility.shape == (1, 2) and np.all(result.uav_utility > 0.9)
    assert jain_index(np.array([1.0, 1.0, 1.0])) == pytest.approx(1.0)
    assert jain_index(np.array([1.0, 0.0, 0.0, 0.0])) == pytest.approx(0.25)
    assert jain_index(np.zeros(3)) == 1.0
    # A UAV nobody is associated with contributes 0.
    far = np.array([[100.0, 250.0, 25.0], [490.0, 10.0, 100.0]])
    lonely = FleetModel(FleetConfig(n_uavs=2)).step(far, users[:1], load[:1])
    assert lonely.uav_utility[0, 1] == 0.0


def test_a_batch_of_fleets_is_each_fleet_alone() -> None:
    scenario = generate_scenarios(1, 15, seed=1, family="uniform")[0]
    model = FleetModel(FleetConfig(n_uavs=3))
    rng = np.random.default_rng(2)
    fleets = rng.uniform([0, 0, 25], [500, 500, 100], (4, 3, 3))
    batch = model.step(fleets, scenario.users_xy_m, scenario.load_bps)
    for b in range(4):
        alone = model.step(fleets[b], scenario.users_xy_m, scenario.load_bps)
        np.testing.assert_allclose(alone.throughput_bps[0], batch.throughput_bps[b], rtol=1e-12)
        assert alone.utility[0] == pytest.approx(batch.utility[b], rel=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"n_uavs": 0}, "n_uavs"),
        ({"n_uavs": 9}, "n_uavs"),
        ({"n_uavs": 2.5}, "n_uavs"),
        ({"n_uavs": True}, "n_uavs"),
        ({"separation_m": 0.0}, "separation_m"),
        ({"separation_m": -3.0}, "separation_m"),
        ({"separation_m": float("nan")}, "separation_m"),
        ({"channel_mode": "mixed"}, "channel_mode"),
        ({"hysteresis_db": -1.0}, "hysteresis_db"),
        ({"handover_outage_s": -0.1}, "handover_outage_s"),
    ],
)
def test_bad_fleet_settings_are_one_line_errors_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(InputError) as caught:
        FleetConfig(**kwargs)
    message = str(caught.value)
    assert message.startswith(f"{field}:") and "\n" not in message


def test_bad_step_input_names_the_argument() -> None:
    model = FleetModel(FleetConfig(n_uavs=2))
    users, load = np.array([[10.0, 10.0]]), np.array([1e6])
    with pytest.raises(InputError, match=r"^uav_xyz_m:"):
        model.step(np.zeros((3, 3)), users, load)
    with pytest.raises(InputError, match=r"^load_bps:"):
        model.step(np.full((2, 3), 30.0), users, np.array([1e6, 2e6]))
    with pytest.raises(InputError, match=r"^users_xy_m:"):
        model.step(np.full((2, 3), 30.0), np.array([[np.nan, 1.0]]), load)


def test_channels() -> None:
    assert FleetConfig(n_uavs=4).channels == (36, 40, 44, 48)
    assert FleetConfig(n_uavs=3, channel_mode="shared").channels == (36, 36, 36)


# --------------------------------------------------------------------------------------------
# Separation: a hard constraint on every set of targets

# Volumes that hold 8 vehicles 30 m apart with room to spare (one of them flat): the rule
# refuses only volumes too small for the fleet (tested below).
AREAS = (
    AreaConfig(),
    AreaConfig(size_x_m=250.0, size_y_m=250.0, zone_m=25.0, z_min_m=25.0, z_max_m=25.0),
)
coordinate = st.floats(-100.0, 600.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    targets=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=1, max_size=8),
    separation_m=st.floats(0.5, 30.0),
    area=st.sampled_from(AREAS),
)
def test_enforced_targets_are_separated_and_inside_the_volume(
    targets: list, separation_m: float, area: AreaConfig
) -> None:
    wanted = np.array(targets, dtype=float)
    out = enforce_separation(wanted, separation_m, area)
    lower, upper = volume_bounds(area)
    assert out.shape == wanted.shape
    assert np.all(out >= lower) and np.all(out <= upper)
    gap = out[:, None, :] - out[None, :, :]
    distance = np.sqrt(np.sum(gap * gap, axis=-1)) + np.diag(np.full(len(out), np.inf))
    assert distance.min() >= separation_m
    np.testing.assert_array_equal(out, enforce_separation(wanted, separation_m, area))
    assert np.array_equal(out[0], np.clip(wanted[0], lower, upper))  # the first keeps its own


def test_separated_targets_are_left_alone_and_coincident_ones_pushed_apart() -> None:
    area = AreaConfig()
    apart = np.array([[100.0, 100.0, 25.0], [200.0, 100.0, 25.0]])
    np.testing.assert_array_equal(enforce_separation(apart, 10.0, area), apart)
    same = np.array([[100.0, 100.0, 25.0]] * 3)
    out = enforce_separation(same, 10.0, area)
    assert np.all(np.linalg.norm(out[1:] - same[1:], axis=1) < 10.0 + 1e-6)  # moved minimally
    with pytest.raises(ValueError, match="separation_m"):
        enforce_separation(same, 0.0, area)
    tiny = AreaConfig(size_x_m=25.0, size_y_m=25.0, zone_m=25.0, z_min_m=25.0, z_max_m=25.0)
    with pytest.raises(ValueError, match="separation_m: the volume cannot hold"):
        enforce_separation(np.zeros((8, 3)), 20.0, tiny)


@settings(max_examples=100, deadline=None)
@given(
    start=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=2, max_size=6),
    moves=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=6, max_size=6),
)
def test_holding_keeps_vehicles_separated(start: list, moves: list) -> None:
    area = AreaConfig()
    previous = enforce_separation(np.array(start), 10.0, area)
    proposed = np.array(moves[: len(previous)])
    out = hold_separation(previous, proposed, 10.0, area)
    gap = out[:, None, :] - out[None, :, :]
    distance = np.sqrt(np.sum(gap * gap, axis=-1)) + np.diag(np.full(len(out), np.inf))
    assert distance.min() >= 10.0 * (1 - 1e-12)
    lower, upper = volume_bounds(area)
    for k in range(len(out)):
        # Where it was, where it wanted to be, or a detour: its step turned about the vertical
        # (clipped into the volume), no longer than the step it wanted.
        if np.array_equal(out[k], previous[k]) or np.array_equal(out[k], proposed[k]):
            continue
        step, taken = proposed[k] - previous[k], out[k] - previous[k]
        assert np.hypot(*taken[:2]) <= np.hypot(*step[:2]) + 1e-9
        assert taken[2] == pytest.approx(
            np.clip(proposed[k][2], lower[2], upper[2]) - previous[k][2]
        )
        assert np.all((out[k] >= lower) & (out[k] <= upper))


@pytest.mark.parametrize(
    "starts, targets",
    [
        # A path straight through a vehicle that hovers on it.
        (
            [[200.0, 250.0, 25.0], [250.0, 250.0, 25.0]],
            [[300.0, 250.0, 25.0], [250.0, 250.0, 25.0]],
        ),
        # Head on: each wants the other's place.
        (
            [[200.0, 250.0, 25.0], [300.0, 250.0, 25.0]],
            [[300.0, 250.0, 25.0], [200.0, 250.0, 25.0]],
        ),
        # Three in a row at the fleet's homes, the outer two crossing to the far sides.
        (
            [[237.5, 262.5, 25.0], [262.5, 262.5, 25.0], [287.5, 262.5, 25.0]],
            [[400.0, 262.5, 25.0], [262.5, 262.5, 25.0], [100.0, 262.5, 25.0]],
        ),
    ],
)
def test_vehicles_go_round_each_other_instead_of_waiting(starts: list, targets: list) -> None:
    area, flight = AreaConfig(), Flight(10.0, 3.0)
    here, goal = np.array(starts, dtype=float), np.array(targets, dtype=float)
    for _ in range(60):  # bounded: 100-odd metres at 10 m/s, with detours
        here = hold_separation(here, fly_many(here, goal, flight, 1.0), 10.0, area)
        assert min_pairwise_distance_m(here) >= 10.0 - 1e-9
        if np.array_equal(here, goal):
            break
    np.testing.assert_allclose(here, goal)


@pytest.mark.parametrize("mode", ["distinct", "shared"])
@pytest.mark.parametrize("environment", ["open", "dense-urban"])
@pytest.mark.parametrize("stochastic", [False, True])
def test_every_mode_keeps_the_model_invariants(
    mode: str, environment: str, stochastic: bool
) -> None:
    area = AreaConfig(environment=environment)
    scenario = generate_scenarios(1, 30, seed=9, family="hotspots", total_load_bps=120e6)[0]
    model = FleetModel(FleetConfig(n_uavs=4, channel_mode=mode), area=area)
    rng = np.random.default_rng(1) if stochastic else None
    uavs = np.array([[100.0, 100.0, 25.0], [400.0, 100.0, 50.0], [100, 400, 75], [400, 400, 100]])
    state = None
    for _ in range(4):
        result = model.step(uavs, scenario.users_xy_m, scenario.load_bps, state, rng)
        state = result.state
        assert np.all(result.throughput_bps >= 0) and np.all(np.isfinite(result.delay_s))
        assert np.all((result.plr >= 0) & (result.plr <= 1))
        assert np.all((result.association >= 0) & (result.association < 4))
        assert 0 <= result.utility[0] <= 1 and 0 <= result.served_fraction[0] <= 1
        assert np.all(result.uav_utility >= 0) and np.all(result.uav_utility <= 1)
    assert np.all(result.state.queues.backlog_pkts >= 0)


def test_a_user_out_of_every_ap_s_range_does_not_roam() -> None:
    radio = RadioConfig()
    rx = np.array([[[-95.0], [-93.0]]])  # neither AP heard (minimum -90 dBm)
    kept, handover = associate(rx, np.array([[0]]), 0.0, radio.min_rssi_dbm)
    assert kept[0, 0] == 0 and not handover.any()
    rx = np.array([[[-95.0], [-80.0]]])  # its AP lost, another heard: it moves
    moved, handover = associate(rx, np.array([[0]]), 3.0, radio.min_rssi_dbm)
    assert moved[0, 0] == 1 and handover[0, 0]
