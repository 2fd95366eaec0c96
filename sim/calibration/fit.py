"""Fit the fast model's free constants to the ns-3 calibration set.

::

    .venv/bin/python -m sim.calibration.fit          # -> sim/calibration/fitted.json (~1 min)

Only the *fit* part of the calibration set is used (``cases.json`` minus its ``held_out``
list); the held-out part is evaluated once, after the search, with the constants found, and
reported beside the same figures for the hand-set constants the search starts from
(:data:`HAND_SET`, the first single-user values). Each candidate is a
:class:`~sim.config.NetworkConfig` passed to :class:`~sim.network.NetworkModel`, and
``fitted.json`` records the values so that :func:`fitted_config` can rebuild that
configuration. The model's defaults in
``sim/config.py`` are the fitted values; ``tests/sim/test_calibration_fit.py`` fails when the
two drift apart (refit → copy the ``config_fields`` of ``fitted.json`` into ``sim/config.py``).
``benchmarks/fidelity_ns3.py`` reports both sets of constants.

The free constants (:data:`FREE`) are the ones that stand for something the model abstracts
rather than a setting ns-3 was given; see docs/network-model.md for why each is free and why
the others are not. The search is a bounded coordinate search (numpy only, deterministic): each
round tries, for every constant in turn, a few values around the current one and keeps the best;
the step halves when a round improves nothing. Both queueing variants are fitted together: the
constants are the same in both.

The objective, over the fit cases of both variants, is

    mean_u min(rel_u, 1) + mean_{u congested} min(rel_u, 1) + W_UTILITY · mean_c |Δutility_c|

with ``rel_u = |fast − ns3| / max(ns3, 10 kbit/s)`` the per-user throughput error (capped at 1 so
a handful of stalled light users, which no constant can fix, does not steer the fit), congested
users those ns-3 shows losing more than 1 %, and ``Δutility`` the case utility error: the same
quantities the targets are set on, smoothed (means, not medians, so the search sees every user).
Constants under which a single user's throughput would rise with distance anywhere (a slower
MCS carrying more) are rejected (:func:`falls_monotonically`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_json
from sim.config import MacConfig, NetworkConfig, PhyConfig
from sim.evaluate import evaluate_case
from sim.files import load_cases
from sim.network import NetworkModel
from sim.scenarios import Case

HERE = Path(__file__).resolve().parent
CASES_PATH = HERE / "cases.json"
FITTED_PATH = HERE / "fitted.json"
FITTED_FORMAT = "tupa-fitted-constants/1"
VARIANTS = ("fq-codel", "mac-only")
THROUGHPUT_FLOOR_BPS = 1e4
CONGESTED_PLR = 0.01
W_UTILITY = 2.0


@dataclass(frozen=True)
class FreeConstant:
    """One constant the fit may move: its bounds, first search step and meaning."""

    name: str
    lo: float
    hi: float
    step: float
    integer: bool
    why: str


FREE: tuple[FreeConstant, ...] = (
    FreeConstant(
        "per_offset_db",
        -3.0,
        3.0,
        1.0,
        False,
        "added to every PhyConfig.per_mid_snr_db: the model's logistic subframe-error waterfall "
        "stands in for ns-3's TableBasedErrorRateModel (tabulated, per MCS, per frame size)",
    ),
    FreeConstant(
        "threshold_offset_db",
        -3.0,
        3.0,
        1.0,
        False,
        "added to every PhyConfig.ideal_threshold_db: where IdealWifiManager switches MCS "
        "follows from ns-3's error tables and its SNR estimate, which the model does not carry",
    ),
    FreeConstant(
        "per_slope_per_db",
        0.5,
        4.0,
        0.5,
        False,
        "PhyConfig.per_slope_per_db: steepness of the same waterfall",
    ),
    FreeConstant(
        "contention_cw_min",
        3,
        63,
        8,
        True,
        "MacConfig.contention_cw_min: the CWmin of the model's contention abstraction (mean idle "
        "backoff per TXOP = CWmin/(n + 1) slots, and Bianchi's saturated collision probability "
        "with CWmax 1023), which stands in for ns-3's slot-by-slot EDCA",
    ),
)
# The constants set by hand first (single-user checks against ns-3): the fit's start and
# the base its offsets apply to.
HAND_SET = NetworkConfig(
    phy=replace(
        PhyConfig(),
        ideal_threshold_db=(2.0, 5.0, 7.5, 11.0, 14.0, 18.5, 20.0, 21.5, 25.5),
        per_mid_snr_db=(-0.5, 2.5, 5.0, 8.5, 11.5, 16.0, 17.5, 19.0, 23.0),
        per_slope_per_db=2.0,
    ),
    mac=replace(MacConfig(), contention_cw_min=15),
)
HAND_SET_VALUES: dict[str, float] = {
    "per_offset_db": 0.0,
    "threshold_offset_db": 0.0,
    "per_slope_per_db": HAND_SET.phy.per_slope_per_db,
    "contention_cw_min": HAND_SET.mac.contention_cw_min,
}


def make_config(values: dict[str, float], base: NetworkConfig = HAND_SET) -> NetworkConfig:
    """``base`` (the hand-set constants) with the free constants set to ``values`` (missing:
    the hand-set values)."""
    v = {**HAND_SET_VALUES, **values}
    phy = replace(
        base.phy,
        per_mid_snr_db=tuple(float(x) + v["per_offset_db"] for x in base.phy.per_mid_snr_db),
        ideal_threshold_db=tuple(
            float(x) + v["threshold_offset_db"] for x in base.phy.ideal_threshold_db
        ),
        per_slope_per_db=float(v["per_slope_per_db"]),
    )
    mac = replace(base.mac, contention_cw_min=round(v["contention_cw_min"]))
    return replace(base, phy=phy, mac=mac)


def load_fitted(path: Path = FITTED_PATH) -> dict[str, Any]:
    """The committed fit (``fitted.json``)."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    if doc.get("format") != FITTED_FORMAT:
        raise ValueError(f"{path}: format must be {FITTED_FORMAT!r}")
    return doc


