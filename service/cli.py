"""The ``tupa`` command.

Each package declares its own subcommands in a light ``cli`` module (argparse only); the heavy
imports (numpy kernels, torch, FastAPI, pymavlink) happen inside the handlers, so ``tupa --help``
and ``tupa sim ...`` never pay for torch or FastAPI at start-up.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# Modules that contribute subcommands, each exposing ``register(subparsers)``.
_COMMAND_MODULES: tuple[str, ...] = (
    "sim.cli",
    "policies.cli",
    "sitl_mock.cli",
    "api.cli",
    "closed_loop.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tupa",
        allow_abbrev=False,
        description="Traffic-aware UAV placement: simulate, train, evaluate and serve.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module_name in _COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from sim.errors import InputError

    parser = build_parser()
    args = parser.parse_args(argv)
    # What was asked, for handlers that record their own command (a training run's metadata).
    args.command_line = ["tupa", *(sys.argv[1:] if argv is None else argv)]
    try:
        result = args.handler(args)
    except InputError as exc:
        print(f"tupa {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:  # Ctrl-C; a command may say what it saved, and where
        said = str(stop)
        print(f"tupa {args.command}: {said}" if said else "interrupted", file=sys.stderr)
        return int(getattr(stop, "exit_code", 130))
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
