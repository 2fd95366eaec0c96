"""``tupa sweep``: the sweep file's checks, the local backend, resuming, retries, the report.

Trials are tiny real training runs (a few episodes, a small network) in fresh processes; every
wait is on a condition with a timeout.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import yaml

from policies.sweep.backends import LocalBackend
from policies.sweep.runner import run_sweep
from policies.sweep.spec import load_spec
from policies.sweep.state import STATE_FILE, SUMMARY_FILE
from policies.sweep.trial import WORKER_FILE
from policies.training.training import CURVE_POINTS
from service.cli import main
from tests.helpers import wait_for

ROOT = Path(__file__).resolve().parents[2]

TINY_TRAIN = {
    "episodes": 6,
    "preset": "fast",
    "preset.learning_starts": 64,
    "preset.batch_size": 32,
    "preset.buffer_size": 5000,
    "preset.network.channels": [8],
    "preset.network.hidden": 32,
    "preset.network.features_dim": 32,
}


def tiny_spec(tmp_path: Path, name: str = "tiny", **changes: Any) -> Path:
    """A sweep file of tiny trials (DDQN and DDPG on 3 generated test scenarios, seed 1)."""
    document: dict[str, Any] = {
        "name": name,
        "retries": 1,
        "test_sets": {"t3": {"generate": {"n": 3, "users": 3, "seed": 4242}}},
        "grid": {"algorithm": ["ddqn", "ddpg"], "seed": [1]},
        "train": {"strategy": "spec", **TINY_TRAIN},
        "evaluate": {"curve_scenarios": 3},
    }
    for key, value in changes.items():
        section, _, field = key.partition("__")
        if field:
            document[section][field.replace("_DOT_", ".")] = value
        else:
            document[section] = value
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def read_state(out: Path) -> dict[str, Any]:
    return json.loads((out / STATE_FILE).read_text())


def kill_worker_once(trial_dir: Path, killed: list[int], timeout_s: float = 120.0) -> None:
    """Wait for the trial's worker to say who it is, then SIGKILL it (once)."""
    worker = wait_for(
        lambda: (
            (trial_dir / WORKER_FILE).exists() and json.loads((trial_dir / WORKER_FILE).read_text())
        ),
        timeout_s=timeout_s,
        interval_s=0.05,
        message=f"{trial_dir / WORKER_FILE}",
    )
    os.kill(worker["pid"], signal.SIGKILL)
    killed.append(worker["pid"])


# --------------------------------------------------------------------------------------------
# The sweep file


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


GOOD = """\
test_sets:
  t: {generate: {n: 2, users: 3, seed: 1}}
grid:
  algorithm: [ddqn]
  strategy: [spec]
  episodes: [2]
  seed: [1]
"""

BAD_FILES = [
    (GOOD + "colour: blue\n", "colour: unknown key"),
    (GOOD.replace("  seed: [1]\n", "  seed: [1]\n  sead: [2]\n"), "grid.sead: unknown trial"),
    (GOOD + "train: {preset.learning_rat: 0.1}\n", "train.preset.learning_rat: unknown"),
    (GOOD.replace("seed: [1]", "seed: []"), "grid.seed: must be a non-empty list"),
    (GOOD.replace("seed: [1]", "seed: [1, 1]"), "grid.seed: repeated value 1"),
    (GOOD.replace("  seed: [1]\n", ""), "grid.seed: missing"),
    (GOOD.replace("episodes: [2]", "episodes: [0]"), "grid.episodes: must be an integer >= 1"),
    (GOOD.replace("algorithm: [ddqn]", "algorithm: [dqn]"), "grid.algorithm: must be one of"),
    (GOOD + "train: {seed: 3}\n", "grid.seed: also given in train"),
    (
        GOOD + "train: {action: residual}\n",
        "grid: impossible trial (action=residual, algorithm=ddqn",
    ),
    (GOOD + "train: {world: moon}\n", "train.world: unknown world 'moon'"),
    (GOOD + "train: {preset.batch_size: 1.5}\n", "train.preset.batch_size: must be an integer"),
    (
        GOOD.replace("t: {generate: {n: 2, users: 3, seed: 1}}", "t: {file: nowhere.json}"),
        "test_sets.t.file: no such scenario file",
    ),
    (
        GOOD.replace("{n: 2, users: 3, seed: 1}", "{n: 2, users: 3, sed: 1}"),
        "test_sets.t.generate.sed: unknown key",
    ),
    (
        GOOD.replace("test_sets:\n  t: {generate: {n: 2, users: 3, seed: 1}}\n", ""),
        "test_sets: missing",
    ),
    (GOOD + "evaluate: {test_sets: [big]}\n", "evaluate.test_sets: 'big' is not in test_sets"),
    (GOOD + "train: {test_set: big}\n", "train.test_set: must be one of t"),
    (GOOD + "retries: -1\n", "retries: must be an integer >= 0"),
    ("grid: [1, 2\n", "not valid YAML"),
]


