"""The scheduler both backends share: submit, retry, record, show, summarise.

:func:`run_sweep` runs every trial of a sweep that is not done yet, at most ``backend.slots``
at a time. After every change of a trial's status the state file is rewritten atomically
(:mod:`.state`). A failed attempt (the training raised, or its worker died) is retried up to
``retries`` times, after the other pending trials; a trial that fails every attempt is reported
``failed``, with one error line per attempt, never dropped. Ctrl-C stops the workers, puts the
running trials back to ``pending`` (their attempt not counted) and saves the state: the same
command then resumes.

Progress goes to ``stream``: one line per event (a trial started, finished, failed) and, on a
terminal, a live table below them (trials pending / running / done / failed, the best so far,
what runs and for how long), redrawn every second. At the end ``OUT/summary.json``
(:data:`.state.SUMMARY_FILE`) lists every trial and the final table is printed.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from policies.sweep.backends import Backend
from policies.sweep.spec import SweepSpec, train_config, write_test_sets
from policies.sweep.state import (
    STATE_FILE,
    SUMMARY_FILE,
    SweepState,
    best_trial,
    final_utility,
    is_sweep_dir,
)
from policies.sweep.trial import trial_payload
from sim.atomic import atomic_write_json
from sim.errors import InputError

SUMMARY_FORMAT = "tupa-sweep-summary/1"
LOCK_FILE = ".sweep.lock"
_REDRAW_S = 1.0


@dataclass(frozen=True)
class SweepSummary:
    """What a run of the sweep left: status counts of this sweep's trials, the best finished
    trial (id, mean utility), the ids that failed, how many trials this run ran, wall time."""

    counts: dict[str, int]
    best: tuple[str, float] | None
    failed: tuple[str, ...]
    ran: int
    wall_time_s: float


def check_out_dir(out_dir: Path) -> None:
    """``--out`` must be a new or empty directory, or hold a sweep (then it resumes)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out: {out_dir} exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not is_sweep_dir(out_dir):
        raise InputError(
            f"--out: {out_dir} is not empty and holds no sweep ({STATE_FILE}): choose another"
        )


