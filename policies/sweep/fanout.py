"""``tupa eval --backend local|ray``: a large test set evaluated in slices on the sweep backends.

The scenarios are cut into contiguous slices (about two per worker, so that a slow slice does
not leave the others idle); each slice is one task on a backend (:mod:`.backends`,
:mod:`.ray_backend`), which rebuilds the world and the policy from ``tupa eval``'s own options
and runs :func:`policies.evaluation.evaluation.evaluate_policy` on its slice with the fading seed
its scenarios would have had in one run (scenario i: seed S + i). The slices' rows are joined in
order and the summary is recomputed from them as ``evaluate_policy`` computes it, so the result
is the one an unsplit ``tupa eval`` writes. A slice that fails is retried (``retries`` times),
then the command fails naming the policy and the slice.
"""

from __future__ import annotations

import math
import time
from argparse import Namespace
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from policies.sweep.backends import Backend
from sim.errors import InputError

WORLD_OPTIONS: tuple[str, ...] = ("world", "world_set", "environment", "queueing", "episode_steps")
SLICES_PER_WORKER = 2


def merge_slices(parts: Sequence[dict[str, Any]], seed: int) -> dict[str, Any]:
    """One ``evaluate_policy`` result from its slices' results, in order."""
    rows = [row for part in parts for row in part["scenarios"]]
    values = np.array([row["utility"] for row in rows])
    first = parts[0]
    return {
        "policy": first["policy"],
        "world": first["world"],
        "environment": first["environment"],
        "n_scenarios": len(rows),
        "mean_utility": float(values.mean()),
        "median_utility": float(np.median(values)),
        "p25_utility": float(np.percentile(values, 25)),
        "mean_time_to_final_s": float(np.mean([row["time_to_final_s"] for row in rows])),
        "seed": seed,
        "queueing": first["queueing"],
        "episode_steps": first["episode_steps"],
        "mode": first["mode"],
        "scenarios": rows,
    }


def evaluate_fanned(
    names: Sequence[str],
    scenario_file: Path,
    n_scenarios: int,
    args: Namespace,
    make_backend: Callable[[], Backend],
    retries: int = 2,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Every policy in ``names`` (baseline names or checkpoint paths) evaluated on the file's
    ``n_scenarios`` scenarios in slices on one backend; one result per name, in order."""
    import sys

    options = {key: getattr(args, key, None) for key in WORLD_OPTIONS}
    options["world_set"] = list(options["world_set"] or [])
    resolved = [str(Path(n).resolve()) if Path(n).exists() else n for n in names]
    backend = make_backend()
    try:
        size = max(1, math.ceil(n_scenarios / (backend.slots * SLICES_PER_WORKER)))
        tasks: dict[str, dict[str, Any]] = {}
        for p, name in enumerate(resolved):
            for start in range(0, n_scenarios, size):
                tasks[f"{p}:{start}"] = {
                    "kind": "eval",
                    "policy": name,
                    "scenarios": str(Path(scenario_file).resolve()),
                    "start": start,
                    "stop": min(start + size, n_scenarios),
                    "seed": args.seed,
                    "world_options": options,
                }
        done: dict[str, dict[str, Any]] = {}
        attempts = dict.fromkeys(tasks, 0)
        queue = list(tasks)
        started = time.monotonic()
        while queue or backend.running():
            while queue and len(backend.running()) < backend.slots:
                key = queue.pop(0)
                attempts[key] += 1
                backend.submit(key, tasks[key])
            for key, outcome in backend.wait(0.5):
                if outcome.ok:
                    assert outcome.result is not None
                    done[key] = outcome.result
                    if progress:
                        print(
                            f"{len(done)}/{len(tasks)} slices evaluated "
                            f"({time.monotonic() - started:.0f} s, {backend.describe()})",
                            end="\r" if sys.stderr.isatty() else "\n",
                            file=sys.stderr,
                            flush=True,
                        )
                elif attempts[key] <= retries:
                    queue.append(key)
                else:
                    p, start = (int(x) for x in key.split(":"))
                    task = tasks[key]
                    raise InputError(
                        f"--policy {names[p]}: scenarios {start}..{task['stop'] - 1} failed "
                        f"{attempts[key]} times on the {backend.name} backend: {outcome.error}"
                    )
        if progress and sys.stderr.isatty():
            print(file=sys.stderr)
    finally:
        backend.close()
    results = []
    for p in range(len(resolved)):
        keys = sorted(
            (k for k in done if int(k.split(":")[0]) == p), key=lambda k: int(k.split(":")[1])
        )
        results.append(merge_slices([done[k] for k in keys], args.seed))
    return results


def evaluate_from_args(
    names: Sequence[str], n_scenarios: int, args: Namespace
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``tupa eval --backend``: the results for ``names`` and, when the oracle is not among
    them, the oracle's on the side (for each scenario's ``ratio_to_oracle``), fanned out too."""
    import importlib.util

    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers: must be at least 1, got {args.workers}")
    if args.address is not None and args.backend != "ray":
        raise InputError("--address: only with --backend ray")
    if args.backend == "ray" and importlib.util.find_spec("ray") is None:
        raise InputError("--backend ray: Ray is not installed (pip install 'tupa[ray]')")

    def make_backend() -> Backend:
        if args.backend == "ray":
            from policies.sweep.ray_backend import RayBackend

            return RayBackend(address=args.address, workers=args.workers)
        from policies.sweep.backends import LocalBackend

        return LocalBackend(workers=args.workers)

    wanted = list(names) + ([] if "oracle" in names else ["oracle"])
    results = evaluate_fanned(
        wanted, args.scenarios, n_scenarios, args, make_backend, progress=not args.no_progress
    )
    return results[: len(names)], results[len(names) :]
