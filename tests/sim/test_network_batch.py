"""The batched model side of a vectorised environment: ``step_many``, ``build_observations`` and
``network_utility`` over (E, U), each exactly what E single-environment calls give."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.channel import rician_power_gain
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.network import RATE_DRAWS_PER_STEP, NetworkModel, QueueState
from sim.observation import UserReports, build_observation, build_observations
from sim.utility import network_utility

MODEL = NetworkModel()
MAC_ONLY = NetworkModel(NetworkConfig().with_queueing("mac-only"))
AREA = AreaConfig()
FIELDS = ("throughput_bps", "delay_s", "plr", "snr_db", "connected")


def cells(seed: int, n_envs: int, n_users: int):
    """E random cells: UAV positions (E, 3), users (E, U, 2), loads (E, U) (some idle users)."""
    gen = np.random.default_rng(seed)
    uav = np.column_stack(
        [
            gen.uniform(0, AREA.size_x_m, n_envs),
            gen.uniform(0, AREA.size_y_m, n_envs),
            gen.uniform(AREA.z_min_m, AREA.z_max_m, n_envs),
        ]
    )
    users = gen.uniform(0, AREA.size_x_m, (n_envs, n_users, 2))
    load = gen.uniform(0, 3 * 40e6 / n_users, (n_envs, n_users))
    load[gen.random((n_envs, n_users)) < 0.1] = 0.0
    return uav, users, load


class DrawStream:
    """Stands in for a generator: hands out a fixed sequence of standard normals in order."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = np.asarray(values, dtype=float).ravel()
        self.taken = 0

    def standard_normal(self, size):
        n = int(np.prod(size))
        out = self.values[self.taken : self.taken + n].reshape(size)
        self.taken += n
        return out.copy()


def state_row(state: QueueState | None, e: int) -> QueueState | None:
    if state is None:
        return None
    return state.map(lambda a: a[e : e + 1])


def assert_rows_equal(batch, e: int, one) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(batch, name)[e], getattr(one, name)[0], name)
    np.testing.assert_array_equal(batch.state.backlog_pkts[e], one.state.backlog_pkts[0])
    np.testing.assert_array_equal(batch.state.codel_count[e], one.state.codel_count[0])
    np.testing.assert_array_equal(batch.state.at_cap_s[e], one.state.at_cap_s[0])


@pytest.mark.parametrize("model", [MODEL, MAC_ONLY], ids=["fq-codel", "mac-only"])
@pytest.mark.parametrize("n_users", [1, 3, 12])
def test_step_many_expected_mode_equals_one_step_per_environment(model, n_users):
    """Several steps, queues carried over: every row is bit for bit its own ``step``."""
    uav, users, load = cells(n_users, 9, n_users)
    state = None
    singles: list[QueueState | None] = [None] * len(uav)
    for _ in range(4):
        batch = model.step_many(uav, users, load, state, step_s=0.5)
        assert batch.throughput_bps.shape == (len(uav), n_users)
        for e in range(len(uav)):
            one = model.step(uav[e], users[e], load[e], singles[e], step_s=0.5)
            assert_rows_equal(batch, e, one)
            singles[e] = one.state
        state = batch.state
        uav = uav + np.array([15.0, -10.0, 0.0])  # fly a little; the backlogs follow


@pytest.mark.parametrize("n_users", [1, 3, 7])
def test_step_many_stochastic_equals_per_environment_steps_with_the_same_draws(n_users):
    """The documented draw order: (2, E, U, RATE_DRAWS_PER_STEP) standard normals, real parts
    of every cell first; cell e's step sees its real block, then its imaginary block."""
    uav, users, load = cells(100 + n_users, 6, n_users)
    n_envs = len(uav)
    state = None
    singles: list[QueueState | None] = [None] * n_envs
    for step in range(3):
        rng = np.random.default_rng(step)
        batch = MODEL.step_many(uav, users, load, state, rng)
        draws = np.random.default_rng(step).standard_normal((2, n_envs, n_users, 8))
        assert RATE_DRAWS_PER_STEP == 8
        # One rician_power_gain call of (E, U, draws): the generator is left where it says.
        assert (
            rng.standard_normal() == np.random.default_rng(step).standard_normal(draws.size + 1)[-1]
        )
        for e in range(n_envs):
            stream = DrawStream(np.concatenate([draws[0, e].ravel(), draws[1, e].ravel()]))
            one = MODEL.step(uav[e], users[e], load[e], singles[e], stream)  # type: ignore[arg-type]
            assert stream.taken == 2 * n_users * RATE_DRAWS_PER_STEP
            assert_rows_equal(batch, e, one)
            singles[e] = one.state
        state = batch.state