def _lock(out_dir: Path) -> int:
    """Hold ``OUT/.sweep.lock`` (released when the process ends, however it ends): two
    commands writing the same sweep would run its trials twice and overwrite its state."""
    out_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(out_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise InputError(f"--out: another tupa sweep is running in {out_dir}") from None
    return fd


def run_sweep(
    spec: SweepSpec,
    out_dir: Path,
    make_backend: Callable[[], Backend],
    retries: int | None = None,
    stream: TextIO | None = None,
    backend_name: str | None = None,
) -> SweepSummary:
    """Run the sweep's unfinished trials into ``out_dir`` (see the module doc).

    ``make_backend`` is called only when there is something to run, and before anything is
    written (a backend that cannot start, such as an unreachable Ray address, leaves nothing
    behind). ``retries`` overrides the spec's. An ``out_dir`` that already holds the sweep is
    resumed, and the first line says so, naming ``--out`` and ``backend_name`` (the backend
    asked for): how many trials are done and skipped and how many run, or, when every one is
    done, that nothing runs and how to run the sweep again."""
    stream = stream or sys.stdout
    shown = Path(out_dir)  # as the user gave it
    out_dir = Path(out_dir).resolve()
    check_out_dir(out_dir)
    retries = spec.retries if retries is None else retries
    if retries < 0:
        raise InputError(f"--retries: must be >= 0, got {retries}")
    ids = [t.id for t in spec.trials]
    test_paths = {name: ts.path(out_dir) for name, ts in spec.test_sets.items()}
    state = SweepState.open(out_dir, spec, test_paths)
    todo = [i for i in ids if state.trials[i]["status"] != "done"]
    started = time.monotonic()
    progress = Progress(stream, spec.name, len(ids))
    on = f" on {backend_name}" if backend_name else ""
    if not todo:
        on_backend = f" on the {backend_name} backend" if backend_name else ""
        progress.line(
            f"--out {shown} holds sweep {spec.name} with all {len(ids)} trials done: nothing "
            f"to run{on_backend} (a rerun never repeats a finished trial); to run the sweep "
            "again, give another --out or remove this one"
        )
        return _finish(state, spec, ids, 0, started, progress, None)
    done_before = len(ids) - len(todo)
    if done_before:
        progress.line(
            f"resuming the sweep in --out {shown}: {done_before} of {len(ids)} trials already "
            f"done (skipped), {len(todo)} to run{on}"
        )
    backend = make_backend()
    lock = None
    try:
        lock = _lock(out_dir)
        state.save()
        write_test_sets(spec, out_dir)
        progress.backend = backend.describe()
        ran = _loop(spec, state, backend, deque(todo), retries, test_paths, progress)
    except KeyboardInterrupt:
        backend.cancel_all()
        for entry in state.trials.values():
            if entry["status"] == "running":
                entry["status"] = "pending"
                entry["attempts"] = max(0, entry["attempts"] - 1)
        state.save()
        progress.close()
        counts = state.counts(ids)
        print(
            f"interrupted: {counts['done']} of {len(ids)} trials done; run the same command "
            "again to resume",
            file=stream,
            flush=True,
        )
        raise
    finally:
        backend.close()
        if lock is not None:
            os.close(lock)
    return _finish(state, spec, ids, ran, started, progress, backend.describe())


def _loop(
    spec: SweepSpec,
    state: SweepState,
    backend: Backend,
    queue: deque[str],
    retries: int,
    test_paths: dict[str, Path],
    progress: Progress,
) -> int:
    ran = 0
    started_at: dict[str, float] = {}
    ids = [t.id for t in spec.trials]
    while queue or backend.running():
        while queue and len(backend.running()) < backend.slots:
            trial_id = queue.popleft()
            entry = state.trials[trial_id]
            entry["status"] = "running"
            entry["attempts"] += 1
            state.save()
            backend.submit(trial_id, _payload(spec, state, trial_id, test_paths))
            started_at[trial_id] = time.monotonic()
            attempt = f" (attempt {entry['attempts']})" if entry["attempts"] > 1 else ""
            progress.line(f"started {trial_id}{attempt}")
        for trial_id, outcome in backend.wait(0.5):
            entry = state.trials[trial_id]
            elapsed = time.monotonic() - started_at.pop(trial_id, time.monotonic())
            entry["elapsed_s"] = round(elapsed, 2)  # the attempt, start-up included
            if outcome.ok:
                ran += 1
                entry["status"] = "done"
                entry["result"] = outcome.result
                utility = final_utility(entry)
                score = f": mean utility {utility:.3f}" if utility is not None else ""
                progress.line(f"done {trial_id}{score} ({elapsed:.0f} s)")
            else:
                entry["errors"].append(f"attempt {entry['attempts']}: {outcome.error}")
                if entry["attempts"] <= retries:
                    entry["status"] = "pending"
                    queue.append(trial_id)
                    progress.line(
                        f"attempt {entry['attempts']} of {trial_id} failed, will "
                        f"retry: {outcome.error}"
                    )
                else:
                    entry["status"] = "failed"
                    progress.line(
                        f"FAILED {trial_id} after {entry['attempts']} attempts: {outcome.error}"
                    )
            state.save()
        progress.table(state, ids, started_at)
    return ran


def _payload(
    spec: SweepSpec, state: SweepState, trial_id: str, test_paths: dict[str, Path]
) -> dict[str, Any]:
    trial = spec.trial(trial_id)
    config = train_config(
        trial,
        test_paths[trial.params["test_set"]],
        state.trial_dir(trial_id),
        curve_scenarios=spec.curve_scenarios,
        final_eval=spec.final_eval,
    )
    extra = {name: str(test_paths[name]) for name in spec.extra_test_sets}
    return trial_payload(trial_id, config.to_dict(), extra, state.out_dir)


def _finish(
    state: SweepState,
    spec: SweepSpec,
    ids: list[str],
    ran: int,
    started: float,
    progress: Progress,
    backend: str | None,
) -> SweepSummary:
    progress.close()
    counts = state.counts(ids)
    best = best_trial(state.trials, ids)
    failed = tuple(i for i in ids if state.trials[i]["status"] == "failed")
    wall = time.monotonic() - started
    if backend is None and ran == 0:  # nothing ran: the backend that ran the trials stays
        with contextlib.suppress(OSError, ValueError, AttributeError):
            backend = json.loads((state.out_dir / SUMMARY_FILE).read_text()).get("backend")
    rows = []
    for trial_id in ids:
        entry = state.trials[trial_id]
        evaluation = (entry.get("result") or {}).get("evaluation") or {}
        rows.append(
            {
                "id": trial_id,
                "label": entry["label"],
                "params": entry["params"],
                "status": entry["status"],
                "attempts": entry["attempts"],
                "errors": entry["errors"],
                "mean_utility": final_utility(entry),
                "ratio_to_oracle": evaluation.get("ratio_to_oracle"),
                "wall_time_s": (entry.get("result") or {}).get("wall_time_s"),
                "elapsed_s": entry.get("elapsed_s"),
                "dir": entry["dir"],
            }
        )
    atomic_write_json(
        state.out_dir / SUMMARY_FILE,
        {
            "format": SUMMARY_FORMAT,
            "name": spec.name,
            "backend": backend,
            "counts": counts,
            "ran_this_time": ran,
            "wall_time_s": round(wall, 2),
            "best": {"id": best[0], "mean_utility": best[1]} if best else None,
            "trials": rows,
        },
    )
    progress.summary(rows, counts, best, wall)
    return SweepSummary(counts=counts, best=best, failed=failed, ran=ran, wall_time_s=wall)


class Progress:
    """Event lines and, on a terminal, the live table below them (see the module doc)."""

    def __init__(self, stream: TextIO, name: str, total: int) -> None:
        self.stream = stream
        self.name = name
        self.total = total
        self.backend = ""
        self.live = bool(getattr(stream, "isatty", lambda: False)())
        self._drawn = 0
        self._last_draw = 0.0
        self._started = time.monotonic()

    def _erase(self) -> None:
        if self._drawn:
            self.stream.write(f"\x1b[{self._drawn}F\x1b[J")
            self._drawn = 0

    def line(self, text: str) -> None:
        self._erase()
        stamp = time.strftime("%H:%M:%S")
        self.stream.write(f"[{stamp}] {text}\n")
        self.stream.flush()
        self._last_draw = 0.0

    def table(self, state: SweepState, ids: list[str], started_at: dict[str, float]) -> None:
        if not self.live or time.monotonic() - self._last_draw < _REDRAW_S:
            return
        self._erase()
        counts = state.counts(ids)
        elapsed = time.monotonic() - self._started
        lines = [
            f"sweep {self.name} ({self.backend}), {self.total} trials, {elapsed:.0f} s: "
            + ", ".join(f"{k} {v}" for k, v in counts.items()),
        ]
        best = best_trial(state.trials, ids)
        lines.append(
            f"  best so far: {best[0]}, mean utility {best[1]:.3f}" if best else "  best so far: -"
        )
        now = time.monotonic()
        for trial_id, since in sorted(started_at.items(), key=lambda kv: kv[1]):
            lines.append(f"  running {trial_id} ({now - since:.0f} s)")
        self.stream.write("\n".join(lines) + "\n")
        self.stream.flush()
        self._drawn = len(lines)
        self._last_draw = time.monotonic()

    def close(self) -> None:
        self._erase()
        self.stream.flush()

    def summary(
        self,
        rows: list[dict[str, Any]],
        counts: dict[str, int],
        best: tuple[str, float] | None,
        wall_s: float,
    ) -> None:
        out = self.stream
        width = max([len(r["id"]) for r in rows] + [5])
        out.write(f"{'trial':<{width}}  status   tries  mean utility  x oracle  train (s)\n")
        for r in rows:
            utility = f"{r['mean_utility']:.3f}" if r["mean_utility"] is not None else "-"
            ratio = f"{r['ratio_to_oracle']:.3f}" if r["ratio_to_oracle"] is not None else "-"
            wall = f"{r['wall_time_s']:.0f}" if r["wall_time_s"] is not None else "-"
            out.write(
                f"{r['id']:<{width}}  {r['status']:<7}  {r['attempts']:>5}  {utility:>12}  "
                f"{ratio:>8}  {wall:>9}\n"
            )
            if r["status"] == "failed":
                out.write(f"{'':<{width}}  last error: {r['errors'][-1]}\n")
        out.write(
            f"sweep {self.name}: {counts['done']} done, {counts['failed']} failed, "
            f"{counts['pending'] + counts['running']} not run, of {self.total}, in {wall_s:.0f} s"
        )
        out.write(f"; best {best[0]} ({best[1]:.3f})\n" if best else "\n")
        out.flush()
