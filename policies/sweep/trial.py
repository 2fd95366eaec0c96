"""What a worker runs (:func:`run_payload`): one trial, an ordinary training run then the extra
evaluations (:func:`run_trial`), or a slice of a ``tupa eval`` fanned out over the same backends
(:func:`evaluate_slice`).

:func:`run_trial` takes a plain-JSON payload (so that any backend can ship it: a pipe to a
spawned process, a Ray task's argument) and returns a plain-JSON result. It runs in a fresh
process on one CPU thread (``torch.set_num_threads(1)``, the caller's count restored after:
:func:`one_torch_thread`), which is what makes a trial give the same numbers on either backend
and alone or beside others.

The trial directory is cleared first: a trial interrupted half-way starts again from scratch,
so its result never depends on when it was interrupted. ``worker.json`` in it says which
process on which host runs it (an operator can find, or kill, a trial's worker).
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

WORKER_FILE = "worker.json"


def trial_payload(
    trial_id: str, config: dict[str, Any], extra_tests: dict[str, str], sweep_dir: Path
) -> dict[str, Any]:
    """The payload of one trial: its ``TrainConfig.to_dict()`` (absolute paths), the extra
    test sets ``{name: scenario file}`` and the sweep directory (checked by the worker: a node
    that does not see it cannot run the trial)."""
    return {
        "trial_id": trial_id,
        "config": config,
        "extra_tests": extra_tests,
        "sweep_dir": str(Path(sweep_dir).resolve()),
    }


def run_payload(payload: dict[str, Any]) -> dict[str, Any]:
    """What a backend's worker runs: a training trial, or (``"kind": "eval"``) a slice of a
    ``tupa eval`` fanned out (:func:`evaluate_slice`)."""
    if payload.get("kind") == "eval":
        return evaluate_slice(payload)
    return run_trial(payload)


def run_trial(payload: dict[str, Any]) -> dict[str, Any]:
    """Train one trial (see the module doc) and return its result: the final evaluation, the
    episodes and steps trained, the wall time and ``extra`` ({test set: mean, median and p25
    utility}, each also written as ``eval_<set>.json`` in the trial directory)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with one_torch_thread():
        return _train_and_evaluate(payload)


def evaluate_slice(payload: dict[str, Any]) -> dict[str, Any]:
    """A worker's part: ``evaluate_policy`` on scenarios ``start:stop`` of the file, on one
    torch thread."""
    with one_torch_thread():
        return _evaluate_slice(payload)


def _evaluate_slice(payload: dict[str, Any]) -> dict[str, Any]:
    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import resolve_policy
    from policies.world_options import world_from_args
    from sim.files import load_scenarios

    area, scenarios = load_scenarios(Path(payload["scenarios"]))
    world = world_from_args(argparse.Namespace(**payload["world_options"]), "paper", area)
    policy = resolve_policy(payload["policy"], world)
    start, stop = payload["start"], payload["stop"]
    return evaluate_policy(
        policy, scenarios[start:stop], world, seed=payload["seed"] + start, progress=False
    )


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch on one thread while the block runs, and the caller's count back after it: a worker
    process of its own does not care, a caller that runs a trial or a slice in its own process
    (the tests) would otherwise keep one thread for everything after."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _train_and_evaluate(payload: dict[str, Any]) -> dict[str, Any]:
    from policies.training.training import TrainConfig, train
    from sim.atomic import atomic_write_json
    from sim.errors import InputError

    sweep_dir = Path(payload["sweep_dir"])
    if not sweep_dir.is_dir():
        raise InputError(
            f"{socket.gethostname()} does not see the sweep directory {sweep_dir}: put it on a "
            "file system every node mounts at the same path"
        )
    config = TrainConfig.from_dict(payload["config"])
    out = config.out_dir
    if out.exists() or out.is_symlink():
        if out.is_dir() and not out.is_symlink():
            shutil.rmtree(out)
        else:
            out.unlink()
    out.mkdir(parents=True)
    atomic_write_json(
        out / WORKER_FILE,
        {"pid": os.getpid(), "host": socket.gethostname(), "trial": payload["trial_id"]},
    )
    metadata = train(config)
    extra = {}
    for name, scenario_file in payload["extra_tests"].items():
        extra[name] = _evaluate_on(config, Path(scenario_file), out / f"eval_{name}.json")
    return {
        "evaluation": metadata.get("evaluation"),
        "episodes": metadata["episodes"],
        "timesteps": metadata["timesteps"],
        "wall_time_s": metadata["wall_time_s"],
        "extra": extra,
    }


def _evaluate_on(config: Any, scenario_file: Path, out_file: Path) -> dict[str, float]:
    """The trained checkpoint on another test set, as ``tupa eval`` scores it (fading seed 0)
    in the run's world over that set's area; the result file has ``tupa eval``'s shape."""
    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import resolve_policy
    from sim.atomic import atomic_write_json
    from sim.files import load_scenarios

    area, scenarios = load_scenarios(scenario_file)
    world = config.eval_world(area)
    policy = resolve_policy(str(config.out_dir / "model.zip"), world)
    result = evaluate_policy(policy, scenarios, world, seed=0, progress=False)
    atomic_write_json(out_file, result)
    return {k: result[k] for k in ("mean_utility", "median_utility", "p25_utility")}