def test_step_many_fading_fluctuates_around_the_expected_mode():
    """Statistics: the same cell repeated E times sees E different draws, centred on the
    expected mode's throughput."""
    n_envs = 400
    xy = np.array([[100.0, 100.0], [300.0, 120.0], [250.0, 400.0]])
    users = np.broadcast_to(xy, (n_envs, 3, 2))
    load = np.broadcast_to(np.array([4e6, 4e6, 4e6]), (n_envs, 3))
    uav = np.broadcast_to(np.array([250.0, 250.0, 60.0]), (n_envs, 3))
    sampled = MODEL.step_many(uav, users, load, rng=np.random.default_rng(1))
    expected = MODEL.step(uav[0], xy, load[0])
    assert np.unique(sampled.throughput_bps[:, 2]).size > n_envs // 2
    mean = sampled.throughput_bps.mean(axis=0)
    np.testing.assert_allclose(mean, expected.throughput_bps[0], rtol=0.05)


def test_step_draws_one_rician_block_per_call_and_nothing_when_refused():
    uav = np.array([[100.0, 100.0, 25.0], [400.0, 300.0, 75.0]])
    xy = np.array([[10.0, 20.0], [480.0, 250.0], [250.0, 250.0]])
    load = np.array([1e7, 2e7, 5e6])
    rng = np.random.default_rng(4)
    MODEL.step(uav, xy, load, rng=rng)
    reference = np.random.default_rng(4)
    reference.standard_normal(2 * uav.shape[0] * xy.shape[0] * RATE_DRAWS_PER_STEP)
    assert rng.standard_normal() == reference.standard_normal()
    # A refused call draws nothing.
    rng = np.random.default_rng(4)
    with pytest.raises(InputError, match="load_bps"):
        MODEL.step(uav, xy, -load, rng=rng)
    assert rng.standard_normal() == np.random.default_rng(4).standard_normal()


@settings(max_examples=30, deadline=None)
@given(
    k_db=st.floats(-5.0, 25.0),
    shape=st.lists(st.integers(0, 5), min_size=1, max_size=3).map(tuple),
    seed=st.integers(0, 2**32 - 1),
)
def test_rician_power_gain_is_the_two_call_formula(k_db, shape, seed):
    """One standard_normal call of (2, *size): the same numbers as the real and imaginary
    parts drawn by two calls, the same gains to the bit."""
    k = 10.0 ** (k_db / 10.0)
    los, sigma = np.sqrt(k / (k + 1.0)), np.sqrt(1.0 / (2.0 * (k + 1.0)))
    reference = np.random.default_rng(seed)
    re = los + sigma * reference.standard_normal(shape)
    im = sigma * reference.standard_normal(shape)
    rng = np.random.default_rng(seed)
    np.testing.assert_array_equal(rician_power_gain(rng, k_db, shape), re * re + im * im)
    assert rng.standard_normal() == reference.standard_normal()


def test_step_many_refuses_bad_inputs_naming_them():
    uav, users, load = cells(3, 4, 3)
    with pytest.raises(InputError, match="uav_xyz_m"):
        MODEL.step_many(uav[:, :2], users, load)
    with pytest.raises(InputError, match="users_xy_m"):
        MODEL.step_many(uav, users[:3], load)
    with pytest.raises(InputError, match="users_xy_m"):
        MODEL.step_many(uav, users[0], load)
    with pytest.raises(InputError, match="load_bps"):
        MODEL.step_many(uav, users, load[:, :2])
    with pytest.raises(InputError, match="state"):
        MODEL.step_many(uav, users, load, QueueState.empty(3, 3))
    bad = users.copy()
    bad[2, 1, 0] = np.nan
    with pytest.raises(InputError, match="users_xy_m"):
        MODEL.step_many(uav, bad, load)
    bad = load.copy()
    bad[3, 2] = -1.0
    with pytest.raises(InputError, match="load_bps"):
        MODEL.step_many(uav, users, bad)
    with pytest.raises(InputError, match="step_s"):
        MODEL.step_many(uav, users, load, step_s=float("nan"))


