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
    _uniform_help(parser)
    return parser


REQUIRED_GROUP = "required arguments"


class _DefaultsShown:
    """Help formatter mix-in: ``(default: X)`` after an option's help, unless the help already
    says its default or it has none worth saying (None, False, an empty list)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if _has_default(action) and "default" not in text.lower():
            text = f"{text} (default: %(default)s)" if text else "(default: %(default)s)"
        return text


def _has_default(action: argparse.Action) -> bool:
    return (
        bool(action.option_strings)
        and action.default not in (None, False, argparse.SUPPRESS)
        and action.default != []
        and not isinstance(action, argparse._HelpAction | argparse._VersionAction)
    )


_FORMATTERS: dict[type, type] = {}


def _uniform_help(parser: argparse.ArgumentParser) -> None:
    """Every subcommand's ``--help`` alike, whichever package declared it: each option's
    default shown (:class:`_DefaultsShown` over the parser's own formatter, so a raw
    description stays raw), and the options argparse requires listed first, under
    :data:`REQUIRED_GROUP` (a parser may declare a group of that title itself, with a
    description, where options are required only in some uses, as ``tupa train`` does)."""
    base = parser.formatter_class
    if base not in _FORMATTERS:
        _FORMATTERS[base] = type(f"Tupa{base.__name__}", (_DefaultsShown, base), {})
    parser.formatter_class = _FORMATTERS[base]
    for action in parser._actions:
        if action.help is None and _has_default(action):
            action.help = "(default: %(default)s)"
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _uniform_help(child)
    groups = parser._action_groups
    required = [a for a in parser._optionals._group_actions if a.required and a.option_strings]
    if required:
        group = next((g for g in groups if g.title == REQUIRED_GROUP), None)
        group = group or parser.add_argument_group(REQUIRED_GROUP)
        for action in required:
            parser._optionals._group_actions.remove(action)
            group._group_actions.append(action)
    for group in [g for g in groups if g.title == REQUIRED_GROUP]:
        groups.remove(group)
        groups.insert(groups.index(parser._optionals), group)  # after the positionals


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
