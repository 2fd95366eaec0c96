"""How an overloaded FqCoDel flow's delay grows: ns-3 3.44 against the fast model.

The single-user check of docs/network-model.md: one user at 450 m from a UAV at 25 m height
offering 40 Mbit/s, the queues empty when its traffic starts (no warm-up). ns-3 runs it with
both queueing variants for 8 s in 1-s intervals and for one 2-s window, seeds 0-3; the fast
model steps 1 s at a time with its queue state carried over (and one 2-s step), with the
default (fitted) constants and with the hand-set ones the fit started from. The delay is that
of the packets delivered in each interval (ns-3's FlowMonitor; :mod:`sim.queues`).

Writes ``benchmarks/results/queue_delay_ns3.json``. About a minute.
Run: ``.venv/bin/python benchmarks/queue_delay_ns3.py``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sim.atomic import atomic_write_json
from sim.calibration.fit import HAND_SET
from sim.config import NetworkConfig
from sim.network import NetworkModel
from sim.ns3_backend import Ns3Runner, Ns3Settings, ns3_version, require_ns3
from sim.scenarios import Case

RESULTS = Path(__file__).resolve().parent / "results" / "queue_delay_ns3.json"
CASE = Case("single-d450-z25-L40", np.array([450.0, 0.0, 25.0]), np.zeros((1, 2)), np.array([40e6]))
SECONDS = 8


def model_delays(config: NetworkConfig) -> dict[str, list[float] | float]:
    """The model's delay per 1-s step over ``SECONDS``, and over one 2-s step, from empty."""
    model = NetworkModel(config)
    uav, xy, load = CASE.uav_xyz_m[None, :], CASE.users_xy_m, CASE.load_bps
    state, per_s, loss = None, [], []
    for _ in range(SECONDS):
        r = model.step(uav, xy, load, state, None, 1.0)
        state = r.state
        per_s.append(round(float(r.delay_s[0, 0]), 4))
        loss.append(round(float(r.plr[0, 0]), 4))
    first = model.step(uav, xy, load, None, None, 2.0)
    return {
        "delay_per_1s_s": per_s,
        "plr_per_1s": loss,
        "mean_delay_8s_s": round(float(np.mean(per_s)), 4),
        "delay_first_2s_s": round(float(first.delay_s[0, 0]), 4),
        "throughput_bps": round(float(first.throughput_bps[0, 0])),
    }


def ns3_delays(queueing: str, seeds: list[int], runner: Ns3Runner) -> dict[str, object]:
    per_seed = []
    for seed in seeds:
        long = runner.run(
            CASE, Ns3Settings(queueing, 0.0, float(SECONDS), 1.0, seed=seed), seed
        ).intervals
        first = runner.run(CASE, Ns3Settings(queueing, 0.0, 2.0, seed=seed), seed).metrics
        per_seed.append(
            {
                "seed": seed,
                "delay_per_1s_s": [round(float(m.delay_s[0]), 4) for m in long],
                "plr_per_1s": [round(float(m.plr[0]), 4) for m in long],
                "delay_first_2s_s": round(float(first.delay_s[0]), 4),
                "throughput_bps": round(float(first.throughput_bps[0])),
            }
        )
    per_s = np.array([s["delay_per_1s_s"] for s in per_seed])
    first_2s = np.array([s["delay_first_2s_s"] for s in per_seed])
    return {
        "per_seed": per_seed,
        "delay_per_1s_s": [round(float(x), 4) for x in per_s.mean(axis=0)],
        "mean_delay_8s_s": round(float(per_s.mean()), 4),
        "mean_delay_8s_s_range": [
            round(float(x), 4) for x in (per_s.mean(1).min(), per_s.mean(1).max())
        ],
        "delay_first_2s_s": round(float(first_2s.mean()), 4),
        "delay_first_2s_s_range": [
            round(float(first_2s.min()), 4),
            round(float(first_2s.max()), 4),
        ],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="ns-3 seeds 0 .. N-1 (default 4)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds: must be >= 1, got {args.seeds}")
    require_ns3()
    seeds = list(range(args.seeds))
    result: dict[str, object] = {
        "case": {"uav_xyz_m": [450.0, 0.0, 25.0], "user_xy_m": [0.0, 0.0], "load_bps": 40e6},
        "ns3_version": ns3_version(),
        "seeds": seeds,
    }
    with Ns3Runner() as runner:
        for queueing in ("fq-codel", "mac-only"):
            result[queueing] = {
                "ns3": ns3_delays(queueing, seeds, runner),
                "fast_default": model_delays(NetworkConfig().with_queueing(queueing)),
                "fast_hand_set": model_delays(HAND_SET.with_queueing(queueing)),
            }
            ns3, fast = result[queueing]["ns3"], result[queueing]["fast_default"]
            print(
                f"{queueing}: first 2 s ns-3 {ns3['delay_first_2s_s']} s, model "
                f"{fast['delay_first_2s_s']} s; 8 s mean ns-3 {ns3['mean_delay_8s_s']} s, "
                f"model {fast['mean_delay_8s_s']} s"
            )
            print(f"  ns-3 per 1 s  {ns3['delay_per_1s_s']}")
            print(f"  model per 1 s {fast['delay_per_1s_s']}")
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
