"""Utility against altitude (policies/placements/altitude.py) and the report's altitude figure."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policies.placements.altitude import altitude_profile
from policies.report import build_report
from policies.report.altitude import MAX_PANELS, ProfileCurve, altitude_drawing
from service.cli import main
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import save_scenarios
from sim.scenarios import Scenario, generate_scenarios
from sim.world import get_world

# Three heavy users far apart: no altitude serves them all in free space better than the
# floor; in a town, only climbing gives the far ones line of sight.
SPREAD = Scenario(
    "spread", np.array([[60.0, 60.0], [440.0, 440.0], [60.0, 440.0]]), np.full(3, 12e6)
)


def _world(environment: str):
    return replace(get_world("paper"), area=AreaConfig(environment=environment), episode_steps=20)


def test_free_space_prefers_the_floor_and_a_town_climbs() -> None:
    open_air = altitude_profile(SPREAD, _world("open"), levels=6)
    town = altitude_profile(SPREAD, _world("urban"), levels=6)
    np.testing.assert_allclose(open_air.altitudes_m, np.linspace(25, 100, 6))
    assert int(np.argmax(open_air.best_utility)) == 0
    assert open_air.best_utility[0] > open_air.best_utility[-1] + 0.01
    assert int(np.argmax(town.best_utility)) == 5
    assert town.best_utility[-1] > town.best_utility[0] + 0.05
    assert town.environment == "urban" and town.scenario_id == "spread"
    # The (x, y) reported for each altitude is a zone centre inside the area.
    assert np.all((town.best_xy_m > 0) & (town.best_xy_m < 500))


def test_eval_records_profiles_and_the_report_draws_them(tmp_path: Path) -> None:
    area = AreaConfig(environment="urban")
    scenarios = tmp_path / "town.json"
    save_scenarios(scenarios, area, [SPREAD, *generate_scenarios(2, 3, seed=3, area=area)])
    results = tmp_path / "results"
    results.mkdir()
    common = ["eval", "--scenarios", str(scenarios), "--episode-steps", "5", "--no-progress"]
    assert main([*common, "--policy", "min-distance", "--json", str(results / "md.json")]) == 0
    out = results / "oracle.json"
    assert (
        main([*common, "--policy", "oracle", "--json", str(out), "--altitude-profiles", "2"]) == 0
    )
    document = json.loads(out.read_text())
    assert [p["id"] for p in document["altitude_profiles"]] == ["spread", "s0000"]
    assert all(len(p["best_utility"]) == 16 for p in document["altitude_profiles"])
    report = build_report(results, tmp_path / "report", warn=lambda _: None)
    assert (tmp_path / "report" / "altitude.png") in report.written
    assert (tmp_path / "report" / "altitude.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (tmp_path / "report" / "results.md").read_text()
    assert "![utility against altitude](altitude.png)" in text
    assert "| spread | urban | 100 |" in text


def test_a_bad_profile_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    area = AreaConfig()
    scenarios = tmp_path / "s.json"
    save_scenarios(scenarios, area, generate_scenarios(2, 3, seed=3))
    results = tmp_path / "results"
    results.mkdir()
    out = results / "md.json"
    common = ["eval", "--scenarios", str(scenarios), "--policy", "min-distance", "--no-progress"]
    assert main([*common, "--json", str(out), "--altitude-profiles", "1"]) == 0
    document = json.loads(out.read_text())
    document["altitude_profiles"][0]["best_utility"] = [0.5]
    out.write_text(json.dumps(document))
    with pytest.raises(InputError, match=r"altitude_profiles\[0\]: best_utility"):
        build_report(results, tmp_path / "report")
    assert not (tmp_path / "report").exists()
    assert main([*common, "--json", str(tmp_path / "x.json"), "--altitude-profiles", "-1"]) == 2
    assert not (tmp_path / "x.json").exists()


def _profiles(n: int) -> list[ProfileCurve]:
    altitudes = np.linspace(25.0, 100.0, 4)
    return [
        ProfileCurve(f"s{i:04d}", "urban", altitudes, np.linspace(0.5, 0.6 + i / 100, 4))
        for i in range(n)
    ]


def test_every_requested_profile_is_drawn(tmp_path: Path) -> None:
    """Issue 42: five profiles asked for, four drawn, nothing said."""
    said: list[str] = []
    figure = altitude_drawing(_profiles(5), [], {}, warn=said.append)
    titles = [ax.get_title() for ax in figure.axes if ax.get_title()]
    assert titles == [f"s{i:04d} (urban)" for i in range(5)]
    assert said == []


def test_profiles_beyond_the_panels_are_named_in_the_figure_and_a_log_line() -> None:
    said: list[str] = []
    profiles = _profiles(MAX_PANELS + 2)
    figure = altitude_drawing(profiles, [], {}, warn=said.append)
    assert len([ax for ax in figure.axes if ax.get_title()]) == MAX_PANELS
    left_out = [p.scenario_id for p in profiles[MAX_PANELS:]]
    notes = " ".join(t.get_text() for t in figure.texts)
    assert all(i in notes for i in left_out) and f"at most {MAX_PANELS}" in notes, notes
    assert len(said) == 1 and all(i in said[0] for i in left_out), said
    assert "altitude.png" in said[0] and f"at most {MAX_PANELS}" in said[0]
