"""The scenario generator, the Scenario/Case types and the heterogeneity histogram."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.config import AreaConfig
from sim.errors import InputError
from sim.scenarios import (
    Case,
    GeneratorConfig,
    Scenario,
    format_heterogeneity_histogram,
    generate_scenarios,
    heterogeneity_histogram,
    heterogeneity_indices,
)
from sim.utility import heterogeneity_index

AREA = AreaConfig()


@pytest.fixture(scope="module")
def paper_set() -> list[Scenario]:
    """500 scenarios of 3 users: the paper's test-set size."""
    return generate_scenarios(500, 3, seed=1, area=AREA)


def test_ids_and_shapes() -> None:
    scenarios = generate_scenarios(12, 4, seed=0)
    assert [s.id for s in scenarios] == [f"s{i:04d}" for i in range(12)]
    for s in scenarios:
        assert s.n_users == 4
        assert s.users_xy_m.shape == (4, 2)
        assert s.load_bps.shape == (4,)
        assert s.users_xy_m.dtype == np.float64
        assert s.load_bps.dtype == np.float64


def test_same_seed_same_set_different_seed_different() -> None:
    a = generate_scenarios(20, 3, seed=7)
    b = generate_scenarios(20, 3, seed=7)
    c = generate_scenarios(20, 3, seed=8)
    assert a == b
    assert all(x != y for x, y in zip(a, c, strict=True))


def test_smaller_set_is_a_prefix_of_a_larger_one() -> None:
    assert generate_scenarios(5, 3, seed=3) == generate_scenarios(30, 3, seed=3)[:5]


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_users=st.integers(1, 12),
    total_load_bps=st.floats(1e3, 1e9),
    zones=st.tuples(st.integers(1, 40), st.integers(1, 40)),
)
def test_generated_scenarios_are_valid(
    seed: int, n_users: int, total_load_bps: float, zones: tuple[int, int]
) -> None:
    area = AreaConfig(size_x_m=25.0 * zones[0], size_y_m=25.0 * zones[1])
    config = GeneratorConfig()
    for s in generate_scenarios(10, n_users, seed=seed, area=area, total_load_bps=total_load_bps):
        assert s.load_bps.sum() == pytest.approx(total_load_bps, rel=1e-9)
        floor_bps = total_load_bps * config.min_load_share / n_users
        assert np.all(s.load_bps >= floor_bps * (1 - 1e-9))
        assert np.all(s.load_bps > 0)
        x, y = s.users_xy_m[:, 0], s.users_xy_m[:, 1]
        assert np.all((x > 0) & (x < area.size_x_m))
        assert np.all((y > 0) & (y < area.size_y_m))
        assert 0.0 <= heterogeneity_index(s.users_xy_m, s.load_bps, area) <= 1.0


def test_single_user_scenarios_have_zero_heterogeneity() -> None:
    scenarios = generate_scenarios(10, 1, seed=2)
    assert np.all(heterogeneity_indices(scenarios, AREA) == 0.0)
    assert all(s.load_bps[0] == pytest.approx(40e6, rel=1e-12) for s in scenarios)


def test_set_spans_the_heterogeneity_range(paper_set: list[Scenario]) -> None:
    counts = np.array([count for _, _, count in heterogeneity_histogram(paper_set, AREA)])
    assert counts.sum() == 500
    assert np.count_nonzero(counts) >= 10
    assert counts.max() < 0.35 * 500
    # Homogeneous and the most heterogeneous bins reachable with 3 users are both populated.
    assert counts[0] + counts[1] > 0
    assert counts[12:].sum() > 0  # H >= 0.60


def test_co_located_equal_load_users_have_zero_heterogeneity() -> None:
    xy_m = np.full((3, 2), 123.0)
    load_bps = np.full(3, 40e6 / 3)
    assert heterogeneity_index(xy_m, load_bps, AREA) == pytest.approx(0.0, abs=1e-12)
    bins = heterogeneity_histogram([Scenario("s", xy_m, load_bps)], AREA)
    assert bins[0] == (0.0, 0.05, 1)


