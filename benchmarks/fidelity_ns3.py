"""How faithful is the fast network model? Its numbers against ns-3 3.44 on the calibration set.

Reads the committed ns-3 results (``sim/calibration/ns3_<queueing>.json``, built by
``python -m sim.calibration.build run``), evaluates the same cases with the fast model in
expected mode under the same protocol (0.5 s warm-up from empty queues, 2 s measured) and
writes ``benchmarks/results/fidelity_ns3.json`` and ``fidelity_ns3.png``. Every figure is
computed twice: with the model's default constants (``variants``), which are the constants
fitted to the fit part of the set (``sim/calibration/fitted.json``, made by
``python -m sim.calibration.fit``), and with the hand-set constants the fit started from
(``hand_set``: ``sim.calibration.fit.HAND_SET``); ``held_out_hand_set_vs_default`` puts the
held-out target figures side by side with ns-3's own seed-to-seed error (the noise floor).
The figures:

* per-user throughput relative error ``|fast − ns3| / ns3`` (ns-3 throughput floored at
  10 kbit/s), median and p90, for all users and for the congested ones (ns-3 loss > 1 %),
  on the held-out cases and on all cases; the same normalised by the user's offered load;
* absolute error of the per-user loss ratio and of the case utility; delay error (absolute and
  as a log10 ratio);
* placement agreement: for each group of candidate UAV positions of one scenario, the ns-3
  utility at the candidate the fast model ranks best over the best ns-3 utility among them;
* the ns-3 seed-to-seed spread (the noise floor any model meets), errors by case family;
* the 10 s runs: mean delay per 1 s interval, ns-3 vs the fast model stepping 1 s at a time
  with its queue state carried over (how FqCoDel delays grow);
* why ns-3 loses packets, from its drop traces: lost packets by cause, and for light users
  beside backlogged ones (the case the fast model misses) their backoffs and longest gaps;
* the speed anchor: wall time per simulated second, ns-3 (a few cases timed live, same run)
  vs the fast model on the same cases;
* ``per_environment``: the held-out target figures per channel environment (issue 15), with the
  default constants: ``open`` is the calibration set above, each urban class its own set
  (``sim/calibration/cases_<environment>.json``, ns-3 results ``ns3_<environment>_*.json``),
  where ns-3 is given the fast model's per-user mean path loss (:mod:`sim.ns3_backend`) and the
  fast model runs in that environment's expected mode. Besides all users, it reports the
  *served* users (either backend delivers ≥ 10 kbit/s): users out of range in both agree
  trivially (0 = 0), and there are many in the towns; and the served users at the *edge* of
  coverage (mean RSSI within 3 dB of the −90 dBm preamble-detection threshold, where ns-3 loses
  the frames that fade under it and the model's connection is all or nothing) apart from the
  *inner* ones.

* ``per_site`` (issue 38): the same figures on each site's calibration set (``site:munich``:
  ``sim/calibration/cases_site_munich.json``, ns-3 results ``ns3_site_munich_*.json``), where
  ns-3 is given the site's ray-traced per-user loss at the UAV's exact position (the fast
  model's expected-mode loss there; no path: out of coverage in both) and the fast model runs
  on the site in expected mode.

* ``per_regime`` (issue 19): the held-out target figures by queueing variant × station count
  (1–3, 4–8, 9–20) × congested / uncongested users, each beside ns-3's seed-to-seed figure, on
  the open set's held-out part and on the few-station set (``sim/calibration/
  cases_few_stations.json``, held out entirely, ns-3 results ``ns3_few_stations_*.json``);
* ``few_stations_mechanism`` (issue 19): where the few-station set's congested users' packets
  go in ns-3 (drops by cause, still queued, backlog at the window's end) beside the fast
  model's throughput, loss, delay and backlog for the same users, and which FIFO delay rule
  (delivered vs arriving packets) reproduces ns-3's delay from its own throughput.

Run (ns-3 needed only for the live timing; ``--no-live`` uses the calibration's timings)::

    nice -n 19 .venv/bin/python benchmarks/fidelity_ns3.py
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim.calibration.build import (
    FEW_STATIONS_PATH,
    SITE_ENVIRONMENTS,
    cases_path,
    few_stations_results_path,
    load_meta,
    results_path,
)
from sim.calibration.fit import HAND_SET, load_fitted, make_config
from sim.channel import NO_LINK_LOSS_DB, area_site, mean_path_loss_db, site_link_channel
from sim.config import ENVIRONMENTS, AreaConfig, NetworkConfig, RadioConfig
from sim.evaluate import CaseMetrics, evaluate_case
from sim.files import load_cases
from sim.network import NetworkModel
from sim.scenarios import Case

ROOT = Path(__file__).resolve().parent.parent
CALIBRATION = ROOT / "sim" / "calibration"
RESULTS = ROOT / "benchmarks" / "results" / "fidelity_ns3.json"
FIGURE = ROOT / "benchmarks" / "results" / "fidelity_ns3.png"
VARIANTS = ("fq-codel", "mac-only")
THROUGHPUT_FLOOR_BPS = 1e4
CONGESTED_PLR = 0.01
PACKET_BYTES = 512
TURNOVER_PPS = 500 / 0.5  # WifiMacQueue MaxSize / MaxDelay
SPEED_CASES = (
    "single-d450-z25-L40",
    "p3-s0002-centroid",
    "many-u12-L40-centroid",
    "many-u20-L40-centroid",
)
TARGETS = {
    "throughput_rel_error_median": 0.10,
    "throughput_rel_error_p90": 0.25,
    "congested_throughput_rel_error_median": 0.15,
    "utility_abs_error_median": 0.05,
    "placement_agreement_mean": 0.97,
    "speedup_per_simulated_second": 10_000,
}


def summary(values: np.ndarray) -> dict[str, float | int]:
    """Count, median, p90 and mean of ``values`` (NaN-free), rounded for the JSON."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size),
        "median": round(float(np.median(v)), 4),
        "p90": round(float(np.percentile(v, 90)), 4),
        "mean": round(float(np.mean(v)), 4),
    }


def load_ns3(queueing: str, long: bool = False) -> dict[str, Any]:
    name = f"ns3_long_{queueing}.json" if long else f"ns3_{queueing}.json"
    path = CALIBRATION / name
    if not path.exists():
        return {}
    return json.loads(path.read_text(encoding="utf-8"))


def user_rows(
    cases: dict[str, Case],
    ns3: dict[str, Any],
    fast: dict[str, CaseMetrics],
    meta: dict[str, Any],
) -> list[dict[str, Any]]:
    """One row per (case, user) with both backends' metrics."""
    held_out = set(meta["held_out"])
    rows = []
    for entry in ns3.get("cases", []):
        case = cases[entry["id"]]
        f = fast[entry["id"]]
        seeds = entry["per_seed"]
        for u, user in enumerate(entry["users"]):
            per_seed_tput = [s["users"][u]["throughput_bps"] for s in seeds]
            rows.append(
                {
                    "id": entry["id"],
                    "family": meta["family"][entry["id"]],
                    "held_out": entry["id"] in held_out,
                    "n_users": case.n_users,
                    "load_bps": float(case.load_bps[u]),
                    "ns3_tput": user["throughput_bps"],
                    "ns3_delay": user["delay_s"],
                    "ns3_plr": user["plr"],
                    "fast_tput": float(f.throughput_bps[u]),
                    "fast_delay": float(f.delay_s[u]),
                    "fast_plr": float(f.plr[u]),
                    "seed_spread": (
                        (max(per_seed_tput) - min(per_seed_tput))
                        / max(np.mean(per_seed_tput), THROUGHPUT_FLOOR_BPS)
                        if len(seeds) > 1
                        else np.nan
                    ),
                    "detail": seeds[0]["users"][u].get("ns3", {}),
                }
            )
    return rows


