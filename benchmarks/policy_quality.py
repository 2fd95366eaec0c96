"""Quality of trained policies against the oracle and the paper's baseline (issue 4 targets).

For each checkpoint, on test scenarios drawn from a seed never used in training:

- mean utility, and its ratio to the oracle's (target >= 0.95);
- the share of the oracle's gain over min-distance it captures, sum over scenarios of
  (U_policy - U_min-distance) / sum of (U_oracle - U_min-distance), overall and in every
  heterogeneity bin holding >= 10 scenarios (target >= 0.9);
- the share of scenarios where it is worse than min-distance (target <= 2 %);
- the paper's headline figures on our model: gain over min-distance at the 25th percentile and
  in the most heterogeneous bin (the paper: 1.75x and about 4x);
- zero-shot on 5 and 10 users (trained with 3): ratio to the oracle (target >= 0.9);
- the training wall time recorded in the checkpoint's metadata.

Supplementary, because the capture ratio divides by the oracle's gain, which is ~0 where H is
low (min-distance is already optimal there): the share of scenarios worse than min-distance by
more than 0.01 utility, the lowest capture among bins of >= 10 scenarios where the oracle gains
>= 0.01, and the gain in the highest bin holding >= 10 scenarios.

Writes benchmarks/results/policy_quality.json. Run:
``.venv/bin/python benchmarks/policy_quality.py [--checkpoint DIR_OR_ZIP ...] [--n 500]``
(default: the shipped checkpoints in policies/checkpoints/).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from policies.adapters import CheckpointPolicy
from policies.evaluation.evaluation import evaluate_policy, heterogeneity_bin
from policies.registry import make_placement
from sim.config import AreaConfig
from sim.scenarios import generate_scenarios
from sim.world import PAPER

RESULTS = Path(__file__).parent / "results" / "policy_quality.json"
SHIPPED = Path(__file__).resolve().parent.parent / "policies" / "checkpoints"
TEST_SEED = 20_261_122  # never used for training (training sets use 1_000_000 + seed)
MIN_BIN_SCENARIOS = 10
MATERIAL_GAIN = 0.01  # utility; for the supplementary figures (see quality())


def evaluate_all(
    agents: list[Any], n_scenarios: int, n_users: int, area: AreaConfig
) -> dict[str, Any]:
    scenarios = generate_scenarios(n_scenarios, n_users, seed=TEST_SEED + n_users, area=area)
    results = {}
    world = replace(PAPER, area=area)
    for policy in [make_placement("min-distance", world), make_placement("oracle", world), *agents]:
        results[policy.name] = evaluate_policy(policy, scenarios, world, seed=0, progress=True)
    return results


def per_scenario(result: dict[str, Any], key: str = "utility") -> np.ndarray:
    return np.array([row[key] for row in result["scenarios"]])


def quality(
    policy: dict[str, Any], baseline: dict[str, Any], oracle: dict[str, Any]
) -> dict[str, Any]:
    u_p, u_b, u_o = per_scenario(policy), per_scenario(baseline), per_scenario(oracle)
    h = per_scenario(policy, "heterogeneity")
    bins = np.array([heterogeneity_bin(x) for x in h])

    def capture(mask: np.ndarray) -> float | None:
        gain = float(np.sum(u_o[mask] - u_b[mask]))
        return None if gain <= 1e-9 else float(np.sum(u_p[mask] - u_b[mask]) / gain)

    by_bin = {}
    for b in np.unique(bins):
        mask = bins == b
        by_bin[f"{b * 0.05:.2f}-{(b + 1) * 0.05:.2f}"] = {
            "n": int(mask.sum()),
            "policy": float(u_p[mask].mean()),
            "min_distance": float(u_b[mask].mean()),
            "oracle": float(u_o[mask].mean()),
            "oracle_gain": float((u_o[mask] - u_b[mask]).mean()),
            "gain_capture": capture(mask),
        }
    eligible = [
        v["gain_capture"]
        for v in by_bin.values()
        if v["n"] >= MIN_BIN_SCENARIOS and v["gain_capture"] is not None
    ]
    # Where the oracle gains almost nothing over min-distance (low H: min-distance is already
    # optimal), the capture ratio divides by ~0 and says nothing; these two read the same
    # targets with a materiality threshold. Supplementary: the figures stay above.
    material = [
        v["gain_capture"]
        for v in by_bin.values()
        if v["n"] >= MIN_BIN_SCENARIOS and v["oracle_gain"] >= MATERIAL_GAIN
    ]
    top_mask = bins == bins.max()
    counts = {b: int(np.sum(bins == b)) for b in np.unique(bins)}
    top10 = max((b for b, n in counts.items() if n >= MIN_BIN_SCENARIOS), default=bins.max())
    top = max(by_bin)
    return {
        "mean_utility": float(u_p.mean()),
        "ratio_to_oracle": float(u_p.mean() / u_o.mean()),
        "gain_capture": capture(np.ones_like(u_p, dtype=bool)),
        "min_gain_capture_in_bins_with_10": min(eligible) if eligible else None,
        "worse_than_min_distance_share": float(np.mean(u_p < u_b - 1e-9)),
        "worse_than_min_distance_by_0.01_share": float(np.mean(u_p < u_b - MATERIAL_GAIN)),
        "min_gain_capture_in_bins_with_10_and_oracle_gain_0.01": min(material)
        if material
        else None,
        "gain_over_min_distance_p25": float(np.percentile(u_p, 25) / np.percentile(u_b, 25)),
        "gain_over_min_distance_top_bin": float(u_p[top_mask].mean() / u_b[top_mask].mean()),
        "top_bin": top,
        "top_bin_n": int(top_mask.sum()),
        "gain_over_min_distance_top_bin_with_10": float(
            u_p[bins == top10].mean() / u_b[bins == top10].mean()
        ),
        "top_bin_with_10": f"{top10 * 0.05:.2f}-{(top10 + 1) * 0.05:.2f}",
        "by_heterogeneity_bin": by_bin,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", action="append", type=Path, help="checkpoint (repeat)")
    parser.add_argument("--n", type=int, default=500, help="test scenarios (default 500)")
    parser.add_argument("--zero-shot-n", type=int, default=100, help="scenarios for 5 and 10 users")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    area = AreaConfig()
    paths = args.checkpoint or sorted(p for p in SHIPPED.glob("*.zip"))
    if not paths:
        raise SystemExit(f"no checkpoints given and none shipped in {SHIPPED}")
    agents = [CheckpointPolicy.load(p, replace(PAPER, area=area)) for p in paths]
    names = [a.name for a in agents]

    started = time.monotonic()
    results = evaluate_all(agents, args.n, 3, area)
    base, oracle = results["min-distance"], results["oracle"]
    report: dict[str, Any] = {
        "benchmark": "policy_quality",
        "command": "python benchmarks/policy_quality.py " + " ".join(sys.argv[1:]),
        "test_seed": TEST_SEED,
        "n_scenarios": args.n,
        "min_distance_mean_utility": base["mean_utility"],
        "oracle_mean_utility": oracle["mean_utility"],
        "oracle": quality(oracle, base, oracle),
        "policies": {},
    }
    for agent in agents:
        q = quality(results[agent.name], base, oracle)
        q["training_wall_time_s"] = agent.metadata.get("wall_time_s")
        q["training_episodes"] = agent.metadata.get("episodes")
        q["training_strategy"] = agent.metadata.get("strategy")
        q["training_preset"] = agent.metadata.get("preset", {}).get("name")
        report["policies"][agent.name] = q
        print(
            f"{agent.name}: mean {q['mean_utility']:.3f} = {q['ratio_to_oracle']:.3f} x oracle; "
            f"captures {q['gain_capture']:.2f} of the oracle's gain over min-distance; worse than "
            f"min-distance in {q['worse_than_min_distance_share']:.1%} of scenarios"
        )
    zero_shot: dict[str, Any] = {}
    for n_users in (5, 10):
        shot = evaluate_all(agents, args.zero_shot_n, n_users, area)
        best = shot["oracle"]["mean_utility"]
        zero_shot[str(n_users)] = {
            name: shot[name]["mean_utility"] / best for name in [*names, "min-distance"]
        }
        print(f"zero-shot {n_users} users, ratio to oracle: {zero_shot[str(n_users)]}")
    report["zero_shot_ratio_to_oracle"] = zero_shot
    report["targets"] = {
        "ratio_to_oracle": 0.95,
        "gain_capture": 0.9,
        "worse_than_min_distance_share": 0.02,
        "zero_shot_ratio_to_oracle": 0.9,
    }
    report["benchmark_wall_time_s"] = round(time.monotonic() - started, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
