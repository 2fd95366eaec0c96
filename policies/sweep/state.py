"""``OUT/sweep.json`` (format ``tupa-sweep-state/1``): every trial's status, written atomically
after every change, so that an interrupted sweep (Ctrl-C, a dead worker, a lost node, a killed
driver) resumes where it stopped.

::

    {"format": "tupa-sweep-state/1", "name": "smoke", "spec_file": "sweeps/smoke.yaml",
     "test_sets": {"small": "test_sets/small-1c2d3e4f.json"},
     "trials": {"ddqn-spec-e8-s1-3f9a2c1b": {
         "params": {...}, "label": "ddqn-spec", "dir": "trials/ddqn-spec-e8-s1-3f9a2c1b",
         "status": "done", "attempts": 1, "errors": [], "worker": "pid 4242 on host",
         "result": {"evaluation": {...}, "episodes": 8, "timesteps": 240,
                    "wall_time_s": 3.1, "extra": {}}}}}

Statuses: ``pending`` (never run, or interrupted), ``running``, ``done``, ``failed`` (every
attempt failed: ``errors`` holds one line per attempt). A state read back with ``running``
trials comes from an interrupted sweep: they become ``pending`` again and rerun from scratch
(the trial directory is cleared first), so a trial's result never depends on when the sweep was
interrupted. Trials of an earlier version of the sweep file (ids no longer in the grid) are
kept as they are and left out of this run's counts.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from policies.sweep.spec import SweepSpec
from sim.atomic import atomic_write_json
from sim.errors import InputError

STATE_FORMAT = "tupa-sweep-state/1"
STATE_FILE = "sweep.json"
SUMMARY_FILE = "summary.json"
TRIALS_DIR = "trials"
STATUSES: tuple[str, ...] = ("pending", "running", "done", "failed")


@dataclass
class SweepState:
    """The state file in memory; :meth:`save` writes it (atomically)."""

    out_dir: Path
    document: dict[str, Any] = field(default_factory=dict)

    @property
    def trials(self) -> dict[str, dict[str, Any]]:
        return self.document["trials"]

    @classmethod
    def open(cls, out_dir: Path, spec: SweepSpec, test_sets: dict[str, Path]) -> SweepState:
        """The state in ``out_dir`` (read back, interrupted trials made pending) with every
        trial of ``spec`` in it, new ones pending; nothing is written until :meth:`save`.
        Retry budgets are per run of the command: a failed trial gets its attempts again."""
        path = Path(out_dir) / STATE_FILE
        document = read_state(out_dir) if path.exists() else None
        if document is None:
            document = {"format": STATE_FORMAT, "created": _now(), "trials": {}}
        document.update(
            {
                "name": spec.name,
                "spec_file": str(spec.path),
                "spec": json.loads(json.dumps(spec.raw, default=str)),
                "test_sets": {name: _relative(p, Path(out_dir)) for name, p in test_sets.items()},
            }
        )
        trials = document["trials"]
        for trial in spec.trials:
            entry = trials.get(trial.id)
            if entry is None:
                trials[trial.id] = {
                    "params": trial.params,
                    "label": trial.label,
                    "dir": f"{TRIALS_DIR}/{trial.id}",
                    "status": "pending",
                    "attempts": 0,
                    "errors": [],
                    "result": None,
                }
            elif entry["status"] in ("running", "failed"):
                entry["status"] = "pending"
                entry["attempts"] = 0
        return cls(out_dir=Path(out_dir), document=document)

    def save(self) -> None:
        self.document["updated"] = _now()
        atomic_write_json(self.out_dir / STATE_FILE, self.document)

    def counts(self, ids: list[str]) -> dict[str, int]:
        """How many of ``ids`` are in each status."""
        counts = dict.fromkeys(STATUSES, 0)
        for trial_id in ids:
            counts[self.trials[trial_id]["status"]] += 1
        return counts

    def trial_dir(self, trial_id: str) -> Path:
        return self.out_dir / self.trials[trial_id]["dir"]


def read_state(out_dir: Path) -> dict[str, Any]:
    """The state document of the sweep in ``out_dir`` (``InputError`` if it is not one)."""
    path = Path(out_dir) / STATE_FILE
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{out_dir}: not a sweep directory ({STATE_FILE} missing)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the sweep state: {exc}") from None
    if not isinstance(document, dict) or document.get("format") != STATE_FORMAT:
        raise InputError(f"{path}: format: expected {STATE_FORMAT!r}")
    if not isinstance(document.get("trials"), dict):
        raise InputError(f"{path}: trials: must be an object")
    return document


def is_sweep_dir(path: Path) -> bool:
    """Whether ``path`` holds a sweep (its state file)."""
    return (Path(path) / STATE_FILE).is_file()


def best_trial(trials: dict[str, dict[str, Any]], ids: list[str]) -> tuple[str, float] | None:
    """The finished trial among ``ids`` with the highest final mean utility, and that utility."""
    best = None
    for trial_id in ids:
        utility = final_utility(trials[trial_id])
        if utility is not None and (best is None or utility > best[1]):
            best = (trial_id, utility)
    return best


def final_utility(entry: dict[str, Any]) -> float | None:
    """A finished trial's mean utility on its test set (its final evaluation), if any."""
    evaluation = (entry.get("result") or {}).get("evaluation")
    if entry.get("status") != "done" or not evaluation:
        return None
    return float(evaluation["policy"]["mean_utility"])


def _relative(path: Path, root: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(root.resolve()))
    except ValueError:
        return str(Path(path).resolve())


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
