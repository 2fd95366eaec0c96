"""Policies over the shipped districts in the closed loop, the buildings obstacles: a checkpoint
trained over munich and etoile, judged on held-out scenarios there and over florence, which it
never saw, against the planning and tracking oracles and the baselines.

For each site (munich, etoile, florence), user count (``--users``, 3 and 10) and world
(``closed-loop``, ``closed-loop-moving``): ``--scenarios`` held-out scenarios generated on the
site (seed 88U, used nowhere else), one ``tupa eval`` of every policy on them (``--episode-steps``
40, two workers), then one table: each policy's mean, its ratio to the planning oracle's mean
and whether it is above every baseline (min-distance, min-distance-env, load-weighted) in the
mean, and per scenario: the share where it is worse than the best baseline of that scenario by
more than 0.01. Per site, every set pooled (user counts, static and moving), the mean of each
policy per heterogeneity bin (width 0.05, as ``tupa eval``) that holds at least 10 episodes,
and whether the planning oracle (the served default over a site: policies/served_defaults.json)
and the checkpoint are above every baseline there (tolerance 0.005).
Writes ``benchmarks/results/sites_closed_loop.json``, ``.md`` and ``.png`` (the mean
utility of every policy over the episode, step by step, per site and world, ``--figure-users``
users); each ``tupa eval``'s own output is kept in ``--work`` (default
``runs/sites_closed_loop``).

The checkpoint (``--checkpoint``) is trained by the command in the docs (docs/results.md,
"Over the districts"); with ``--aggregate`` the evaluations already in ``--work`` are only
summarised::

    .venv/bin/python benchmarks/sites_closed_loop.py --checkpoint runs/ship40/ddpg-sites/model.zip
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TUPA = Path(sys.executable).with_name("tupa")
SITES = ("munich", "etoile", "florence")
WORLDS = ("closed-loop", "closed-loop-moving")
BASELINES = ("min-distance", "min-distance-env", "load-weighted")
REFERENCES = ("planning-oracle", "oracle")
WORSE_BY = 0.01
"""A scenario counts as lost to the baselines when a policy is below its best by more than this."""
BIN_TOLERANCE = 0.005
MIN_BIN_EPISODES = 10


def _run(command: list[str]) -> None:
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def _evaluate(args: argparse.Namespace, site: str, users: int, world: str) -> Path:
    work: Path = args.work
    scenarios = work / f"test_{site}_{users}.json"
    if not scenarios.exists():
        _run([str(TUPA), "scenarios", "generate", "--n", str(args.scenarios), "--users",
              str(users), "--seed", f"88{users}", "--environment", f"site:{site}",
              "--out", str(scenarios)])  # fmt: skip
    out = work / f"eval_{site}_{users}_{world}.json"
    policies = [args.checkpoint, *REFERENCES, *BASELINES]
    command = [str(TUPA), "eval", *[a for p in policies for a in ("--policy", str(p))]]
    command += ["--scenarios", str(scenarios), "--world", world, "--json", str(out)]
    command += ["--episode-steps", str(args.episode_steps), "--workers", "2", "--no-progress"]
    started = time.monotonic()
    _run(command)
    print(f"{site} {users} users {world}: {time.monotonic() - started:.0f} s", file=sys.stderr)
    return out


def _summary(path: Path, site: str, users: int, world: str) -> dict[str, Any]:
    results = json.loads(path.read_text())["results"]
    means = {r["policy"]: r["mean_utility"] for r in results}
    learned = results[0]["policy"]
    per = {r["policy"]: [s["utility"] for s in r["scenarios"]] for r in results}
    best = [max(values) for values in zip(*(per[b] for b in BASELINES), strict=True)]

    def lost_share(policy: str) -> float:
        lost = sum(u < b - WORSE_BY for u, b in zip(per[policy], best, strict=True))
        return lost / len(best)

    planner = means["planning-oracle"]
    best_baseline = max(means[b] for b in BASELINES)
    return {
        "site": site,
        "users": users,
        "world": world,
        "scenarios": results[0]["n_scenarios"],
        "means": means,
        "learned": learned,
        "learned_over_planner": means[learned] / planner if planner else None,
        "learned_over_best_baseline": means[learned] / best_baseline if best_baseline else None,
        "learned_above_every_baseline": means[learned] > best_baseline,
        "planner_over_best_baseline": planner / best_baseline if best_baseline else None,
        "planner_lost_share": lost_share("planning-oracle"),
        "learned_lost_share": lost_share(learned),
    }


def _bins(paths: list[Path], site: str) -> list[dict[str, Any]]:
    """Each policy's mean utility per heterogeneity bin over every episode of ``paths`` (one
    site's sets), for the bins holding at least :data:`MIN_BIN_EPISODES`."""
    from policies.evaluation.evaluation import HETEROGENEITY_BIN_WIDTH, heterogeneity_bin

    values: dict[int, dict[str, list[float]]] = {}
    learned = ""
    for path in paths:
        results = json.loads(path.read_text())["results"]
        learned = results[0]["policy"]
        for result in results:
            for scenario in result["scenarios"]:
                b = heterogeneity_bin(scenario["heterogeneity"])
                values.setdefault(b, {}).setdefault(result["policy"], []).append(
                    scenario["utility"]
                )
    rows = []
    for b in sorted(values):
        count = len(values[b]["planning-oracle"])
        if count < MIN_BIN_EPISODES:
            continue
        means = {p: sum(v) / len(v) for p, v in values[b].items()}
        best = max(means[x] for x in BASELINES)
        rows.append(
            {
                "site": site,
                "h_bin": [
                    round(b * HETEROGENEITY_BIN_WIDTH, 2),
                    round((b + 1) * HETEROGENEITY_BIN_WIDTH, 2),
                ],
                "episodes": count,
                "means": means,
                "planner_above_baselines": means["planning-oracle"] >= best - BIN_TOLERANCE,
                "learned_above_baselines": means[learned] >= best - BIN_TOLERANCE,
            }
        )
    return rows


