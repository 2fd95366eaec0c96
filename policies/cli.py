"""``tupa eval`` and ``tupa report`` (policies package). Argparse only at import: numpy,
matplotlib and friends load in handlers."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from policies.sweep.cli import register as register_sweep
from policies.training.train_cli import register as register_train

_EVAL_DESCRIPTION = """\
Evaluate placement policies on a scenario set: one episode per scenario in a world (--world:
paper, the paper's protocol with a teleporting UAV, by default; closed-loop flies at 10 m/s
horizontally and 3 m/s vertically from home, with reports one step old; closed-loop-moving adds
walking users and changing demand; --world-set key=value changes any setting, e.g.
flight.horizontal_mps=5). Every policy sees the same fading draws, user motion and demand on a
scenario (scenario i is reset with seed S + i). A static policy (min-distance, load-weighted,
oracle) is re-placed every step from the latest report; in the closed loop the oracle is the
tracking oracle, the upper bound of the loop. Under the paper's protocol a static policy starts
at its placement; in the closed-loop worlds every policy starts at home.

Per scenario: utility = the episode's mean utility; throughput_bps = mean aggregate throughput;
delay_s = mean of the users' mean delay; plr = mean of the users' mean packet loss ratio;
heterogeneity = the scenario's index H; time_to_final_s = when the utility came within 0.01 of
its final value (5-step moving mean against the mean of the last 10 steps); trace = the utility
of every step.

A --policy is a baseline name or a trained checkpoint (model.zip, or a tupa train output
directory): DDQN checkpoints act in the discrete environment, DDPG ones in the continuous one.

Output (--json): with one --policy, the object
  {"policy", "world", "n_scenarios", "mean_utility", "median_utility", "p25_utility",
   "mean_time_to_final_s", "seed", "queueing", "episode_steps", "mode", "scenarios": [{"id",
   "utility", "heterogeneity", "throughput_bps", "delay_s", "plr", "time_to_final_s",
   "uav_xyz_m", "trace", "ratio_to_oracle"}]}
(ratio_to_oracle: the scenario's utility over the oracle's; the oracle is evaluated on the side
when it is not among the policies)

