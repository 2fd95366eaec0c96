"""``tupa eval`` and ``tupa report`` (policies package). Argparse only at import: numpy,
matplotlib and friends load in handlers."""

from __future__ import annotations

import argparse
from pathlib import Path

from policies.train_cli import register as register_train

_EVAL_DESCRIPTION = """\
Evaluate placement policies on a scenario set: one stochastic episode per scenario (the
paper's 100 steps of 1 s by default), the same fading draws for every policy on a scenario
(scenario i is reset with seed S + i). A static policy holds its position for the whole episode.

Per scenario: utility = the episode's mean utility; throughput_bps = mean aggregate throughput;
delay_s = mean of the users' mean delay; plr = mean of the users' mean packet loss ratio;
heterogeneity = the scenario's index H.

A --policy is a baseline name or a trained checkpoint (model.zip, or a tupa train output
directory): DDQN checkpoints act in the discrete environment, DDPG ones in the continuous one.

Output (--json): with one --policy, the object
  {"policy", "n_scenarios", "mean_utility", "median_utility", "p25_utility", "seed",
   "queueing", "episode_steps", "mode", "scenarios": [{"id", "utility", "heterogeneity",
   "throughput_bps", "delay_s", "plr", "uav_xyz_m", "ratio_to_oracle"}]}
(ratio_to_oracle: the scenario's utility over the oracle's; the oracle is evaluated on the side
when it is not among the policies)
with several, {"results": [object, ...]} in the order given. The file is written atomically,
and not at all on an error. Prints a summary table and the mean utility per heterogeneity bin
(width 0.05) with each policy's gain over min-distance.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from sim.config import QUEUEING_CHOICES  # sim.cli already loads it; no torch here

    evaluate = subparsers.add_parser(
        "eval",
        help="evaluate placement policies on a scenario file and write the results as JSON",
        description=_EVAL_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    evaluate.add_argument(
        "--policy",
        action="append",
        required=True,
        metavar="NAME",
        help=(
            "policy to evaluate, repeat for several: min-distance (the paper's baseline), "
            "load-weighted, oracle (best static position found with the model: the upper "
            "bound), or a trained checkpoint (a model.zip or a tupa train output directory)"
        ),
    )
    evaluate.add_argument(
        "--scenarios",
        type=Path,
        required=True,
        metavar="FILE",
        help="scenario file (tupa-scenarios/1 JSON)",
    )
    evaluate.add_argument(
        "--json", type=Path, required=True, metavar="OUT", help="output file (JSON)"
    )
    evaluate.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="S",
        help="fading seed; scenario i uses S + i (default 0)",
    )
    evaluate.add_argument(
        "--queueing",
        choices=QUEUEING_CHOICES,
        default="fq-codel",
        metavar="Q",
        help="queueing above the Wi-Fi MAC: fq-codel (default) or mac-only",
    )
    evaluate.add_argument(
        "--episode-steps",
        type=int,
        default=100,
        metavar="N",
        help="steps (of 1 s) per episode (default 100, the paper's T)",
    )
    evaluate.add_argument(
        "--no-progress", action="store_true", help="no progress bar (it goes to stderr)"
    )
    evaluate.set_defaults(handler=_eval)
    _register_report(subparsers)
    register_train(subparsers)


def _eval(args: argparse.Namespace) -> int:
    from policies.baselines import BASELINES, make_policy
    from policies.evaluation import evaluate_policy, format_results
    from sim.config import NetworkConfig
    from sim.errors import InputError
    from sim.files import atomic_write_json, load_scenarios

    names = list(dict.fromkeys(args.policy))  # drop repeats, keep the order
    for name in names:
        if name not in BASELINES and not Path(name).exists():
            raise InputError(
                f"--policy: {name!r} is neither a policy ({', '.join(BASELINES)}) "
                "nor an existing checkpoint"
            )
    if args.episode_steps < 1:
        raise InputError(f"--episode-steps: must be at least 1, got {args.episode_steps}")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")

    area, scenarios = load_scenarios(args.scenarios)
    if not scenarios:
        raise InputError(f"{args.scenarios}: scenarios: empty (nothing to evaluate)")
    network = NetworkConfig().with_queueing(args.queueing)
    policies = []
    for name in names:
        if name in BASELINES:
            policies.append(make_policy(name, area, network, episode_steps=args.episode_steps))
        else:
            from policies.agents import TrainedAgent

            policies.append(TrainedAgent.load(Path(name), area))
    results = []
    for policy in policies:
        results.append(
            evaluate_policy(
                policy,
                scenarios,
                area,
                seed=args.seed,
                queueing=args.queueing,
                episode_steps=args.episode_steps,
                progress=not args.no_progress,
            )
        )
    _add_ratio_to_oracle(results, policies, scenarios, area, network, args)
    document = results[0] if len(results) == 1 else {"results": results}
    try:
        atomic_write_json(args.json, document)
    except OSError as exc:
        raise InputError(f"{args.json}: cannot write: {exc.strerror or exc}") from None
    print(
        f"evaluated {', '.join(names)} on {len(scenarios)} scenarios "
        f"({args.queueing}, {args.episode_steps} steps, seed {args.seed}); wrote {args.json}"
    )
    print(format_results(results))
    return 0


_REPORT_DESCRIPTION = """\
Draw the paper's figures and write their tables from tupa eval results.

