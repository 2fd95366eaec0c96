"""A training run that talks and survives: an estimate early on and a live time left, progress
through the final evaluation, SIGTERM saving what Ctrl-C saves and saying where, the replay
buffer saved only when asked, and an interrupted run's checkpoint found by ``tupa eval`` and
pointed at by ``tupa report``."""

from __future__ import annotations

import io
import json
import os
import re
import signal
from collections.abc import Iterator
from contextlib import redirect_stderr
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

from policies.learned.checkpoints import CheckpointError, read_checkpoint
from policies.training import training
from policies.training.progress import Progress, format_duration
from service.cli import main
from tests.policies.test_training import small_config
from tests.tiers import needs

EPISODES = 40
STOP_AFTER = 7


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_progress_lines_say_how_far_and_how_long_is_left():
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(100, "ddqn-gen10k", "ep", stream=out, bar=False, clock=clock)
    clock.t = 10.0
    progress.update(10, utility="0.700")
    assert out.getvalue() == ""  # a line every 30 s, not every item
    clock.t = 30.0
    progress.update(10)
    assert out.getvalue() == (
        "ddqn-gen10k: 20/100 ep (20 %), utility 0.700; 30 s elapsed, about 2.0 min left\n"
    )
    progress.close()
    assert out.getvalue().splitlines()[-1] == "ddqn-gen10k: 20/100 ep, utility 0.700 in 30 s"


def test_progress_times_only_what_it_saw_done():
    """A resumed run's earlier episodes are not timed: 10 done in 20 s, 50 left: 100 s."""
    clock = FakeClock()
    progress = Progress(100, "x", "ep", initial=40, stream=io.StringIO(), bar=False, clock=clock)
    assert progress.left_s() is None
    clock.t = 20.0
    progress.update(10)
    assert progress.left_s() == pytest.approx(100.0)


def test_on_a_terminal_progress_is_a_bar_and_lines_go_above_it():
    out = io.StringIO()
    progress = Progress(10, "ddqn-spec", "ep", stream=out, bar=True)
    progress.update(3, utility="0.500")
    progress.write("ddqn-spec: about 1 min for 10 episodes")
    progress.close()
    text = out.getvalue()
    assert "ddqn-spec: about 1 min for 10 episodes\n" in text
    assert "3/10" in text and "\r" in text  # tqdm's bar, redrawn in place


def test_disabled_progress_says_nothing():
    out = io.StringIO()
    progress = Progress(10, "x", "ep", stream=out, bar=False, enabled=False, interval_s=0.0)
    progress.update(5)
    progress.write("estimate")
    progress.close()
    assert out.getvalue() == ""


@pytest.mark.parametrize(
    ("seconds", "text"),
    [(0.4, "0 s"), (45, "45 s"), (210, "3.5 min"), (3480, "58 min"), (7500, "2 h 05 min")],
)
def test_durations_read_as_a_person_says_them(seconds, text):
    assert format_duration(seconds) == text


@dataclass
class Stopped:
    out: Path
    test_file: Path
    error: BaseException
    stderr: str


@pytest.fixture(scope="module")
def test_file(tmp_path_factory) -> Path:
    from sim.config import AreaConfig
    from sim.files import save_scenarios
    from sim.scenarios import generate_scenarios

    path = tmp_path_factory.mktemp("data") / "test.json"
    save_scenarios(path, AreaConfig(), generate_scenarios(6, 3, seed=99))
    return path


@pytest.fixture(scope="module")
@needs("training")
def sigterm_run(tmp_path_factory, test_file) -> Iterator[Stopped]:
    """A tiny run told to stop by SIGTERM (as ``timeout``, systemd and ``docker stop`` send)
    after 7 of its 40 episodes, its progress on a non-terminal standard error."""
    out = tmp_path_factory.mktemp("run") / "run"
    config = replace(small_config(test_file, out, "ddqn", EPISODES), progress=True)
    original = training.TrainingCallback._on_step

    def terminate_after_seven(self):
        keep_going = original(self)
        if self.run.episodes_done >= STOP_AFTER:
            os.kill(os.getpid(), signal.SIGTERM)
        return keep_going

    training.TrainingCallback._on_step = terminate_after_seven
    handler_before = signal.getsignal(signal.SIGTERM)
    stderr = io.StringIO()
    try:
        with redirect_stderr(stderr):
            training.train(config)
    except BaseException as exc:
        error = exc
    else:
        error = AssertionError("training was not stopped")
    finally:
        training.TrainingCallback._on_step = original
    assert signal.getsignal(signal.SIGTERM) is handler_before  # put back as it was
    yield Stopped(out, test_file, error, stderr.getvalue())


def test_sigterm_saves_the_checkpoint_ctrl_c_saves_and_says_where(sigterm_run):
    error, out = sigterm_run.error, sigterm_run.out
    assert isinstance(error, training.TrainingInterrupted)
    assert isinstance(error, KeyboardInterrupt)  # what Ctrl-C raises: one way out for both
    assert error.exit_code == 128 + signal.SIGTERM
    message = str(error)
    assert message.startswith(f"interrupted (SIGTERM) after {STOP_AFTER} of {EPISODES} episodes")
    assert str(out / "checkpoints" / "latest.zip") in message
    assert f"tupa train --resume {out}" in message and f"tupa eval --policy {out}" in message
    assert (out / "checkpoints" / "latest.zip").is_file()
    assert (out / "checkpoints" / "latest.json").is_file()
    state = json.loads((out / training.RUN_FILE).read_text())
    assert state["episodes_done"] == STOP_AFTER
    assert not (out / "model.zip").exists()