def errors(rows: list[dict[str, Any]], ns3_cases: list[dict[str, Any]], fast, ids) -> dict:
    """The error figures over the users of ``rows`` and the cases in ``ids``."""
    if not rows:
        return {"n_users": 0}
    ns3_t = np.array([r["ns3_tput"] for r in rows])
    fast_t = np.array([r["fast_tput"] for r in rows])
    load = np.array([r["load_bps"] for r in rows])
    rel = np.abs(fast_t - ns3_t) / np.maximum(ns3_t, THROUGHPUT_FLOOR_BPS)
    over_load = np.abs(fast_t - ns3_t) / load
    congested = np.array([r["ns3_plr"] > CONGESTED_PLR for r in rows])
    plr_err = np.abs(np.array([r["fast_plr"] - r["ns3_plr"] for r in rows]))
    ns3_d = np.maximum([r["ns3_delay"] for r in rows], 1e-5)
    fast_d = np.maximum([r["fast_delay"] for r in rows], 1e-5)
    util_err = np.array(
        [abs(fast[c["id"]].utility - c["utility"]) for c in ns3_cases if c["id"] in ids]
    )
    util_bias = np.array(
        [fast[c["id"]].utility - c["utility"] for c in ns3_cases if c["id"] in ids]
    )
    return {
        "n_cases": len(util_err),
        "n_users": len(rows),
        "n_congested_users": int(congested.sum()),
        "throughput_rel_error": {
            "all_users": summary(rel),
            "congested_users": summary(rel[congested]),
            "uncongested_users": summary(rel[~congested]),
        },
        "throughput_error_over_load": {
            "all_users": summary(over_load),
            "congested_users": summary(over_load[congested]),
        },
        "throughput_bias_fast_minus_ns3_over_load_mean": round(
            float(np.mean((fast_t - ns3_t) / load)), 4
        ),
        "loss_abs_error": {
            "all_users": summary(plr_err),
            "congested_users": summary(plr_err[congested]),
        },
        "delay_abs_error_s": summary(np.abs(fast_d - ns3_d)),
        "delay_log10_ratio_fast_over_ns3": summary(np.log10(fast_d / ns3_d)),
        "utility_abs_error": summary(util_err),
        "utility_bias_fast_minus_ns3_mean": round(float(np.mean(util_bias)), 4),
    }


def placement(meta, ns3_by_id, fast) -> dict[str, Any]:
    """Per group: ns-3 utility at the fast model's best candidate / best ns-3 utility."""
    held = set(meta["held_out"])
    groups = {}
    for group, ids in meta["groups"].items():
        if not all(i in ns3_by_id for i in ids):
            continue
        ns3_u = np.array([ns3_by_id[i]["utility"] for i in ids])
        fast_u = np.array([fast[i].utility for i in ids])
        choice = int(np.argmax(fast_u))
        groups[group] = {
            "held_out": ids[0] in held,
            "fast_choice": ids[choice],
            "ns3_best": ids[int(np.argmax(ns3_u))],
            "ratio": round(float(ns3_u[choice] / ns3_u.max()), 4),
            "ns3_utilities": [round(float(x), 4) for x in ns3_u],
            "fast_utilities": [round(float(x), 4) for x in fast_u],
        }
    ratios = [g["ratio"] for g in groups.values()]
    held_ratios = [g["ratio"] for g in groups.values() if g["held_out"]]
    return {
        "groups": groups,
        "mean_ratio": round(float(np.mean(ratios)), 4) if ratios else None,
        "min_ratio": round(float(np.min(ratios)), 4) if ratios else None,
        "mean_ratio_held_out": round(float(np.mean(held_ratios)), 4) if held_ratios else None,
    }


def drop_causes(rows: list[dict[str, Any]], variant: str) -> dict[str, Any]:
    """Where ns-3's lost packets were dropped (seed 0), all users and light users apart.

    A *light* user offers at most half the mean load Λ/U of its case and shares the cell with
    at least one congested user (ns-3 loss > 1 %).
    """
    causes = {
        "queue disc (FqCoDel) drop": "drop_qdisc",
        "MAC queue full (no queue disc: TcDrop)": "drop_tc",
        "MAC lifetime expired (MaxDelay 500 ms)": "drop_mac_expired",
        "Block Ack window passed (QOS_OLD_PACKET)": "drop_mac_old_packet",
        "retry limit": "drop_mac_retry_limit",
        "not associated / MacTxDrop": "drop_mac_tx",
        "ARP pending queue": "drop_arp",
    }

    def shares(subset: list[dict[str, Any]]) -> dict[str, Any]:
        totals = {
            name: sum(r["detail"].get(key, 0) for r in subset) for name, key in causes.items()
        }
        total = sum(totals.values())
        expired = totals["MAC lifetime expired (MaxDelay 500 ms)"]
        unsent = sum(r["detail"].get("expired_unsent", 0) for r in subset)
        return {
            "lost_packets": int(total),
            "share_by_cause": {k: round(v / total, 4) for k, v in totals.items()} if total else {},
            "expired_never_transmitted_share": round(unsent / expired, 4) if expired else None,
        }

    by_case: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        by_case.setdefault(r["id"], []).append(r)
    light, heavy = [], []
    for users in by_case.values():
        if len(users) < 2 or not any(u["ns3_plr"] > CONGESTED_PLR for u in users):
            continue
        mean_load = np.mean([u["load_bps"] for u in users])
        for u in users:
            (light if u["load_bps"] <= 0.5 * mean_load else heavy).append(u)

    def profile(subset: list[dict[str, Any]]) -> dict[str, Any]:
        def per_user(key_num: str, key_den: str | None = None) -> np.ndarray:
            out = []
            for r in subset:
                d = r["detail"]
                num = d.get(key_num, 0)
                out.append(num / max(d.get(key_den, 0), 1) if key_den else num)
            return np.array(out)

        return {
            "n_users": len(subset),
            "ns3_plr": summary(np.array([r["ns3_plr"] for r in subset])),
            "ns3_delay_s": summary(np.array([r["ns3_delay"] for r in subset])),
            "fast_plr": summary(np.array([r["fast_plr"] for r in subset])),
            "missed_response_per_data_ppdu": summary(per_user("response_timeouts", "data_ppdus")),
            "mean_backoff_slots": summary(per_user("backoff_slots_sum", "backoff_draws")),
            "backoffs_with_cw_ge_127_per_2s": summary(per_user("backoff_long_draws")),
            "longest_gap_between_data_ppdus_s": summary(per_user("max_tx_gap_s")),
            **shares(subset),
        }

    # Check of the mechanism behind most fq-codel losses: with packets waiting in the queue disc
    # the 500-packet MAC queue stays full, so once the station's service is below 500 packets /
    # 0.5 s MaxDelay = 1000 packets/s its head-of-line packets expire: it loses about
    # min(arrival, 1000) - service packets/s however large the queue disc.
    congested = [r for r in rows if r["ns3_plr"] > CONGESTED_PLR]
    bits = 8.0 * PACKET_BYTES
    predicted = np.array(
        [
            max(min(r["load_bps"] / bits, TURNOVER_PPS) - r["ns3_tput"] / bits, 0.0)
            / (r["load_bps"] / bits)
            for r in congested
        ]
    )
    observed = np.array([r["ns3_plr"] for r in congested])
    hard = sorted(
        (r for r in light if r["ns3_plr"] > 0.2 and r["ns3_delay"] < 0.15),
        key=lambda r: -r["ns3_plr"],
    )
    examples = [
        {
            "case": r["id"],
            "load_bps": r["load_bps"],
            "ns3_plr": round(r["ns3_plr"], 3),
            "ns3_delay_s": round(r["ns3_delay"], 3),
            "fast_plr": round(r["fast_plr"], 3),
            "seed0_expired": r["detail"].get("drop_mac_expired", 0),
            "seed0_expired_never_sent": r["detail"].get("expired_unsent", 0),
            "seed0_old_packet": r["detail"].get("drop_mac_old_packet", 0),
            "seed0_backoffs_cw_ge_127": r["detail"].get("backoff_long_draws", 0),
            "seed0_longest_gap_s": r["detail"].get("max_tx_gap_s", 0),
        }
        for r in hard[:6]
    ]
    out = {
        "all_users": shares(rows),
        "light_users_losing_over_20pct_with_delay_under_150ms": {
            "n_users": len(hard),
            "share_of_light_users": round(len(hard) / len(light), 4) if light else None,
            "examples": examples,
        },
        "light_users_beside_congested": profile(light),
        "other_users_in_those_cases": profile(heavy),
    }
    if variant == "fq-codel":
        out["mac_lifetime_turnover_check"] = {
            "rule": "loss = (min(arrival, 1000 pkt/s) - ns-3 service) / arrival, congested users",
            "n_users": len(congested),
            "observed_plr": summary(observed),
            "abs_error_of_rule": summary(np.abs(predicted - observed)),
            "abs_error_of_fast_model_plr": summary(
                np.abs(np.array([r["fast_plr"] for r in congested]) - observed)
            ),
        }
    return out


