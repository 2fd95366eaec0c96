"""Build the ns-3 calibration set and run it through ns-3 (issue 3).

Two steps, both deterministic::

    python -m sim.calibration.build cases          # -> sim/calibration/cases.json
    nice -n 19 python -m sim.calibration.build run # -> sim/calibration/ns3_*.json (ns-3 needed)

``cases`` writes a ``tupa-cases/1`` file of 114 cases in five families, with extra top-level
keys (ignored by ``load_cases``) that say what each case is for:

* ``single-*`` (16): one user, the UAV in the area's corner, 50–700 m horizontal distance,
  altitudes 25–100 m, 5–40 Mbit/s: the rate ladder and the saturated single link.
* ``p3-*`` (24): the paper's setting, 3 users from :func:`sim.scenarios.generate_scenarios`
  (Λ = 40 Mbit/s), each at three UAV positions (users' centroid, load-weighted centroid,
  a random grid point).
* ``many-*`` (30): 5, 8, 12, 16 and 20 users with Λ = 10, 20 and 40 Mbit/s (unsaturated to
  saturated), at the centroid and at a random grid point: contention and collisions.
* ``light-*`` (8): one light user (0.5–2 Mbit/s) beside backlogged ones, near and far: the case
  where ns-3 loses a light user's packets while its delay stays low.
* ``grp*-c*`` (6 groups × 6 candidates = 36): one scenario (3–20 users) at six candidate UAV
  positions each, for placement agreement (does the fast model pick the position ns-3 rates
  best?).

``held_out`` lists the cases kept out of any fit: every 4th case of the first four families and
every case of the odd groups (grp1, grp3, grp5). ``long_runs`` lists six cases also simulated
for 10 s (1 s intervals), to show how FqCoDel delays grow.

``run`` simulates every case with both queueing variants and ``--seeds`` seeds (ns-3 varies by
±10 % from seed to seed on overloaded cases), seed-major so an interrupted run still has every
case once, then the long runs. Results are rewritten atomically after every case and a rerun
skips what is already there: a crash loses one case at most. Output per variant,
``ns3_<queueing>.json``: the ``tupa sim evaluate`` format (``tupa-case-results/1``) whose
``users`` are the means over seeds (throughput, delay, loss) and ``utility`` the mean of the
per-seed utilities, with ``backend``, ``ns3_version``, the ns-3 settings, ``per_seed`` results
and a few ns-3 counters per user (drops by cause, PPDUs, MCS, backoffs; see
:data:`sim.ns3_worker.FIELDS`). ``ns3_long_<queueing>.json`` holds the 10 s runs.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim.config import AreaConfig
from sim.files import atomic_write_json, cases_document, load_cases
from sim.scenarios import Case, generate_scenarios

HERE = Path(__file__).resolve().parent
CASES_PATH = HERE / "cases.json"
AREA = AreaConfig()
MBPS = 1e6

# ns-3 counters kept per user in the committed results (window differences or end levels).
KEPT_DETAIL = (
    "tx_pkts",
    "rx_pkts",
    "drop_qdisc",
    "drop_mac_expired",
    "drop_mac_retry_limit",
    "drop_mac_old_packet",
    "drop_tc",
    "drop_mac_tx",
    "drop_arp",
    "data_ppdus",
    "data_mpdus",
    "mcs_mpdu_sum",
    "response_timeouts",
    "ap_rx_ppdu_drops",
    "backoff_draws",
    "backoff_slots_sum",
    "backoff_long_draws",
    "expired_unsent",
    "max_tx_gap_s",
    "backlog_qdisc_pkts",
    "backlog_mac_pkts",
)


# --------------------------------------------------------------------------------------------
# Cases


def _grid_point(rng: np.random.Generator) -> np.ndarray:
    """A random zone centre at a random altitude level."""
    return AREA.grid_positions_m()[rng.integers(len(AREA.grid_positions_m()))]


def _centroid(xy_m: np.ndarray, weights: np.ndarray | None, z_m: float) -> np.ndarray:
    w = np.ones(len(xy_m)) if weights is None else weights
    centre = (xy_m * w[:, None]).sum(axis=0) / w.sum()
    return np.array([centre[0], centre[1], z_m])


def make_cases() -> tuple[list[Case], dict[str, Any]]:
    """The calibration cases and the metadata (families, held-out split, groups, long runs)."""
    rng = np.random.default_rng(20250301)
    cases: list[Case] = []
    family: dict[str, str] = {}

    def add(case: Case, kind: str) -> None:
        cases.append(case)
        family[case.id] = kind

    # single: (horizontal distance m, altitude m, load Mbit/s), UAV in the south-west corner.
    singles = [
        (50, 25, 40), (200, 25, 40), (300, 25, 40), (450, 25, 40), (550, 25, 40), (650, 25, 40),
        (700, 25, 40), (200, 100, 40), (450, 100, 40), (650, 100, 40), (300, 50, 40),
        (450, 75, 40), (450, 25, 10), (650, 25, 10), (650, 75, 20), (100, 50, 5),
    ]  # fmt: skip
    for d_m, z_m, load in singles:
        xy = np.array([[d_m / math.sqrt(2.0), d_m / math.sqrt(2.0)]])
        add(Case(f"single-d{d_m}-z{z_m}-L{load}", [0.0, 0.0, z_m], xy, [load * MBPS]), "single")

    # p3: the paper's 3-user scenarios.
    for s in generate_scenarios(8, 3, seed=31, area=AREA):
        positions = {
            "centroid": _centroid(s.users_xy_m, None, 25.0),
            "loadw": _centroid(s.users_xy_m, s.load_bps, 50.0),
            "random": _grid_point(rng),
        }
        for name, uav in positions.items():
            add(Case(f"p3-{s.id}-{name}", uav, s.users_xy_m, s.load_bps), "p3")

    # many: contention with 5-20 users, unsaturated to saturated.
    for n_users in (5, 8, 12, 16, 20):
        for total_mbps in (10, 20, 40):
            (s,) = generate_scenarios(
                1, n_users, seed=1000 + 10 * n_users + total_mbps, total_load_bps=total_mbps * MBPS
            )
            base = f"many-u{n_users}-L{total_mbps}"
            add(Case(f"{base}-centroid", _centroid(s.users_xy_m, None, 25.0), s.users_xy_m,
                     s.load_bps), "many")  # fmt: skip
            add(Case(f"{base}-random", _grid_point(rng), s.users_xy_m, s.load_bps), "many")

    # light: one light user beside backlogged ones.
    centre = [250.0, 250.0, 25.0]
    lights = {
        "light-far-2far": ([[0, 0], [500, 500], [0, 500]], [2, 19, 19]),
        "light-far-2near": ([[0, 0], [250, 260], [260, 250]], [2, 19, 19]),
        "light-mid-2far": ([[250, 100], [500, 500], [0, 500]], [2, 19, 19]),
        "light-near-2far": ([[255, 250], [480, 480], [20, 480]], [1, 19.5, 19.5]),
        "light-far-4mid": ([[10, 10], [400, 250], [100, 250], [250, 400], [250, 100]],
                           [0.5, 9.875, 9.875, 9.875, 9.875]),
        "light-near-4far": ([[240, 240], [480, 250], [20, 250], [250, 480], [250, 20]],
                            [1, 9.75, 9.75, 9.75, 9.75]),
        "light-two-3far": ([[200, 200], [300, 300], [490, 10], [10, 490], [490, 490]],
                           [1, 1, 12.67, 12.67, 12.66]),
        "light-far-unsat": ([[0, 0], [500, 500], [0, 500]], [2, 9, 9]),
    }  # fmt: skip
    for name, (xy, loads) in lights.items():
        add(Case(name, centre, np.array(xy, float), np.array(loads) * MBPS), "light")

    # groups: one scenario, six candidate UAV positions.
    groups: dict[str, list[str]] = {}
    for g, (n_users, total_mbps) in enumerate([(3, 40), (3, 40), (3, 20), (6, 40), (10, 40),
                                               (20, 40)]):  # fmt: skip
        (s,) = generate_scenarios(1, n_users, seed=2000 + g, total_load_bps=total_mbps * MBPS)
        heavy = s.users_xy_m[int(np.argmax(s.load_bps))]
        candidates = [
            _centroid(s.users_xy_m, None, 25.0),
            _centroid(s.users_xy_m, s.load_bps, 25.0),
            np.array([heavy[0], heavy[1], 25.0]),
            np.array([250.0, 250.0, 25.0]),
            np.array([250.0, 250.0, 100.0]),
            _grid_point(rng),
        ]
        ids = []
        for c, uav in enumerate(candidates):
            case_id = f"grp{g}-c{c}"
            add(Case(case_id, uav, s.users_xy_m, s.load_bps), "group")
            ids.append(case_id)
        groups[f"grp{g}"] = ids

    individual = [c.id for c in cases if family[c.id] != "group"]
    held_out = [case_id for i, case_id in enumerate(individual) if i % 4 == 3]
    held_out += [case_id for g, ids in groups.items() if int(g[3:]) % 2 == 1 for case_id in ids]
    meta = {
        "description": "ns-3 calibration set (issue 3); see sim/calibration/build.py",
        "family": family,
        "held_out": held_out,
        "groups": groups,
        "long_runs": [
            "single-d450-z25-L40",
            "p3-s0002-centroid",
            "many-u12-L40-centroid",
            "many-u20-L40-centroid",
            "light-far-2far",
            "many-u8-L20-centroid",
        ],
    }
    return cases, meta


def write_cases(path: Path = CASES_PATH) -> None:
    cases, meta = make_cases()
    doc = cases_document(AREA, cases)
    doc.update(meta)
    atomic_write_json(path, doc)
    load_cases(path)  # validates
    print(f"wrote {len(cases)} cases ({len(meta['held_out'])} held out) to {path}")


def load_meta(path: Path = CASES_PATH) -> dict[str, Any]:
    """The extra top-level keys of the calibration case file (family, held_out, groups ...)."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    return {k: v for k, v in doc.items() if k not in ("format", "area", "cases")}


