"""``tupa sweep --backend ray`` on a local Ray instance the test starts (2 CPUs, loopback only,
no dashboard, stopped afterwards): the same per-trial results as the local backend for the
same seeds, a killed trial retried, a resumed sweep that skips finished trials.

Skipped, with the reason, when the ``ray`` extra is not installed (pip install 'tupa[ray]').
"""

from __future__ import annotations

import io
import json
import threading
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'tupa[ray]')")

from policies.sweep.backends import LocalBackend  # noqa: E402
from policies.sweep.ray_backend import RayBackend, init_local_ray  # noqa: E402
from policies.sweep.runner import run_sweep  # noqa: E402
from policies.sweep.spec import load_spec  # noqa: E402
from service.cli import main  # noqa: E402
from tests.policies.test_sweep import kill_worker_once, read_state, tiny_spec  # noqa: E402

# One private Ray instance at a time: the Ray tests run one after another, on one worker.
pytestmark = [pytest.mark.ray, pytest.mark.xdist_group("ray")]


@pytest.fixture
def local_ray():
    """A private Ray instance, started as the sweep starts its own: 2 CPUs, listening on
    loopback only, no dashboard; shut down after."""
    init_local_ray(2)
    try:
        yield ray
    finally:
        ray.shutdown()


@pytest.mark.slow
@pytest.mark.process
@pytest.mark.training
def test_ray_gives_the_local_results_retries_a_killed_trial_and_resumes(
    tmp_path: Path, local_ray
) -> None:
    spec = load_spec(tiny_spec(tmp_path, grid={"algorithm": ["ddqn", "ddpg"], "seed": [1, 2]}))
    victim = spec.trials[0]
    ray_out = tmp_path / "ray"
    killed: list[int] = []
    killer = threading.Thread(
        target=kill_worker_once, args=(ray_out / "trials" / victim.id, killed), daemon=True
    )
    killer.start()
    summary = run_sweep(spec, ray_out, lambda: RayBackend(workers=2), stream=io.StringIO())
    killer.join(timeout=5)
    assert killed, "the victim's worker was never killed"
    assert summary.counts == {"pending": 0, "running": 0, "done": 4, "failed": 0}
    ray_state = read_state(ray_out)["trials"]
    assert ray_state[victim.id]["attempts"] == 2
    assert ray_state[victim.id]["errors"][0].startswith("attempt 1: worker died")
    assert all(t["attempts"] == 1 for i, t in ray_state.items() if i != victim.id)
    assert ray.is_initialized()  # the backend leaves a Ray it did not start running

    # The same sweep on the local backend: the same numbers, trial by trial.
    local_out = tmp_path / "local"
    run_sweep(spec, local_out, lambda: LocalBackend(workers=2), stream=io.StringIO())
    local_state = read_state(local_out)["trials"]
    assert set(local_state) == set(ray_state)
    for trial_id, entry in ray_state.items():
        ours, theirs = entry["result"], local_state[trial_id]["result"]
        assert ours["timesteps"] == theirs["timesteps"]
        for policy in ("policy", "min-distance", "oracle"):
            for key, value in ours["evaluation"][policy].items():
                assert value == pytest.approx(theirs["evaluation"][policy][key], rel=1e-9), (
                    trial_id,
                    policy,
                    key,
                )
        ray_curve = json.loads((ray_out / entry["dir"] / "model.json").read_text())
        assert (
            ray_curve["scenario_set_hash"]
            == json.loads((local_out / entry["dir"] / "model.json").read_text())[
                "scenario_set_hash"
            ]
        )

    # Resuming a finished sweep runs nothing (and starts no backend).
    def no_backend():
        raise AssertionError("a finished sweep must not start a backend")

    again = run_sweep(spec, ray_out, no_backend, stream=io.StringIO())
    assert again.ran == 0 and again.counts["done"] == 4


@pytest.mark.slow
def test_the_command_starts_a_private_ray_instance_and_stops_it(tmp_path: Path, capsys) -> None:
    """``tupa sweep --backend ray`` without --address: a Ray instance of --workers CPUs on
    127.0.0.1 for the command only."""
    assert not ray.is_initialized()
    spec = tiny_spec(tmp_path, grid={"algorithm": ["ddqn"], "seed": [1, 2]})
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out), "--backend", "ray", "--workers", "2"]) == 0
    assert not ray.is_initialized()  # shut down with the command
    printed = capsys.readouterr().out
    assert "sweep tiny: 2 done, 0 failed" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backend"] == "ray, local instance, 2 CPUs"
    assert all(t["status"] == "done" and t["attempts"] == 1 for t in summary["trials"])