def fitted_config(path: Path = FITTED_PATH) -> NetworkConfig:
    """The configuration with the fitted constants of ``fitted.json`` (the committed one equals
    ``NetworkConfig()``)."""
    return make_config(load_fitted(path)["fitted"])


# --------------------------------------------------------------------------------------------
# Data and errors


@dataclass(frozen=True)
class Calibration:
    """The calibration cases, their split and the ns-3 results of both variants (seed means)."""

    cases: dict[str, Case]
    held_out: frozenset[str]
    groups: dict[str, list[str]]
    ns3: dict[str, dict[str, dict[str, Any]]]  # variant -> case id -> results entry

    def ids(self, part: str) -> list[str]:
        """Case ids of ``part``: "fit", "held_out" or "all", in file order."""
        if part == "all":
            return list(self.cases)
        keep = part == "held_out"
        return [i for i in self.cases if (i in self.held_out) == keep]


def load_calibration(directory: Path = HERE) -> Calibration:
    _, case_list = load_cases(directory / "cases.json")
    doc = json.loads((directory / "cases.json").read_text(encoding="utf-8"))
    ns3 = {}
    for variant in VARIANTS:
        results = json.loads((directory / f"ns3_{variant}.json").read_text(encoding="utf-8"))
        ns3[variant] = {c["id"]: c for c in results["cases"]}
    return Calibration(
        cases={c.id: c for c in case_list},
        held_out=frozenset(doc["held_out"]),
        groups=doc["groups"],
        ns3=ns3,
    )


def compare(
    calib: Calibration, config: NetworkConfig, variant: str, ids: list[str]
) -> dict[str, np.ndarray]:
    """Per-user and per-case arrays, fast model (expected mode) beside ns-3, over ``ids``."""
    model = NetworkModel(config.with_queueing(variant))
    ns3 = calib.ns3[variant]
    fast_t, ns3_t, ns3_plr, case_of_user, fast_u, ns3_u = [], [], [], [], [], []
    for c, case_id in enumerate(ids):
        f = evaluate_case(model, calib.cases[case_id], None)
        entry = ns3[case_id]
        fast_t.extend(f.throughput_bps)
        ns3_t.extend(u["throughput_bps"] for u in entry["users"])
        ns3_plr.extend(u["plr"] for u in entry["users"])
        case_of_user.extend([c] * len(entry["users"]))
        fast_u.append(f.utility)
        ns3_u.append(entry["utility"])
    fast_t_a, ns3_t_a = np.array(fast_t), np.array(ns3_t)
    return {
        "rel": np.abs(fast_t_a - ns3_t_a) / np.maximum(ns3_t_a, THROUGHPUT_FLOOR_BPS),
        "congested": np.array(ns3_plr) > CONGESTED_PLR,
        "utility_err": np.abs(np.array(fast_u) - np.array(ns3_u)),
        "fast_utility": np.array(fast_u),
        "ns3_utility": np.array(ns3_u),
    }


def objective_terms(arrays: dict[str, np.ndarray]) -> float:
    capped = np.minimum(arrays["rel"], 1.0)
    congested = capped[arrays["congested"]]
    return float(
        capped.mean()
        + (congested.mean() if congested.size else 0.0)
        + W_UTILITY * arrays["utility_err"].mean()
    )


