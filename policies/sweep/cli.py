"""``tupa sweep SPEC.yaml``: a grid of training runs (argparse only here)."""

from __future__ import annotations

import argparse
import importlib.util
import signal
import threading
from pathlib import Path
from typing import Any

_DESCRIPTION = """\
Run a sweep: every combination of a sweep file's grid (algorithms, strategies, episode budgets,
seeds, worlds, environments, preset fields, test sets) is one trial, an ordinary tupa train
run into OUT/trials/<trial id>/ (model.zip + model.json, learning_curve.json, TensorBoard logs
in tb/). See sweeps/smoke.yaml and sweeps/paper.yaml, and policies/sweep/spec.py for every key.

Backends: local (default) runs one fresh process per trial, --workers at once (default: the
machine's cores), each on one CPU thread; ray runs one Ray task per trial (pip install
'tupa[ray]'), on a private Ray instance started for the command (127.0.0.1, no dashboard,
stopped at the end) or, with --address auto or HOST:PORT, on a running cluster (the out
directory must then be on a file system every node mounts at the same path). Both give the
same per-trial results for the same seeds.

Resumable: OUT/sweep.json records every trial's status; rerunning the same command skips
finished trials and reruns interrupted ones from scratch. A failed trial is retried up to
--retries times (default: the file's retries, else 2) and then reported as failed. Ctrl-C
leaves a resumable state. Progress: one line per event and, on a terminal, a live table; at
the end a summary table and OUT/summary.json. tupa report --results OUT --out DIR merges the
results. Exit status: 0 when every trial is done, 1 when some failed, 2 on bad input.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sweep",
        allow_abbrev=False,
        help="run a grid of training runs (locally or on Ray), resumable",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("spec", type=Path, metavar="SPEC.yaml", help="the sweep file")
    parser.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="output directory (default: runs/sweeps/<the sweep's name>)",
    )
    parser.add_argument("--backend", choices=("local", "ray"), default="local")
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="trials at once (default: the machine's cores; with ray, the cluster's CPUs)",
    )
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="ray only: join a running cluster (auto, or HOST:PORT of its head)",
    )
    parser.add_argument(
        "--retries", type=int, metavar="N", help="retries of a failed trial (default: the file's)"
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="check the file and list the trials, run nothing"
    )
    parser.set_defaults(handler=_sweep)


def _sweep(args: argparse.Namespace) -> int:
    from policies.sweep.spec import load_spec
    from sim.errors import InputError

    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers: must be at least 1, got {args.workers}")
    if args.address is not None and args.backend != "ray":
        raise InputError("--address: only with --backend ray")
    spec = load_spec(args.spec)
    out = args.out or Path("runs") / "sweeps" / spec.name
    if args.dry_run:
        for trial in spec.trials:
            print(trial.id)
        print(f"{len(spec.trials)} trials; would write to {out}")
        return 0
    if args.backend == "ray" and importlib.util.find_spec("ray") is None:
        raise InputError("--backend ray: Ray is not installed (pip install 'tupa[ray]')")
    from policies.sweep.runner import check_out_dir, run_sweep

    check_out_dir(out)
    # A stop request (kill, a batch system's end of allocation) leaves a resumable state too.
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        summary = run_sweep(
            spec, out, lambda: _backend(args), retries=args.retries, backend_name=args.backend
        )
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    print(f"wrote {out / 'summary.json'}; tupa report --results {out} --out DIR merges it")
    return 1 if summary.failed else 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _backend(args: argparse.Namespace) -> Any:  # a Backend (imported lazily)
    if args.backend == "ray":
        from policies.sweep.ray_backend import RayBackend

        return RayBackend(address=args.address, workers=args.workers)
    from policies.sweep.backends import LocalBackend

    return LocalBackend(workers=args.workers)