@pytest.mark.parametrize(("text", "expected"), BAD_FILES)
def test_a_bad_sweep_file_is_one_line_naming_the_key_exit_2_nothing_written(
    tmp_path: Path, capsys, text: str, expected: str
) -> None:
    spec = _write(tmp_path, text)
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("tupa sweep: error: ")
    assert expected in err[0]
    assert not out.exists()


def test_an_unreachable_address_is_named_exit_2_nothing_written(tmp_path: Path, capsys) -> None:
    import socket

    with socket.socket() as sock:  # a loopback port nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "out"
    spec = _write(tmp_path, GOOD)
    code = main(["sweep", str(spec), "--out", str(out), "--backend", "ray",
                 "--address", f"127.0.0.1:{port}"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2
    if "not installed" in err:
        pytest.skip("ray is not installed (pip install 'tupa[ray]')")
    assert f"--address: cannot reach a Ray cluster at 127.0.0.1:{port}" in err
    assert len(err.splitlines()) == 1
    assert not out.exists()


def test_an_occupied_out_dir_that_is_no_sweep_is_refused(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["sweep", str(_write(tmp_path, GOOD)), "--out", str(out)]) == 2
    assert "--out" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_trial_ids_are_stable_and_cover_what_shapes_the_run(tmp_path: Path) -> None:
    spec = load_spec(tiny_spec(tmp_path, "a"))
    assert [t.id.rsplit("-", 1)[0] for t in spec.trials] == ["ddqn-spec-e6-s1", "ddpg-spec-e6-s1"]
    # Reordered axes and values, an added seed: the same ids for the same trials.
    reordered = load_spec(
        tiny_spec(tmp_path, "b", grid={"seed": [2, 1], "algorithm": ["ddpg", "ddqn"]})
    )
    assert {t.id for t in spec.trials} < {t.id for t in reordered.trials}
    assert len(reordered.trials) == 4
    # Another preset field or another test set: new ids.
    other_lr = load_spec(tiny_spec(tmp_path, "c", train__preset_DOT_learning_rate=1e-3))
    assert not {t.id for t in spec.trials} & {t.id for t in other_lr.trials}
    other_set = load_spec(
        tiny_spec(tmp_path, "d", test_sets={"t3": {"generate": {"n": 4, "users": 3}}})
    )
    assert not {t.id for t in spec.trials} & {t.id for t in other_set.trials}


def test_the_shipped_sweep_files_are_valid() -> None:
    smoke = load_spec(ROOT / "sweeps" / "smoke.yaml")
    assert 4 <= len(smoke.trials) <= 12
    paper = load_spec(ROOT / "sweeps" / "paper.yaml")
    params = [t.params for t in paper.trials]
    assert {(p["algorithm"], p["strategy"]) for p in params} >= {
        ("ddqn", "spec"), ("ddqn", "gen10k"), ("ddpg", "spec"), ("ddpg", "gen10k")
    }  # fmt: skip
    assert len({p["seed"] for p in params}) >= 3
    # 10^2 ... 10^4 episodes: the trainer's curve points inside 10^4-episode runs.
    assert max(p["episodes"] for p in params) >= 10_000
    assert {100, 1_000, 10_000} <= set(CURVE_POINTS)


# --------------------------------------------------------------------------------------------
# Running


def _interruptible_and_nice() -> None:
    """In the sweep's process before exec: SIGINT at its default, lowest CPU priority."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    os.nice(19)


@pytest.mark.slow
@pytest.mark.process
@pytest.mark.training
def test_ctrl_c_leaves_a_resumable_sweep_and_the_rerun_skips_finished_trials(
    tmp_path: Path,
) -> None:
    """One worker, two trials: Ctrl-C after the first is done; the rerun trains only the
    second; then tupa report merges the sweep. The sweep starts with SIGINT at its default
    (a shell's background job, as ``.ci/run &``, ignores SIGINT, and a child inherits that, so
    Python would install no Ctrl-C handler and the sweep would run to its end), and at the
    lowest CPU priority, so that on a loaded machine it is the sweep that slows down, not this
    test's watch of its state."""
    spec = tiny_spec(tmp_path)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    command = [sys.executable, "-m", "service.cli", "sweep", str(spec), "--out", str(out),
               "--workers", "1"]  # fmt: skip
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True,
                               preexec_fn=_interruptible_and_nice)  # fmt: skip
    try:
        first = wait_for(
            lambda: (
                (out / STATE_FILE).exists()
                and [i for i, t in read_state(out)["trials"].items() if t["status"] == "done"]
            ),
            timeout_s=180,
            interval_s=0.1,
            message="the first trial to finish",
        )[0]
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, output
    assert "run the same command again to resume" in output
    state = read_state(out)
    assert {i: t["status"] for i, t in state["trials"].items()} == {
        i: "done" if i == first else "pending" for i in state["trials"]
    }
    model = out / state["trials"][first]["dir"] / "model.zip"
    before = model.stat().st_mtime_ns

    assert main(["sweep", str(spec), "--out", str(out), "--workers", "2"]) == 0
    state = read_state(out)
    assert all(t["status"] == "done" for t in state["trials"].values())
    assert model.stat().st_mtime_ns == before  # the finished trial was not run again
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["ran_this_time"] == 1
    for entry in state["trials"].values():
        trial_dir = out / entry["dir"]
        for name in ("model.zip", "model.json", "run.json"):
            assert (trial_dir / name).is_file()
        assert any((trial_dir / "tb").rglob("events.out.tfevents.*"))
        metadata = json.loads((trial_dir / "model.json").read_text())
        assert metadata["episodes"] == 6
        assert metadata["evaluation"] == entry["result"]["evaluation"]

    # Nothing left to do: the third run trains nothing.
    assert main(["sweep", str(spec), "--out", str(out)]) == 0
    assert json.loads((out / SUMMARY_FILE).read_text())["ran_this_time"] == 0

    report = tmp_path / "report"
    assert main(["report", "--results", str(out), "--out", str(report)]) == 0
    text = (report / "results.md").read_text()
    assert "`ddqn-spec`" in text and "`ddpg-spec`" in text
    assert (report / "sweep_learning_curve.png").stat().st_size > 1000
    exported = sorted(p.name for p in (report / "best").glob("*.zip"))
    assert exported == ["ddpg-spec-e6.zip", "ddqn-spec-e6.zip"]
    note = json.loads((report / "best" / "ddqn-spec-e6.json").read_text())
    assert note["sweep"]["trial"].startswith("ddqn-spec-e6-s1-")
    assert "exported_from" in note


@pytest.mark.slow
@pytest.mark.process
def test_a_trial_that_keeps_failing_is_retried_then_reported(tmp_path: Path, capsys) -> None:
    spec = tiny_spec(tmp_path, grid={"algorithm": ["ddqn"], "seed": [1]})
    out = tmp_path / "out"
    out.mkdir()
    (out / STATE_FILE).write_text(json.dumps({"format": "tupa-sweep-state/1", "trials": {}}))
    (out / "trials").write_text("a file where the trial directories go: every attempt fails")
    assert main(["sweep", str(spec), "--out", str(out), "--retries", "1"]) == 1
    (entry,) = read_state(out)["trials"].values()
    assert entry["status"] == "failed"
    assert entry["attempts"] == 2
    assert [e.split(":")[0] for e in entry["errors"]] == ["attempt 1", "attempt 2"]
    assert all("NotADirectoryError" in e or "FileExistsError" in e for e in entry["errors"])
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["counts"]["failed"] == 1
    assert "last error: attempt 2" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.process
@pytest.mark.training
def test_a_killed_local_worker_is_retried(tmp_path: Path) -> None:
    spec = load_spec(
        tiny_spec(tmp_path, grid={"algorithm": ["ddqn"], "seed": [1]}, train__episodes=30)
    )
    out = tmp_path / "out"
    (trial,) = spec.trials
    killed: list[int] = []
    killer = threading.Thread(
        target=kill_worker_once, args=(out / "trials" / trial.id, killed), daemon=True
    )
    killer.start()
    summary = run_sweep(spec, out, lambda: LocalBackend(workers=1), stream=io.StringIO())
    killer.join(timeout=5)
    assert killed, "the worker was never killed"
    entry = read_state(out)["trials"][trial.id]
    assert summary.counts["done"] == 1
    assert entry["attempts"] == 2
    assert entry["errors"] == ["attempt 1: worker died (SIGKILL)"]
    worker = json.loads((out / "trials" / trial.id / WORKER_FILE).read_text())
    assert worker["pid"] != killed[0]


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_live_table_is_redrawn_below_the_event_lines() -> None:
    from policies.sweep.runner import Progress
    from policies.sweep.state import SweepState

    trials = {
        "a": {"status": "done", "result": {"evaluation": {"policy": {"mean_utility": 0.9}}}},
        "b": {"status": "running", "result": None},
        "c": {"status": "failed", "result": None},
        "d": {"status": "pending", "result": None},
    }
    state = SweepState(out_dir=Path("."), document={"trials": trials})
    terminal = _Terminal()
    progress = Progress(terminal, "demo", 4)
    progress.backend = "local, 2 worker processes"
    progress.table(state, list(trials), {"b": 0.0})
    first = terminal.getvalue()
    assert "pending 1, running 1, done 1, failed 1" in first
    assert "best so far: a, mean utility 0.900" in first
    assert "running b" in first
    progress.line("done b")
    # The three table lines are erased (cursor up 3, clear) before the event line.
    assert terminal.getvalue()[len(first) :].startswith("\x1b[3F\x1b[J")
    assert terminal.getvalue().endswith("done b\n")

    plain = io.StringIO()  # not a terminal: event lines only, no table
    quiet = Progress(plain, "demo", 4)
    quiet.table(state, list(trials), {})
    assert plain.getvalue() == ""


def test_a_second_command_on_a_running_sweep_is_refused(tmp_path: Path, capsys) -> None:
    import fcntl

    from policies.sweep.runner import LOCK_FILE

    spec = tiny_spec(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / STATE_FILE).write_text(json.dumps({"format": "tupa-sweep-state/1", "trials": {}}))
    with open(out / LOCK_FILE, "w") as held:  # what a running tupa sweep holds
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(["sweep", str(spec), "--out", str(out)]) == 2
    assert f"--out: another tupa sweep is running in {out}" in capsys.readouterr().err
    assert read_state(out)["trials"] == {}  # untouched


def _finished_sweep(tmp_path: Path, done: int) -> tuple[Path, Path, list[str]]:
    """A tiny sweep's file and an out dir whose state has its first ``done`` trials done (a
    result written by hand: nothing trains)."""
    from policies.sweep.state import SweepState

    spec_file = tiny_spec(tmp_path)
    spec = load_spec(spec_file)
    out = tmp_path / "out"
    out.mkdir()
    test_paths = {name: ts.path(out) for name, ts in spec.test_sets.items()}
    state = SweepState.open(out, spec, test_paths)
    ids = [t.id for t in spec.trials]
    for trial_id in ids[:done]:
        state.trials[trial_id].update(status="done", attempts=1, result={"wall_time_s": 1.0})
    state.save()
    return spec_file, out, ids


class _InstantBackend:
    """Every trial done at once, with no result worth reading: the scheduler's view only."""

    name = "instant"
    slots = 4

    def __init__(self) -> None:
        self._running: list[str] = []

    def describe(self) -> str:
        return "instant"

    def submit(self, trial_id: str, payload: dict[str, Any]) -> None:
        self._running.append(trial_id)

    def running(self) -> list[str]:
        return list(self._running)

    def wait(self, timeout_s: float) -> list:
        from policies.sweep.backends import Outcome

        done, self._running = self._running, []
        return [(i, Outcome(result={"wall_time_s": 0.0})) for i in done]

    def cancel_all(self) -> None:
        self._running = []

    def close(self) -> None:
        pass


@pytest.mark.parametrize("backend", ["local", "ray"])
def test_a_finished_sweep_in_out_says_nothing_runs_and_how_to_run_it_again(
    tmp_path: Path, capsys, backend: str
) -> None:
    """Issue 42: ``--backend ray`` on the --out of a finished sweep did nothing without saying
    so. Both backends say that --out holds the finished sweep, that nothing ran on the backend
    asked for, and how to run it again; the summary keeps the backend that ran the trials."""
    import importlib.util

    if backend == "ray" and importlib.util.find_spec("ray") is None:
        pytest.skip("ray is not installed (pip install 'tupa[ray]')")
    spec_file, out, ids = _finished_sweep(tmp_path, done=2)
    (out / SUMMARY_FILE).write_text(json.dumps({"backend": "local, 2 worker processes"}))
    assert main(["sweep", str(spec_file), "--out", str(out), "--backend", backend]) == 0
    said = capsys.readouterr().out
    line = next(x for x in said.splitlines() if "nothing to run" in x)
    assert f"--out {out}" in line and f"all {len(ids)} trials" in line, line
    assert f"nothing to run on the {backend} backend" in line, line
    assert "another --out" in line, line
    assert json.loads((out / SUMMARY_FILE).read_text())["backend"] == "local, 2 worker processes"


def test_a_partly_finished_sweep_in_out_says_it_resumes(tmp_path: Path) -> None:
    spec_file, out, ids = _finished_sweep(tmp_path, done=1)
    stream = io.StringIO()
    summary = run_sweep(load_spec(spec_file), out, _InstantBackend, stream=stream,
                        backend_name="ray")  # fmt: skip
    assert summary.ran == len(ids) - 1
    line = next(x for x in stream.getvalue().splitlines() if "resuming" in x)
    assert f"--out {out}" in line, line
    assert f"1 of {len(ids)} trials already done (skipped), {len(ids) - 1} to run on ray" in line
