"""``tupa train``: offline training of a DDQN or DDPG placement policy (argparse only here)."""

from __future__ import annotations

import argparse
from pathlib import Path

_DESCRIPTION = """\
Train a TUPA policy on the embedded network model (paper §IV-A).

Strategies: spec trains on the test scenarios cycled in order; gen10k on as many unique
generated scenarios as episodes, each once; gen500 on 500 unique generated scenarios cycled.
Presets (policies/training/presets.py): paper (the paper's hyper-parameters) or fast (tuned for 2
CPU cores). Writes into --out: model.zip + model.json (the final checkpoint and its metadata),
checkpoints/latest.zip every --checkpoint-every episodes, learning_curve.json, run.json, and
TensorBoard logs in tb/.

Progress goes to standard error: once a few episodes have been timed with learning under way,
one line with the estimated time of the run, then the episodes done and the time left (a bar
on a terminal, a line every 30 s elsewhere), and the final evaluation's progress.

Ctrl-C or SIGTERM (timeout, systemd, docker stop) saves checkpoints/latest.zip and run.json,
says so, and exits (130, 143); --resume DIR continues it, tupa eval --policy DIR evaluates it.
The replay buffer (hundreds of MB) is saved with it only with --save-replay-buffer; without,
a resumed run starts from an empty buffer.
"""


_USAGE = """\
%(prog)s --algo {ddqn,ddpg} --strategy {spec,gen10k,gen500} --episodes N
                  --test-scenarios FILE --out DIR [options]
       %(prog)s --resume DIR [--episodes N] [options]
       %(prog)s --uavs K --algo {ddqn,ddpg} --episodes N --out DIR [options]"""


