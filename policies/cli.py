"""``tupa eval`` (policies package). Argparse only at import: numpy and friends load in handlers."""

from __future__ import annotations

import argparse
from pathlib import Path

_EVAL_DESCRIPTION = """\
Evaluate placement policies on a scenario set: one stochastic episode per scenario (the
paper's 100 steps of 1 s by default), the same fading draws for every policy on a scenario
(scenario i is reset with seed S + i). A static policy holds its position for the whole episode.

Per scenario: utility = the episode's mean utility; throughput_bps = mean aggregate throughput;
delay_s = mean of the users' mean delay; plr = mean of the users' mean packet loss ratio;
heterogeneity = the scenario's index H.

Output (--json): with one --policy, the object
  {"policy", "n_scenarios", "mean_utility", "median_utility", "p25_utility",
   "scenarios": [{"id", "utility", "heterogeneity", "throughput_bps", "delay_s", "plr"}]}
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
            "load-weighted, oracle (best static position found with the model: the upper bound)"
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


def _eval(args: argparse.Namespace) -> int:
    from policies.baselines import BASELINES, make_policy
    from policies.evaluation import evaluate_policy, format_results
    from sim.config import NetworkConfig
    from sim.errors import InputError
    from sim.files import atomic_write_json, load_scenarios

    names = list(dict.fromkeys(args.policy))  # drop repeats, keep the order
    for name in names:
        if name not in BASELINES:
            raise InputError(f"--policy: unknown policy {name!r} (choices: {', '.join(BASELINES)})")
    if args.episode_steps < 1:
        raise InputError(f"--episode-steps: must be at least 1, got {args.episode_steps}")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")

    area, scenarios = load_scenarios(args.scenarios)
    if not scenarios:
        raise InputError(f"{args.scenarios}: scenarios: empty (nothing to evaluate)")
    network = NetworkConfig().with_queueing(args.queueing)
    results = []
    for name in names:
        policy = make_policy(name, area, network, episode_steps=args.episode_steps)
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
