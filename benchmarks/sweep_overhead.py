"""What running a sweep costs beyond its trials: the Ray backend against the local one, and N
trials on the machine's cores against one trial alone.

One run measures, on the same sweep of N trials (default 8: DDQN and DDPG x 4 seeds, the fast
preset, 150 episodes each on 8 generated test scenarios, so that a trial trains for tens of
seconds as a real one would for minutes):

1. one trial alone (the local backend, one worker), before and after the rest: ``t1`` (mean);
2. all N trials on the local backend (one process per trial, as many at once as cores): ``local``;
3. all N trials on the Ray backend (a private local Ray instance started and stopped inside
   the measured time, as ``tupa sweep --backend ray`` does): ``ray``.

and reports ``ray / local`` (target <= 1.10) and ``local / (N / cores x t1)`` (target ~ 1: a
sweep of N trials on 2 cores takes N / 2 trials' time; only meaningful on an otherwise idle
machine), and, for each backend, its *packing*: wall time / (sum of the trials' own times /
cores), which other load on the machine does not move (it slows trials and sweep alike): 1.0
means the scheduler kept every core busy with trials. Each measurement is a complete
``run_sweep`` into a fresh directory: state file, test set, trial processes, summary. The
per-trial results of the local and Ray runs are compared too (the same seeds must give the same
numbers). Writes ``benchmarks/results/sweep_overhead.json``.

    nice -n 10 python benchmarks/sweep_overhead.py               # about 5 minutes on 2 cores
    python benchmarks/sweep_overhead.py --seeds 2 --episodes 60  # quicker, noisier

A benchmark, not a test: the machine's other load moves the numbers (the load average before
and after is recorded).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "benchmarks" / "results"


def sweep_document(seeds: int, episodes: int) -> dict[str, Any]:
    return {
        "name": "overhead",
        "retries": 0,
        "test_sets": {"t8": {"generate": {"n": 8, "users": 3, "seed": 4242}}},
        "grid": {"algorithm": ["ddqn", "ddpg"], "seed": list(range(1, seeds + 1))},
        "train": {"strategy": "gen10k", "episodes": episodes, "preset": "fast"},
        "evaluate": {"curve_scenarios": 8},
    }


def timed_sweep(spec: Any, out: Path, make_backend: Any) -> tuple[float, dict[str, Any]]:
    from policies.sweep.runner import run_sweep

    started = time.perf_counter()
    summary = run_sweep(spec, out, make_backend, stream=io.StringIO())
    wall = time.perf_counter() - started
    if summary.failed:
        raise SystemExit(f"trials failed in {out}: {summary.failed}")
    state = json.loads((out / "sweep.json").read_text())
    trials = state["trials"].items()
    return wall, {i: {**t["result"], "elapsed_s": t["elapsed_s"]} for i, t in trials}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="seeds per algorithm (N = 2 x this)")
    parser.add_argument("--episodes", type=int, default=150)
    parser.add_argument("--out", type=Path, default=RESULTS / "sweep_overhead.json")
    args = parser.parse_args()

    import yaml

    from policies.sweep.backends import LocalBackend, machine_cores
    from policies.sweep.ray_backend import RayBackend
    from policies.sweep.spec import load_spec, parse_spec

    cores = machine_cores()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="tupa-sweep-overhead-") as tmp:
        root = Path(tmp)
        spec_file = root / "overhead.yaml"
        spec_file.write_text(yaml.safe_dump(sweep_document(args.seeds, args.episodes)))
        spec = load_spec(spec_file)
        n = len(spec.trials)
        one = parse_spec({**spec.raw, "grid": {"algorithm": ["ddqn"], "seed": [1]}}, spec_file)
        print(f"{n} trials of {args.episodes} episodes on {cores} cores", flush=True)

        t1_before, _ = timed_sweep(one, root / "one", lambda: LocalBackend(workers=1))
        print(f"one trial alone: {t1_before:.1f} s", flush=True)
        local, local_results = timed_sweep(spec, root / "local", lambda: LocalBackend())
        print(f"local backend, {n} trials: {local:.1f} s", flush=True)
        ray, ray_results = timed_sweep(spec, root / "ray", lambda: RayBackend())
        print(f"ray backend, {n} trials: {ray:.1f} s", flush=True)
        t1_after, _ = timed_sweep(one, root / "one-again", lambda: LocalBackend(workers=1))
        print(f"one trial alone, again: {t1_after:.1f} s", flush=True)
    t1 = (t1_before + t1_after) / 2

    same = all(
        ray_results[i]["evaluation"]["policy"] == local_results[i]["evaluation"]["policy"]
        for i in local_results
    )
    ideal = n / cores * t1
    # Packing: the sweep's wall time against its trials' own times (each attempt from start to
    # end, process start-up included) spread over the slots. Other load on the machine slows
    # the trials and the sweep alike, so this ratio isolates what the scheduler adds.
    packing = {
        name: wall / (sum(r["elapsed_s"] for r in results.values()) / cores)
        for name, wall, results in (("local", local, local_results), ("ray", ray, ray_results))
    }
    document = {
        "benchmark": "sweep_overhead",
        "command": "python benchmarks/sweep_overhead.py "
        f"--seeds {args.seeds} --episodes {args.episodes}",
        "trials": n,
        "episodes": args.episodes,
        "cores": cores,
        "one_trial_s": round(t1, 2),
        "one_trial_before_s": round(t1_before, 2),
        "one_trial_after_s": round(t1_after, 2),
        "local_s": round(local, 2),
        "ray_s": round(ray, 2),
        "ray_over_local": round(ray / local, 3),
        "ray_overhead_target": 1.10,
        "ray_overhead_met": ray / local <= 1.10,
        "local_over_ideal": round(local / ideal, 3),
        "ideal_s": round(ideal, 2),
        "local_packing": round(packing["local"], 3),
        "ray_packing": round(packing["ray"], 3),
        "trial_elapsed_s": {
            "local": {i: r["elapsed_s"] for i, r in sorted(local_results.items())},
            "ray": {i: r["elapsed_s"] for i, r in sorted(ray_results.items())},
        },
        "trial_train_wall_s": {i: r["wall_time_s"] for i, r in sorted(local_results.items())},
        "same_results_local_and_ray": same,
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "python": sys.version.split()[0],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    print(
        f"ray / local = {document['ray_over_local']} (target <= 1.10); local / (N / cores x one "
        f"trial) = {document['local_over_ideal']}; packing (wall / (sum of trial times / "
        f"cores)): local {document['local_packing']}, ray {document['ray_packing']}; same "
        f"per-trial results: {same}; "
        f"wrote {args.out}"
    )


if __name__ == "__main__":
    main()