With --uavs K (2..8): a fleet of K UAVs in the fleet environment (world closed-loop unless
--world says otherwise), one episode per scenario from the fleet's homes. --policy is then
kmeans-min-distance, kmeans-load-weighted, kmeans-scored (k-means partitions scored on the
fleet model: milliseconds), fleet-oracle (the search oracle over the world's
network and episode: seconds per search) or a fleet checkpoint (tupa train --uavs K, any K); a
fleet checkpoint decides every step, the placements are placed on the first report and
re-placed every --replan-every decisions (default: once per episode). Per scenario: utility,
served_fraction, jain_fairness, min_throughput_bps (episode means), handovers (over the
episode), heterogeneity. Output: one "tupa-fleet-eval/1" document per policy (several:
{"format", "results": [...]}), with ratio_to_oracle when fleet-oracle is among the policies
(policies/evaluation/fleet_evaluation.py); tupa report draws the fleet figures from them.
with several, {"results": [object, ...]} in the order given; --altitude-profiles N adds
"altitude_profiles": [{"id", "environment", "altitudes_m", "best_utility", "best_xy_m"}] beside
them (policies/placements/altitude.py). The file is written atomically,
and not at all on an error. Prints a summary table and the mean utility per heterogeneity bin
(width 0.05) with each policy's gain over min-distance.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from sim.config import QUEUEING_CHOICES  # sim.cli already loads it; no torch here

    evaluate = subparsers.add_parser(
        "eval",
        allow_abbrev=False,
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
            "load-weighted, min-distance-env (min-distance at the altitude of best mean SNR in "
            "the area's environment), oracle (best static position found with the model, "
            "re-placed every decision: the tracking oracle), planning-oracle (a receding-horizon "
            "planner over flown trajectories: the closed loop's reference), default (what tupa "
            "serve serves over the environment evaluated: policies/served_defaults.json), or a "
            "trained checkpoint (a model.zip or a tupa train output directory)"
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
    add_world_arguments(evaluate)
    evaluate.add_argument(
        "--queueing",
        choices=QUEUEING_CHOICES,
        default=None,
        metavar="Q",
        help="queueing above the Wi-Fi MAC: fq-codel (default) or mac-only",
    )
    evaluate.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        metavar="N",
        help="steps per episode (default: the world's, 100 as the paper's T)",
    )
    evaluate.add_argument(
        "--altitude-profiles",
        type=int,
        default=0,
        metavar="N",
        help="also record utility against altitude (the best placement at each altitude) for "
        "the first N scenarios, for tupa report's altitude figure (default 0; a second or so "
        "per scenario)",
    )
    evaluate.add_argument(
        "--no-progress", action="store_true", help="no progress bar (it goes to stderr)"
    )
    evaluate.add_argument(
        "--backend",
        choices=("local", "ray"),
        default=None,
        help="fan the scenarios out in slices: local (one process per slice, --workers at "
        "once) or ray (tasks on a private Ray instance, or a cluster with --address); the same "
        "results as in one process (policies/sweep/fanout.py). Default: one process",
    )
    evaluate.add_argument(
        "--workers", type=int, default=None, metavar="N", help="with --backend: slices at once"
    )
    evaluate.add_argument(
        "--address", default=None, metavar="ADDR", help="with --backend ray: a running cluster"
    )
    evaluate.add_argument(
        "--uavs",
        type=int,
        default=None,
        metavar="K",
        help="evaluate fleet policies for K UAVs (2..8) in the fleet environment (see above)",
    )
    evaluate.add_argument(
        "--replan-every",
        type=int,
        default=None,
        metavar="N",
        help="with --uavs: re-place the k-means and oracle placements every N decisions "
        "(default: once per episode)",
    )
    evaluate.set_defaults(handler=_eval)
    _register_report(subparsers)
    register_train(subparsers)
    register_sweep(subparsers)


def add_world_arguments(parser: argparse.ArgumentParser) -> None:
    """``--world NAME`` and ``--world-set key=value`` (``tupa eval``, ``train``, ``demo``)."""
    parser.add_argument(
        "--world",
        default=None,
        metavar="NAME",
        help="the world: paper (default for eval), closed-loop, closed-loop-moving",
    )
    parser.add_argument(
        "--world-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=(
            "change one setting of the world, repeat for several: e.g. flight.horizontal_mps=5, "
            "mobility.model=group, demand.quiet_rate_per_s=0.01, reports.age_steps=2, home=random"
        ),
    )
    parser.add_argument(
        "--environment",
        default=None,
        metavar="NAME",
        help="what stands on the ground: open, suburban, urban, dense-urban, highrise-urban, or "
        "site:PATH (a site directory, docs/sites.md) (default: the scenario file's, open when "
        "it says none)",
    )


def check_scenarios_in(world: Any, scenarios: Sequence[Any], path: Path) -> None:
    """Every scenario's users can stand in the world's area: on a site given by
    ``--environment`` or ``--world-set`` (not by the file, whose loading checked it), none
    inside a building (``FILE: scenario s0003: users[1]: (...) is inside a building on ...``)."""
    from sim.scenarios import check_scenario_area

    for scenario in scenarios:
        check_scenario_area(scenario, world.area, f"{path}: scenario {scenario.id}: ")