def placement_agreement(calib: Calibration, config: NetworkConfig, variant: str, part: str):
    """Mean over the groups of ``part`` of ns-3 utility at the fast model's pick / ns-3 best."""
    ratios = []
    for ids in calib.groups.values():
        if (ids[0] in calib.held_out) != (part == "held_out") and part != "all":
            continue
        arrays = compare(calib, config, variant, ids)
        pick = int(np.argmax(arrays["fast_utility"]))
        ratios.append(arrays["ns3_utility"][pick] / arrays["ns3_utility"].max())
    return round(float(np.mean(ratios)), 4) if ratios else None


def figures(calib: Calibration, config: NetworkConfig, part: str) -> dict[str, Any]:
    """The target figures on ``part`` for both variants (definitions: fidelity benchmark)."""
    out: dict[str, Any] = {}
    for variant in VARIANTS:
        a = compare(calib, config, variant, calib.ids(part))
        rel, congested = a["rel"], a["congested"]
        out[variant] = {
            "n_cases": int(a["utility_err"].size),
            "n_users": int(rel.size),
            "throughput_rel_error_median": round(float(np.median(rel)), 4),
            "throughput_rel_error_p90": round(float(np.percentile(rel, 90)), 4),
            "congested_throughput_rel_error_median": (
                round(float(np.median(rel[congested])), 4) if congested.any() else None
            ),
            "utility_abs_error_median": round(float(np.median(a["utility_err"])), 4),
            "placement_agreement_mean": placement_agreement(calib, config, variant, part),
            "objective": round(objective_terms(a), 4),
        }
    return out


# --------------------------------------------------------------------------------------------
# Search


def falls_monotonically(config: NetworkConfig) -> bool:
    """Whether one user offering 40 Mbit/s gets less, never more, the farther it is (1-700 m
    horizontally, 1 m apart, UAV at 25 and 100 m): the constraint the hand-set constants of
    the first model met (tests/sim/test_network.py). Constants that break it make the rate manager
    switch to a slower MCS that carries more, which neither ns-3's curve nor placement wants."""
    model = NetworkModel(config)
    distance_m = np.arange(1.0, 701.0)
    for z_m in (25.0, 100.0):
        uav = np.stack([distance_m, np.zeros_like(distance_m), np.full_like(distance_m, z_m)], 1)
        step = model.step(uav, np.zeros((1, 2)), np.array([40e6]), step_s=2.0)
        if np.any(np.diff(step.throughput_bps[:, 0]) > 1e-6 * 40e6):
            return False
    return True


def objective(calib: Calibration, values: dict[str, float], ids: list[str]) -> float:
    """The fit objective (module docstring), summed over both queueing variants; infinite for
    constants under which throughput does not fall monotonically with distance."""
    config = make_config(values)
    if not falls_monotonically(config):
        return float("inf")
    return sum(objective_terms(compare(calib, config, v, ids)) for v in VARIANTS)


def _clip(constant: FreeConstant, value: float) -> float:
    value = min(max(value, constant.lo), constant.hi)
    return float(round(value)) if constant.integer else round(value, 3)


def _min_step(constant: FreeConstant, fraction: float) -> float:
    return 1.0 if constant.integer else constant.step * fraction


def coordinate_search(
    calib: Calibration,
    start: dict[str, float],
    ids: list[str],
    rounds: int = 20,
    min_step_fraction: float = 1 / 8,
    log=print,
) -> tuple[dict[str, float], float, list[dict[str, Any]]]:
    """Bounded coordinate search from ``start``; returns (best values, objective, history)."""
    best = dict(start)
    cache: dict[tuple, float] = {}

    def f(values: dict[str, float]) -> float:
        key = tuple(values[c.name] for c in FREE)
        if key not in cache:
            cache[key] = objective(calib, values, ids)
        return cache[key]

    best_f = f(best)
    steps = {c.name: c.step for c in FREE}
    history = [{"round": 0, "objective": round(best_f, 5), "values": dict(best)}]
    log(f"start: objective {best_f:.4f} {best}")
    for r in range(1, rounds + 1):
        improved = False
        for c in FREE:
            for mult in (-2, -1, 1, 2):
                trial = dict(best)
                trial[c.name] = _clip(c, best[c.name] + mult * steps[c.name])
                if trial[c.name] == best[c.name]:
                    continue
                value = f(trial)
                if value < best_f - 1e-6:
                    best, best_f, improved = trial, value, True
        history.append({"round": r, "objective": round(best_f, 5), "values": dict(best)})
        log(f"round {r}: objective {best_f:.4f} {best} ({len(cache)} evaluations)")
        if not improved:
            if all(steps[c.name] <= _min_step(c, min_step_fraction) for c in FREE):
                break
            for c in FREE:
                steps[c.name] = max(steps[c.name] / 2, _min_step(c, min_step_fraction))
    return best, best_f, history


