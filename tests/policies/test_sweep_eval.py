"""``tupa eval --backend``: a test set evaluated in slices gives what one process gives."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from policies.evaluation.evaluation import evaluate_policy
from policies.registry import make_placement
from policies.sweep.fanout import merge_slices
from policies.sweep.trial import evaluate_slice
from service.cli import main
from sim.config import AreaConfig
from sim.files import load_scenarios, save_scenarios
from sim.scenarios import generate_scenarios
from sim.world import get_world, world_with


@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    path = tmp_path / "scenarios.json"
    save_scenarios(path, AreaConfig(), generate_scenarios(3, 3, seed=5))
    return path


def test_slices_joined_equal_one_run(scenario_file: Path) -> None:
    options = {"world": "closed-loop", "world_set": [], "environment": None,
               "queueing": None, "episode_steps": 6}  # fmt: skip
    area, scenarios = load_scenarios(scenario_file)
    world = world_with(replace(get_world("closed-loop"), area=area, episode_steps=6), [])
    whole = evaluate_policy(make_placement("load-weighted", world), scenarios, world, seed=7,
                            progress=False)  # fmt: skip
    parts = [
        evaluate_slice({"policy": "load-weighted", "scenarios": str(scenario_file),
                        "start": a, "stop": b, "seed": 7, "world_options": options})
        for a, b in ((0, 1), (1, 3))
    ]  # fmt: skip
    assert merge_slices(parts, seed=7) == whole
    # The slices really are different draws: scenario 1 alone with seed 7 is not scenario 1
    # of the whole run (its seed is 8), so the equality above is not trivial.
    alone = evaluate_policy(make_placement("load-weighted", world), scenarios[1:2], world, seed=7,
                            progress=False)  # fmt: skip
    assert alone["scenarios"][0]["trace"] != whole["scenarios"][1]["trace"]


def test_a_slice_runs_on_one_torch_thread_and_gives_the_caller_s_count_back(
    scenario_file: Path,
) -> None:
    import torch

    from policies.sweep.trial import one_torch_thread

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        options = {"world": "closed-loop", "world_set": [], "environment": None,
                   "queueing": None, "episode_steps": 2}  # fmt: skip
        evaluate_slice({"policy": "load-weighted", "scenarios": str(scenario_file),
                        "start": 0, "stop": 1, "seed": 7, "world_options": options})  # fmt: skip
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError), one_torch_thread():
            assert torch.get_num_threads() == 1
            raise RuntimeError("a failing trial")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.slow
@pytest.mark.process
def test_tupa_eval_on_the_local_backend_writes_the_same_file(
    scenario_file: Path, tmp_path: Path
) -> None:
    common = ["eval", "--policy", "min-distance", "--policy", "oracle", "--scenarios",
              str(scenario_file), "--episode-steps", "5", "--no-progress"]  # fmt: skip
    one, fanned = tmp_path / "one.json", tmp_path / "fanned.json"
    assert main([*common, "--json", str(one)]) == 0
    assert main([*common, "--json", str(fanned), "--backend", "local", "--workers", "2"]) == 0
    assert json.loads(fanned.read_text()) == json.loads(one.read_text())


def test_bad_fan_out_options_are_named(scenario_file: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "x.json"
    base = ["eval", "--policy", "min-distance", "--scenarios", str(scenario_file), "--json",
            str(out), "--no-progress"]  # fmt: skip
    assert main([*base, "--backend", "local", "--workers", "0"]) == 2
    assert "--workers: must be at least 1" in capsys.readouterr().err
    assert main([*base, "--backend", "local", "--address", "auto"]) == 2
    assert "--address: only with --backend ray" in capsys.readouterr().err
    assert not out.exists()
