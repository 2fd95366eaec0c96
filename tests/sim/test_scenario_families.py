"""Scenario families (exponential, uniform, hotspots, corners, mixture), any user count 1..300,
the ScenarioSampler used for domain randomisation, and ``tupa scenarios generate --family``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.cli import main
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import load_scenarios
from sim.scenarios import (
    FAMILIES,
    MAX_USERS,
    FamilyConfig,
    Scenario,
    ScenarioSampler,
    generate_scenarios,
)

AREA = AreaConfig()
LAMBDA_BPS = 40e6
BASE_FAMILIES = ("exponential", "uniform", "hotspots", "corners")


def _drawn_family(scenario: Scenario) -> str:
    """The family a scenario was drawn from, read off its id (``s0000`` is exponential)."""
    return scenario.id.split("-")[-1] if "-" in scenario.id else "exponential"


def _assert_valid(scenarios: list[Scenario], n_users: int, area: AreaConfig) -> None:
    size = np.array([area.size_x_m, area.size_y_m])
    assert len({s.id for s in scenarios}) == len(scenarios)
    for s in scenarios:
        assert s.users_xy_m.shape == (n_users, 2)
        assert np.all(s.users_xy_m > 0) and np.all(s.users_xy_m < size), s.id
        assert np.all(s.load_bps > 0), s.id
        assert s.load_bps.sum() == pytest.approx(LAMBDA_BPS, rel=1e-9)


def test_families_are_listed() -> None:
    assert FAMILIES == ("exponential", "uniform", "hotspots", "corners", "mixture")
    assert MAX_USERS == 300


@pytest.mark.parametrize("n_users", [1, 3, 12, 300])
@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_and_user_count_is_valid_and_deterministic(family: str, n_users: int) -> None:
    n = 4 if n_users == 300 else 12
    scenarios = generate_scenarios(n, n_users, seed=3, family=family)
    _assert_valid(scenarios, n_users, AREA)
    assert scenarios == generate_scenarios(n, n_users, seed=3, family=family)
    other = generate_scenarios(n, n_users, seed=4, family=family)
    assert all(
        not np.array_equal(a.users_xy_m, b.users_xy_m)
        for a, b in zip(scenarios, other, strict=True)
    )
    # A set is a prefix of a larger one.
    assert generate_scenarios(n + 3, n_users, seed=3, family=family)[:n] == scenarios


@given(
    family=st.sampled_from(FAMILIES),
    n_users=st.integers(1, MAX_USERS),
    seed=st.integers(0, 2**63 - 1),
)
@settings(max_examples=40, deadline=None)
def test_property_users_inside_loads_sum_to_lambda(family: str, n_users: int, seed: int) -> None:
    area = AreaConfig(size_x_m=300.0, size_y_m=700.0)  # not square: axes must not be swapped
    _assert_valid(
        generate_scenarios(2, n_users, seed=seed, area=area, family=family), n_users, area
    )


def test_exponential_is_the_default_and_unchanged() -> None:
    default = generate_scenarios(30, 3, seed=1)
    assert default == generate_scenarios(30, 3, seed=1, family="exponential")
    assert [s.id for s in default[:2]] == ["s0000", "s0001"]
    # Pinned values of the paper generator: any change to its draws breaks existing seeds.
    np.testing.assert_allclose(
        default[1].users_xy_m,
        [
            [490.78501165809104, 56.756966676369814],
            [361.9246072172266, 54.03890517187256],
            [472.8354074237128, 157.79920323050138],
        ],
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        default[1].load_bps, [9697908.83236332, 4868427.514279781, 25433663.653356895], rtol=1e-12
    )


def test_ids_name_the_family() -> None:
    assert [s.id for s in generate_scenarios(2, 3, seed=1, family="hotspots")] == [
        "s0000-hotspots",
        "s0001-hotspots",
    ]
    for s in generate_scenarios(5, 3, seed=1, family="mixture"):
        assert s.id.startswith(s.id[:5] + "-mixture-")
        assert _drawn_family(s) in BASE_FAMILIES


def test_families_differ_for_the_same_seed() -> None:
    firsts = [generate_scenarios(1, 12, seed=9, family=f)[0].users_xy_m for f in BASE_FAMILIES]
    for i in range(len(firsts)):
        for j in range(i + 1, len(firsts)):
            assert not np.array_equal(firsts[i], firsts[j])


def _mean_nearest_neighbour_m(scenarios: list[Scenario]) -> float:
    means = []
    for s in scenarios:
        d = np.linalg.norm(s.users_xy_m[:, None, :] - s.users_xy_m[None, :, :], axis=-1)
        np.fill_diagonal(d, np.inf)
        means.append(d.min(axis=1).mean())
    return float(np.mean(means))


def _corner_distances_m(scenarios: list[Scenario]) -> tuple[np.ndarray, np.ndarray]:
    """Each user's distance to its nearest corner, and which corner (0..3) that is."""
    corners = np.array([[0, 0], [AREA.size_x_m, 0], [0, AREA.size_y_m], [AREA.size_x_m] * 2])
    xy = np.concatenate([s.users_xy_m for s in scenarios])
    d = np.linalg.norm(xy[:, None, :] - corners[None, :, :], axis=-1)
    return d.min(axis=1), d.argmin(axis=1)