def _markdown(rows: list[dict[str, Any]], bins: list[dict[str, Any]]) -> str:
    learned = rows[0]["learned"]
    names = [learned, *REFERENCES, *BASELINES]
    lines = [
        "| site | users | world | n | " + " | ".join(names) + " | learned / planner |",
        "| --- | ---: | --- | ---: | " + " | ".join("---:" for _ in names) + " | ---: |",
    ]
    for r in rows:
        cells = [f"{r['means'][n]:.3f}" for n in names]
        lines.append(
            f"| {r['site']} | {r['users']} | {r['world']} | {r['scenarios']} | "
            + " | ".join(cells)
            + f" | {r['learned_over_planner']:.2f} |"
        )
    lines += [
        "",
        f"Scenarios lost to the best baseline of the scenario by more than {WORSE_BY}:",
        "",
        "| site | users | world | planning-oracle | learned |",
        "| --- | ---: | --- | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['site']} | {r['users']} | {r['world']} | {r['planner_lost_share']:.0%} | "
            f"{r['learned_lost_share']:.0%} |"
        )
    if bins:
        lines += [
            "",
            f"Per heterogeneity bin (every set of the site pooled; bins of at least "
            f"{MIN_BIN_EPISODES} episodes):",
            "",
            "| site | H | episodes | " + " | ".join(names) + " |",
            "| --- | --- | ---: | " + " | ".join("---:" for _ in names) + " |",
        ]
        for b in bins:
            cells = [f"{b['means'][n]:.3f}" for n in names]
            lines.append(
                f"| {b['site']} | {b['h_bin'][0]:.2f}–{b['h_bin'][1]:.2f} | {b['episodes']} | "
                + " | ".join(cells)
                + " |"
            )
    return "\n".join(lines) + "\n"


def _figure(work: Path, users: int, out: Path) -> None:
    """Mean utility per step of each policy (over the set's scenarios), a panel per site and
    world: how each gets there and what it holds, flown round the buildings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(
        len(WORLDS), len(SITES), figsize=(4.2 * len(SITES), 3.2 * len(WORLDS)), sharey=True
    )
    for row, world in enumerate(WORLDS):
        for column, site in enumerate(SITES):
            ax = axes[row][column]
            results = json.loads((work / f"eval_{site}_{users}_{world}.json").read_text())
            for result in results["results"]:
                traces = np.array([s["trace"] for s in result["scenarios"]], dtype=float)
                steps = np.arange(1, traces.shape[1] + 1)
                ax.plot(steps, traces.mean(axis=0), label=result["policy"], linewidth=1.4)
            ax.set_title(f"{site}, {world}, {users} users", fontsize=9)
            ax.set_xlabel("step (s)")
            ax.grid(alpha=0.3)
        axes[row][0].set_ylabel("mean utility")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=Path("runs/sites_closed_loop"))
    parser.add_argument("--scenarios", type=int, default=16, help="per site and user count")
    parser.add_argument("--users", default="3,10")
    parser.add_argument("--episode-steps", type=int, default=40)
    parser.add_argument("--aggregate", action="store_true", help="only summarise --work")
    parser.add_argument("--figure-users", type=int, default=10, help="the figure's user count")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/sites_closed_loop")
    args = parser.parse_args()
    if not args.checkpoint.exists() and not args.aggregate:
        parser.error(f"--checkpoint: {args.checkpoint}: no such file")
    args.work.mkdir(parents=True, exist_ok=True)
    users_counts = [int(u) for u in args.users.split(",")]
    rows, bins = [], []
    for site in SITES:
        paths = []
        for users in users_counts:
            for world in WORLDS:
                path = args.work / f"eval_{site}_{users}_{world}.json"
                if not args.aggregate:
                    path = _evaluate(args, site, users, world)
                rows.append(_summary(path, site, users, world))
                paths.append(path)
        bins += _bins(paths, site)
    document = {
        "command": " ".join(["python", *sys.argv]),
        "checkpoint": str(args.checkpoint),
        "episode_steps": args.episode_steps,
        "rows": rows,
        "h_bins": bins,
    }
    args.out.with_suffix(".json").write_text(json.dumps(document, indent=1) + "\n")
    args.out.with_suffix(".md").write_text(_markdown(rows, bins))
    if args.figure_users in users_counts:
        _figure(args.work, args.figure_users, args.out.with_suffix(".png"))
    print(_markdown(rows, bins))
    return 0


if __name__ == "__main__":
    sys.exit(main())