def test_step_still_names_the_first_bad_argument_and_takes_huge_finite_values():
    xy = np.array([[10.0, 10.0], [20.0, 20.0]])
    load = np.array([1e6, 2e6])
    # Finite, but their sum overflows: the reference check's own message.
    with pytest.raises(InputError, match="too large"), np.errstate(over="ignore"):
        MODEL.step(np.array([[1e308, 1e308, 25.0]]), xy, load)
    # Non-finite values are named before a bad state or step_s, as they always were.
    with pytest.raises(InputError, match="uav_xyz_m"):
        MODEL.step(np.array([[np.nan, 1.0, 25.0]]), xy, load, QueueState.empty(3, 3), step_s=0)
    with pytest.raises(InputError, match="step_s"):
        MODEL.step(np.array([[1.0, 1.0, 25.0]]), xy, load, QueueState.empty(3, 3), step_s=0)
    # Huge but harmless values take the slow check's word and are simulated.
    far = MODEL.step(np.array([[1e301, 0.0, 25.0]]), xy, load)
    assert not far.connected.any()
    np.testing.assert_array_equal(far.throughput_bps, 0.0)


@pytest.mark.parametrize("n_users", [1, 3, 9, 40])
def test_network_utility_over_environments_equals_one_row_at_a_time(n_users):
    gen = np.random.default_rng(n_users)
    shape = (17, n_users)
    offered = gen.uniform(0, 2e7, shape)
    throughput = offered * gen.uniform(0, 1.2, shape)
    delay = gen.exponential(0.5, shape)
    plr = gen.uniform(0, 1, shape)
    config = UtilityConfig(delay_ref_s=0.7)
    batch = network_utility(throughput, delay, plr, offered, config)
    assert batch.shape == (17,)
    for e in range(17):
        one = network_utility(throughput[e], delay[e], plr[e], offered[e], config)
        assert isinstance(one, np.float64)
        assert one == batch[e]
        # The 1-D fast path is the general formula, to the bit.
        reference = (
            config.weight_throughput
            * np.maximum(
                np.minimum(np.sum(throughput[e]) / np.maximum(np.sum(offered[e]), 1e-12), 1.0), 0.0
            )
            + config.weight_delay
            * (1.0 - np.maximum(np.minimum(np.mean(delay[e]) / config.delay_ref_s, 1.0), 0.0))
            + config.weight_loss * (1.0 - np.maximum(np.minimum(np.mean(plr[e]), 1.0), 0.0))
        )
        assert one == reference


def test_build_observations_rows_equal_build_observation():
    gen = np.random.default_rng(8)
    n_envs, n_users = 11, 5
    uav, users, load = cells(8, n_envs, n_users)
    users[0, :, :] = users[0, 0]  # every user of one cell in one zone
    users[1, 0] = [-30.0, 700.0]  # off the grid: clipped into the border zones
    throughput = load * gen.uniform(0, 1.1, load.shape)
    delay = gen.exponential(0.8, load.shape)
    plr = gen.uniform(0, 1, load.shape)
    args = (users[..., 0], users[..., 1], load, throughput, delay, plr)
    maps = build_observations(uav, *args, AREA, 0.5)
    assert maps.shape == (n_envs, 6, AREA.n_zones_x, AREA.n_zones_y)
    assert maps.dtype == np.float32
    for e in range(n_envs):
        reports = UserReports(*(values[e] for values in args))
        np.testing.assert_array_equal(maps[e], build_observation(uav[e], reports, AREA, 0.5))


def test_build_observations_refuses_mismatched_shapes():
    uav, users, load = cells(9, 3, 2)
    args = [users[..., 0], users[..., 1], load, load, load, load]
    with pytest.raises(ValueError, match="uav_xyz_m"):
        build_observations(uav[:, :2], *args, AREA)
    for i, name in enumerate(UserReports._fields):
        bad = list(args)
        bad[i] = bad[i][:, :1] if i else bad[i][:2]
        with pytest.raises(ValueError, match=name):
            build_observations(uav, *bad, AREA)


def test_one_vectorised_step_end_to_end():
    """What a vectorised environment does each step: model, utility, observations, in batch."""
    uav, users, load = cells(12, 64, 3)
    result = MODEL.step_many(uav, users, load, rng=np.random.default_rng(0))
    reward = network_utility(result.throughput_bps, result.delay_s, result.plr, load)
    maps = build_observations(
        uav,
        users[..., 0],
        users[..., 1],
        load,
        result.throughput_bps,
        result.delay_s,
        result.plr,
        AREA,
    )
    assert reward.shape == (64,) and np.all((reward >= 0) & (reward <= 1))
    assert maps.shape == (64, 6, AREA.n_zones_x, AREA.n_zones_y)
    assert np.all((maps >= 0) & (maps <= 1))