def _eval(args: argparse.Namespace) -> int:
    from policies.evaluation.evaluation import evaluate_policy, format_results
    from policies.registry import POLICY_NAMES, close_names, resolve_policy, unknown_name
    from policies.world_options import world_from_args
    from sim.atomic import atomic_write_json
    from sim.errors import InputError
    from sim.files import load_scenarios

    if args.uavs is not None:
        return _eval_fleet(args)
    if args.replan_every is not None:
        raise InputError("--replan-every: only with --uavs (fleet placements)")
    from policies.defaults import DEFAULT, served_default

    names = list(dict.fromkeys(_latest_of_interrupted(n) for n in args.policy))
    for name in names:
        if name != DEFAULT and name not in POLICY_NAMES and not Path(name).exists():
            close = close_names(name, POLICY_NAMES)
            if close:
                raise InputError(unknown_name(name, close, POLICY_NAMES, "--policy"))
            raise InputError(
                f"--policy: {name!r} is neither a policy ({', '.join(POLICY_NAMES)}) "
                "nor an existing checkpoint"
            )
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.altitude_profiles < 0:
        raise InputError(f"--altitude-profiles: must be >= 0, got {args.altitude_profiles}")

    area, scenarios = load_scenarios(args.scenarios)
    if not scenarios:
        raise InputError(f"{args.scenarios}: scenarios: empty (nothing to evaluate)")
    world = world_from_args(args, "paper", area)
    check_scenarios_in(world, scenarios, args.scenarios)
    if DEFAULT in names:  # what tupa serve would serve over this environment
        served = served_default(world.environment)
        print(f"--policy default: {served.policy} ({served.why})", file=sys.stderr)
        names = list(dict.fromkeys(served.policy if n == DEFAULT else n for n in names))
    policies = [resolve_policy(name, world) for name in names]
    results = []
    if args.backend is not None:  # fanned out in slices (policies/sweep/fanout.py)
        from policies.sweep.fanout import evaluate_from_args

        results, side = evaluate_from_args(names, len(scenarios), args)
        _add_ratio_to_oracle(results + side, scenarios, world, args)
    else:
        for policy in policies:
            results.append(
                evaluate_policy(
                    policy, scenarios, world, seed=args.seed, progress=not args.no_progress
                )
            )
        _add_ratio_to_oracle(results, scenarios, world, args)
    document = results[0] if len(results) == 1 else {"results": results}
    if args.altitude_profiles:
        from policies.placements.altitude import altitude_profile

        document["altitude_profiles"] = [
            altitude_profile(scenario, world).to_dict()
            for scenario in scenarios[: args.altitude_profiles]
        ]
    try:
        atomic_write_json(args.json, document)
    except OSError as exc:
        raise InputError(f"{args.json}: cannot write: {exc.strerror or exc}") from None
    print(
        f"evaluated {', '.join(names)} on {len(scenarios)} scenarios "
        f"(world {world.name}, environment {world.environment}, {world.network.queue.queueing}, "
        f"{world.episode_steps} steps, seed {args.seed}); wrote {args.json}"
    )
    print(format_results(results))
    return 0


def _latest_of_interrupted(spec: str) -> str:
    """``spec``, or for the directory of an interrupted training run (no ``model.zip``) its
    latest checkpoint, said on standard error."""
    from policies.learned.checkpoints import training_run
    from policies.registry import POLICY_NAMES

    if spec in POLICY_NAMES or spec == "default":
        return spec
    run = training_run(spec)
    if run is None or not run.interrupted or run.latest is None:
        return spec
    print(
        f"tupa eval: {spec}: an interrupted run (no model.zip): evaluating its latest "
        f"checkpoint, {run.latest} ({run.progress()})",
        file=sys.stderr,
    )
    return str(run.latest)