def test_the_replay_buffer_is_saved_only_when_asked(sigterm_run):
    assert not list(sigterm_run.out.rglob("*replay*"))
    assert "replay buffer" not in str(sigterm_run.error)


def test_training_says_an_estimate_once_it_has_timed_a_few_episodes(sigterm_run):
    lines = sigterm_run.stderr.splitlines()
    estimates = [line for line in lines if " for 40 episodes " in line]
    assert len(estimates) == 1, sigterm_run.stderr
    assert re.fullmatch(
        r"ddqn-spec: about \d+(\.\d)? (s|min) for 40 episodes \(\d+\.\d\d s an episode, timed "
        r"over episodes 4-6 once learning started\)",
        estimates[0],
    ), estimates[0]
    # Without a terminal, the progress ends with a line of where it stopped.
    assert lines[-1].startswith(f"ddqn-spec: {STOP_AFTER}/{EPISODES} ep, utility ")


def test_tupa_eval_of_an_interrupted_run_evaluates_its_latest_checkpoint(
    sigterm_run, tmp_path, capsys
):
    out, result = sigterm_run.out, tmp_path / "eval.json"
    argv = ["eval", "--policy", str(out), "--scenarios", str(sigterm_run.test_file)]
    code = main([*argv, "--json", str(result), "--episode-steps", "3", "--no-progress"])
    assert code == 0
    err = capsys.readouterr().err
    assert f"{out}: an interrupted run (no model.zip)" in err
    assert str(out / "checkpoints" / "latest.zip") in err
    assert f"{STOP_AFTER} of {EPISODES} episodes" in err
    assert json.loads(result.read_text())["n_scenarios"] == 6


def test_loading_an_interrupted_run_says_where_its_latest_checkpoint_is(sigterm_run):
    with pytest.raises(CheckpointError) as refused:
        read_checkpoint(sigterm_run.out)
    assert refused.value.problem == "no such checkpoint"  # what the service tells a client
    assert str(sigterm_run.out / "checkpoints" / "latest.zip") in str(refused.value)


def test_tupa_report_on_a_training_run_says_how_to_evaluate_it(sigterm_run, tmp_path, capsys):
    out = sigterm_run.out
    assert main(["report", "--results", str(out), "--out", str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"tupa report: error: --results: {out} is a training run")
    expected = (
        f"tupa eval --policy {out / 'checkpoints' / 'latest.zip'} --scenarios "
        f"{sigterm_run.test_file} --json {out / 'eval.json'}"
    )
    assert expected in err
    assert not (tmp_path / "report").exists()


def test_the_final_evaluation_shows_its_progress(sigterm_run, monkeypatch, capsys):
    """Three policies on the whole test set can take minutes: one progress over all of it."""
    config = training.resume_config(sigterm_run.out)
    model = training.algorithm_class("ddqn").load(sigterm_run.out / "checkpoints" / "latest.zip")
    seen: list[int] = []

    def evaluate(policy, scenarios, world, seed=0, progress=True, on_scenario=None):
        assert progress is False and on_scenario is not None
        for _ in scenarios:
            on_scenario()
        seen.append(len(scenarios))
        return {"mean_utility": 0.5, "median_utility": 0.5, "p25_utility": 0.4}

    monkeypatch.setattr(training, "evaluate_policy", evaluate)
    summary = training.final_evaluation(training._Run(config, STOP_AFTER), model)
    assert seen == [6, 6, 6] and summary["n_scenarios"] == 6
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == (
        "final evaluation on the 6 test scenarios: the trained policy, min-distance and the oracle"
    )
    assert re.fullmatch(r"final evaluation: 18/18 scenarios in \d+ s", lines[-1]), lines


def test_the_command_says_interrupted_and_where_and_exits_as_signalled(monkeypatch, capsys):
    def stopped(config, resume=False):
        raise training.TrainingInterrupted(
            "interrupted (SIGTERM) after 3 of 9 episodes; saved X", signal.SIGTERM
        )

    monkeypatch.setattr(training, "train", stopped)
    monkeypatch.setattr(training, "resume_config", lambda *args: None)
    code = main(["train", "--resume", "runs/nowhere"])
    assert code == 128 + signal.SIGTERM
    assert capsys.readouterr().err == (
        "tupa train: interrupted (SIGTERM) after 3 of 9 episodes; saved X\n"
    )


@pytest.mark.training
def test_an_interruption_in_the_final_evaluation_keeps_the_trained_policy(
    tmp_path, test_file, monkeypatch, capsys
):
    """The trained policy is saved before the final evaluation: stopping there loses no
    training, and ``--resume`` (with an empty replay buffer, none was saved) only evaluates."""
    out = tmp_path / "run"
    config = replace(small_config(test_file, out, "ddqn", 3), final_eval=True)

    def stopped(run, model):
        raise KeyboardInterrupt

    monkeypatch.setattr(training, "final_evaluation", stopped)
    with pytest.raises(training.TrainingInterrupted) as interrupted:
        training.train(config)
    assert str(interrupted.value).startswith(
        "interrupted (Ctrl-C) during the final evaluation, after all 3 episodes; saved "
    )
    assert json.loads((out / training.RUN_FILE).read_text())["episodes_done"] == 3
    assert not (out / "model.zip").exists()

    summary = {"n_scenarios": 6}
    monkeypatch.setattr(training, "final_evaluation", lambda run, model: summary)
    metadata = training.train(replace(config, progress=True), resume=True)
    assert metadata["episodes"] == 3 and metadata["evaluation"] == summary
    assert (out / "model.zip").is_file()
    assert "with an empty replay buffer" in capsys.readouterr().err