def test_hotspots_cluster_and_corners_hug_the_corners() -> None:
    sets = {f: generate_scenarios(150, 12, seed=5, family=f) for f in BASE_FAMILIES}
    uniform_nn = _mean_nearest_neighbour_m(sets["uniform"])
    assert _mean_nearest_neighbour_m(sets["hotspots"]) < 0.5 * uniform_nn
    uniform_corner, _ = _corner_distances_m(sets["uniform"])
    corner_d, corner = _corner_distances_m(sets["corners"])
    assert corner_d.mean() < 0.5 * uniform_corner.mean()
    assert np.median(corner_d) < 60.0
    # Mirrored corners: every corner gets users, not only one.
    assert set(np.bincount(corner, minlength=4).nonzero()[0]) == {0, 1, 2, 3}
    # Uniform really is uniform: about a quarter of the users in each quadrant.
    xy = np.concatenate([s.users_xy_m for s in sets["uniform"]])
    quadrant = (xy[:, 0] > 250).astype(int) + 2 * (xy[:, 1] > 250).astype(int)
    shares = np.bincount(quadrant, minlength=4) / len(xy)
    assert np.all(np.abs(shares - 0.25) < 0.04)


@pytest.mark.parametrize("family", FAMILIES)
def test_load_heterogeneity_spans_a_range_in_every_family(family: str) -> None:
    top_share = [
        s.load_bps.max() / LAMBDA_BPS for s in generate_scenarios(200, 3, 2, family=family)
    ]
    assert min(top_share) < 0.45  # near-equal loads
    assert max(top_share) > 0.85  # one dominant user


def test_mixture_draws_several_families() -> None:
    drawn = [_drawn_family(s) for s in generate_scenarios(200, 3, seed=8, family="mixture")]
    counts = {f: drawn.count(f) for f in BASE_FAMILIES}
    assert sum(counts.values()) == 200
    assert all(c > 20 for c in counts.values()), counts
    only = FamilyConfig(mixture_families=("uniform", "corners"))
    drawn = {
        _drawn_family(s)
        for s in generate_scenarios(50, 3, seed=8, family="mixture", family_config=only)
    }
    assert drawn == {"uniform", "corners"}