# --------------------------------------------------------------------------------------------
# Running ns-3


def _mean_entry(case_id: str, per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over seeds of each user's metrics; utility: the mean of the per-seed utilities."""
    n_users = len(per_seed[0]["users"])
    users = []
    for u in range(n_users):
        users.append(
            {
                key: float(np.mean([s["users"][u][key] for s in per_seed]))
                for key in ("throughput_bps", "delay_s", "plr")
            }
        )
    return {
        "id": case_id,
        "utility": float(np.mean([s["utility"] for s in per_seed])),
        "users": users,
        "wall_s": float(np.mean([s["wall_s"] for s in per_seed])),
        "per_seed": per_seed,
    }


def _round(value: Any) -> Any:
    """Floats to 6 significant digits, recursively (keeps the committed files small)."""
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, dict):
        return {k: _round(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_round(v) for v in value]
    return value


def _compact(result_dict: dict[str, Any], seed: int) -> dict[str, Any]:
    out = {
        "seed": seed,
        "utility": result_dict["utility"],
        "wall_s": result_dict["wall_s"],
        "association_max_s": max(result_dict["association_s"]),
    }
    out["users"] = [
        {
            "throughput_bps": user["throughput_bps"],
            "delay_s": user["delay_s"],
            "plr": user["plr"],
            "ns3": {k: v for k, v in user.get("ns3", {}).items() if k in KEPT_DETAIL},
        }
        for user in result_dict["users"]
    ]
    if "intervals" in result_dict:
        out["intervals"] = result_dict["intervals"]
    return _round(out)


def run_variant(
    out_path: Path,
    cases: list[Case],
    indices: list[int],
    settings_kwargs: dict[str, Any],
    seeds: list[int],
    niceness: int,
    deadline: float,
) -> None:
    """Simulate ``cases`` for every seed, rewriting ``out_path`` after each case (resumable)."""
    from sim.ns3_backend import Ns3CaseError, Ns3Runner, Ns3Settings

    doc: dict[str, Any] = {}
    if out_path.exists():
        doc = json.loads(out_path.read_text(encoding="utf-8"))
    done: dict[str, dict[int, dict[str, Any]]] = {}
    for entry in doc.get("cases", []):
        done[entry["id"]] = {s["seed"]: s for s in entry["per_seed"]}
    failed: list[dict[str, str]] = doc.get("failed", [])
    base = Ns3Settings(**settings_kwargs)
    with Ns3Runner(niceness=niceness) as runner:
        for seed in seeds:
            settings = Ns3Settings(**{**settings_kwargs, "seed": seed})
            for case, index in zip(cases, indices, strict=True):
                if seed in done.get(case.id, {}):
                    continue
                if time.monotonic() > deadline:
                    print("time budget spent; stopping (rerun to resume)", flush=True)
                    return
                started = time.perf_counter()
                try:
                    result = runner.run(case, settings, index)
                except Ns3CaseError as exc:
                    failed.append({"id": case.id, "seed": str(seed), "error": exc.reason})
                    print(f"  FAILED {exc}", flush=True)
                    continue
                done.setdefault(case.id, {})[seed] = _compact(result.to_dict(), seed)
                print(
                    f"  {out_path.name} seed {seed} {case.id}: utility "
                    f"{result.metrics.utility:.3f}, {time.perf_counter() - started:.1f} s",
                    flush=True,
                )
                entries = [
                    _mean_entry(c.id, [done[c.id][s] for s in sorted(done[c.id])])
                    for c in cases
                    if c.id in done
                ]
                seeds_done = sorted({s for per_case in done.values() for s in per_case})
                atomic_write_json(
                    out_path,
                    {
                        "format": "tupa-case-results/1",
                        "source": str(CASES_PATH.relative_to(HERE.parent.parent)),
                        "backend": "ns3",
                        "ns3_version": runner.version,
                        "mode": "stochastic",
                        "seed": seeds_done[0],
                        "seeds": seeds_done,
                        "queueing": base.queueing,
                        "warmup_s": base.warmup_s,
                        "measure_s": base.measure_s,
                        "ns3": {k: v for k, v in base.to_dict().items() if k != "seed"},
                        "cases": entries,
                        "failed": failed,
                    },
                )


def run_all(seeds: list[int], niceness: int, budget_s: float) -> None:
    _, cases = load_cases(CASES_PATH)
    meta = load_meta()
    indices = list(range(len(cases)))
    deadline = time.monotonic() + budget_s
    started = time.perf_counter()
    # Seed-major across both variants: every case once before any case twice.
    for seed in seeds:
        for queueing in ("fq-codel", "mac-only"):
            print(f"{queueing}, seed {seed}", flush=True)
            run_variant(
                HERE / f"ns3_{queueing}.json",
                cases,
                indices,
                {"queueing": queueing},
                [seed],
                niceness,
                deadline,
            )
    by_id = {c.id: (i, c) for i, c in enumerate(cases)}
    long_cases = [by_id[i][1] for i in meta["long_runs"]]
    long_indices = [by_id[i][0] for i in meta["long_runs"]]
    for queueing in ("fq-codel", "mac-only"):
        print(f"long runs, {queueing}", flush=True)
        run_variant(
            HERE / f"ns3_long_{queueing}.json",
            long_cases,
            long_indices,
            {"queueing": queueing, "measure_s": 10.0, "interval_s": 1.0},
            [seeds[0]],
            niceness,
            deadline,
        )
    print(f"done in {time.perf_counter() - started:.0f} s", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("cases", help="write sim/calibration/cases.json")
    run = sub.add_parser("run", help="simulate the cases in ns-3 (resumable)")
    run.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    run.add_argument("--nice", type=int, default=19, help="worker niceness (default 19)")
    run.add_argument("--budget-s", type=float, default=40 * 60, help="stop after this long")
    args = parser.parse_args(argv)
    if args.command == "cases":
        write_cases()
    else:
        run_all(args.seeds, args.nice, args.budget_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
