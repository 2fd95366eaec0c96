"""Evaluate given UAV positions (case files) with the network model, as an ns-3 run would.

Each case is simulated from empty queues: a warm-up, then a measurement window whose per-user
throughput, mean delay and loss are reported (the protocol the ns-3 backend uses, so the two can
be compared case by case).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_json
from sim.config import NetworkConfig, Queueing, UtilityConfig
from sim.files import load_cases
from sim.network import NetworkModel
from sim.scenarios import Case
from sim.utility import network_utility

RESULTS_FORMAT = "tupa-case-results/1"


@dataclass(frozen=True)
class CaseMetrics:
    """Per-user metrics of one case over the measurement window, arrays (U,)."""

    id: str
    utility: float
    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "utility": self.utility,
            "users": [
                {"throughput_bps": float(t), "delay_s": float(d), "plr": float(p)}
                for t, d, p in zip(self.throughput_bps, self.delay_s, self.plr, strict=True)
            ],
        }


def evaluate_case(
    model: NetworkModel,
    case: Case,
    rng: np.random.Generator | None,
    warmup_s: float = 0.5,
    measure_s: float = 2.0,
    utility: UtilityConfig = UtilityConfig(),
) -> CaseMetrics:
    """Simulate one case: warm-up from empty queues, then measure (``rng=None``: expected mode)."""
    uav = case.uav_xyz_m[None, :]
    state = None
    if warmup_s > 0:
        state = model.step(uav, case.users_xy_m, case.load_bps, None, rng, warmup_s).state
    result = model.step(uav, case.users_xy_m, case.load_bps, state, rng, measure_s)
    value = network_utility(
        result.throughput_bps[0], result.delay_s[0], result.plr[0], case.load_bps, utility
    )
    return CaseMetrics(
        case.id, float(value), result.throughput_bps[0], result.delay_s[0], result.plr[0]
    )


def evaluate_cases_file(
    cases_path: Path,
    out_path: Path,
    seed: int | None,
    queueing: Queueing = "fq-codel",
    warmup_s: float = 0.5,
    measure_s: float = 2.0,
) -> str:
    """Evaluate every case of a ``tupa-cases/1`` file and write the results atomically.

    ``seed=None`` is the deterministic expected mode; otherwise case i draws its fading from
    ``SeedSequence(seed, spawn_key=(i,))``, so a case's result does not depend on the others.
    Returns a one-line summary.
    """
    area, cases = load_cases(cases_path)
    model = NetworkModel(NetworkConfig().with_queueing(queueing), area)
    results = []
    for i, case in enumerate(cases):
        rng = (
            None
            if seed is None
            else np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(i,)))
        )
        results.append(evaluate_case(model, case, rng, warmup_s, measure_s).to_dict())
    atomic_write_json(
        out_path,
        {
            "format": RESULTS_FORMAT,
            "source": str(cases_path),
            "mode": "expected" if seed is None else "stochastic",
            "seed": seed,
            "queueing": queueing,
            "warmup_s": warmup_s,
            "measure_s": measure_s,
            "cases": results,
        },
    )
    mean_utility = float(np.mean([r["utility"] for r in results]))
    return f"evaluated {len(results)} cases (mean utility {mean_utility:.3f}); wrote {out_path}"
