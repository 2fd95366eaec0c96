"""``tupa eval``: success and failure paths (exit 2, one-line error, nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli import main
from sim.config import AreaConfig
from sim.files import save_scenarios
from sim.scenarios import generate_scenarios

AREA = AreaConfig()


@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    path = tmp_path / "scenarios.json"
    save_scenarios(path, AREA, generate_scenarios(4, 3, seed=2, area=AREA))
    return path


def eval_args(scenarios: Path, out: Path, *policies: str) -> list[str]:
    args = ["eval", "--scenarios", str(scenarios), "--json", str(out), "--episode-steps", "5"]
    for name in policies:
        args += ["--policy", name]
    return [*args, "--no-progress"]


def test_one_policy_writes_the_object(scenario_file: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out" / "eval.json"
    assert main(eval_args(scenario_file, out, "min-distance")) == 0
    document = json.loads(out.read_text())
    assert document["policy"] == "min-distance"
    assert document["n_scenarios"] == 4
    assert len(document["scenarios"]) == 4
    printed = capsys.readouterr().out
    assert "min-distance" in printed and "H bin" in printed


def test_several_policies_write_a_results_list(scenario_file: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "eval.json"
    code = main(eval_args(scenario_file, out, "min-distance", "oracle", "min-distance"))
    assert code == 0
    document = json.loads(out.read_text())
    assert list(document) == ["results"]
    assert [r["policy"] for r in document["results"]] == ["min-distance", "oracle"]
    assert "oracle/min-distance" in capsys.readouterr().out


def test_same_seed_same_file(scenario_file: Path, tmp_path: Path) -> None:
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert main([*eval_args(scenario_file, a, "load-weighted"), "--seed", "7"]) == 0
    assert main([*eval_args(scenario_file, b, "load-weighted"), "--seed", "7"]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_unknown_policy_is_an_input_error(scenario_file: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "eval.json"
    assert main(eval_args(scenario_file, out, "min-distance", "nearest")) == 2
    err = capsys.readouterr().err
    assert "--policy" in err and "nearest" in err
    assert "min-distance, load-weighted, min-distance-env, oracle" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "no such file"),
        ("{not json", "not valid JSON"),
        ('{"format": "tupa-cases/1"}', "format"),
    ],
)
def test_bad_scenarios_file_is_an_input_error(
    tmp_path: Path, capsys, content: str | None, message: str
) -> None:
    scenarios = tmp_path / "scenarios.json"
    if content is not None:
        scenarios.write_text(content)
    out = tmp_path / "eval.json"
    assert main(eval_args(scenarios, out, "min-distance")) == 2
    err = capsys.readouterr().err
    assert message in err and str(scenarios) in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("extra", "flag"), [(["--episode-steps", "0"], "--episode-steps"), (["--seed", "-1"], "--seed")]
)
def test_bad_numbers_are_input_errors(
    scenario_file: Path, tmp_path: Path, capsys, extra: list[str], flag: str
) -> None:
    out = tmp_path / "eval.json"
    assert main([*eval_args(scenario_file, out, "min-distance"), *extra]) == 2
    assert flag in capsys.readouterr().err
    assert not out.exists()


def test_an_existing_output_survives_an_error(tmp_path: Path) -> None:
    out = tmp_path / "eval.json"
    out.write_text("old")
    assert main(eval_args(tmp_path / "missing.json", out, "oracle")) == 2
    assert out.read_text() == "old"
