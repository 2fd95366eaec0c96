"""The served default per world: which policy ``tupa serve`` serves, and ``tupa eval --policy
default`` evaluates, for the environment it flies over.

The table is ``policies/served_defaults.json`` (``tupa-served-defaults/1``), written by the
closed-loop benchmark that ranks the policies (``benchmarks/planning_oracle.py
--write-defaults``), never by hand: for each environment it measured, the policy with the highest
mean utility per step over that environment's held-out closed-loop sets, a tie (within
:data:`TIE`) going to the cheaper policy (:data:`BY_COST`: the tracking oracle decides in a few
milliseconds, the planning oracle in about a hundred). An environment is looked up exactly
(``open``, ``urban``, ``site:munich``), then by its kind (``site`` for any site); one the
benchmark has not measured gets :data:`FALLBACK`, the tracking oracle, and says so.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from sim.config import site_path
from sim.errors import InputError

TABLE = Path(__file__).resolve().parent / "served_defaults.json"
FORMAT = "tupa-served-defaults/1"
FALLBACK = "oracle"
"""Served where the benchmark has not measured: the tracking oracle."""
TIE = 0.005
"""Means within this of the best are a tie (``benchmarks/closed_loop.py``'s tolerance)."""
BY_COST = ("oracle", "load-weighted", "min-distance", "min-distance-env", "planning-oracle")
"""Cheapest first: a tie goes to the earliest."""
DEFAULT = "default"
"""``--policy default``: the served default for the environment evaluated."""


@dataclass(frozen=True)
class ServedDefault:
    """The policy served over an environment, and why (a line for logs and ``tupa eval``)."""

    policy: str
    why: str


def environment_kind(environment: str) -> str:
    """``site`` for any site environment, else the environment's own name."""
    return "site" if site_path(environment) is not None else environment


def rank(means: dict[str, float]) -> str:
    """The policy :data:`TABLE` serves given mean utilities per policy: the best, a tie within
    :data:`TIE` going to the cheapest (:data:`BY_COST`, then by name)."""
    if not means:
        raise ValueError("rank: no policy measured")
    best = max(means.values())
    tied = [name for name, value in means.items() if value >= best - TIE]
    order = {name: i for i, name in enumerate(BY_COST)}
    return min(tied, key=lambda name: (order.get(name, len(order)), name))


@lru_cache(maxsize=4)
def _table(path: str, stamp: int) -> dict[str, Any]:
    try:
        document = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the served-defaults table ({exc})") from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise InputError(f"{path}: format: must be {FORMAT!r}")
    entries = document.get("defaults")
    if not isinstance(entries, dict) or not all(
        isinstance(v, dict) and isinstance(v.get("policy"), str) for v in entries.values()
    ):
        raise InputError(f"{path}: defaults: must map environments to {{'policy': NAME, ...}}")
    return document


def served_default(environment: str, table: Path = TABLE) -> ServedDefault:
    """The policy served over ``environment`` (module doc); :data:`FALLBACK` when the table
    has no entry for it or its kind (or there is no table)."""
    if not table.is_file():
        return ServedDefault(FALLBACK, f"no served-defaults table ({table.name}): the fallback")
    document = _table(str(table), table.stat().st_mtime_ns)
    entries = document["defaults"]
    for key in (environment, environment_kind(environment)):
        entry = entries.get(key)
        if entry is not None:
            ranked = entry.get("means", {})
            detail = ", ".join(f"{k} {v:.4f}" for k, v in ranked.items())
            return ServedDefault(
                entry["policy"],
                f"ranked first over {key} by {document.get('source', '?')}"
                + (f" ({detail})" if detail else ""),
            )
    return ServedDefault(FALLBACK, f"{environment} not measured by the benchmark: the fallback")


def write_table(means_by_environment: dict[str, dict[str, float]], source: str) -> Path:
    """Write :data:`TABLE` from measured means (environment → policy → mean utility per step):
    each environment's :func:`rank`, and ``site`` (any site) from the sites measured together,
    their means averaged. Atomic."""
    from sim.atomic import atomic_write_json

    defaults: dict[str, Any] = {}
    for environment, means in sorted(means_by_environment.items()):
        defaults[environment] = {"policy": rank(means), "means": _rounded(means)}
    sites = [m for env, m in means_by_environment.items() if environment_kind(env) == "site"]
    if sites:
        shared = set.intersection(*(set(m) for m in sites))
        pooled = {name: sum(m[name] for m in sites) / len(sites) for name in shared}
        defaults["site"] = {"policy": rank(pooled), "means": _rounded(pooled)}
    atomic_write_json(
        TABLE,
        {
            "format": FORMAT,
            "source": source,
            "rule": (
                f"the highest mean utility per step over the environment's closed-loop sets; "
                f"within {TIE} of it, the cheapest of {', '.join(BY_COST)}"
            ),
            "fallback": FALLBACK,
            "defaults": defaults,
        },
    )
    return TABLE


def _rounded(means: dict[str, float]) -> dict[str, float]:
    return {k: round(float(v), 4) for k, v in sorted(means.items(), key=lambda kv: -kv[1])}