def test_histogram_bins_and_edges() -> None:
    bins = heterogeneity_histogram([], AREA)
    assert len(bins) == 20
    assert bins[0][:2] == (0.0, 0.05)
    assert bins[-1][:2] == (0.95, 1.0)
    assert all(count == 0 for _, _, count in bins)
    assert len(heterogeneity_histogram([], AREA, bin_width=0.1)) == 10
    with pytest.raises(ValueError, match="bin_width"):
        heterogeneity_histogram([], AREA, bin_width=0.3)


def test_formatted_histogram_skips_empty_top_bins(paper_set: list[Scenario]) -> None:
    text = format_heterogeneity_histogram(paper_set, AREA)
    lines = text.splitlines()
    assert "500 scenarios" in lines[0]
    rows = lines[1:]
    assert rows[0].strip().startswith("[0.00, 0.05)")
    assert "#" in rows[-1]  # the last row shown is non-empty
    assert not any("[0.95, 1.00)" in row for row in rows)  # unreachable with 3 users
    counts = [int(row.split(")")[1].split()[0]) for row in rows]
    assert sum(counts) == 500


def test_generator_rejects_bad_arguments() -> None:
    with pytest.raises(InputError, match="n_users"):
        generate_scenarios(3, 0, seed=1)
    with pytest.raises(InputError, match="total_load_bps"):
        generate_scenarios(3, 3, seed=1, total_load_bps=0.0)
    with pytest.raises(InputError, match="n:"):
        generate_scenarios(-1, 3, seed=1)
    assert generate_scenarios(0, 3, seed=1) == []
    with pytest.raises(ValueError, match="scatter_probability"):
        GeneratorConfig(scatter_probability=1.5)


def test_scenario_arrays_are_read_only_copies() -> None:
    xy_m = np.array([[1.0, 2.0]])
    s = Scenario("s", xy_m, [5.0])
    xy_m[0, 0] = 99.0
    assert s.users_xy_m[0, 0] == 1.0
    with pytest.raises(ValueError):
        s.users_xy_m[0, 0] = 3.0
    with pytest.raises(ValueError, match="load_bps"):
        Scenario("s", [[1.0, 2.0], [3.0, 4.0]], [1.0])
    with pytest.raises(ValueError, match="users_xy_m"):
        Scenario("s", [1.0, 2.0], [1.0])


@pytest.mark.parametrize(
    ("xy_m", "load_bps", "message"),
    [
        ([[1.0, 2.0], [np.nan, 4.0]], [1.0, 1.0], r"users_xy_m: user 1 has a non-finite"),
        ([[1.0, np.inf]], [1.0], r"users_xy_m: user 0 has a non-finite"),
        ([[1.0, 2.0]], [np.nan], r"load_bps: user 0 has nan"),
        ([[1.0, 2.0], [3.0, 4.0]], [1.0, -5.0], r"load_bps: user 1 has -5.0"),
    ],
)
def test_scenario_refuses_non_finite_positions_and_bad_loads(
    xy_m: list[list[float]], load_bps: list[float], message: str
) -> None:
    # What the oracle and the model would otherwise turn into NaN utilities or a crash.
    with pytest.raises(ValueError, match=message):
        Scenario("s", xy_m, load_bps)


def test_case_holds_a_scenario_and_a_uav() -> None:
    case = Case("c0", [250.0, 250.0, 25.0], [[1.0, 2.0], [3.0, 4.0]], [1e6, 2e6])
    assert case.n_users == 2
    assert case.scenario == Scenario("c0", [[1.0, 2.0], [3.0, 4.0]], [1e6, 2e6])
    assert case != Case("c0", [250.0, 250.0, 50.0], [[1.0, 2.0], [3.0, 4.0]], [1e6, 2e6])
    with pytest.raises(ValueError, match="uav_xyz_m"):
        Case("c0", [250.0, 250.0], [[1.0, 2.0]], [1e6])