def _eval_fleet(args: argparse.Namespace) -> int:
    """``tupa eval --uavs K``: fleet policies on a scenario file
    (policies/evaluation/fleet_evaluation.py)."""
    from policies.evaluation.fleet_evaluation import (
        FLEET_EVAL_FORMAT,
        add_ratio_to_oracle,
        build_fleet_candidate,
        check_fleet_size,
        evaluate_fleet,
        format_fleet_results,
    )
    from policies.world_options import world_from_args
    from sim.atomic import atomic_write_json
    from sim.errors import InputError
    from sim.files import load_scenarios
    from sim.fleet import FleetConfig

    k = check_fleet_size(args.uavs)
    for option, given in (
        ("--backend", args.backend is not None),
        ("--workers", args.workers is not None),
        ("--address", args.address is not None),
        ("--altitude-profiles", args.altitude_profiles != 0),
    ):
        if given:
            raise InputError(f"{option}: not with --uavs (a single-UAV evaluation's option)")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.replan_every is not None and args.replan_every < 1:
        raise InputError(f"--replan-every: must be at least 1, got {args.replan_every}")
    area, scenarios = load_scenarios(args.scenarios)
    if not scenarios:
        raise InputError(f"{args.scenarios}: scenarios: empty (nothing to evaluate)")
    world = world_from_args(args, "closed-loop", area)
    check_scenarios_in(world, scenarios, args.scenarios)
    fleet = FleetConfig(n_uavs=k)
    replan = args.replan_every or world.episode_steps
    candidates: dict[str, object] = {}
    for spec in dict.fromkeys(args.policy):  # drop repeats, keep the order
        name, candidate = build_fleet_candidate(spec, k, world, fleet, args.seed, "--policy")
        if name in candidates:
            raise InputError(f"--policy: two policies are named {name!r} ({spec} is the second)")
        candidates[name] = candidate
    progress = not args.no_progress
    documents = [
        evaluate_fleet(c, scenarios, k, world, fleet, replan, args.seed, name=n, progress=progress)
        for n, c in candidates.items()
    ]
    add_ratio_to_oracle(documents)
    document = (
        documents[0] if len(documents) == 1 else {"format": FLEET_EVAL_FORMAT, "results": documents}
    )
    try:
        atomic_write_json(args.json, document)
    except OSError as exc:
        raise InputError(f"{args.json}: cannot write: {exc.strerror or exc}") from None
    print(
        f"evaluated {', '.join(candidates)} with {k} UAVs on {len(scenarios)} scenarios "
        f"(world {world.name}, environment {world.environment}, {world.episode_steps} steps, "
        f"placements re-placed every {replan}, seed {args.seed}); wrote {args.json}"
    )
    print(format_fleet_results(documents))
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

Given a tupa sweep directory (it holds sweep.json), merges the sweep instead: writes
sweep_learning_curve.png (median and inter-quartile band across seeds per version),
results.md (the trials, the paper's 4 versions, Gen500 vs Gen10k, the learning-curve table)
and best/<version>-e<episodes>.zip, the best seed of each cell exported (policies/report/sweep.py).

Given fleet results (tupa eval --uavs K files, format tupa-fleet-eval/1; not mixed with
single-UAV ones), writes fleet_metrics.png (one panel per metric: utility, served-user
fraction, Jain fairness, minimum user throughput, handovers per episode; a box per policy),
fleet_utility_by_heterogeneity.png and results.md (means, ratio to fleet-oracle, per-bin
table; policies/report/fleet.py).
"""


def _register_report(subparsers: argparse._SubParsersAction) -> None:
    report = subparsers.add_parser(
        "report",
        allow_abbrev=False,
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
    results: list[dict], scenarios: list, world: object, args: argparse.Namespace
) -> None:
    """Add each scenario's ``ratio_to_oracle`` (utility / the oracle's on that scenario) to every
    result; the oracle is evaluated on the side when it is not among the policies."""
    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import make_placement

    oracle = next((r for r in results if r["policy"] == "oracle"), None)
    if oracle is None:
        oracle = evaluate_policy(
            make_placement("oracle", world),
            scenarios,
            world,
            seed=args.seed,
            progress=not args.no_progress,
        )
    best = [row["utility"] for row in oracle["scenarios"]]
    for result in results:
        for row, oracle_utility in zip(result["scenarios"], best, strict=True):
            row["ratio_to_oracle"] = row["utility"] / oracle_utility if oracle_utility > 0 else None