def test_family_config_changes_the_draws() -> None:
    tight = FamilyConfig(hotspots_min=1, hotspots_max=1, hotspot_spread_min_m=5.0,
                         hotspot_spread_max_m=5.0)  # fmt: skip
    for s in generate_scenarios(20, 12, seed=1, family="hotspots", family_config=tight):
        spread = s.users_xy_m - s.users_xy_m.mean(axis=0)
        assert np.sqrt((spread**2).sum(axis=1).mean()) < 20.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"family": "gaussian"}, "family"),
        ({"family": "Uniform"}, "family"),
        ({"n_users": 0}, "users"),
        ({"n_users": 301}, "users"),
        ({"n_users": 3.0}, "users"),
        ({"total_load_bps": 0.0}, "total_load_bps"),
    ],
)
def test_generator_rejects_bad_arguments_in_one_line(kwargs: dict, field: str) -> None:
    call = {"n": 2, "n_users": 3, "seed": 1, **kwargs}
    with pytest.raises(InputError, match=field) as exc:
        generate_scenarios(**call)
    assert "\n" not in str(exc.value)
    if field == "family":
        assert all(f in str(exc.value) for f in FAMILIES)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"hotspots_min": 0}, "hotspots_min"),
        ({"hotspots_min": 3, "hotspots_max": 2}, "hotspots_max"),
        ({"hotspot_spread_min_m": 0.0}, "hotspot_spread_min_m"),
        ({"hotspot_spread_max_m": 1.0}, "hotspot_spread_max_m"),
        ({"corners_max": 5}, "corners_max"),
        ({"corner_scale_min_m": -1.0}, "corner_scale_min_m"),
        ({"mixture_families": ()}, "mixture_families"),
        ({"mixture_families": ("mixture",)}, "mixture_families"),
    ],
)
def test_family_config_validation(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        FamilyConfig(**kwargs)


# --------------------------------------------------------------------------------------------
# ScenarioSampler


def test_sampler_is_deterministic_and_stays_in_range() -> None:
    sampler = ScenarioSampler(families=FAMILIES, users=(1, 20))
    rng1, rng2 = np.random.default_rng(11), np.random.default_rng(11)
    first = [sampler.sample(rng1) for _ in range(300)]
    assert first == [sampler.sample(rng2) for _ in range(300)]
    assert first[0] == sampler.sample(np.random.default_rng(11))
    assert first != [sampler.sample(np.random.default_rng(12)) for _ in range(300)]
    assert len({s.id for s in first}) == 300
    users = {s.n_users for s in first}
    assert users <= set(range(1, 21)) and {1, 20} <= users
    labels = {s.id.split("-")[0] for s in first}
    assert labels == set(FAMILIES)
    for s in first:
        assert np.all(s.users_xy_m > 0) and np.all(s.users_xy_m < 500)
        assert s.load_bps.sum() == pytest.approx(LAMBDA_BPS, rel=1e-9)


def test_sampler_defaults_match_the_paper_generator_and_advance_the_rng_once() -> None:
    rng, twin = np.random.default_rng(4), np.random.default_rng(4)
    for _ in range(5):
        s = ScenarioSampler().sample(rng)
        seed = int(twin.integers(2**63 - 1))  # the one draw sample() takes
        assert s.id == f"exponential-3u-{seed}"
        (expected,) = generate_scenarios(1, 3, seed=seed)
        assert np.array_equal(s.users_xy_m, expected.users_xy_m)
        assert np.array_equal(s.load_bps, expected.load_bps)
    wide = ScenarioSampler(families=("hotspots", "mixture"), users=(5, 300))
    rng, twin = np.random.default_rng(4), np.random.default_rng(4)
    for _ in range(5):
        s = wide.sample(rng)
        seed = int(twin.integers(2**63 - 1))
        family, n_users = wide.pick(seed)
        assert s.n_users == n_users
        (again,) = generate_scenarios(1, n_users, seed=seed, family=family)
        assert np.array_equal(s.users_xy_m, again.users_xy_m)
        label = family if family != "mixture" else f"mixture-{_drawn_family(again)}"
        assert s.id == f"{label}-{n_users}u-{seed}"
    assert rng.integers(1 << 30) == twin.integers(1 << 30)


def test_sampler_normalises_lists_and_a_single_family() -> None:
    sampler = ScenarioSampler(families=["uniform", "corners"], users=[2, 4])  # type: ignore[arg-type]
    assert sampler.families == ("uniform", "corners") and sampler.users == (2, 4)
    assert ScenarioSampler(families="hotspots").families == ("hotspots",)  # type: ignore[arg-type]
    hash(sampler)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"families": ()}, "families"),
        ({"families": ("exponential", "nope")}, "families"),
        ({"families": 3}, "families"),
        ({"users": (0, 3)}, "users"),
        ({"users": (3, 301)}, "users"),
        ({"users": (5, 2)}, "users"),
        ({"users": (3,)}, "users"),
        ({"users": (1.5, 3)}, "users"),
        ({"total_load_bps": 0.0}, "total_load_bps"),
        ({"total_load_bps": float("nan")}, "total_load_bps"),
        ({"area": "big"}, "area"),
    ],
)
def test_sampler_rejects_bad_fields_in_one_line(kwargs: dict, field: str) -> None:
    with pytest.raises(InputError, match=f"^{field}:") as exc:
        ScenarioSampler(**kwargs)
    assert "\n" not in str(exc.value)


def test_sampling_is_cheap() -> None:
    for families in (("exponential",), FAMILIES):
        sampler = ScenarioSampler(families=families)
        rng = np.random.default_rng(0)
        sampler.sample(rng)
        start = time.perf_counter()
        for _ in range(200):
            sampler.sample(rng)
        assert (time.perf_counter() - start) / 200 < 1e-3


# --------------------------------------------------------------------------------------------
# CLI: tupa scenarios generate --family


def test_cli_generate_family_round_trip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "f.json"
    args = ["scenarios", "generate", "--n", "40", "--users", "8", "--family", "hotspots"]
    assert main([*args, "--seed", "1", "--out", str(out)]) == 0
    area, scenarios = load_scenarios(out)
    assert area == AREA
    assert scenarios == generate_scenarios(40, 8, seed=1, family="hotspots")
    generator = json.loads(out.read_text())["generator"]
    assert generator == {"family": "hotspots", "users": 8, "seed": 1, "total_load_bps": 40e6}
    printed = capsys.readouterr().out
    assert "40 scenarios" in printed and "hotspots" in printed
    assert "[0.00, 0.05)" in printed and "#" in printed


def test_cli_generate_defaults_to_exponential(tmp_path: Path) -> None:
    out = tmp_path / "f.json"
    assert main(["scenarios", "generate", "--n", "5", "--users", "300", "--out", str(out)]) == 0
    assert load_scenarios(out)[1] == generate_scenarios(5, 300, seed=1)
    assert json.loads(out.read_text())["generator"]["family"] == "exponential"


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--family", "nope"), ("--family", ""), ("--users", "0"), ("--users", "301")],
)
def test_cli_generate_bad_family_or_users_return_2_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str, value: str
) -> None:
    out = tmp_path / "f.json"
    assert main(["scenarios", "generate", "--n", "5", "--out", str(out), flag, value]) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert flag in err and len(err.strip().splitlines()) == 1
    if flag == "--family":
        assert all(f in err for f in FAMILIES)
