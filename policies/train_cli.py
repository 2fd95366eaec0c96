"""``tupa train``: offline training of a DDQN or DDPG placement policy (argparse only here)."""

from __future__ import annotations

import argparse
from pathlib import Path

_DESCRIPTION = """\
Train a TUPA policy on the embedded network model (paper §IV-A).

Strategies: spec trains on the test scenarios cycled in order; gen10k on as many unique
generated scenarios as episodes, each once; gen500 on 500 unique generated scenarios cycled.
Presets (policies/presets.py): paper (the paper's hyper-parameters) or fast (tuned for 2 CPU
cores). Writes into --out: model.zip + model.json (the final checkpoint and its metadata),
checkpoints/latest.zip every --checkpoint-every episodes, learning_curve.json, run.json, and
TensorBoard logs in tb/. Ctrl-C saves a resumable checkpoint; --resume DIR continues it.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train a DDQN or DDPG placement policy",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--algo", choices=("ddqn", "ddpg"), help="algorithm")
    parser.add_argument("--strategy", choices=("spec", "gen10k", "gen500"), help="training data")
    parser.add_argument("--episodes", type=int, help="training episodes (the paper: 10000)")
    parser.add_argument("--preset", choices=("paper", "fast"), default="fast")
    parser.add_argument(
        "--test-scenarios", type=Path, metavar="FILE", help="test set (tupa-scenarios/1 JSON)"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, metavar="DIR", help="output directory")
    parser.add_argument(
        "--queueing", choices=("fq-codel", "mac-only"), default="fq-codel", metavar="Q"
    )
    parser.add_argument("--checkpoint-every", type=int, default=500, metavar="EPISODES")
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
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the interrupted run in DIR (its settings; --episodes may raise the target)",
    )
    parser.set_defaults(handler=_train)


def _train(args: argparse.Namespace) -> int:
    from sim.errors import InputError

    if args.resume is not None:
        from policies.training import resume_config, train

        config = resume_config(args.resume, args.episodes)
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
        from policies.training import config_from_args, train

        config = config_from_args(
            args.algo,
            args.strategy,
            args.episodes,
            args.preset,
            args.seed,
            args.test_scenarios,
            args.out,
            queueing=args.queueing,
            checkpoint_every=args.checkpoint_every,
            curve_scenarios=args.curve_scenarios,
            final_eval=not args.no_final_eval,
            progress=not args.no_progress,
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