def long_runs(cases: dict[str, Case], queueing: str, config: NetworkConfig) -> dict[str, Any]:
    """Mean user delay per 1 s interval over 10 s: ns-3 vs the fast model stepping 1 s."""
    doc = load_ns3(queueing, long=True)
    model = NetworkModel(config.with_queueing(queueing))
    out = {}
    for entry in doc.get("cases", []):
        case = cases[entry["id"]]
        intervals = entry["per_seed"][0].get("intervals", [])
        ns3_delay = [float(np.mean([u["delay_s"] for u in i["users"]])) for i in intervals]
        ns3_plr = [float(np.mean([u["plr"] for u in i["users"]])) for i in intervals]
        uav = case.uav_xyz_m[None, :]
        state = model.step(uav, case.users_xy_m, case.load_bps, None, None, 0.5).state
        fast_delay, fast_plr = [], []
        for _ in intervals:
            step = model.step(uav, case.users_xy_m, case.load_bps, state, None, 1.0)
            state = step.state
            fast_delay.append(float(step.delay_s[0].mean()))
            fast_plr.append(float(step.plr[0].mean()))
        out[entry["id"]] = {
            "ns3_mean_delay_s": [round(x, 4) for x in ns3_delay],
            "fast_mean_delay_s": [round(x, 4) for x in fast_delay],
            "ns3_mean_plr": [round(x, 4) for x in ns3_plr],
            "fast_mean_plr": [round(x, 4) for x in fast_plr],
        }
    return out


