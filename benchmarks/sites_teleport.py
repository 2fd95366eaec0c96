"""The paper's headline table over a real district: oracle / min-distance by heterogeneity bin,
teleport protocol, on held-out site scenarios (issue 38, "Targets").

For a site (``--site PATH`` or ``site:PATH``) it draws held-out scenario sets — one per scenario
family (default the site families ``streets``, ``squares``, ``crowd`` and ``mixture``, the
paper's layouts on walkable ground) and user count (default 3, 10, 30) — with seeds
``TEST_SEED + crc32("family/users") mod 100_000``, i.e. in [38_400_000, 38_500_000), a range no
other benchmark, test set or training run uses. Each set is evaluated with ``tupa eval``'s
protocol (:func:`policies.evaluation.evaluation.evaluate_policy`) in the ``paper`` world — the
teleport protocol: a static placement starts at its own position and is re-placed every step, 100
stochastic steps, the same fading draws for every policy — for ``min-distance`` (the paper's
baseline), ``load-weighted``, ``min-distance-env`` (the least mean path loss the site gives)
and ``oracle`` (the best static position found with the model). Scenarios are binned by
heterogeneity index H in 0.05 bins as ``tupa eval`` prints them, and each policy's mean utility
in a bin is divided by min-distance's (the paper's "up to 4x"); the same ratio at the 25th
percentile and over all scenarios, by family and by user count.

Writes ``benchmarks/results/sites_teleport.json`` and ``.md`` (``--out``):

    python benchmarks/sites_teleport.py --site site:munich
    python benchmarks/sites_teleport.py --site /tmp/munich50 --per-set 10 --users 3,10

A benchmark, not a test: minutes on 2 cores (the oracle dominates).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "benchmarks" / "results"
TEST_SEED = 38_400_000
"""Held-out sets: TEST_SEED + crc32(f"{family}/{users}") mod 100_000, never used elsewhere."""
SEED_SPAN = 100_000
FAMILIES = ("streets", "squares", "crowd", "mixture")
USERS = (3, 10, 30)
POLICIES = ("min-distance", "load-weighted", "min-distance-env", "oracle")
REFERENCE = "min-distance"
SMALL_BIN = 10
"""A bin with fewer scenarios than this is marked in the table: its ratio is noisy."""


def set_seed(family: str, users: int) -> int:
    """The held-out seed of the (family, users) set."""
    return TEST_SEED + zlib.crc32(f"{family}/{users}".encode()) % SEED_SPAN


def _environment(site: str) -> str:
    """``--site`` as an environment: ``site:NAME`` or ``site:PATH`` as given, an existing
    directory as ``site:`` and its absolute path, anything else as ``site:`` and the text."""
    if site.startswith("site:"):
        return site
    if Path(site).expanduser().is_dir():
        return f"site:{Path(site).expanduser().resolve()}"
    return f"site:{site}"


def _run(job: tuple[str, str, int, int, int]) -> dict[str, Any]:
    """Every policy on one (family, users) set (runs in a worker process)."""
    import torch

    torch.set_num_threads(1)
    from dataclasses import replace

    from policies.evaluation.evaluation import evaluate_policy
    from policies.registry import resolve_policy
    from sim.config import AreaConfig
    from sim.scenarios import generate_scenarios
    from sim.utility import heterogeneity_index
    from sim.world import get_world

    environment, family, users, n, eval_seed = job
    area = AreaConfig(environment=environment)
    world = replace(get_world("paper"), area=area)
    seed = set_seed(family, users)
    scenarios = generate_scenarios(n, users, seed=seed, family=family, area=area)
    started = time.perf_counter()
    out: dict[str, Any] = {
        "family": family,
        "users": users,
        "seed": seed,
        "ids": [s.id for s in scenarios],
        "heterogeneity": [heterogeneity_index(s.users_xy_m, s.load_bps, area) for s in scenarios],
        "utility": {},
        "uav_xyz_m": {},
    }
    for name in POLICIES:
        result = evaluate_policy(
            resolve_policy(name, world), scenarios, world, seed=eval_seed, progress=False
        )
        out["utility"][name] = [row["utility"] for row in result["scenarios"]]
        out["uav_xyz_m"][name] = [row["uav_xyz_m"] for row in result["scenarios"]]
    out["wall_s"] = round(time.perf_counter() - started, 1)
    print(f"  {family:>9} {users:>3} users: {out['wall_s']:6.1f} s", file=sys.stderr, flush=True)
    return out


def _ratios(utility: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, Any]:
    """Mean utility of each policy over ``mask`` and its ratio to min-distance's mean (and at
    the 25th percentile)."""
    means = {name: float(values[mask].mean()) for name, values in utility.items()}
    p25 = {name: float(np.percentile(values[mask], 25)) for name, values in utility.items()}
    ref, ref25 = means[REFERENCE], p25[REFERENCE]
    return {
        "n": int(mask.sum()),
        "mean_utility": means,
        "p25_utility": p25,
        "ratio_to_min_distance": {n: (m / ref if ref > 0 else None) for n, m in means.items()},
        "p25_ratio_to_min_distance": {
            n: (m / ref25 if ref25 > 0 else None) for n, m in p25.items()
        },
    }


def summarise(done: list[dict[str, Any]]) -> dict[str, Any]:
    """The tables of the document from the sets' results: overall, by H bin, by family, by
    user count."""
    from policies.evaluation.evaluation import HETEROGENEITY_BIN_WIDTH, heterogeneity_bin

    h = np.concatenate([d["heterogeneity"] for d in done])
    utility = {name: np.concatenate([d["utility"][name] for d in done]) for name in POLICIES}
    family = np.concatenate([[d["family"]] * len(d["ids"]) for d in done])
    users = np.concatenate([[d["users"]] * len(d["ids"]) for d in done])
    bins = np.array([heterogeneity_bin(v) for v in h])
    width = HETEROGENEITY_BIN_WIDTH
    return {
        "all": _ratios(utility, np.ones(len(h), bool)),
        "by_h_bin": [
            {
                "h_bin": [round(b * width, 2), round((b + 1) * width, 2)],
                **_ratios(utility, bins == b),
            }
            for b in np.unique(bins)
        ],
        "by_family": {f: _ratios(utility, family == f) for f in dict.fromkeys(family)},
        "by_users": {str(u): _ratios(utility, users == u) for u in dict.fromkeys(users.tolist())},
        "heterogeneity": {
            "min": float(h.min()),
            "median": float(np.median(h)),
            "max": float(h.max()),
        },
    }


def _site_info(environment: str) -> dict[str, Any]:
    from sim.channel import area_site
    from sim.config import AreaConfig
    from sim.sites.format import content_hash

    site = area_site(AreaConfig(environment=environment))
    assert site is not None
    meta = site.meta
    scene = meta.get("scene", {})
    return {
        "environment": environment,
        "content_sha256": content_hash(site),
        "scene": scene.get("name") or scene.get("file"),
        "origin_m": scene.get("origin_m"),
        "size_m": [site.size_x_m, site.size_y_m],
        "cell_m": site.cell_m,
        "uav_grid": {
            "x_m": [float(site.uav_x_m[0]), float(site.uav_x_m[-1]), int(site.uav_x_m.size)],
            "y_m": [float(site.uav_y_m[0]), float(site.uav_y_m[-1]), int(site.uav_y_m.size)],
            "z_m": [float(z) for z in site.uav_z_m],
        },
        "walkable_fraction": float(np.mean(site.walkable)),
        "solver": meta.get("solver"),
        "attribution": scene.get("attribution"),
        "licence": scene.get("licence"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--site",
        required=True,
        help="the site: site:NAME (a shipped one, e.g. site:munich), site:PATH or a directory",
    )
    parser.add_argument(
        "--label", default="", help="what the site is, for the tables (e.g. 'dev site, 50 m grid')"
    )
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--users", default=",".join(map(str, USERS)), help="comma-separated")
    parser.add_argument("--per-set", type=int, default=20, help="scenarios per set (default 20)")
    parser.add_argument("--eval-seed", type=int, default=0, help="tupa eval's --seed (default 0)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS / "sites_teleport.json")
    args = parser.parse_args()

    from sim.atomic import atomic_write_json, atomic_write_text
    from sim.channel import area_site
    from sim.config import AreaConfig, check_environment
    from sim.errors import InputError
    from sim.scenarios import check_family_area

    try:
        environment = check_environment(_environment(args.site), "--site", on_disk=True)
        area = AreaConfig(environment=environment)
        area_site(area)
        families = [f.strip() for f in args.families.split(",") if f.strip()]
        for family in families:
            check_family_area(family, area, "--families")
        users = [int(u) for u in args.users.split(",") if u.strip()]
        if args.per_set < 1:
            raise InputError(f"--per-set: must be at least 1, got {args.per_set}")
    except (InputError, ValueError) as exc:
        parser.exit(2, f"sites_teleport: error: {' '.join(str(exc).split())}\n")
    jobs = [(environment, f, u, args.per_set, args.eval_seed) for f in families for u in users]
    print(f"{len(jobs)} sets of {args.per_set} on {environment}:", file=sys.stderr)
    started = time.perf_counter()
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        done = list(pool.map(_run, jobs, chunksize=1))
    document = {
        "benchmark": "sites_teleport",
        "label": args.label,
        "site": _site_info(environment),
        "protocol": "teleport: tupa eval's paper world (static placements start at their "
        "position, re-placed every step), 100 stochastic steps, fading seed "
        f"{args.eval_seed} + scenario index",
        "policies": list(POLICIES),
        "families": families,
        "users": users,
        "per_set": args.per_set,
        "n_scenarios": sum(len(d["ids"]) for d in done),
        "seeds": {
            "rule": f"{TEST_SEED} + crc32('family/users') mod {SEED_SPAN}",
            "range": [TEST_SEED, TEST_SEED + SEED_SPAN - 1],
            "sets": {f"{d['family']}/{d['users']}": d["seed"] for d in done},
        },
        "wall_s": round(time.perf_counter() - started, 1),
        "command": shlex.join(["python", "benchmarks/sites_teleport.py", *sys.argv[1:]]),
        **summarise(done),
        "scenarios": [
            {
                "id": d["ids"][i],
                "family": d["family"],
                "users": d["users"],
                "heterogeneity": round(d["heterogeneity"][i], 4),
                "utility": {name: round(d["utility"][name][i], 4) for name in POLICIES},
                "uav_xyz_m": {
                    name: [round(v, 1) for v in d["uav_xyz_m"][name][i]] for name in POLICIES
                },
            }
            for d in done
            for i in range(len(d["ids"]))
        ],
    }
    atomic_write_json(args.out, document)
    markdown = render(document)
    atomic_write_text(args.out.with_suffix(".md"), markdown)
    print(markdown)
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")


def _row(title: str, n: int, entry: dict[str, Any], others: list[str], mark: str = "") -> str:
    means = entry["mean_utility"]
    ratios = entry["ratio_to_min_distance"]
    cells = [f"{means[p]:.3f}" for p in POLICIES]
    cells += ["-" if ratios[p] is None else f"{ratios[p]:.2f}×" for p in others]
    return f"| {title}{mark} | {n} | " + " | ".join(cells) + " |"


def render(document: dict[str, Any]) -> str:
    """The markdown: mean utility per policy and its ratio to min-distance, by H bin, by family,
    by user count, and at the 25th percentile."""
    site = document["site"]
    others = [p for p in POLICIES if p != REFERENCE]
    header = (
        "| | n | "
        + " | ".join(POLICIES)
        + " | "
        + " | ".join(f"{p} / {REFERENCE}" for p in others)
        + " |"
    )
    rule = "| --- | --- | " + " | ".join("---" for _ in [*POLICIES, *others]) + " |"
    label = f" — {document['label']}" if document.get("label") else ""
    grid = site["uav_grid"]
    levels = ", ".join(f"{z:g}" for z in grid["z_m"])
    lines = [
        f"# Teleport protocol over a site{label}",
        "",
        f"Site `{site['environment']}` (scene {site['scene']}, "
        f"{site['size_m'][0]:g} m × {site['size_m'][1]:g} m, ground cells {site['cell_m']:g} m, "
        f"UAV grid {grid['x_m'][2]}×{grid['y_m'][2]} at z {levels}"
        f" m, content {str(site['content_sha256'])[:12]}); {document['n_scenarios']} held-out "
        f"scenarios ({', '.join(document['families'])} × {document['users']} users × "
        f"{document['per_set']}; seeds {document['seeds']['range'][0]}–"
        f"{document['seeds']['range'][1]}); {document['protocol']}. "
        f"`{document['command']}` ({document['wall_s']:.0f} s).",
        "",
        "Mean utility, and each policy's mean over min-distance's, by heterogeneity index H "
        f"(bins marked * hold fewer than {SMALL_BIN} scenarios; -: min-distance's mean utility "
        "is 0 there):",
        "",
        header.replace("| |", "| H bin |", 1),
        rule,
    ]
    for entry in document["by_h_bin"]:
        lo, hi = entry["h_bin"]
        mark = "*" if entry["n"] < SMALL_BIN else ""
        lines.append(_row(f"[{lo:.2f}, {hi:.2f})", entry["n"], entry, others, mark))
    lines.append(_row("**all**", document["all"]["n"], document["all"], others))
    p25 = document["all"]["p25_ratio_to_min_distance"]
    lines += [
        "",
        "At the 25th percentile of utility (over all scenarios): "
        + ", ".join(
            f"{p} {document['all']['p25_utility'][p]:.3f} ({p25[p]:.2f}× min-distance's)"
            for p in others
        )
        + f"; min-distance {document['all']['p25_utility'][REFERENCE]:.3f}.",
        "",
        "By family:",
        "",
        header.replace("| |", "| family |", 1),
        rule,
    ]
    for name, entry in document["by_family"].items():
        lines.append(_row(name, entry["n"], entry, others))
    lines += ["", "By users per scenario:", "", header.replace("| |", "| users |", 1), rule]
    for name, entry in document["by_users"].items():
        lines.append(_row(name, entry["n"], entry, others))
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
