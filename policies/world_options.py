"""The world a command line describes: :func:`world_from_args` (``--world``, ``--world-set``,
``--environment``, ``--queueing``, ``--episode-steps``), shared by ``tupa eval``, ``tupa train``
and the sweeps' trials (which rebuild it from the options they were given).
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from sim.config import NetworkConfig, check_environment
from sim.errors import InputError
from sim.world import World, get_world, world_with


def world_from_args(args: argparse.Namespace, default: str, area: object = None) -> World:
    """The world ``--world``/``--world-set`` describe (``InputError`` naming a bad setting),
    with ``--queueing`` and ``--episode-steps`` applied when given, over ``area``."""
    world = get_world(args.world or default)
    overrides: dict[str, object] = {}
    if area is not None:
        overrides["area"] = area
    if getattr(args, "queueing", None):
        overrides["network"] = NetworkConfig().with_queueing(args.queueing)
    steps = getattr(args, "episode_steps", None)
    if steps is not None:
        if steps < 1:
            raise InputError(f"--episode-steps: must be at least 1, got {steps}")
        overrides["episode_steps"] = steps
    if overrides:
        world = replace(world, **overrides)
    settings = list(args.world_set)
    if getattr(args, "environment", None) is not None:
        check_environment(args.environment, "--environment", on_disk=True)
        settings.append(f"environment={args.environment}")
    return world_with(world, settings)
