"""The service's policy: which one it serves by default, and loading one safely.

The policy itself is a :class:`policies.interface.Policy` resolved by
:func:`policies.registry.resolve_policy` (a placement's name or a checkpoint path), the same
object ``tupa eval`` runs, so the service decides exactly as the evaluation does
(``tests/service/test_parity.py`` replays an episode through both).

:func:`load_policy` adds what serving needs: it checks a policy fully (a dry decision on a
synthetic report) before anyone may swap it in, so a bad file never replaces a working policy.
A checkpoint is a pickle: for a client's choice (``PUT /v1/policy``) or the state file's, it is
loaded only from the allowed directories, read once through a descriptor checked as opened, and
only up to a size limit (:func:`policies.learned.checkpoints.read_checkpoint`). Its errors tell the
problem without paths or library text (they go back to HTTP clients); the detail is logged.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sim.config import AreaConfig
from sim.errors import InputError
from sim.observation import UserReports
from sim.world import CLOSED_LOOP, World

if TYPE_CHECKING:
    from policies.interface import Policy
    from policies.learned.checkpoints import CheckpointError

log = logging.getLogger(__name__)
SHIPPED_CHECKPOINTS = Path(__file__).resolve().parent.parent / "policies" / "checkpoints"
SHIPPED_DDQN = SHIPPED_CHECKPOINTS / "ddqn-dr.zip"
SHIPPED_DDPG = SHIPPED_CHECKPOINTS / "ddpg-residual-dr.zip"
SHIPPED_FLEET = SHIPPED_CHECKPOINTS / "fleet" / "fleet-ddpg-residual-scored.zip"
"""The shipped shared-parameter fleet checkpoint (any K; docs/results.md, "Fleets"): served with
``tupa serve --fleet-file F --policy`` and this path; a fleet's default stays ``kmeans-scored``."""
DEFAULT_POLICY = "oracle"
"""The ``policy`` setting's default, and what is served where the closed-loop benchmark has
measured nothing: the tracking oracle, which meets every closed-loop target of
``benchmarks/closed_loop.py`` in the open field. Without ``--policy`` the service
serves the served default for its environment (:meth:`ServiceSettings.served_policy_spec`,
``policies/served_defaults.json``, written by ``benchmarks/planning_oracle.py``): the planning
oracle over the towns and sites it was measured on, the tracking oracle in the open field, where
the two tie and the tracking oracle decides in milliseconds."""


def default_policy_spec() -> str:
    """The ``policy`` setting's default (:data:`DEFAULT_POLICY`)."""
    return DEFAULT_POLICY


def load_policy(
    spec: str,
    world: World = CLOSED_LOOP,
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
) -> Policy:
    """Load ``spec`` (a placement's name or a checkpoint path) for ``world`` and check it can
    decide.

    ``allowed_dirs``: a checkpoint must lie in one of these directories (``None``: anywhere, for
    the operator's own ``--policy``); it is read once, through a checked descriptor, so a link
    flipped meanwhile cannot substitute another file. ``max_bytes`` bounds the checkpoint file
    and what its zip expands to (:func:`policies.learned.checkpoints.load_checkpoint`).

    Raises :class:`InputError` ``policy: <problem>``, without paths or library text (it may go
    back to an HTTP client); the detail, naming the file, is logged as a warning. A spec that
    reads as a misspelt placement name (not a path: :func:`policies.registry.close_names`) is
    refused as an unknown policy naming the close names. A checkpoint marked ``not_for_serving``
    in its metadata is refused when a client chose it (``allowed_dirs`` given), served with a
    warning when the operator did (:func:`_check_servable`). Nothing is
    swapped in by this function, so a failure leaves the serving policy untouched.
    """
    from policies.learned.checkpoints import CheckpointError
    from policies.registry import POLICY_NAMES, close_names, resolve_policy, unknown_name

    spec = str(spec).strip()
    if not spec:
        raise InputError("policy: must be a checkpoint path or one of " + ", ".join(POLICY_NAMES))
    close = [] if spec in POLICY_NAMES else close_names(spec, POLICY_NAMES)
    if close:  # a misspelt name, not a path: said as such (the text only, no file looked at)
        raise InputError(unknown_name(spec, close, POLICY_NAMES, "policy"))
    try:
        policy = resolve_policy(spec, world, allowed_dirs=allowed_dirs, max_bytes=max_bytes)
    except CheckpointError as exc:
        # One log line whatever the path holds (a client chose it).
        detail = str(exc).replace("\r", "\\r").replace("\n", "\\n")
        log.warning("policy %r refused: %s", spec, detail)
        raise InputError(_public_problem(exc, POLICY_NAMES)) from None
    _check_servable(policy, spec, chosen_by_client=allowed_dirs is not None)
    _warn_on_environment(policy, world)
    _dry_run(policy, world)
    return policy


