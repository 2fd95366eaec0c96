"""How faithful is the fleet model (K access points) to ns-3? Issue 16, item 2.

Three steps, all deterministic::

    .venv/bin/python benchmarks/fidelity_fleet_ns3.py cases   # sim/calibration/cases_fleet.json
    nice -n 10 .venv/bin/python benchmarks/fidelity_fleet_ns3.py run  # ns-3 (needs it)
    .venv/bin/python benchmarks/fidelity_fleet_ns3.py report  # benchmarks/results/...json

``cases`` writes 2–4-AP cases (open environment, the single-AP calibration's protocol) in
groups of 3 candidate fleet placements of one user layout each:

* ``split2``: two clusters of 4 users, 10 Mbit/s each, one AP per cluster;
* ``heavy2``: a heavy cell (6 users × 15 Mbit/s, saturated) beside a light one (2 × 3 Mbit/s);
* ``near2``: one hot spot of 8 users × 8 Mbit/s and two APs 20–120 m apart over it (on a
  shared channel the two cells are one contention domain);
* ``far2``: two clusters in opposite corners, APs ~600 m apart: beyond carrier sense
  (−82 dBm) in the fast model, so on a shared channel it adds the other cell as interference;
* ``tri3``: three clusters of 3 users, 12 Mbit/s each, K = 3;
* ``quad4``: four clusters of 3 users, 8 Mbit/s each, K = 4.

Each layout has two seeds (two groups); candidates are the APs over each cluster's centroid at
25 m, the same at 75 m, and the APs pulled half-way towards the area's centre at 50 m (for
``near2``: 20, 60 and 120 m between the APs). Every user is a station of the AP the fast model
associates it with (:class:`sim.fleet.FleetModel`: the strongest, from no association; stored
in the file and passed to ns-3 explicitly, so both backends compare the same cells). Held out:
the second seed of every layout; nothing is fitted on either part (the single-AP constants
are not refitted), the split only keeps the fleet set shaped like the single-AP one.

``run`` simulates every case in ns-3 (:meth:`sim.ns3_backend.Ns3Runner.run_fleet`) in both
channel modes (``distinct``: channels 36, 40, …; ``shared``: all on 36) and both queueing
variants, seeds 0 and 1, 0.5 s warm-up and 2 s measured after 1 s of association, and writes
``sim/calibration/ns3_fleet_<mode>_<queueing>.json`` (per seed: per-user throughput, delay,
loss, the utility).

``report`` runs the fast fleet model on the same cases in expected mode (``rng=None``; 0.5 s
warm-up from empty queues, then 2 s measured with the state carried over, as
:func:`sim.evaluate.evaluate_case` does for one AP) and writes, per channel mode × queueing,
on the held-out cases and on all: per-user throughput relative error ``|fast − ns3| / ns3``
(ns-3's mean over seeds, floored at 10 kbit/s) median and p90, for all users and for the
congested ones (ns-3 loss > 1 %); the utility's absolute error; placement agreement (per
group: ns-3's utility at the placement the fast model ranks best over ns-3's best); per cell
(AP) the aggregate throughput ratio fast / ns-3; per layout family the same figures; and
ns-3's own seed-to-seed spread (the noise floor: seed 0 against seed 1, the same figures).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim.association import received_power_dbm
from sim.atomic import atomic_write_json
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.fleet import CHANNEL_MODES, FleetConfig, FleetModel
from sim.utility import network_utility

ROOT = Path(__file__).resolve().parent.parent

CALIBRATION = ROOT / "sim" / "calibration"
CASES_PATH = CALIBRATION / "cases_fleet.json"
RESULTS = ROOT / "benchmarks" / "results" / "fidelity_fleet_ns3.json"
CASES_FORMAT = "tupa-fleet-cases/1"
NS3_FORMAT = "tupa-fleet-ns3-results/1"
QUEUEINGS = ("fq-codel", "mac-only")
SEEDS = (0, 1)
WARMUP_S = 0.5
MEASURE_S = 2.0
THROUGHPUT_FLOOR_BPS = 1e4
CONGESTED_PLR = 0.01
LAYOUT_SEEDS = (0, 1)  # seed 1 of every layout is held out


def ns3_path(mode: str, queueing: str) -> Path:
    return CALIBRATION / f"ns3_fleet_{mode}_{queueing}.json"


# --------------------------------------------------------------------------------- the cases
def _cluster(rng: np.random.Generator, centre: tuple[float, float], n: int, spread_m: float):
    xy = np.asarray(centre) + rng.normal(0.0, spread_m, size=(n, 2))
    return np.clip(xy, 0.0, 500.0)


def _layouts(seed: int) -> list[dict[str, Any]]:
    """The user layouts of one seed: family, clusters (users, loads) and candidate fleets."""
    rng = np.random.default_rng(1600 + seed)
    jitter = rng.uniform(-30.0, 30.0, size=(8, 2))
    out = []

    def clusters(centres, sizes, loads, spread):
        xy = [_cluster(rng, c, n, spread) for c, n in zip(centres, sizes, strict=True)]
        load = [np.full(n, lo) for n, lo in zip(sizes, loads, strict=True)]
        return xy, load

    def standard(xy_list, z_levels=(25.0, 75.0)):
        centroids = [xy.mean(axis=0) for xy in xy_list]
        cands = [[[*c, z] for c in centroids] for z in z_levels]
        cands.append([[*(0.5 * c + 0.5 * np.array([250.0, 250.0])), 50.0] for c in centroids])
        return cands

    c = [np.array([130.0, 250.0]) + jitter[0], np.array([370.0, 250.0]) + jitter[1]]
    xy, load = clusters(c, (4, 4), (10e6, 10e6), 25.0)
    out.append({"family": "split2", "xy": xy, "load": load, "candidates": standard(xy)})

    c = [np.array([150.0, 150.0]) + jitter[2], np.array([350.0, 350.0]) + jitter[3]]
    xy, load = clusters(c, (6, 2), (15e6, 3e6), 25.0)
    out.append({"family": "heavy2", "xy": xy, "load": load, "candidates": standard(xy)})

    centre = np.array([250.0, 250.0]) + jitter[4]
    xy, load = clusters([centre], (8,), (8e6,), 30.0)
    hub = xy[0].mean(axis=0)
    near = [
        [[hub[0] - d / 2, hub[1], 25.0], [hub[0] + d / 2, hub[1], 25.0]]
        for d in (20.0, 60.0, 120.0)
    ]
    out.append({"family": "near2", "xy": xy, "load": load, "candidates": near})

    c = [np.array([40.0, 40.0]) + jitter[5] / 3, np.array([460.0, 460.0]) - jitter[5] / 3]
    xy, load = clusters(c, (3, 3), (12e6, 12e6), 12.0)
    cands = standard(xy)
    out.append({"family": "far2", "xy": xy, "load": load, "candidates": cands})

    c = [np.array([120.0, 120.0]), np.array([380.0, 150.0]), np.array([250.0, 390.0])]
    c = [ci + j for ci, j in zip(c, jitter[5:8], strict=True)]
    xy, load = clusters(c, (3, 3, 3), (12e6, 12e6, 12e6), 25.0)
    out.append({"family": "tri3", "xy": xy, "load": load, "candidates": standard(xy)})

    c = [np.array(p) for p in ((110.0, 110.0), (390.0, 110.0), (110.0, 390.0), (390.0, 390.0))]
    c = [ci + j for ci, j in zip(c, jitter[0:4], strict=True)]
    xy, load = clusters(c, (3, 3, 3, 3), (8e6,) * 4, 25.0)
    out.append({"family": "quad4", "xy": xy, "load": load, "candidates": standard(xy)})
    return out


def model_association(uav_xyz_m: np.ndarray, users_xy_m: np.ndarray) -> list[int]:
    """The AP the fast model associates each user with from no association (its first step's
    association); a user that hears none (``-1`` there) gets the strongest AP all the same."""
    model = FleetModel(FleetConfig(n_uavs=len(uav_xyz_m)))
    load = np.zeros(len(users_xy_m))
    assoc = model.step(uav_xyz_m, users_xy_m, load, None, None, WARMUP_S).association[0]
    strongest = np.argmax(received_power_dbm(uav_xyz_m[None], users_xy_m, AreaConfig(),
                                             NetworkConfig().radio)[0], axis=0)  # fmt: skip
    return [int(a) if a >= 0 else int(s) for a, s in zip(assoc, strongest, strict=True)]


def make_cases() -> dict[str, Any]:
    cases = []
    for seed in LAYOUT_SEEDS:
        for layout in _layouts(seed):
            users = np.concatenate(layout["xy"])
            load = np.concatenate(layout["load"])
            group = f"{layout['family']}-s{seed}"
            for c, uavs in enumerate(layout["candidates"]):
                uav = np.round(np.asarray(uavs, dtype=float), 2)
                users_r = np.round(users, 2)
                cases.append(
                    {
                        "id": f"{group}-c{c}",
                        "family": layout["family"],
                        "group": group,
                        "held_out": seed == 1,
                        "uavs": uav.tolist(),
                        "users": [
                            [float(x), float(y), float(lo)]
                            for (x, y), lo in zip(users_r, load, strict=True)
                        ],
                        "association": model_association(uav, users_r),
                    }
                )
    return {
        "format": CASES_FORMAT,
        "environment": "open",
        "protocol": {"association_s": 1.0, "warmup_s": WARMUP_S, "measure_s": MEASURE_S},
        "held_out_rule": "layout seed 1 (every family's second group)",
        "cases": cases,
    }


def load_fleet_cases() -> list[dict[str, Any]]:
    doc = json.loads(CASES_PATH.read_text())
    if doc.get("format") != CASES_FORMAT:
        raise SystemExit(f"{CASES_PATH}: not a {CASES_FORMAT} file")
    return doc["cases"]


def fleet_case(entry: dict[str, Any], mode: str):
    from sim.ns3_backend import FleetCase

    users = np.asarray(entry["users"], dtype=float)
    return FleetCase(entry["id"], np.asarray(entry["uavs"]), users[:, :2], users[:, 2],
                     np.asarray(entry["association"]), mode)  # fmt: skip


# --------------------------------------------------------------------------------- ns-3 runs
def run_ns3(modes: list[str], queueings: list[str], seeds: list[int]) -> None:
    from sim.ns3_backend import Ns3CaseError, Ns3Runner, Ns3Settings

    cases = load_fleet_cases()
    with Ns3Runner(niceness=10) as runner:
        for mode in modes:
            for queueing in queueings:
                out: dict[str, Any] = {"cases": []}
                failed = []
                started = time.perf_counter()
                for index, entry in enumerate(cases):
                    case = fleet_case(entry, mode)
                    per_seed = []
                    for seed in seeds:
                        settings = Ns3Settings(queueing=queueing, seed=seed)
                        try:
                            r = runner.run_fleet(case, settings, index)
                        except Ns3CaseError as exc:
                            failed.append({"id": entry["id"], "seed": seed, "error": exc.reason})
                            continue
                        m = r.metrics
                        per_seed.append(
                            {
                                "seed": seed,
                                "utility": round(m.utility, 6),
                                "wall_s": round(r.wall_s, 3),
                                "users": [
                                    {
                                        "throughput_bps": float(m.throughput_bps[u]),
                                        "delay_s": round(float(m.delay_s[u]), 6),
                                        "plr": round(float(m.plr[u]), 6),
                                    }
                                    for u in range(case.n_users)
                                ],
                            }
                        )
                    out["cases"].append({"id": entry["id"], "per_seed": per_seed})
                    utilities = ", ".join(f"{s['utility']:.3f}" for s in per_seed)
                    print(f"{mode} {queueing} {entry['id']}: {utilities}", flush=True)
                doc = {
                    "format": NS3_FORMAT,
                    "source": str(CASES_PATH.relative_to(ROOT)),
                    "backend": "ns3",
                    "ns3_version": runner.version,
                    "channel_mode": mode,
                    "queueing": queueing,
                    "seeds": seeds,
                    "ns3": Ns3Settings(queueing=queueing).to_dict() | {"seed": None},
                    "wall_s": round(time.perf_counter() - started, 1),
                    **out,
                    "failed": failed,
                }
                atomic_write_json(ns3_path(mode, queueing), doc)
                print(f"wrote {ns3_path(mode, queueing)}", flush=True)


# --------------------------------------------------------------------------------- comparison
def fast_fleet(entry: dict[str, Any], mode: str, queueing: str) -> dict[str, Any]:
    """The fast fleet model on one case, expected mode, the single-AP comparison's protocol."""
    uav = np.asarray(entry["uavs"], dtype=float)
    users = np.asarray(entry["users"], dtype=float)
    model = FleetModel(
        FleetConfig(n_uavs=len(uav), channel_mode=mode), NetworkConfig().with_queueing(queueing)
    )
    warm = model.step(uav, users[:, :2], users[:, 2], None, None, WARMUP_S)
    result = model.step(uav, users[:, :2], users[:, 2], warm.state, None, MEASURE_S)
    model_assoc = result.association[0]
    given = np.asarray(entry["association"])
    if np.any((model_assoc >= 0) & (model_assoc != given)):
        raise SystemExit(f"{entry['id']}: the model's association differs from the file's")
    return {
        "throughput_bps": result.throughput_bps[0],
        "delay_s": result.delay_s[0],
        "plr": result.plr[0],
        "utility": float(result.utility[0]),
        "domain": result.domain[0].tolist(),
        "handovers": int(result.handovers[0]),
    }