def run_fit(
    path: Path = FITTED_PATH,
    rounds: int = 20,
    log=print,
    calib: Calibration | None = None,
    start: str = "hand-set",
) -> dict[str, Any]:
    """Fit on the fit cases, score both parts, write ``path``; returns the document.

    ``start``: ``hand-set`` (the first hand-set constants) or ``fitted`` (the values in
    ``path`` now).
    ``rounds=0`` with ``start="fitted"`` keeps the constants and only re-scores them, which is
    what a model change that leaves the constants alone needs (the error figures move).
    """
    if start not in ("hand-set", "fitted"):
        raise ValueError(f"start: must be hand-set or fitted, got {start!r}")
    if rounds < 0:
        raise ValueError(f"rounds: must be >= 0, got {rounds}")
    started = time.perf_counter()
    calib = calib or load_calibration()
    fit_ids = calib.ids("fit")
    previous = load_fitted(path) if start == "fitted" else None
    first = HAND_SET_VALUES if previous is None else dict(previous["fitted"])
    values, value, history = coordinate_search(calib, first, fit_ids, rounds, log=log)
    config = make_config(values)
    if rounds > 0:
        how = f"searched from the {start} constants"
    elif start == "fitted":
        how = "found by the search in earlier_history and re-scored under the current model"
    else:
        how = "the hand-set constants, scored, not searched"
    doc = {
        "format": FITTED_FORMAT,
        "description": "fast-model constants fitted to the fit part of the ns-3 calibration "
        f"set (sim/calibration/fit.py), {how}; the model's defaults in sim/config.py are "
        "these values",
        "start": {"from": start, "values": first, "rounds": rounds},
        "fit_cases": len(fit_ids),
        "held_out_cases": len(calib.ids("held_out")),
        "objective": {
            "definition": "sum over both variants of mean_u min(rel_u, 1) + mean over congested "
            f"users of min(rel_u, 1) + {W_UTILITY} * mean case |utility error|, fit cases only",
            "hand_set": round(objective(calib, HAND_SET_VALUES, fit_ids), 5),
            "fitted": round(value, 5),
        },
        "free_constants": {
            c.name: {"lo": c.lo, "hi": c.hi, "hand_set": HAND_SET_VALUES[c.name], "why": c.why}
            for c in FREE
        },
        "fitted": values,
        "config_fields": {
            "phy.per_mid_snr_db": list(config.phy.per_mid_snr_db),
            "phy.ideal_threshold_db": list(config.phy.ideal_threshold_db),
            "phy.per_slope_per_db": config.phy.per_slope_per_db,
            "mac.contention_cw_min": config.mac.contention_cw_min,
            "mac.cw_max": config.mac.cw_max,
        },
        "errors": {
            part: {
                "hand_set": figures(calib, HAND_SET, part),
                "fitted": figures(calib, config, part),
            }
            for part in ("fit", "held_out")
        },
        "history": history,
        # How the starting values were found, when they come from earlier fits.
        "earlier_history": None if previous is None else _searches(previous),
        "wall_s": 0.0,
    }
    doc["wall_s"] = round(time.perf_counter() - started, 1)
    atomic_write_json(path, doc)
    log(f"wrote {path} in {doc['wall_s']} s")
    return doc


def _searches(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """The search rounds behind a fit document: its earlier ones, then its own unless it only
    re-scored (``rounds`` 0)."""
    earlier = list(doc.get("earlier_history") or [])
    own = [] if doc.get("start", {}).get("rounds") == 0 else list(doc.get("history", []))
    return earlier + own


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--out", type=Path, default=FITTED_PATH)
    parser.add_argument("--rounds", type=int, default=20, help="0: re-score only")
    parser.add_argument(
        "--start",
        choices=("hand-set", "fitted"),
        default="hand-set",
        help="where the search starts: the first hand-set constants, or the values in --out now",
    )
    args = parser.parse_args(argv)
    if args.rounds < 0:
        parser.error(f"--rounds: must be >= 0, got {args.rounds}")
    doc = run_fit(args.out, args.rounds, start=args.start)
    for part, by_config in doc["errors"].items():
        for name, by_variant in by_config.items():
            for variant, f in by_variant.items():
                print(f"{part:8s} {name:7s} {variant:8s} {f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