def _check_servable(policy: Policy, spec: str, chosen_by_client: bool) -> None:
    """A checkpoint whose metadata says ``not_for_serving`` (why, measured) is refused when a
    client chooses it (``PUT /v1/policy``, a state file): InputError ``policy: ...``; the
    operator's own ``--policy`` still serves it, with that reason as a warning."""
    from policies.adapters import CheckpointPolicy

    if not isinstance(policy, CheckpointPolicy):
        return
    reason = policy.metadata.get("not_for_serving")
    if not reason:
        return
    if chosen_by_client:
        log.warning("policy %r refused: not for serving: %s", spec, reason)
        raise InputError(f"policy: {policy.name} is not for serving: {reason}")
    log.warning("serving %s, which is not for serving: %s", policy.name, reason)


def _warn_on_environment(policy: Policy, world: World) -> None:
    """A checkpoint served in a channel environment it was not trained in still decides, but
    the operator should know: one warning."""
    from policies.adapters import CheckpointPolicy, trained_environments

    if isinstance(policy, CheckpointPolicy):
        trained = trained_environments(policy.metadata)
        if world.area.environment not in trained:
            log.warning(
                "policy %s was trained in the %s environment(s); serving it in %s",
                policy.name,
                ", ".join(trained),
                world.area.environment,
            )


def _public_problem(error: CheckpointError, baselines: Iterable[str]) -> str:
    """What an HTTP client is told about an unusable checkpoint: the field and the problem."""
    from policies.learned.checkpoints import (
        NO_SUCH_CHECKPOINT,
        OUTSIDE_ALLOWED,
        CheckpointTooLargeError,
    )

    if error.problem == NO_SUCH_CHECKPOINT:
        return f"policy: {NO_SUCH_CHECKPOINT} (or a baseline: {', '.join(baselines)})"
    if error.problem == OUTSIDE_ALLOWED:
        return f"policy: {OUTSIDE_ALLOWED} (TUPA_POLICY_DIRS)"
    if isinstance(error, CheckpointTooLargeError):
        return f"policy: {error.problem} (checkpoint_max_bytes)"
    return f"policy: {error.problem}"


def synthetic_report(area: AreaConfig) -> UserReports:
    """The test report a policy must decide on before it is served: two users, a heavy
    congested one and a light one, on the area's middle line."""
    return UserReports(
        x_m=np.array([0.25, 0.75]) * area.size_x_m,
        y_m=np.array([0.5, 0.5]) * area.size_y_m,
        offered_bps=np.array([30e6, 10e6]),
        throughput_bps=np.array([20e6, 10e6]),
        delay_s=np.array([0.2, 0.01]),
        plr=np.array([0.1, 0.0]),
    )


def _dry_run(policy: Policy, world: World) -> None:
    """One decision on a synthetic report: a policy that cannot decide is not served."""
    area = world.area
    reports = synthetic_report(area)
    centre = np.array([area.size_x_m / 2, area.size_y_m / 2, area.z_min_m])
    try:
        target = np.asarray(policy.decide(reports, centre), dtype=float)
    except InputError:
        raise
    except Exception as exc:
        log.warning(
            "policy %r fails on a test decision: %s: %s", policy.spec, type(exc).__name__, exc
        )
        raise InputError("policy: fails on a test decision (see the service log)") from None
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        log.warning("policy %r gave a test target %s", policy.spec, target.tolist())
        raise InputError("policy: gives a non-finite target on a test decision")
