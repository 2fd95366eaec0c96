"""Why the utility normalises delay by 1 s: the distribution of per-step mean delays.

Holds the UAV at 16 random grid positions for a 100-step episode in each of 200 generated
3-user scenarios (expected mode) and reports percentiles of the users' mean delay per step, for
both queueing variants. Writes benchmarks/results/delay_distribution.json.
Run: ``.venv/bin/python benchmarks/delay_distribution.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.network import NetworkModel
from sim.scenarios import generate_scenarios

RESULTS = Path(__file__).parent / "results" / "delay_distribution.json"
PERCENTILES = (50, 75, 90, 95, 99)


def main() -> None:
    scenarios = generate_scenarios(200, 3, seed=5)
    grid = AreaConfig().grid_positions_m()
    delay_ref_s = UtilityConfig().delay_ref_s
    result: dict[str, object] = {"delay_ref_s": delay_ref_s, "percentiles": list(PERCENTILES)}
    for queueing in ("fq-codel", "mac-only"):
        model = NetworkModel(NetworkConfig().with_queueing(queueing))
        rng = np.random.default_rng(0)
        means = []
        for scenario in scenarios:
            positions = grid[rng.choice(len(grid), 16)]
            state = None
            for _ in range(100):
                step = model.step(positions, scenario.users_xy_m, scenario.load_bps, state)
                state = step.state
                means.append(step.delay_s.mean(axis=1))
        delays = np.concatenate(means)
        values = np.percentile(delays, PERCENTILES)
        share = float(np.mean(delays <= delay_ref_s))
        result[queueing] = {
            "delay_s_at_percentiles": [round(float(v), 4) for v in values],
            "share_at_or_below_delay_ref": round(share, 4),
        }
        print(
            f"{queueing:>9}: p50/75/90/95/99 = "
            + " / ".join(f"{v:.3f}" for v in values)
            + f" s; {share:.1%} of steps <= {delay_ref_s} s"
        )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
