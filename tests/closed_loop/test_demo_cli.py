"""``tupa demo``'s options: ``--scenarios`` takes a scenario file as every other command's
does, ``--n-scenarios`` the count of generated ones; the old numeric use is a clear error."""

from __future__ import annotations

import pytest

from service.cli import build_parser, main
from sim.config import AreaConfig
from sim.files import save_scenarios
from sim.scenarios import generate_scenarios


@pytest.fixture
def flown(monkeypatch) -> list:
    """The DemoConfig each run_demo call got (nothing is flown)."""
    import closed_loop.demo

    configs: list = []
    monkeypatch.setattr(closed_loop.demo, "run_demo", lambda cfg: configs.append(cfg) or {})
    return configs


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_a_count_given_to_scenarios_is_refused_naming_n_scenarios(capsys, flown, tmp_path):
    assert main(["demo", "--scenarios", "2", "--out", str(tmp_path)]) == 2
    err = _one_line(capsys)
    assert err.startswith("tupa demo: error: --scenarios: takes a scenario file")
    assert "--n-scenarios 2" in err
    assert flown == []


def test_n_scenarios_is_the_count_of_generated_scenarios(flown, tmp_path):
    assert main(["demo", "--n-scenarios", "2", "--out", str(tmp_path)]) == 0
    (cfg,) = flown
    assert cfg.n_scenarios == 2 and cfg.scenario_file is None


def test_scenarios_plays_the_file(flown, tmp_path):
    from closed_loop.demo import demo_scenarios

    path = tmp_path / "two.json"
    scenarios = generate_scenarios(2, 4, seed=5)
    save_scenarios(path, AreaConfig(environment="urban"), scenarios)
    assert main(["demo", "--scenarios", str(path), "--out", str(tmp_path)]) == 0
    (cfg,) = flown
    assert cfg.scenario_file == path
    area, played = demo_scenarios(cfg)
    assert area.environment == "urban"  # the file's, as tupa eval takes it
    assert [s.id for s in played] == [s.id for s in scenarios]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--n-scenarios", "0"], "--n-scenarios: must be positive, got 0"),
        (["--scenarios", "missing.json"], "missing.json: no such file"),
        (["--uavs", "3", "--n-scenarios", "2"], "--n-scenarios: the fleet demo"),
        (["--uavs", "3", "--scenarios", "x.json"], "--scenarios: the fleet demo"),
    ],
)
def test_bad_scenario_options_are_one_line(capsys, flown, tmp_path, argv, message):
    assert main(["demo", *argv, "--out", str(tmp_path)]) == 2
    assert message in _one_line(capsys)
    assert flown == []


def test_help_says_what_each_takes():
    text = build_parser()._subparsers._group_actions[0].choices["demo"].format_help()
    assert "--scenarios FILE" in text and "--n-scenarios N" in text


def test_a_file_in_another_environment_than_asked_is_refused(capsys, flown, tmp_path):
    path = tmp_path / "town.json"
    save_scenarios(path, AreaConfig(environment="urban"), generate_scenarios(1, 3, seed=1))
    argv = ["demo", "--scenarios", str(path), "--environment", "suburban"]
    assert main([*argv, "--out", str(tmp_path)]) == 2
    err = _one_line(capsys)
    assert "--environment: suburban" in err and "urban" in err


def test_the_demo_scenarios_of_a_count_are_the_generated_ones():
    from closed_loop.demo import DemoConfig, demo_scenarios, pick_scenarios

    area, played = demo_scenarios(DemoConfig(n_scenarios=2, seed=4))
    assert area == AreaConfig()
    assert [s.id for s in played] == [s.id for s in pick_scenarios(2, 4, AreaConfig())]


def test_the_closing_table_names_the_column_that_is_below_min_distance():
    """Issue 42: the tag "(below min-distance)" did not say which column was below."""
    from closed_loop.demo import format_table

    row = {"world": "closed-loop", "heterogeneity": 0.4, "achieved": 0.80, "min-distance": 0.85,
           "load-weighted": 0.84, "oracle": 0.90}  # fmt: skip
    lines = format_table([row, {**row, "achieved": 0.849}], "ddqn-dr").splitlines()
    below, tie = lines[3], lines[4]
    assert below.endswith("(ddqn-dr (loop) 0.050 below min-distance (loop))"), below
    assert "below" not in tie, tie
    assert "ddqn-dr (loop)" in lines[1] and "min-distance (loop)" in lines[1]
    # A row without the planning oracle (written before it was flown beside): "-" there.
    assert "planning oracle (sim)" in lines[1] and below.split("|")[1].split()[4] == "-", below
    assert "mean utility per step" in lines[-1] and "by more than 0.005" in lines[-1]