def variant_block(
    config: NetworkConfig,
    variant: str,
    cases: dict[str, Case],
    ns3: dict[str, Any],
    meta: dict[str, Any],
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """All error figures of one queueing variant with one set of constants, and its rows."""
    held = set(meta["held_out"])
    model = NetworkModel(config.with_queueing(variant))
    fast = {c["id"]: evaluate_case(model, cases[c["id"]], None) for c in ns3["cases"]}
    rows = user_rows(cases, ns3, fast, meta)
    ids_all = {c["id"] for c in ns3["cases"]}
    ids_held = ids_all & held
    by_id = {c["id"]: c for c in ns3["cases"]}
    held_rows = [r for r in rows if r["held_out"]]
    by_family = {}
    for fam in sorted({r["family"] for r in rows}):
        fam_rows = [r for r in rows if r["family"] == fam]
        fam_ids = {r["id"] for r in fam_rows}
        e = errors(fam_rows, ns3["cases"], fast, fam_ids)
        by_family[fam] = {
            "n_cases": e["n_cases"],
            "throughput_rel_error_median": e["throughput_rel_error"]["all_users"]["median"],
            "congested_throughput_rel_error_median": e["throughput_rel_error"][
                "congested_users"
            ].get("median"),
            "loss_abs_error_median": e["loss_abs_error"]["all_users"]["median"],
            "utility_abs_error_median": e["utility_abs_error"]["median"],
            "utility_bias_fast_minus_ns3_mean": e["utility_bias_fast_minus_ns3_mean"],
        }
    spread = np.array([r["seed_spread"] for r in rows if np.isfinite(r["seed_spread"])])
    held_errors = errors(held_rows, ns3["cases"], fast, ids_held)
    place = placement(meta, by_id, fast)
    t = held_errors["throughput_rel_error"]
    met = {
        "throughput_rel_error_median": t["all_users"]["median"]
        <= TARGETS["throughput_rel_error_median"],
        "throughput_rel_error_p90": t["all_users"]["p90"] <= TARGETS["throughput_rel_error_p90"],
        "congested_throughput_rel_error_median": t["congested_users"].get("median", 0)
        <= TARGETS["congested_throughput_rel_error_median"],
        "utility_abs_error_median": held_errors["utility_abs_error"]["median"]
        <= TARGETS["utility_abs_error_median"],
        "placement_agreement_mean": (place["mean_ratio"] or 0)
        >= TARGETS["placement_agreement_mean"],
    }
    block = {
        "n_cases_simulated": len(ids_all),
        "held_out": held_errors,
        "all": errors(rows, ns3["cases"], fast, ids_all),
        "by_family": by_family,
        "ns3_seed_spread_of_user_throughput": summary(spread),
        "placement": place,
        "targets_met_on_held_out": met,
        "long_runs_10s": long_runs(cases, variant, config),
    }
    return block, rows


def seed_vs_seed(ns3: dict[str, Any], held: set[str]) -> dict[str, Any]:
    """The noise floor: ns-3 seed 0 scored against seed 1 with the held-out figures' definitions
    (a perfect deterministic model scored against one seed would do about this well)."""
    rel, congested, util = [], [], []
    for entry in ns3.get("cases", []):
        if entry["id"] not in held or len(entry["per_seed"]) < 2:
            continue
        a, b = entry["per_seed"][0], entry["per_seed"][1]
        util.append(abs(a["utility"] - b["utility"]))
        for ua, ub in zip(a["users"], b["users"], strict=True):
            rel.append(
                abs(ua["throughput_bps"] - ub["throughput_bps"])
                / max(ub["throughput_bps"], THROUGHPUT_FLOOR_BPS)
            )
            congested.append(ub["plr"] > CONGESTED_PLR)
    r, c = np.array(rel), np.array(congested, dtype=bool)
    return {
        "definition": "|seed 0 - seed 1| / max(seed 1, 10 kbit/s) per user; congested: seed 1 "
        "loss > 1 %; utility: |seed 0 - seed 1| per case",
        "throughput_rel_error": {"all_users": summary(r), "congested_users": summary(r[c])},
        "utility_abs_error": summary(np.array(util)),
    }


def comparison(result: dict[str, Any]) -> dict[str, Any]:
    """Held-out target figures side by side: hand-set constants, default (fitted) constants,
    target (placement agreement also over all six groups: the fit never used the groups'
    ranking)."""
    out = {}
    for variant, block in result["variants"].items():
        hand_set = result["hand_set"]["variants"][variant]

        def figures(b: dict[str, Any]) -> dict[str, Any]:
            t = b["held_out"]["throughput_rel_error"]
            return {
                "throughput_rel_error_median": t["all_users"]["median"],
                "throughput_rel_error_p90": t["all_users"]["p90"],
                "congested_throughput_rel_error_median": t["congested_users"].get("median"),
                "utility_abs_error_median": b["held_out"]["utility_abs_error"]["median"],
                "placement_agreement_mean_all_groups": b["placement"]["mean_ratio"],
                "placement_agreement_mean_held_out_groups": b["placement"]["mean_ratio_held_out"],
            }

        d, h = figures(block), figures(hand_set)
        noise = block["ns3_seed_vs_seed_held_out"]["throughput_rel_error"]
        out[variant] = {
            k: {
                "hand_set": h[k],
                "default": d[k],
                "target": TARGETS.get(k, TARGETS["placement_agreement_mean"]),
            }
            for k in d
        }
        out[variant]["throughput_rel_error_median"]["ns3_seed_vs_seed"] = noise["all_users"].get(
            "median"
        )
        out[variant]["throughput_rel_error_p90"]["ns3_seed_vs_seed"] = noise["all_users"].get("p90")
        out[variant]["congested_throughput_rel_error_median"]["ns3_seed_vs_seed"] = noise[
            "congested_users"
        ].get("median")
    return out


def speed(cases: dict[str, Case], live: bool, ns3_docs: dict[str, Any]) -> dict[str, Any]:
    """Wall time per simulated second: ns-3 (live, a few cases) vs the fast model, same cases."""
    warmup_s, measure_s, association_s = 0.5, 2.0, 1.0
    traffic_s = warmup_s + measure_s
    chosen = [cases[i] for i in SPEED_CASES]
    model = NetworkModel()
    evaluate_case(model, chosen[0], None)  # compile
    fast_s = {}
    # Best of several batches on both sides: the machine is shared, the minimum is the cost.
    for case in chosen:
        batches = []
        for _ in range(5):
            started = time.perf_counter()
            for _ in range(1000):
                evaluate_case(model, case, None, warmup_s, measure_s)
            batches.append((time.perf_counter() - started) / 1000)
        fast_s[case.id] = min(batches)
    out: dict[str, Any] = {
        "protocol": (
            f"per case: {association_s} s association (no traffic), {warmup_s} s warm-up, "
            f"{measure_s} s measured; 'per traffic second' divides by the {traffic_s} s with "
            "traffic, the fast model's time covers its two steps (warm-up, window); best of 3 "
            "ns-3 runs and of 5 batches of 1000 fast evaluations, same process, same machine"
        ),
        "fast_wall_s_per_traffic_second": {
            k: float(f"{v / traffic_s:.3g}") for k, v in fast_s.items()
        },
    }
    calib = [
        c["wall_s"] / (association_s + traffic_s) for c in ns3_docs["fq-codel"].get("cases", [])
    ]
    out["ns3_calibration_wall_s_per_simulated_second"] = summary(np.array(calib))
    if live:
        from sim.ns3_backend import Ns3Runner, Ns3Settings, ns3_available

        if ns3_available():
            ns3_s = {}
            with Ns3Runner(niceness=0) as runner:
                started = time.perf_counter()
                runner.run(chosen[0], Ns3Settings(measure_s=0.1, warmup_s=0.0))
                out["ns3_worker_start_s"] = round(time.perf_counter() - started, 2)
                for case in chosen:
                    runs = []
                    for _ in range(3):
                        started = time.perf_counter()
                        runner.run(case, Ns3Settings(warmup_s=warmup_s, measure_s=measure_s))
                        runs.append(time.perf_counter() - started)
                    ns3_s[case.id] = min(runs)
            out["ns3_wall_s_per_traffic_second"] = {
                k: round(v / traffic_s, 4) for k, v in ns3_s.items()
            }
            ratios = [ns3_s[k] / fast_s[k] for k in ns3_s]
            out["speedup_per_simulated_second"] = {k: round(ns3_s[k] / fast_s[k]) for k in ns3_s}
            out["speedup_min"] = round(min(ratios))
            out["speedup_median"] = round(float(np.median(ratios)))
    return out


EDGE_MARGIN_DB = 3.0  # "edge" users: mean RSSI within this of the -90 dBm preamble threshold


def mean_rssi_dbm(case: Case, area: AreaConfig, radio: RadioConfig | None = None) -> np.ndarray:
    """Each user's mean received power (dBm) in the area's environment: the transmit power less
    :func:`sim.channel.mean_path_loss_db` (on a site: the site's loss at the UAV's position,
    no path counting as :data:`~sim.channel.NO_LINK_LOSS_DB`), the loss both backends use
    (default radio)."""
    radio = radio or RadioConfig()
    site = area_site(area)
    if site is not None:
        loss, _ = site_link_channel(
            site, case.uav_xyz_m[None, :], case.users_xy_m, radio.rician_k_db, None, 0
        )
        return radio.tx_power_dbm - np.minimum(loss[0], NO_LINK_LOSS_DB)
    ground_m = np.hypot(*(case.users_xy_m - case.uav_xyz_m[:2]).T)
    height_m = max(float(case.uav_xyz_m[2]) - area.user_height_m, 0.0)
    loss_db = mean_path_loss_db(area.environment, ground_m, height_m, radio.frequency_hz)
    return radio.tx_power_dbm - np.asarray(loss_db, dtype=float)


def environment_figures(
    rows: list[dict[str, Any]],
    ns3: dict[str, Any],
    fast: dict[str, CaseMetrics],
    meta: dict[str, Any],
    held_out: bool,
) -> dict[str, Any]:
    """The target figures over the held-out part (``held_out``) or all of one environment's
    set, one queueing variant."""
    held = set(meta["held_out"])
    rows = [r for r in rows if r["held_out"]] if held_out else rows
    ids = {r["id"] for r in rows}
    e = errors(rows, ns3["cases"], fast, ids)
    if not rows:
        return {"n_cases": 0}
    ns3_t = np.array([r["ns3_tput"] for r in rows])
    fast_t = np.array([r["fast_tput"] for r in rows])
    rel = np.abs(fast_t - ns3_t) / np.maximum(ns3_t, THROUGHPUT_FLOOR_BPS)
    served = np.maximum(ns3_t, fast_t) >= THROUGHPUT_FLOOR_BPS
    congested = np.array([r["ns3_plr"] > CONGESTED_PLR for r in rows])
    edge_dbm = RadioConfig().min_rssi_dbm + EDGE_MARGIN_DB
    edge = served & np.array([r["rssi_dbm"] < edge_dbm for r in rows])
    by_id = {c["id"]: c for c in ns3["cases"]}
    ratios = []
    for ids_group in meta["groups"].values():
        if held_out and ids_group[0] not in held:
            continue
        if not all(i in by_id for i in ids_group):
            continue
        ns3_u = np.array([by_id[i]["utility"] for i in ids_group])
        fast_u = np.array([fast[i].utility for i in ids_group])
        ratios.append(float(ns3_u[int(np.argmax(fast_u))] / ns3_u.max()))
    t = e["throughput_rel_error"]
    return {
        "n_cases": e["n_cases"],
        "n_users": e["n_users"],
        "n_served_users": int(served.sum()),
        "n_congested_users": e["n_congested_users"],
        "throughput_rel_error_median": t["all_users"]["median"],
        "throughput_rel_error_p90": t["all_users"]["p90"],
        "served_throughput_rel_error_median": summary(rel[served]).get("median"),
        "served_throughput_rel_error_p90": summary(rel[served]).get("p90"),
        "congested_throughput_rel_error_median": t["congested_users"].get("median"),
        "served_congested_throughput_rel_error_median": summary(rel[served & congested]).get(
            "median"
        ),
        "n_edge_users": int(edge.sum()),
        "edge_throughput_rel_error_median": summary(rel[edge]).get("median"),
        "inner_served_throughput_rel_error_median": summary(rel[served & ~edge]).get("median"),
        "inner_served_throughput_rel_error_p90": summary(rel[served & ~edge]).get("p90"),
        "utility_abs_error_median": e["utility_abs_error"]["median"],
        "utility_bias_fast_minus_ns3_mean": e["utility_bias_fast_minus_ns3_mean"],
        "n_placement_groups": len(ratios),
        "placement_agreement_mean": round(float(np.mean(ratios)), 4) if ratios else None,
        "placement_agreement_min": round(float(np.min(ratios)), 4) if ratios else None,
    }


def per_environment(config: NetworkConfig) -> dict[str, Any]:
    """Held-out (and all-case) target figures per channel environment and queueing variant,
    the fast model with ``config`` in the environment's expected mode vs the committed ns-3
    results of that environment's calibration set."""
    return _environment_blocks(config, ENVIRONMENTS)


def per_site(config: NetworkConfig) -> dict[str, Any]:
    """:func:`per_environment`'s figures for each site with a calibration set
    (:data:`sim.calibration.build.SITE_ENVIRONMENTS`), keyed by its environment
    (``site:munich``)."""
    return _environment_blocks(config, SITE_ENVIRONMENTS)


def _environment_blocks(config: NetworkConfig, environments: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for environment in environments:
        source = cases_path(environment)
        if not source.exists():
            continue
        area, case_list = load_cases(source)
        cases = {c.id: c for c in case_list}
        meta = load_meta(source)
        block: dict[str, Any] = {
            "cases": str(source.relative_to(ROOT)),
            "n_cases": len(case_list),
            "n_held_out": len(meta["held_out"]),
            "coverage_radius_m": meta.get("coverage_radius_m"),
            "variants": {},
        }
        for variant in VARIANTS:
            path = results_path(environment, variant)
            if not path.exists():
                continue
            ns3 = json.loads(path.read_text(encoding="utf-8"))
            model = NetworkModel(config.with_queueing(variant), area)
            fast = {c["id"]: evaluate_case(model, cases[c["id"]], None) for c in ns3["cases"]}
            rows = user_rows(cases, ns3, fast, meta)
            rssi = {i: mean_rssi_dbm(c, area) for i, c in cases.items()}
            by_case: dict[str, int] = {}
            for row in rows:
                u = by_case.get(row["id"], 0)
                row["rssi_dbm"] = float(rssi[row["id"]][u])
                by_case[row["id"]] = u + 1
            held = environment_figures(rows, ns3, fast, meta, held_out=True)
            block["variants"][variant] = {
                "n_cases_simulated": len(ns3["cases"]),
                "seeds": ns3.get("seeds"),
                "held_out": held,
                "all": environment_figures(rows, ns3, fast, meta, held_out=False),
                "ns3_seed_vs_seed_held_out": seed_vs_seed(ns3, set(meta["held_out"])),
                "targets_met_on_held_out": {
                    "throughput_rel_error_median": held.get("throughput_rel_error_median", 1)
                    <= TARGETS["throughput_rel_error_median"],
                    "placement_agreement_mean": (held.get("placement_agreement_mean") or 0)
                    >= TARGETS["placement_agreement_mean"],
                },
            }
        out[environment] = block
    return out


STATION_BINS: tuple[tuple[int, int], ...] = ((1, 3), (4, 8), (9, 20))


def station_bin(n_stations: int) -> str:
    """The per-regime table's station-count bin of a case (``"1-3"``, ``"4-8"``, ``"9-20"``)."""
    for lo, hi in STATION_BINS:
        if lo <= n_stations <= hi:
            return f"{lo}-{hi}"
    raise ValueError(f"n_stations: {n_stations} is outside 1-20")


def _regime_sets() -> dict[str, tuple[dict[str, Case], dict[str, Any], dict[str, Any]]]:
    """The held-out sets the per-regime table scores: the open calibration set's held-out part
    and the few-station set (issue 19, held out entirely). Per set: the cases, the metadata
    (held-out ids, groups) and the ns-3 results per variant."""
    out = {}
    sets = {
        "open_held_out": (cases_path("open"), results_path),
        "few_stations": (FEW_STATIONS_PATH, lambda _env, q: few_stations_results_path(q)),
    }
    for name, (source, result_path) in sets.items():
        if not source.exists():
            continue
        _, case_list = load_cases(source)
        meta = load_meta(source)
        docs = {}
        for variant in VARIANTS:
            path = result_path("open", variant)
            if path.exists():
                docs[variant] = json.loads(path.read_text(encoding="utf-8"))
        out[name] = ({c.id: c for c in case_list}, meta, docs)
    return out


def regime_cell(
    rows: list[dict[str, Any]],
    entries: dict[str, dict[str, Any]],
    fast: dict[str, CaseMetrics],
    groups: list[list[str]],
    all_entries: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """The target figures of one regime cell, each beside ns-3's own seed-to-seed figure.

    ``rows``: the cell's users (:func:`user_rows`, with ``user``: the index in its case);
    ``entries``: the ns-3 results of the cases whose utility is scored in the cell; ``groups``:
    the candidate lists scored for placement; ``all_entries``: every case's ns-3 results.
    Seed to seed: ns-3 seed 0 scored against seed 1 on the same users and cases, as
    :func:`seed_vs_seed` does (cases with one seed are skipped there).
    """
    ns3_t = np.array([r["ns3_tput"] for r in rows])
    fast_t = np.array([r["fast_tput"] for r in rows])
    rel = np.abs(fast_t - ns3_t) / np.maximum(ns3_t, THROUGHPUT_FLOOR_BPS)
    bias = (fast_t - ns3_t) / np.array([r["load_bps"] for r in rows]) if rows else np.array([])
    util = np.array([abs(fast[i].utility - e["utility"]) for i, e in entries.items()])
    seed_rel = []
    for r in rows:
        seeds = all_entries[r["id"]]["per_seed"]
        if len(seeds) >= 2:
            a = seeds[0]["users"][r["user"]]["throughput_bps"]
            b = seeds[1]["users"][r["user"]]["throughput_bps"]
            seed_rel.append(abs(a - b) / max(b, THROUGHPUT_FLOOR_BPS))
    seed_util = [
        abs(e["per_seed"][0]["utility"] - e["per_seed"][1]["utility"])
        for e in entries.values()
        if len(e["per_seed"]) >= 2
    ]
    ratios = []
    for ids in groups:
        ns3_u = np.array([all_entries[i]["utility"] for i in ids])
        fast_u = np.array([fast[i].utility for i in ids])
        ratios.append(float(ns3_u[int(np.argmax(fast_u))] / ns3_u.max()))
    rel_s, seed_s, util_s = summary(rel), summary(np.array(seed_rel)), summary(util)
    return {
        "n_users": len(rows),
        "n_cases": len(entries),
        "throughput_rel_error_median": rel_s.get("median"),
        "throughput_rel_error_p90": rel_s.get("p90"),
        "throughput_bias_fast_minus_ns3_over_load_mean": (
            round(float(np.mean(bias)), 4) if bias.size else None
        ),
        "utility_abs_error_median": util_s.get("median"),
        "n_placement_groups": len(ratios),
        "placement_agreement_mean": round(float(np.mean(ratios)), 4) if ratios else None,
        "ns3_seed_vs_seed": {
            "throughput_rel_error_median": seed_s.get("median"),
            "throughput_rel_error_p90": seed_s.get("p90"),
            "utility_abs_error_median": summary(np.array(seed_util)).get("median"),
        },
    }


def per_regime(config: NetworkConfig) -> dict[str, Any]:
    """Issue 19's table: the held-out target figures by set × queueing variant × station count
    (1–3, 4–8, 9–20) × congested / uncongested, each with ns-3's seed-to-seed figure beside it.

    A user is congested when ns-3 loses > 1 % of its packets (mean over seeds); a case is
    congested when one of its users is (its utility is scored there), and a placement group
    when one of its candidates is. ``pooled``: both sets together.
    """
    out: dict[str, Any] = {
        "definition": "held-out cases only (open: cases.json's held-out part; few_stations: "
        "cases_few_stations.json, never fitted); station count = users in the case; congested "
        "user: ns-3 loss > 1 % (mean of the seeds); utility and placement are per case / group, "
        "a case (group) counting as congested when any of its users (candidates' users) is; "
        "ns3_seed_vs_seed: ns-3 seed 0 scored against seed 1 on the same users and cases",
        "sets": {},
    }
    pooled: dict[str, dict[str, Any]] = {v: {"rows": [], "entries": {}, "fast": {}, "groups": []}
                                         for v in VARIANTS}  # fmt: skip
    for name, (cases, meta, docs) in _regime_sets().items():
        held = set(meta["held_out"])
        block: dict[str, Any] = {}
        for variant, ns3 in docs.items():
            model = NetworkModel(config.with_queueing(variant))
            entries = {e["id"]: e for e in ns3["cases"] if e["id"] in held}
            fast = {i: evaluate_case(model, cases[i], None) for i in entries}
            rows = [
                r
                for r in user_rows(cases, {"cases": list(entries.values())}, fast, meta)
                if r["held_out"]
            ]
            seen: dict[str, int] = {}
            for r in rows:
                r["user"] = seen.get(r["id"], 0)
                seen[r["id"]] = r["user"] + 1
            groups = [ids for ids in meta["groups"].values() if all(i in entries for i in ids)]
            pool = pooled[variant]
            pool["rows"] += [{**r, "id": f"{name}/{r['id']}"} for r in rows]
            pool["entries"].update({f"{name}/{i}": e for i, e in entries.items()})
            pool["fast"].update({f"{name}/{i}": f for i, f in fast.items()})
            pool["groups"] += [[f"{name}/{i}" for i in ids] for ids in groups]
            block[variant] = _regime_table(rows, entries, fast, groups, cases)
        out["sets"][name] = block
    block = {}
    for variant, pool in pooled.items():
        if not pool["rows"]:
            continue
        n_users = {i: len(e["users"]) for i, e in pool["entries"].items()}
        block[variant] = _regime_table(
            pool["rows"], pool["entries"], pool["fast"], pool["groups"], n_users
        )
    out["sets"]["pooled"] = block
    return out


def _regime_table(
    rows: list[dict[str, Any]],
    entries: dict[str, dict[str, Any]],
    fast: dict[str, CaseMetrics],
    groups: list[list[str]],
    cases: dict[str, Case] | dict[str, int],
) -> dict[str, Any]:
    """One variant's cells: station bin → congested / uncongested (and both) → figures.
    ``cases``: each case's :class:`Case`, or its station count."""

    def n_stations(case_id: str) -> int:
        c = cases[case_id]
        return c if isinstance(c, int) else c.n_users

    def congested_case(case_id: str) -> bool:
        return any(u["plr"] > CONGESTED_PLR for u in entries[case_id]["users"])

    table: dict[str, Any] = {}
    for lo, hi in STATION_BINS:
        label = f"{lo}-{hi}"
        in_bin = {i for i in entries if station_bin(n_stations(i)) == label}
        if not in_bin:
            continue
        cells = {}
        for cell, want in (("congested", True), ("uncongested", False), ("all", None)):
            cell_rows = [
                r
                for r in rows
                if r["id"] in in_bin and (want is None or (r["ns3_plr"] > CONGESTED_PLR) == want)
            ]
            cell_cases = {
                i: entries[i] for i in in_bin if want is None or congested_case(i) == want
            }
            cell_groups = [
                ids
                for ids in groups
                if ids[0] in in_bin
                and (want is None or any(congested_case(i) for i in ids) == want)
            ]
            cells[cell] = regime_cell(cell_rows, cell_cases, fast, cell_groups, entries)
        table[label] = cells
    return table


QDISC_LIMIT_PKTS = 10_240 + 500  # FqCoDel's limit + the MAC queue below it
DROP_KEYS = (
    "drop_qdisc",
    "drop_mac_failed_enqueue",
    "drop_mac_expired",
    "drop_mac_retry_limit",
    "drop_mac_old_packet",
    "drop_tc",
    "drop_mac_tx",
    "drop_arp",
)


def fifo_delay_s(load_bps: float, tput_bps: float, rule: str, warmup_s: float = 0.5,
                 measure_s: float = 2.0) -> float:  # fmt: skip
    """Mean queueing delay over the window of an overloaded FIFO flow filling from empty at
    the start of the warm-up, backlog B(t) = min((L − T)·t, limit) packets. ``departure``:
    the delay of the packets *delivered* in the window (what FlowMonitor measures, and the
    fast model's rule since issue 19, :mod:`sim.queues`): a packet delivered at t arrived when
    the backlog was shorter, so it waited (L − T)·t / L, until that reaches limit / T (the
    packets let in once the flow's CoDel queue tail-drops at the limit); ``arrival``: B/T,
    the delay a packet arriving now will see (the fast model's rule before)."""
    bits = 8.0 * PACKET_BYTES
    arrival, service = load_bps / bits, tput_bps / bits
    t = np.linspace(warmup_s, warmup_s + measure_s, 401)
    growth = max(arrival - service, 0.0)
    if rule == "departure":
        delay = np.minimum(growth * t / arrival, QDISC_LIMIT_PKTS / max(service, 1e-9))
    else:
        delay = np.minimum(growth * t, QDISC_LIMIT_PKTS) / max(service, 1e-9)
    return float(np.mean(delay))


def few_stations_mechanism(config: NetworkConfig) -> dict[str, Any]:
    """Issue 19, item 1: where the congested users' packets go in ns-3 on the few-station set
    (its counters, both seeds summed), beside what the fast model predicts for the same users.

    Heavy: ≥ 15 Mbit/s offered; light: ≤ 3 Mbit/s. Congested: ns-3 loss > 1 % (seed mean).
    """
    if not FEW_STATIONS_PATH.exists():
        return {}
    _, case_list = load_cases(FEW_STATIONS_PATH)
    cases = {c.id: c for c in case_list}
    docs = {}
    for variant in VARIANTS:
        path = few_stations_results_path(variant)
        if path.exists():
            docs[variant] = {e["id"]: e for e in json.loads(path.read_text("utf-8"))["cases"]}
    if set(docs) != set(VARIANTS):
        return {}
    models = {v: NetworkModel(config.with_queueing(v)) for v in VARIANTS}
    out: dict[str, Any] = {
        "definition": "few-station set; heavy user: >= 15 Mbit/s offered, light: <= 3 Mbit/s; "
        "congested: ns-3 loss > 1 % (mean of the seeds); ns-3 counters summed over both seeds",
    }
    for variant in VARIANTS:
        model, other = models[variant], VARIANTS[1 - VARIANTS.index(variant)]
        for kind in ("heavy", "light"):
            users = []
            for case_id, entry in docs[variant].items():
                if case_id not in docs[other]:
                    continue
                case = cases[case_id]
                uav = case.uav_xyz_m[None, :]
                warm = model.step(uav, case.users_xy_m, case.load_bps, None, None, 0.5)
                step = model.step(uav, case.users_xy_m, case.load_bps, warm.state, None, 2.0)
                f_other = evaluate_case(models[other], case, None)
                for u, user in enumerate(entry["users"]):
                    heavy = case.load_bps[u] >= 15e6
                    if user["plr"] <= CONGESTED_PLR or heavy != (kind == "heavy"):
                        continue
                    seeds = [s["users"][u]["ns3"] for s in entry["per_seed"]]
                    users.append(
                        {
                            "load": float(case.load_bps[u]),
                            "ns3_t": user["throughput_bps"],
                            "ns3_t_other": docs[other][case_id]["users"][u]["throughput_bps"],
                            "fast_t": float(step.throughput_bps[0, u]),
                            "fast_t_other": float(f_other.throughput_bps[u]),
                            "ns3_plr": user["plr"],
                            "fast_plr": float(step.plr[0, u]),
                            "ns3_d": user["delay_s"],
                            "fast_d": float(step.delay_s[0, u]),
                            "fast_backlog": float(step.state.backlog_pkts[0, u]),
                            "ns3_backlog": float(
                                np.mean(
                                    [
                                        s.get("backlog_qdisc_pkts", 0)
                                        + s.get("backlog_mac_pkts", 0)
                                        for s in seeds
                                    ]
                                )
                            ),
                            "counters": {
                                k: sum(s.get(k, 0) for s in seeds)
                                for k in (*DROP_KEYS, "app_tx_pkts", "rx_pkts", "expired_unsent")
                            },
                        }
                    )
            out[f"{variant}_congested_{kind}_users"] = _mechanism_figures(
                users, variant == "fq-codel" and kind == "heavy"
            )
    return out


def _mechanism_figures(users: list[dict[str, Any]], fifo_rules: bool) -> dict[str, Any]:
    """The figures of :func:`few_stations_mechanism` over one group of users; ``fifo_rules``:
    also score the two FIFO delay rules (:func:`fifo_delay_s`) on ns-3's own throughput
    (overloaded FqCoDel flows)."""
    if not users:
        return {"n_users": 0}

    def col(key: str) -> np.ndarray:
        return np.array([u[key] for u in users], dtype=float)

    totals = {k: sum(u["counters"][k] for u in users) for k in DROP_KEYS}
    lost = sum(totals.values())
    sent = sum(u["counters"]["app_tx_pkts"] for u in users)
    received = sum(u["counters"]["rx_pkts"] for u in users)
    expired = totals["drop_mac_expired"]
    ns3_t, fast_t = col("ns3_t"), col("fast_t")
    out = {
        "n_users": len(users),
        "ns3_packets": {
            "offered": int(sent),
            "received_share": round(received / sent, 4),
            "dropped_share": round(lost / sent, 4),
            "still_queued_at_window_end_share": round((sent - received - lost) / sent, 4),
            "drops_by_cause_share": {k: round(v / lost, 4) for k, v in totals.items() if v}
            if lost
            else {},
            "mac_expired_never_transmitted_share": (
                round(sum(u["counters"]["expired_unsent"] for u in users) / expired, 4)
                if expired
                else None
            ),
        },
        "throughput": {
            "fast_over_ns3_median": round(float(np.median(fast_t / ns3_t)), 4),
            "rel_error_median": round(float(np.median(np.abs(fast_t - ns3_t) / ns3_t)), 4),
            "ns3_this_variant_over_other_median": round(
                float(np.median(ns3_t / col("ns3_t_other"))), 4
            ),
            "fast_this_variant_over_other_median": round(
                float(np.median(fast_t / np.maximum(col("fast_t_other"), 1.0))), 4
            ),
        },
        "loss": {
            "ns3_median": round(float(np.median(col("ns3_plr"))), 4),
            "fast_median": round(float(np.median(col("fast_plr"))), 4),
            "abs_error_median": round(
                float(np.median(np.abs(col("fast_plr") - col("ns3_plr")))), 4
            ),
        },
        "delay": {
            "ns3_median_s": round(float(np.median(col("ns3_d"))), 4),
            "fast_median_s": round(float(np.median(col("fast_d"))), 4),
            "log10_fast_over_ns3_median": round(
                float(np.median(np.log10(np.maximum(col("fast_d"), 1e-5) / col("ns3_d")))), 4
            ),
        },
        "backlog_at_window_end_pkts": {
            "ns3_median": round(float(np.median(col("ns3_backlog"))), 1),
            "fast_median": round(float(np.median(col("fast_backlog"))), 1),
            "ns3_at_limit": int(np.sum(col("ns3_backlog") >= 10_000)),
            "fast_at_limit": int(np.sum(col("fast_backlog") >= 10_000)),
        },
    }
    if fifo_rules:
        # Which FIFO rule gives ns-3's delay, from ns-3's own throughput (no fast model in it)?
        rules = {}
        for rule in ("departure", "arrival"):
            pred = np.array([fifo_delay_s(u["load"], u["ns3_t"], rule) for u in users], dtype=float)
            rules[rule] = {
                "abs_error_median_s": round(float(np.median(np.abs(pred - col("ns3_d")))), 4),
                "log10_over_ns3_median": round(
                    float(np.median(np.log10(np.maximum(pred, 1e-5) / col("ns3_d")))), 4
                ),
            }
        out["delay"]["fifo_rule_on_ns3_throughput"] = rules
    return out


def regime_lines(block: dict[str, Any]) -> list[str]:
    """The per-regime table as text lines: model error (ns-3 seed vs seed)."""
    lines = []
    for name, variants in block["sets"].items():
        for variant, table in variants.items():
            for stations, cells in table.items():
                for cell in ("congested", "uncongested"):
                    c = cells[cell]
                    if not c["n_users"] and not c["n_cases"]:
                        continue
                    n = c["ns3_seed_vs_seed"]
                    lines.append(
                        f"{name} {variant} {stations} stations {cell}: {c['n_users']} users / "
                        f"{c['n_cases']} cases, throughput error median "
                        f"{c['throughput_rel_error_median']} ({n['throughput_rel_error_median']})"
                        f", p90 {c['throughput_rel_error_p90']} ({n['throughput_rel_error_p90']})"
                        f", utility {c['utility_abs_error_median']} "
                        f"({n['utility_abs_error_median']}), placement "
                        f"{c['placement_agreement_mean']} ({c['n_placement_groups']} groups)"
                    )
    return lines


def refit_check() -> dict[str, Any]:
    """Do the urban sets ask for other MAC constants? The fit's objective
    (:func:`sim.calibration.fit.objective_terms`, both variants) on the *fit* part of the urban
    sets, summed over the four classes, at the default (fitted) constants and at each one-step
    neighbour (± half of each constant's first search step), beside the same objective on the
    open set's fit part (:func:`sim.calibration.fit.objective`)."""
    from sim.calibration import fit

    fitted = load_fitted()["fitted"]
    candidates: dict[str, dict[str, float]] = {"default": dict(fitted)}
    for c in fit.FREE:
        for sign in (-1, 1):
            value = fitted[c.name] + sign * c.step / 2
            if c.lo <= value <= c.hi:
                candidates[f"{c.name}{'+' if sign > 0 else '-'}{c.step / 2:g}"] = {
                    **fitted,
                    c.name: value,
                }
    urban_sets = []
    for environment in ENVIRONMENTS[1:]:
        source = cases_path(environment)
        area, case_list = load_cases(source)
        meta = load_meta(source)
        held = set(meta["held_out"])
        cases = {c.id: c for c in case_list if c.id not in held}
        docs = {}
        for variant in VARIANTS:
            path = results_path(environment, variant)
            if path.exists():
                doc = json.loads(path.read_text(encoding="utf-8"))
                docs[variant] = {c["id"]: c for c in doc["cases"] if c["id"] in cases}
        urban_sets.append((area, cases, docs))
    calib = fit.load_calibration()
    urban, opened = {}, {}
    for name, values in candidates.items():
        config = make_config(values)
        total = 0.0
        for area, cases, docs in urban_sets:
            for variant, entries in docs.items():
                model = NetworkModel(config.with_queueing(variant), area)
                fast_t, ns3_t, plr, util = [], [], [], []
                for case_id, entry in entries.items():
                    f = evaluate_case(model, cases[case_id], None)
                    fast_t.extend(f.throughput_bps)
                    ns3_t.extend(u["throughput_bps"] for u in entry["users"])
                    plr.extend(u["plr"] for u in entry["users"])
                    util.append(abs(f.utility - entry["utility"]))
                ns3_a = np.array(ns3_t)
                total += fit.objective_terms(
                    {
                        "rel": np.abs(np.array(fast_t) - ns3_a)
                        / np.maximum(ns3_a, THROUGHPUT_FLOOR_BPS),
                        "congested": np.array(plr) > CONGESTED_PLR,
                        "utility_err": np.array(util),
                    }
                )
        urban[name] = round(total, 4)
        open_value = fit.objective(calib, values, calib.ids("fit"))
        opened[name] = round(open_value, 4) if np.isfinite(open_value) else None
    allowed = [name for name in urban if opened[name] is not None]
    best = min(allowed, key=lambda name: urban[name])
    return {
        "definition": "sim.calibration.fit's objective on the fit part (never the held-out "
        "cases), both variants; urban: summed over the four urban classes; neighbours move one "
        "free constant by half its first search step; open None: rejected by the fit (a slower "
        "MCS would carry more), not a candidate",
        "urban_fit_part_objective": urban,
        "open_fit_part_objective": opened,
        "best_urban_candidate": best,
        "urban_improvement_of_best_over_default": round(urban["default"] - urban[best], 4),
        "open_change_at_that_candidate": round(opened[best] - opened["default"], 4),
    }


def few_station_rows(config: NetworkConfig) -> dict[str, list[dict[str, Any]]]:
    """Per variant, the per-user rows of the few-station set (issue 19; every case held out)."""
    sets = _regime_sets()
    if "few_stations" not in sets:
        return {}
    cases, meta, docs = sets["few_stations"]
    out: dict[str, list[dict[str, Any]]] = {}
    for variant, ns3 in docs.items():
        model = NetworkModel(config.with_queueing(variant))
        fast = {c["id"]: evaluate_case(model, cases[c["id"]], None) for c in ns3["cases"]}
        out[variant] = user_rows(cases, ns3, fast, meta)
    return out


def urban_rows(config: NetworkConfig) -> dict[str, list[dict[str, Any]]]:
    """Per variant, the per-user rows of every urban set (key ``environment`` added)."""
    out: dict[str, list[dict[str, Any]]] = {v: [] for v in VARIANTS}
    for environment in ENVIRONMENTS[1:]:
        source = cases_path(environment)
        if not source.exists():
            continue
        area, case_list = load_cases(source)
        cases = {c.id: c for c in case_list}
        meta = load_meta(source)
        for variant in VARIANTS:
            path = results_path(environment, variant)
            if not path.exists():
                continue
            ns3 = json.loads(path.read_text(encoding="utf-8"))
            model = NetworkModel(config.with_queueing(variant), area)
            fast = {c["id"]: evaluate_case(model, cases[c["id"]], None) for c in ns3["cases"]}
            for row in user_rows(cases, ns3, fast, meta):
                out[variant].append({**row, "environment": environment})
    return out


def _scatter_users(
    ax: Any,
    rows: list[dict[str, Any]],
    key: str,
    scale: float,
    floor: float,
    colour: str,
    face: str,
    label: str,
) -> None:
    """Per-user ns-3 (x) against fast-model (y) values of ``key``, scaled, floored for the
    log axes: one marker style (open: fit part, filled: held out)."""
    x = np.maximum([r[f"ns3_{key}"] * scale for r in rows], floor)
    y = np.maximum([r[f"fast_{key}"] * scale for r in rows], floor)
    ax.scatter(x, y, s=14, facecolors=face, edgecolors=colour, linewidths=0.8, label=label)


def _style_panel(ax: Any, key: str, floor: float, hi: float, title: str, legend: bool) -> None:
    """A log-log fast-vs-ns-3 panel of ``key`` (``tput`` or ``delay``): diagonal, limits,
    labels, ``title: per-user ...``, grid, and (``legend``) a small legend."""
    ax.plot([floor, hi], [floor, hi], color="black", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(floor, hi)
    ax.set_ylim(floor, hi)
    label = "throughput (Mbit/s)" if key == "tput" else "mean delay (s)"
    ax.set_xlabel(f"ns-3 {label}")
    ax.set_ylabel(f"fast model {label}")
    ax.set_title(f"{title}: per-user {label.split(' (')[0]}")
    ax.grid(True, which="major", lw=0.3)
    if legend:
        ax.legend(fontsize=7, loc="upper left")


def scatter(
    rows_by_config: dict[str, dict[str, list[dict[str, Any]]]],
    path: Path,
    urban: dict[str, list[dict[str, Any]]] | None = None,
    few: dict[str, list[dict[str, Any]]] | None = None,
) -> None:
    """Fast vs ns-3 per user: throughput (top) and delay (second row), log axes, one column
    per queueing variant and set of constants (default, hand-set); held-out users filled,
    congested users (ns-3 loss > 1 %) in red. Third row: the urban sets (default constants),
    throughput and delay per variant, one colour per environment, held-out users filled.
    Bottom row: the few-station set (issue 19, all held out, default constants), throughput and
    delay per variant, congested users in red."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(20, 20), dpi=90)
    FigureCanvasAgg(fig)
    axes = fig.subplots(4, 4)
    colours = {
        "suburban": "tab:green",
        "urban": "tab:orange",
        "dense-urban": "tab:purple",
        "highrise-urban": "tab:brown",
    }
    urban_columns = [(v, key) for key in ("tput", "delay") for v in VARIANTS]
    for col, (variant, key) in enumerate(urban_columns):
        ax = axes[2][col]
        scale, floor, hi = (1e-6, 1e-2, 100.0) if key == "tput" else (1.0, 1e-4, 10.0)
        for environment, colour in colours.items():
            for held, face in ((False, "none"), (True, colour)):
                sel = [
                    r
                    for r in (urban or {}).get(variant, [])
                    if r["environment"] == environment and r["held_out"] == held
                ]
                if not sel:
                    continue
                legend = environment + (", held out" if held else "")
                _scatter_users(ax, sel, key, scale, floor, colour, face, legend)
        _style_panel(ax, key, floor, hi, f"{variant}, urban sets", legend=col == 0)
    for col, (variant, key) in enumerate(urban_columns):
        ax = axes[3][col]
        scale, floor, hi = (1e-6, 1e-2, 100.0) if key == "tput" else (1.0, 1e-4, 10.0)
        for congested, colour in ((False, "tab:blue"), (True, "tab:red")):
            sel = [
                r
                for r in (few or {}).get(variant, [])
                if (r["ns3_plr"] > CONGESTED_PLR) == congested
            ]
            if sel:
                legend = "congested" if congested else "uncongested"
                _scatter_users(ax, sel, key, scale, floor, colour, colour, legend)
        _style_panel(ax, key, floor, hi, f"{variant}, few-station set", legend=col == 0)
    columns = [(v, name) for v in VARIANTS for name in rows_by_config]
    for col, (variant, name) in enumerate(columns):
        rows = rows_by_config[name].get(variant, [])
        for row_i, (key, label, floor) in enumerate(
            (("tput", "throughput (Mbit/s)", 1e-2), ("delay", "mean delay (s)", 1e-4))
        ):
            ax = axes[row_i][col]
            scale = 1e-6 if key == "tput" else 1.0
            for congested, colour in ((False, "tab:blue"), (True, "tab:red")):
                for held, face in ((False, "none"), (True, colour)):
                    sel = [
                        r
                        for r in rows
                        if (r["ns3_plr"] > CONGESTED_PLR) == congested and r["held_out"] == held
                    ]
                    if not sel:
                        continue
                    legend = ("congested" if congested else "uncongested") + (
                        ", held out" if held else ""
                    )
                    _scatter_users(ax, sel, key, scale, floor, colour, face, legend)
            lo = floor
            hi = 100.0 if key == "tput" else 10.0
            ax.plot([lo, hi], [lo, hi], color="black", lw=0.8)
            if key == "tput":
                ax.plot([lo, hi], [lo * 1.25, hi * 1.25], color="grey", lw=0.5, ls="--")
                ax.plot([lo, hi], [lo * 0.75, hi * 0.75], color="grey", lw=0.5, ls="--")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(lo, hi)
            ax.set_ylim(lo, hi)
            ax.set_xlabel(f"ns-3 {label}")
            ax.set_ylabel(f"fast model {label}")
            ax.set_title(
                f"{variant}, {name.replace('_', '-')} constants: per-user {label.split(' (')[0]}"
            )
            ax.grid(True, which="major", lw=0.3)
            if row_i == 0 and col == 0:
                ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(
        "Fast model vs ns-3 3.44, calibration set (dashed: ±25 %); third row: urban sets, "
        "ns-3 on the model's per-user mean path loss; bottom: the few-station set (held out)"
    )
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--no-live", action="store_true", help="skip the live ns-3 timing (speed anchor)"
    )
    args = parser.parse_args(argv)

    _, case_list = load_cases(CALIBRATION / "cases.json")
    cases = {c.id: c for c in case_list}
    doc = json.loads((CALIBRATION / "cases.json").read_text(encoding="utf-8"))
    meta = {k: doc[k] for k in ("family", "held_out", "groups", "long_runs")}
    held = set(meta["held_out"])

    ns3_docs = {q: load_ns3(q) for q in VARIANTS}
    result: dict[str, Any] = {
        "benchmark": "fidelity_ns3",
        "machine": {"cpu": platform.machine(), "python": platform.python_version()},
        "ns3_version": ns3_docs["fq-codel"].get("ns3_version"),
        "calibration": {
            "cases": "sim/calibration/cases.json",
            "n_cases": len(case_list),
            "n_held_out": len(held),
            "seeds": ns3_docs["fq-codel"].get("seeds"),
        },
        "fast_model": "expected mode (rng=None), same warm-up and window; 'variants': the "
        "default constants (sim/config.py, equal to sim/calibration/fitted.json), 'hand_set': "
        "the hand-set constants the fit started from (sim.calibration.fit.HAND_SET)",
        "definitions": {
            "throughput_rel_error": "|fast - ns3| / max(ns3, 10 kbit/s), per user",
            "congested_user": "ns-3 loss ratio > 1 % in the window",
            "ns3_metrics": "mean over seeds of each user's throughput, delay and loss; utility: "
            "mean of the per-seed utilities",
            "placement_agreement": "ns-3 utility at the fast model's best candidate / best ns-3 "
            "utility among the group's candidates",
        },
        "targets": TARGETS,
        "variants": {},
    }
    fitted_doc = load_fitted()
    configs = {"default": NetworkConfig(), "hand_set": HAND_SET}
    result["fit"] = {
        "source": "sim/calibration/fitted.json (python -m sim.calibration.fit)",
        "fitted_on": f"the {fitted_doc['fit_cases']} fit cases only (never the held-out ones)",
        "fitted_constants_are_the_defaults": make_config(fitted_doc["fitted"]) == NetworkConfig(),
        "constants": fitted_doc["fitted"],
        "hand_set": {k: v["hand_set"] for k, v in fitted_doc["free_constants"].items()},
    }
    result["hand_set"] = {"variants": {}}
    rows_by_config: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for name, config in configs.items():
        rows_by_config[name] = {}
        for variant in VARIANTS:
            ns3 = ns3_docs[variant]
            if not ns3:
                continue
            block, rows = variant_block(config, variant, cases, ns3, meta)
            rows_by_config[name][variant] = rows
            if name == "default":
                block["ns3_seed_vs_seed_held_out"] = seed_vs_seed(ns3, held)
                block["ns3_drop_causes"] = drop_causes(rows, variant)
                result["variants"][variant] = block
            else:
                result["hand_set"]["variants"][variant] = block
    result["held_out_hand_set_vs_default"] = comparison(result)
    for variant, table in result["held_out_hand_set_vs_default"].items():
        for figure, entry in table.items():
            print(
                f"{variant} held-out {figure}: hand-set {entry['hand_set']}, "
                f"default (fitted) {entry['default']} (target {entry['target']})"
            )
    result["per_environment"] = per_environment(NetworkConfig())
    result["per_site"] = per_site(NetworkConfig())
    blocks = {**result["per_environment"], **result["per_site"]}
    for environment, block in blocks.items():
        for variant, figures in block["variants"].items():
            h = figures["held_out"]
            print(
                f"{environment} {variant} held-out ({h['n_cases']} cases, {h['n_users']} users, "
                f"{h['n_served_users']} served): throughput error median "
                f"{h['throughput_rel_error_median']} "
                f"(served {h['served_throughput_rel_error_median']}), "
                f"p90 {h['throughput_rel_error_p90']}, congested median "
                f"{h['congested_throughput_rel_error_median']}, utility "
                f"{h['utility_abs_error_median']}, placement {h['placement_agreement_mean']} "
                f"({h['n_placement_groups']} groups)"
            )
    result["per_regime"] = per_regime(NetworkConfig())
    for line in regime_lines(result["per_regime"]):
        print(line)
    result["few_stations_mechanism"] = few_stations_mechanism(NetworkConfig())
    print(json.dumps(result["few_stations_mechanism"], indent=1))
    result["per_environment_refit_check"] = refit_check()
    check = result["per_environment_refit_check"]
    print(
        f"refit check: urban fit-part objective {check['urban_fit_part_objective']['default']} at "
        f"the default constants, best one-step neighbour {check['best_urban_candidate']} "
        f"({check['urban_improvement_of_best_over_default']} better there, open fit part "
        f"{check['open_change_at_that_candidate']:+} there)"
    )
    result["speed"] = speed(cases, not args.no_live, ns3_docs)
    if "speedup_min" in result["speed"]:
        result["speed"]["target_met"] = (
            result["speed"]["speedup_min"] >= TARGETS["speedup_per_simulated_second"]
        )
        print(f"speed: fast model {result['speed']['speedup_min']}x+ faster per simulated second")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    scatter(rows_by_config, FIGURE, urban_rows(NetworkConfig()), few_station_rows(NetworkConfig()))
    print(f"wrote {RESULTS} and {FIGURE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