SINGLE_ONLY = (
    "strategy",
    "test_scenarios",
    "queueing",
    "world_set",
    "checkpoint_every",
    "curve_scenarios",
    "no_final_eval",
    "save_replay_buffer",
)
"""The options (argparse destinations) of a single-UAV run that a fleet run would not use: a
fleet run refuses them, named, when they differ from the parser's defaults."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train",
        allow_abbrev=False,
        help="train a DDQN or DDPG placement policy",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        usage=_USAGE,
    )
    # Required for a new run, but not with --resume DIR (nor all of them for a fleet): checked
    # in _train, listed apart so that --help shows them as required.
    required = parser.add_argument_group(
        "required arguments",
        "a new run needs all five; --resume DIR none of them;\n"
        "a fleet (--uavs K > 1) only --algo, --episodes and --out",
    )
    required.add_argument("--algo", choices=("ddqn", "ddpg"), help="algorithm")
    required.add_argument("--strategy", choices=("spec", "gen10k", "gen500"), help="training data")
    required.add_argument(
        "--episodes",
        type=int,
        help="training episodes (the paper: 10000); with --resume, a higher target",
    )
    parser.add_argument(
        "--preset", choices=("paper", "fast"), default="fast", help="hyper-parameters"
    )
    required.add_argument(
        "--test-scenarios", type=Path, metavar="FILE", help="test set (tupa-scenarios/1 JSON)"
    )
    parser.add_argument("--seed", type=int, default=1, help="random seed of the run")
    required.add_argument("--out", type=Path, metavar="DIR", help="output directory")
    parser.add_argument(
        "--queueing",
        choices=("fq-codel", "mac-only"),
        default="fq-codel",
        metavar="Q",
        help="the access point's queueing: fq-codel or mac-only",
    )
    parser.add_argument(
        "--uavs",
        type=int,
        default=1,
        metavar="K",
        help="fleet size 1..8 (default 1). K > 1 trains one network shared by the K UAVs "
        "(policies/training/fleet_training.py; --algo ddpg (--action coordinates or residual) "
        "or ddqn, --episodes, --out, --preset, --seed, --world (default closed-loop), --families, "
        "--users (default 20), --envs fleets per batch)",
    )
    parser.add_argument(
        "--world",
        default=None,
        metavar="NAME",
        help="the world to train (and evaluate) in: paper (default), closed-loop, "
        "closed-loop-moving; several separated by commas: one drawn per episode, evaluations in "
        "the first",
    )
    parser.add_argument(
        "--environment",
        default=None,
        metavar="ENV",
        help="the channel environment (open, suburban, urban, dense-urban, highrise-urban, or "
        "site:PATH, a site directory); several separated by commas: one drawn per episode (with "
        "the world), evaluations in the first; a fleet (--uavs K > 1): one. Default: the test "
        "set's (a fleet: the world's, open)",
    )
    parser.add_argument(
        "--action",
        choices=("coordinates", "residual"),
        default="coordinates",
        help="DDPG's action: absolute coordinates (the paper) or residual, a correction to the "
        "load-weighted placement (policies/learned/residual.py)",
    )
    parser.add_argument(
        "--residual-radius-m",
        type=float,
        default=None,
        metavar="M",
        help="with --uavs K > 1 and --action residual: how far (m, per axis) each UAV may move "
        "from its place in the prior (default 125)",
    )
    parser.add_argument(
        "--prior",
        choices=("kmeans-load-weighted", "kmeans-scored"),
        default=None,
        help="with --uavs K > 1 and --action residual: the placement the residual corrects: "
        "load-weighted k-means (default) or kmeans-scored, k-means partitions scored on the "
        "fleet model from where the fleet is (policies/learned/fleet_residual.py; slower per step)",
    )
    parser.add_argument(
        "--imitate",
        type=int,
        default=0,
        metavar="N",
        help="experimental, with --uavs K > 1 and --algo ddqn or --action residual: first fit "
        "the DDQN's moves or the residual actor to the fleet search oracle's decisions over N "
        "teacher episodes (policies/training/fleet_imitation.py; docs/results.md has what it "
        "flies); --episodes of reinforcement learning follow (may be 0)",
    )
    parser.add_argument(
        "--teacher",
        choices=("search", "local"),
        default="search",
        help="with --imitate: the oracle search that teaches: 'search' (one sweep over the "
        "area from the k-means placements, then refinement) or 'local' (the k-means "
        "placements refined only) (default search)",
    )
    parser.add_argument(
        "--symmetries",
        action="store_true",
        help="with --imitate: fit every mini-batch mirrored or rotated by one of the square "
        "area's eight symmetries, drawn at random (eight times the distinct teacher targets)",
    )
    parser.add_argument(
        "--dagger",
        type=int,
        default=0,
        metavar="R",
        help="with --imitate N: R more rounds in which the fitted policy flies N episodes, the "
        "teacher labels every state it visits, and the fit is redone on all the data (DAgger; "
        "default 0)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="W",
        help="with --imitate: processes the teacher episodes are spread over (default 1)",
    )
    parser.add_argument(
        "--envs",
        type=int,
        default=1,
        metavar="E",
        help="episodes stepping as one numpy batch (sim.vector_env; default 1). Gradient steps "
        "are counted per batch step: raise the preset's gradient_steps to keep the update ratio",
    )
    parser.add_argument(
        "--families",
        default="exponential",
        metavar="F1,F2",
        help="scenario families generated training scenarios come from (default exponential; "
        "see tupa scenarios generate --family)",
    )
    parser.add_argument(
        "--users",
        default=None,
        metavar="LO-HI",
        help="user counts of generated training scenarios, a range (default: the test set's)",
    )
    parser.add_argument(
        "--world-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one setting of the world (repeatable), e.g. flight.horizontal_mps=5",
    )
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        default=500,
        metavar="EPISODES",
        help="episodes between two saves of checkpoints/latest.zip",
    )
    parser.add_argument(
        "--curve-scenarios",
        type=int,
        default=100,
        metavar="N",
        help="test scenarios evaluated at 100, 200, 500, ... episodes (default 100)",
    )
    parser.add_argument(
        "--no-final-eval", action="store_true", help="skip the final evaluation on the test set"
    )
    parser.add_argument(
        "--no-progress", action="store_true", help="no progress, estimate or time left"
    )
    parser.add_argument(
        "--save-replay-buffer",
        action="store_true",
        help="on Ctrl-C or SIGTERM, also save the replay buffer (checkpoints/latest_replay.pkl, "
        "up to about 1 GB with the presets' buffers), so that --resume continues with it",
    )
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the interrupted run in DIR (its settings; --episodes may raise the target)",
    )
    parser.set_defaults(
        handler=_train,
        single_only_defaults={dest: parser.get_default(dest) for dest in SINGLE_ONLY},
    )


def _user_range(text: str | None) -> tuple[int, int] | None:
    from sim.errors import InputError

    if text is None:
        return None
    low, _, high = text.partition("-")
    try:
        return (int(low), int(high or low))
    except ValueError:
        raise InputError(f"--users: expected a count or a range LO-HI, got {text!r}") from None


def _train(args: argparse.Namespace) -> int:
    from sim.errors import InputError

    if not 1 <= args.uavs <= 8:
        raise InputError(f"--uavs: must be in 1..8, got {args.uavs}")
    if args.uavs > 1:
        return _train_fleet(args)
    if args.residual_radius_m is not None:
        raise InputError("--residual-radius-m: for fleets only (--uavs K > 1)")
    if args.prior is not None:
        raise InputError("--prior: for fleets only (--uavs K > 1 --action residual)")
    if args.imitate:
        raise InputError("--imitate: for fleets only (--uavs K > 1)")
    for flag, given in (
        ("--workers", args.workers != 1),
        ("--teacher", args.teacher != "search"),
        ("--symmetries", args.symmetries),
        ("--dagger", args.dagger != 0),
    ):
        if given:
            raise InputError(f"{flag}: for fleets only (--uavs K > 1 --imitate N)")
    if args.world is None:
        args.world = "paper"
    if args.resume is not None:
        from policies.training.training import resume_config, train

        config = resume_config(args.resume, args.episodes, args.save_replay_buffer)
        metadata = train(config, resume=True)
    else:
        missing = [
            f"--{name.replace('_', '-')}"
            for name in ("algo", "strategy", "episodes", "test_scenarios", "out")
            if getattr(args, name) is None
        ]
        if missing:
            raise InputError(f"{', '.join(missing)}: required (unless --resume is given)")
        if (args.out / "model.zip").exists() or (args.out / "run.json").exists():
            raise InputError(
                f"--out: {args.out} already holds a training run (use --resume or another dir)"
            )
        from policies.training.training import config_from_args, train

        config = config_from_args(
            args.algo,
            args.strategy,
            args.episodes,
            args.preset,
            args.seed,
            args.test_scenarios,
            args.out,
            queueing=args.queueing,
            world=args.world,
            world_set=tuple(args.world_set),
            environments=tuple(e.strip() for e in (args.environment or "").split(",") if e.strip()),
            families=tuple(f.strip() for f in args.families.split(",")),
            action=args.action,
            envs=args.envs,
            users=_user_range(args.users),
            checkpoint_every=args.checkpoint_every,
            curve_scenarios=args.curve_scenarios,
            final_eval=not args.no_final_eval,
            progress=not args.no_progress,
            save_replay_buffer=args.save_replay_buffer,
        )
        metadata = train(config)
    evaluation = metadata.get("evaluation")
    print(
        f"trained {metadata['algorithm']}-{metadata['strategy']} for {metadata['episodes']} "
        f"episodes ({metadata['timesteps']} steps) in {metadata['wall_time_s']:.0f} s on "
        f"{metadata['device']}; wrote {config.out_dir / 'model.zip'}"
    )
    if evaluation:
        print(
            f"test set ({evaluation['n_scenarios']} scenarios): mean utility "
            f"{evaluation['policy']['mean_utility']:.3f} (min-distance "
            f"{evaluation['min-distance']['mean_utility']:.3f}, oracle "
            f"{evaluation['oracle']['mean_utility']:.3f}; "
            f"{evaluation['ratio_to_oracle']:.3f} of the oracle)"
        )
    return 0


def _train_fleet(args: argparse.Namespace) -> int:
    """``tupa train --uavs K`` with K > 1: one network shared by the fleet's UAVs."""
    import shlex

    from sim.errors import InputError

    if args.resume is not None:
        raise InputError("--uavs: fleet runs cannot be resumed yet (drop --resume)")
    missing = [f"--{name}" for name in ("algo", "episodes", "out") if getattr(args, name) is None]
    if missing:
        raise InputError(f"{', '.join(missing)}: required with --uavs K > 1")
    defaults = args.single_only_defaults
    ignored = [
        f"--{dest.replace('_', '-')}"
        for dest in SINGLE_ONLY
        if getattr(args, dest) != defaults[dest]
    ]
    if ignored:
        raise InputError(
            f"{', '.join(ignored)}: for single-UAV runs only (a fleet run, --uavs K > 1, "
            "would not use it)"
        )
    environments = [e.strip() for e in (args.environment or "").split(",") if e.strip()]
    if len(environments) > 1:
        raise InputError(
            f"--environment: a fleet run trains in one environment, got {len(environments)} "
            f"({', '.join(environments)})"
        )
    if (args.out / "model.zip").exists():
        raise InputError(f"--out: {args.out} already holds a trained model (use another dir)")
    from policies.training.fleet_training import FleetTrainConfig, train_fleet

    config = FleetTrainConfig(
        n_uavs=args.uavs,
        episodes=args.episodes,
        out_dir=args.out,
        algorithm=args.algo,
        preset=args.preset,
        seed=args.seed,
        world=args.world or "closed-loop",
        environment=environments[0] if environments else None,
        families=tuple(f.strip() for f in args.families.split(",")),
        users=_user_range(args.users) or (20, 20),
        n_fleets=args.envs,
        action=args.action,
        **({"prior": args.prior} if args.prior is not None else {}),
        imitate=args.imitate,
        imitate_teacher=args.teacher,
        imitate_symmetries=args.symmetries,
        imitate_rounds=args.dagger,
        workers=args.workers,
        **(
            {"residual_radius_m": args.residual_radius_m}
            if args.residual_radius_m is not None
            else {}
        ),
        command=shlex.join(args.command_line),
        progress=not args.no_progress,
    )
    metadata = train_fleet(config)
    imitation = metadata["imitation"]
    fitted = ""
    if imitation and "validation_mse" in imitation:
        fitted = (
            f"fitted to {imitation['samples']} teacher decisions (validation error "
            f"{imitation['validation_mse']:.4f}, zero action "
            f"{imitation['zero_action_validation_mse']:.4f}), "
        )
    elif imitation:
        fitted = (
            f"fitted to {imitation['samples']} teacher moves (validation accuracy "
            f"{imitation['validation_accuracy']:.3f}, 'stay' "
            f"{imitation['stay_validation_accuracy']:.3f}), "
        )
    print(
        f"trained a shared {metadata['algorithm']} policy for {metadata['n_uavs_trained']} UAVs, "
        f"{fitted}over {metadata['episodes']} episodes ({metadata['timesteps']} agent-steps) in "
        f"{metadata['wall_time_s']:.0f} s on {metadata['device']}; wrote "
        f"{config.out_dir / 'model.zip'}"
    )
    return 0