def _summary(values: Any) -> dict[str, float | int]:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size),
        "median": round(float(np.median(v)), 4),
        "p90": round(float(np.percentile(v, 90)), 4),
        "mean": round(float(np.mean(v)), 4),
    }


def _seed_users(entry: dict[str, Any], key: str) -> np.ndarray:
    """(seeds, U) of one per-user metric."""
    return np.array([[u[key] for u in s["users"]] for s in entry["per_seed"]])


def _figures(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Error figures of ``a`` against ``b`` over the case rows given (each: per-user arrays
    ``a_tput``, ``b_tput``, ``b_plr``, ``load``, ``assoc``; utilities ``a_u``, ``b_u``)."""
    if not rows:
        return {"n_cases": 0}
    a = np.concatenate([r["a_tput"] for r in rows])
    b = np.concatenate([r["b_tput"] for r in rows])
    load = np.concatenate([r["load"] for r in rows])
    congested = np.concatenate([r["b_plr"] for r in rows]) > CONGESTED_PLR
    rel = np.abs(a - b) / np.maximum(b, THROUGHPUT_FLOOR_BPS)
    cell_ratio = []
    for r in rows:
        for k in np.unique(r["assoc"]):
            mine = r["assoc"] == k
            total_b = r["b_tput"][mine].sum()
            if total_b > THROUGHPUT_FLOOR_BPS:
                cell_ratio.append(r["a_tput"][mine].sum() / total_b)
    util = np.array([r["a_u"] - r["b_u"] for r in rows])
    terms = np.array([_terms(r, "a") - _terms(r, "b") for r in rows])
    return {
        "n_cases": len(rows),
        "n_users": int(a.size),
        "n_congested_users": int(congested.sum()),
        "throughput_rel_error": {
            "all_users": _summary(rel),
            "congested_users": _summary(rel[congested]),
            "uncongested_users": _summary(rel[~congested]),
        },
        "throughput_error_over_load": _summary(np.abs(a - b) / load),
        "cell_throughput_ratio": _summary(cell_ratio),
        "utility_abs_error": _summary(np.abs(util)),
        "utility_bias_mean": round(float(util.mean()), 4),
        "utility_terms_bias_mean": {
            name: round(float(v), 4)
            for name, v in zip(("throughput", "delay", "loss"), terms.mean(axis=0), strict=True)
        },
    }


def _terms(row: dict[str, Any], side: str) -> np.ndarray:
    """The utility's three weighted parts of one case: 0.6·T, 0.3·(1 − D), 0.1·(1 − P)."""
    c = UtilityConfig()
    t = min(float(row[f"{side}_tput"].sum() / row["load"].sum()), 1.0)
    d = min(float(row[f"{side}_delay"].mean()) / c.delay_ref_s, 1.0)
    p = min(float(row[f"{side}_plr"].mean()), 1.0)
    return np.array(
        [c.weight_throughput * t, c.weight_delay * (1.0 - d), c.weight_loss * (1.0 - p)]
    )


def _placement(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per group: ``b``'s utility at the candidate ``a`` ranks best over ``b``'s best."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r["group"], []).append(r)
    out = {}
    for group, members in groups.items():
        a_u = np.array([m["a_u"] for m in members])
        b_u = np.array([m["b_u"] for m in members])
        choice = int(np.argmax(a_u))
        out[group] = {
            "choice": members[choice]["id"],
            "best": members[int(np.argmax(b_u))]["id"],
            "ratio": round(float(b_u[choice] / b_u.max()), 4),
            "a_utilities": [round(float(x), 4) for x in a_u],
            "b_utilities": [round(float(x), 4) for x in b_u],
        }
    ratios = [g["ratio"] for g in out.values()]
    return {
        "mean_ratio": round(float(np.mean(ratios)), 4) if ratios else None,
        "min_ratio": round(float(np.min(ratios)), 4) if ratios else None,
        "same_choice": int(sum(g["choice"] == g["best"] for g in out.values())),
        "n_groups": len(out),
        "groups": out,
    }


def block(cases: list[dict[str, Any]], mode: str, queueing: str) -> dict[str, Any] | None:
    path = ns3_path(mode, queueing)
    if not path.exists():
        return None
    ns3 = {e["id"]: e for e in json.loads(path.read_text())["cases"] if e["per_seed"]}
    fast_rows, seed_rows = [], []
    for entry in cases:
        if entry["id"] not in ns3:
            continue
        e = ns3[entry["id"]]
        users = np.asarray(entry["users"], dtype=float)
        load = users[:, 2]
        tput = _seed_users(e, "throughput_bps")
        plr = _seed_users(e, "plr")
        delay = _seed_users(e, "delay_s")
        mean_t, mean_p, mean_d = tput.mean(axis=0), plr.mean(axis=0), delay.mean(axis=0)
        ns3_u = float(network_utility(mean_t, mean_d, mean_p, load))
        f = fast_fleet(entry, mode, queueing)
        common = {
            "id": entry["id"],
            "group": entry["group"],
            "family": entry["family"],
            "held_out": entry["held_out"],
            "load": load,
            "assoc": np.asarray(entry["association"]),
        }
        fast_rows.append(
            common
            | {
                "a_tput": f["throughput_bps"],
                "a_delay": f["delay_s"],
                "a_plr": f["plr"],
                "b_tput": mean_t,
                "b_delay": mean_d,
                "b_plr": mean_p,
                "a_u": f["utility"],
                "b_u": ns3_u,
                "domain": f["domain"],
            }
        )
        if len(e["per_seed"]) >= 2:
            s0, s1 = e["per_seed"][0], e["per_seed"][1]
            seed_rows.append(
                common
                | {
                    "a_tput": tput[1],
                    "a_delay": delay[1],
                    "a_plr": plr[1],
                    "b_tput": tput[0],
                    "b_delay": delay[0],
                    "b_plr": plr[0],
                    "a_u": s1["utility"],
                    "b_u": s0["utility"],
                }
            )

    def both(rows: list[dict[str, Any]]) -> dict[str, Any]:
        held = [r for r in rows if r["held_out"]]
        return {
            "held_out": _figures(held) | {"placement": _placement(held)},
            "all": _figures(rows) | {"placement": _placement(rows)},
        }

    families = sorted({r["family"] for r in fast_rows})
    per_family = {}
    for fam in families:
        rows = [r for r in fast_rows if r["family"] == fam]
        seeds = [r for r in seed_rows if r["family"] == fam]
        fig, noise = _figures(rows), _figures(seeds)
        per_family[fam] = {
            "throughput_rel_error_median": fig["throughput_rel_error"]["all_users"]["median"],
            "throughput_rel_error_p90": fig["throughput_rel_error"]["all_users"]["p90"],
            "cell_throughput_ratio_median": fig["cell_throughput_ratio"].get("median"),
            "utility_abs_error_median": fig["utility_abs_error"]["median"],
            "utility_bias_mean": fig["utility_bias_mean"],
            "utility_terms_bias_mean": fig["utility_terms_bias_mean"],
            "placement_agreement_mean": _placement(rows)["mean_ratio"],
            "seed_to_seed_throughput_rel_error_median": (
                noise["throughput_rel_error"]["all_users"]["median"] if seeds else None
            ),
            "seed_to_seed_utility_abs_error_median": (
                noise["utility_abs_error"]["median"] if seeds else None
            ),
            "fast_model_domains": sorted({str(r["domain"]) for r in rows}),
        }
    return {
        "fast_vs_ns3": both(fast_rows),
        "ns3_seed_to_seed": both(seed_rows),
        "per_family": per_family,
    }


FAR_CASES = ("far2-s0-c0", "far2-s0-c1", "far2-s1-c0", "far2-s1-c1")
COUNTERS_PATH = CALIBRATION / "ns3_fleet_far2_counters.json"


def far2_check(cases: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``far2`` family on a shared channel, per case: ns-3's aggregate throughput and
    utility (mean of the seeds) beside the fast model's with its carrier-sense level
    (−82 dBm, ``FleetConfig.cca_threshold_dbm``) and, as a diagnostic only (not adopted), with
    −90 dBm (ns-3's preamble-detection ``MinimumRssi``, below which nothing is decoded)."""
    out: dict[str, Any] = {}
    for queueing in QUEUEINGS:
        path = ns3_path("shared", queueing)
        if not path.exists():
            continue
        ns3 = {e["id"]: e for e in json.loads(path.read_text())["cases"] if e["per_seed"]}
        rows = {}
        for entry in cases:
            if entry["family"] != "far2" or entry["id"] not in ns3:
                continue
            e = ns3[entry["id"]]
            uav = np.asarray(entry["uavs"], dtype=float)
            users = np.asarray(entry["users"], dtype=float)
            gap_m = float(np.linalg.norm(uav[0] - uav[1]))
            row: dict[str, Any] = {
                "ap_distance_m": round(gap_m, 1),
                "altitude_m": float(uav[0, 2]),
                "ns3_total_mbps": round(
                    float(_seed_users(e, "throughput_bps").mean(0).sum()) / 1e6, 2
                ),
                "ns3_utility": round(float(np.mean([s["utility"] for s in e["per_seed"]])), 4),
            }
            for cca in (-82.0, -90.0):
                model = FleetModel(
                    FleetConfig(n_uavs=len(uav), channel_mode="shared", cca_threshold_dbm=cca),
                    NetworkConfig().with_queueing(queueing),
                )
                warm = model.step(uav, users[:, :2], users[:, 2], None, None, WARMUP_S)
                r = model.step(uav, users[:, :2], users[:, 2], warm.state, None, MEASURE_S)
                row[f"fast_cca{int(cca)}"] = {
                    "domains": r.domain[0].tolist(),
                    "total_mbps": round(float(r.throughput_bps[0].sum()) / 1e6, 2),
                    "utility": round(float(r.utility[0]), 4),
                }
            rows[entry["id"]] = row
        out[queueing] = rows
    return out


def run_counters() -> None:
    """ns-3's MAC counters for the ``far2`` cases at 25 and 75 m, distinct vs shared channel
    (mac-only, seed 0): per cell the mean MCS of the data MPDUs sent, NAcked MPDUs per MPDU
    acknowledged, the loss and the AP's mean received power from its own stations."""
    from sim.ns3_backend import Ns3Runner, Ns3Settings

    cases = load_fleet_cases()
    index = {c["id"]: i for i, c in enumerate(cases)}
    out: dict[str, Any] = {}
    with Ns3Runner(niceness=10) as runner:
        for cid in FAR_CASES:
            entry = cases[index[cid]]
            for mode in CHANNEL_MODES:
                case = fleet_case(entry, mode)
                r = runner.run_fleet(case, Ns3Settings(queueing="mac-only"), index[cid])
                d = r.detail
                cells = []
                for k in range(case.n_uavs):
                    mine = case.association == k
                    mpdus = max(float(d["data_mpdus"][mine].sum()), 1.0)
                    acked = max(float(d["acked_mpdus"][mine].sum()), 1.0)
                    rx = max(float(d["ap_rx_mpdus"][mine].sum()), 1.0)
                    cells.append(
                        {
                            "throughput_mbps": round(
                                float(r.metrics.throughput_bps[mine].sum()) / 1e6, 2
                            ),
                            "plr_mean": round(float(r.metrics.plr[mine].mean()), 4),
                            "mcs_mean": round(float(d["mcs_mpdu_sum"][mine].sum()) / mpdus, 2),
                            "nacked_per_acked": round(
                                float(d["nacked_mpdus"][mine].sum()) / acked, 3
                            ),
                            "ap_rx_dbm_mean": round(float(d["ap_rx_dbm_sum"][mine].sum()) / rx, 1),
                        }
                    )
                out[f"{cid}/{mode}"] = cells
                print(cid, mode, cells, flush=True)
    atomic_write_json(
        COUNTERS_PATH,
        {
            "command": "nice -n 10 .venv/bin/python benchmarks/fidelity_fleet_ns3.py counters",
            "queueing": "mac-only",
            "seed": 0,
            "cells": out,
        },
    )
    print(f"wrote {COUNTERS_PATH}")


def headline(b: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for part in ("held_out", "all"):
        f, n = b["fast_vs_ns3"][part], b["ns3_seed_to_seed"][part]
        out[part] = {
            "n_cases": f["n_cases"],
            "n_users": f.get("n_users"),
            "throughput_rel_error_median": f["throughput_rel_error"]["all_users"]["median"],
            "throughput_rel_error_p90": f["throughput_rel_error"]["all_users"]["p90"],
            "congested_throughput_rel_error_median": f["throughput_rel_error"][
                "congested_users"
            ].get("median"),
            "utility_abs_error_median": f["utility_abs_error"]["median"],
            "utility_bias_mean": f["utility_bias_mean"],
            "utility_terms_bias_mean": f["utility_terms_bias_mean"],
            "cell_throughput_ratio_median": f["cell_throughput_ratio"].get("median"),
            "placement_agreement_mean": f["placement"]["mean_ratio"],
            "placement_same_choice": f"{f['placement']['same_choice']}/"
            f"{f['placement']['n_groups']}",
            "ns3_seed_to_seed": {
                "throughput_rel_error_median": n["throughput_rel_error"]["all_users"].get("median"),
                "throughput_rel_error_p90": n["throughput_rel_error"]["all_users"].get("p90"),
                "utility_abs_error_median": n["utility_abs_error"].get("median"),
                "placement_agreement_mean": n["placement"]["mean_ratio"],
            }
            if n.get("n_cases")
            else None,
        }
    return out


def report() -> dict[str, Any]:
    cases = load_fleet_cases()
    blocks, table = {}, {}
    versions = set()
    for mode in CHANNEL_MODES:
        for queueing in QUEUEINGS:
            b = block(cases, mode, queueing)
            if b is None:
                continue
            versions.add(json.loads(ns3_path(mode, queueing).read_text()).get("ns3_version"))
            key = f"{mode}/{queueing}"
            blocks[key] = b
            table[key] = headline(b)
    return {
        "benchmark": "fidelity_fleet_ns3",
        "command": "nice -n 10 .venv/bin/python benchmarks/fidelity_fleet_ns3.py run && "
        ".venv/bin/python benchmarks/fidelity_fleet_ns3.py report",
        "ns3_version": sorted(v for v in versions if v),
        "machine": platform.machine(),
        "cases": str(CASES_PATH.relative_to(ROOT)),
        "n_cases": len(cases),
        "n_held_out": sum(c["held_out"] for c in cases),
        "protocol": {
            "ns3": "association 1 s, warm-up 0.5 s, 2 s measured; seeds 0 and 1 (mean over "
            "seeds compared); every user a station of the AP the fast model associates it with",
            "fast_model": "sim.fleet.FleetModel, expected mode (rng=None), 0.5 s warm-up from "
            "empty queues then 2 s with the state carried over; default (single-AP fitted) "
            "constants, nothing refitted",
        },
        "definitions": {
            "throughput_rel_error": "|fast - ns3| / max(ns3, 10 kbit/s) per user",
            "congested_users": "ns-3 loss > 1 % (mean over seeds)",
            "cell_throughput_ratio": "per AP: sum of its users' fast throughput / ns-3's",
            "placement_agreement": "per group of 3 candidate fleets: ns-3 utility at the fast "
            "model's best candidate / best ns-3 utility",
            "ns3_seed_to_seed": "the same figures with ns-3 seed 1 in place of the fast model "
            "and seed 0 in place of the mean (the noise floor)",
        },
        "table": table,
        "shared_far2_check": far2_check(cases),
        "far2_ns3_counters": (
            json.loads(COUNTERS_PATH.read_text()) if COUNTERS_PATH.exists() else None
        ),
        "blocks": blocks,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "step", choices=("cases", "run", "counters", "report"), nargs="?", default="report"
    )
    parser.add_argument("--modes", nargs="+", default=list(CHANNEL_MODES))
    parser.add_argument("--queueing", nargs="+", default=list(QUEUEINGS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    args = parser.parse_args(argv)
    if args.step == "cases":
        doc = make_cases()
        atomic_write_json(CASES_PATH, doc)
        print(f"wrote {len(doc['cases'])} fleet cases to {CASES_PATH}")
        return 0
    if args.step == "run":
        run_ns3(args.modes, args.queueing, args.seeds)
        return 0
    if args.step == "counters":
        run_counters()
        return 0
    result = report()
    atomic_write_json(RESULTS, result)
    for key, row in result["table"].items():
        h, n = row["held_out"], row["held_out"]["ns3_seed_to_seed"] or {}
        print(
            f"{key}: held-out tput err median {h['throughput_rel_error_median']} "
            f"p90 {h['throughput_rel_error_p90']} (ns-3 seed-to-seed "
            f"{n.get('throughput_rel_error_median')} / {n.get('throughput_rel_error_p90')}), "
            f"utility err {h['utility_abs_error_median']} (seeds "
            f"{n.get('utility_abs_error_median')}), placement {h['placement_agreement_mean']} "
            f"({h['placement_same_choice']} same)"
        )
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
