"""Names and checkpoint paths to policies: the one place that knows what ``--policy`` may say.

* :data:`PLACEMENTS`: the static placements by name — ``min-distance`` (the paper's baseline),
  ``load-weighted``, ``min-distance-env`` (:mod:`policies.placements.baselines`) and ``oracle``
  (:mod:`policies.placements.oracle`: the model's own exhaustive search). :func:`make_placement`
  builds one for a world.
* :data:`NAMED_POLICIES`: policies by name that are not placements (they decide from where the
  vehicle is, not only from the users) — ``planning-oracle`` (:mod:`policies.placements.planning`:
  the receding-horizon planner over flown trajectories). :data:`POLICY_NAMES` is every name
  ``--policy`` may say, placements first: what the error messages list.
* :func:`resolve_policy`: a :class:`~policies.interface.Policy` from a spec — a placement's name
  (re-placed every decision: :class:`~policies.adapters.StaticPolicy`), a named policy, or a
  checkpoint path (:class:`~policies.adapters.CheckpointPolicy`). ``tupa eval``, the
  benchmarks, the demo and the service all resolve through it.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from policies.adapters import CheckpointPolicy, StaticPolicy
from policies.interface import Placement, Policy
from policies.placements.baselines import MinDistancePlacement
from sim.world import PAPER, World


def _oracle(world: World) -> Placement:
    from policies.placements.oracle import OracleConfig, OraclePlacement

    config = OracleConfig(episode_steps=world.episode_steps, step_s=world.step_s)
    return OraclePlacement(world.area, world.network, world.utility, config)


PLACEMENTS: dict[str, Callable[[World], Placement]] = {
    "min-distance": lambda world: MinDistancePlacement(world.area),
    "load-weighted": lambda world: MinDistancePlacement(world.area, load_weighted=True),
    "min-distance-env": lambda world: MinDistancePlacement(
        world.area, altitude="best-snr", frequency_hz=world.network.radio.frequency_hz
    ),
    "oracle": _oracle,
}
"""Each placement's name and its factory (from the world it will place in)."""


def _planning_oracle(world: World) -> Policy:
    from policies.placements.planning import PlanningPolicy

    return PlanningPolicy(world)


NAMED_POLICIES: dict[str, Callable[[World], Policy]] = {"planning-oracle": _planning_oracle}
"""Each named policy that is not a placement, and its factory (from the world it decides in)."""

POLICY_NAMES: tuple[str, ...] = (*PLACEMENTS, *NAMED_POLICIES)
"""Every policy name ``--policy`` may say (besides a checkpoint path), placements first."""


def make_placement(name: str, world: World = PAPER) -> Placement:
    """The placement registered as ``name`` (a key of :data:`PLACEMENTS`) for ``world``.

    The world matters to the oracle only: it optimises the utility of an episode of the world's
    length and step under its network configuration (use the queueing the evaluation runs
    with). Raises ``ValueError`` naming the choices for an unknown name.
    """
    try:
        factory = PLACEMENTS[name]
    except KeyError:
        raise ValueError(f"unknown policy {name!r} (choices: {', '.join(PLACEMENTS)})") from None
    return factory(world)


def close_names(spec: str, names: Iterable[str]) -> list[str]:
    """The names among ``names`` that ``spec`` reads as a misspelling of, closest first
    (:func:`difflib.get_close_matches`, ignoring case and ``_`` for ``-``); none for a spec
    that reads as a path (a separator, a ``.zip``, a leading ``.`` or ``~``) or is too long for
    a name. Looks at the text only, never at the file system."""
    text = str(spec).strip()
    if len(text) > 64 or text.endswith(".zip") or text.startswith((".", "~")):
        return []
    if "/" in text or "\\" in text:
        return []
    return difflib.get_close_matches(text.lower().replace("_", "-"), list(names), n=3, cutoff=0.75)


def unknown_name(spec: str, close: Sequence[str], names: Iterable[str], field: str) -> str:
    """The one-line error for a misspelt policy name: ``field``, the name, the closest name
    and every name there is."""
    return (
        f"{field}: unknown policy {spec!r}: did you mean {close[0]!r}? (a checkpoint path, or "
        f"one of {', '.join(names)})"
    )


def resolve_policy(
    spec: str | Path,
    world: World = PAPER,
    device: str = "cpu",
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
) -> Policy:
    """The policy ``spec`` names: a key of :data:`PLACEMENTS` or :data:`NAMED_POLICIES`, else a
    checkpoint path.

    A checkpoint that cannot be used raises :class:`~policies.learned.checkpoints.CheckpointError`
    (an ``InputError`` naming the file and the problem); ``allowed_dirs`` and ``max_bytes`` restrict
    which files may be loaded (:func:`policies.learned.checkpoints.read_checkpoint`).
    """
    text = str(spec)
    if text in PLACEMENTS:
        return StaticPolicy(make_placement(text, world), text)
    if text in NAMED_POLICIES:
        return NAMED_POLICIES[text](world)
    return CheckpointPolicy.load(
        Path(text), world, device=device, allowed_dirs=allowed_dirs, max_bytes=max_bytes
    )