Reads every *.json in --results written by tupa eval (one policy or {"results": [...]}); other
JSON files are skipped with a warning, and each policy may appear in one file only. All policies
must have been evaluated on the same scenarios (same ids, same heterogeneity): otherwise an
error names the two policies. An optional learning_curve.json in --results (format
tupa-learning-curve/1, written by the trainer) adds the learning-curve figure and table.

Writes to --out (created if missing): utility_cdf.png, throughput_cdf.png, delay_cdf.png,
plr_cdf.png, metrics_cdf.png (the three side by side), utility_by_heterogeneity.png (bins of
0.05), learning_curve.png (with a learning curve) and results.md (summary, per-bin and
learning-curve tables, and the paper's two headline numbers, "1.75x at the 25th percentile"
and "~4x in the most heterogeneous bin", as measured against min-distance). Each file is
written atomically, and none at all on bad input.
"""


def _register_report(subparsers: argparse._SubParsersAction) -> None:
    report = subparsers.add_parser(
        "report",
        help="draw the paper's figures and write results.md from tupa eval results",
        description=_REPORT_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    report.add_argument(
        "--results",
        type=Path,
        required=True,
        metavar="DIR",
        help="directory with tupa eval JSON files (and optionally learning_curve.json)",
    )
    report.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="output directory for PNGs and results.md",
    )
    report.set_defaults(handler=_report)


def _report(args: argparse.Namespace) -> int:
    from policies.report import build_report

    report = build_report(args.results, args.out)
    names = ", ".join(path.name for path in report.written)
    print(f"wrote {len(report.written)} files to {args.out}: {names}")
    for line in report.headlines:
        print(line)
    return 0


def _add_ratio_to_oracle(
    results: list[dict], policies: list, scenarios: list, area, network, args: argparse.Namespace
) -> None:
    """Add each scenario's ``ratio_to_oracle`` (utility / the oracle's on that scenario) to every
    result; the oracle is evaluated on the side when it is not among the policies."""
    from policies.baselines import make_policy
    from policies.evaluation import evaluate_policy

    oracle = next((r for r in results if r["policy"] == "oracle"), None)
    if oracle is None:
        oracle = evaluate_policy(
            make_policy("oracle", area, network, episode_steps=args.episode_steps),
            scenarios,
            area,
            seed=args.seed,
            queueing=args.queueing,
            episode_steps=args.episode_steps,
            progress=not args.no_progress,
        )
    best = [row["utility"] for row in oracle["scenarios"]]
    for result in results:
        for row, oracle_utility in zip(result["scenarios"], best, strict=True):
            row["ratio_to_oracle"] = row["utility"] / oracle_utility if oracle_utility > 0 else None
