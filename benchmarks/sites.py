"""Sites (issue 38): the shipped site's build, its lookup against Sionna RT itself, the noise
floor of that comparison, the environment's speed on the site against the open field, and the
grid study that chose the shipped grid.

Writes ``benchmarks/results/sites.json`` (parts run separately are merged into it):

``build``: what the site's build recorded in its ``site.json`` (default: the shipped ``munich``,
    ``sim/sites/data/munich``): wall time, UAV grid, rays, traced points, the exact command;
    its size on disk. ``--build`` runs that command again into ``runs/sites_bench/build`` and
    reports that run's time too.
``accuracy``: (b) the lookup's error against a direct Sionna RT computation
    (:func:`sim.sites.build.direct_loss_db`: the site's own scene, origin, cells and solver
    settings) at ``--positions`` random UAV positions, uniform over the flight volume
    ``[0, size]² × [25, 100] m`` (seed :data:`POSITION_SEED`, used nowhere else; a position
    less than ``CLEARANCE_M`` above the building under it is drawn again, as the build skips
    such grid points and the envelope keeps a vehicle out of them; continuous, so off the
    grid). Over every walkable ground cell (where users stand) of every position: the median
    and 90th percentile of |lookup − reference| (dB) over the cells with a path in both, and
    the coverage agreement (a path in both or in neither) over all of them; the same for
    links around the model's thresholds (:data:`CONNECT_LOSS_DB`), by the reference's
    loss and by altitude. (c) The *noise floor*: the reference computed again at the same
    positions with another seed *and* ``rays + 7919`` rays — Sionna launches its rays along a
    Fibonacci lattice fixed by their number, so a seed alone changes only the random choices
    at surfaces, not which cells the rays reach — compared with the first run the same way.
    The lookup cannot beat it.
``speed``: (d) ``sim.envs.FapDiscreteEnv`` steps per second (stochastic, random valid moves,
    the ``paper`` and ``closed-loop`` worlds) on the site and in the open field, 3 and 30
    users, interleaved rounds, best of ``--repeats``, and their ratio (target ≥ 0.8).
``grid-study``: how the shipped grid was chosen (:func:`grid_study`): a fine grid over a
    100 m patch at several ray counts, every coarser grid as its subset, the lookup and the
    lookup it replaced against references in the patch, and each grid's cost for a whole site.

Ray-traced maps are cached under ``--cache`` (default ``runs/sites_bench/``, one file per
position, named by what they depend on), so a run that is interrupted or repeated continues.
``--quick``: 12 positions at 4·10⁶ rays, fewer steps (minutes). A benchmark, not a test: the
full ``accuracy`` part ray-traces 400 radio maps at 3.2·10⁷ rays (about an hour on this 2-core
machine), the grid study some 2,000 more. ``accuracy`` and ``grid-study`` need
``pip install 'tupa[sites]'`` and libllvm19.

    .venv/bin/python benchmarks/sites.py [--quick] [--parts build,accuracy,speed,grid-study]
        [--site munich|DIR] [--positions 200] [--reference-rays 32000000] [--build]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sim.config import AreaConfig, site_directory  # noqa: E402
from sim.sites import Site, load_site, path_loss_db  # noqa: E402
from sim.sites.build import CLEARANCE_M  # noqa: E402
from sim.sites.format import DATA_FILE, META_FILE  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "sites.json"
CACHE = ROOT / "runs" / "sites_bench"
POSITION_SEED = 38_038
"""The positions' seed: used nowhere else (no scenario set, no training run)."""
FLOOR_RAYS_OFFSET = 7919
"""The noise floor's second run has this many more rays: another Fibonacci lattice."""
CONNECT_LOSS_DB = (110.0, 120.0)
"""Loss thresholds the model cares about, at its 20 dBm: 110 dB is the −90 dBm preamble
threshold (connected in expected mode); above 120 dB a Rayleigh fade would have to exceed
+10 dB (probability e⁻¹⁰) for a link to connect."""
Z_RANGE_M = (25.0, 100.0)
Z_BANDS_M = ((25.0, 37.5), (37.5, 50.0), (50.0, 75.0), (75.0, 100.0))


# ------------------------------------------------------------------------------- (a) build


def site_size_bytes(directory: Path) -> int:
    return sum((directory / name).stat().st_size for name in (DATA_FILE, META_FILE))


def build_record(site: Site, directory: Path) -> dict[str, Any]:
    """What the site's own build recorded (time, grid, rays) and its size on disk."""
    grid = site.meta.get("grid", {})
    build = site.meta.get("build", {})
    solver = site.meta.get("solver", {})
    return {
        "site": str(directory.relative_to(ROOT) if directory.is_relative_to(ROOT) else directory),
        "scene": site.meta.get("scene", {}).get("name"),
        "area_m": [site.size_x_m, site.size_y_m],
        "cell_m": site.cell_m,
        "grid_xy_m": grid.get("xy_m"),
        "grid_z_m": grid.get("z_m"),
        "grid_points": int(site.uav_x_m.size * site.uav_y_m.size * site.uav_z_m.size),
        "traced_points": build.get("traced"),
        "rays_per_point": solver.get("samples_per_tx"),
        "max_depth": solver.get("max_depth"),
        "build_seconds": build.get("seconds"),
        "build_minutes": round(build["seconds"] / 60, 1) if "seconds" in build else None,
        "build_command": build.get("command"),
        "size_bytes": site_size_bytes(directory),
        "size_mb": round(site_size_bytes(directory) / 1e6, 2),
    }


def rebuild(site: Site, out: Path) -> dict[str, Any]:
    """Run the site's recorded build command again into ``out``; its wall time and size."""
    command = site.meta.get("build", {}).get("command")
    if not command:
        raise SystemExit("the site records no build command: cannot --build it")
    argv = shlex.split(command)
    argv[argv.index("--out") + 1] = str(out)
    if argv[0] == "tupa":
        argv = [str(Path(sys.executable).parent / "tupa"), *argv[1:]]
    print("building:", " ".join(argv), flush=True)
    started = time.monotonic()
    subprocess.run(argv, check=True)
    seconds = time.monotonic() - started
    rebuilt = load_site(out)
    return {
        "command": " ".join(argv),
        "wall_seconds": round(seconds, 1),
        "recorded_seconds": rebuilt.meta.get("build", {}).get("seconds"),
        "size_mb": round(site_size_bytes(out) / 1e6, 2),
        "same_grid": bool(
            np.array_equal(rebuilt.uav_x_m, site.uav_x_m)
            and np.array_equal(rebuilt.uav_z_m, site.uav_z_m)
        ),
    }


# ---------------------------------------------------------------------- (b), (c) accuracy


def draw_positions(
    site: Site, n: int, seed: int = POSITION_SEED, xy_m: tuple[float, float] | None = None
) -> np.ndarray:
    """``n`` UAV positions (area frame) uniform over the flight volume — x and y over the area,
    or over ``xy_m`` — each at least CLEARANCE_M above the building height of its ground cell
    (redrawn otherwise)."""
    rng = np.random.default_rng(seed)
    x_range = xy_m or (0.0, site.size_x_m)
    y_range = xy_m or (0.0, site.size_y_m)
    out = np.empty((n, 3))
    k = 0
    while k < n:
        p = np.array([rng.uniform(*x_range), rng.uniform(*y_range), rng.uniform(*Z_RANGE_M)])
        column = min(int(p[0] // site.cell_m), site.cells_x - 1)
        row = min(int(p[1] // site.cell_m), site.cells_y - 1)
        if p[2] > site.building_height_m[row, column] + CLEARANCE_M:
            out[k] = p
            k += 1
    return out


def references(
    site: Site, positions: np.ndarray, rays: int, seed: int, cache: Path, label: str
) -> np.ndarray:
    """Direct Sionna RT path loss at each position (N, cells_y, cells_x), cached per position
    under ``cache`` (float32 dB files); progress on standard error."""
    from sim.sites.build import direct_loss_db

    directory = cache / f"{_reference_key(site)}-{rays}-{seed}"
    directory.mkdir(parents=True, exist_ok=True)
    out = np.empty((positions.shape[0], site.cells_y, site.cells_x))
    scene = None
    started, done = time.monotonic(), 0
    for k, p in enumerate(positions):
        path = directory / f"{p[0]:.3f}_{p[1]:.3f}_{p[2]:.3f}.npy"
        if path.exists():
            out[k] = np.load(path)
            continue
        if scene is None:
            from sim.sites import raytrace

            recorded = site.meta["scene"]
            scene = raytrace.load_scene(recorded.get("name"), recorded.get("file"))
        out[k] = direct_loss_db(site, p[None], rays, seed, scene=scene)[0]
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, out[k].astype(np.float32))
        os.replace(tmp, path)
        done += 1
        elapsed = time.monotonic() - started
        left = (positions.shape[0] - k - 1) * elapsed / done
        print(
            f"{label}: {k + 1}/{positions.shape[0]} positions, {elapsed / done:.1f} s each, "
            f"about {left / 60:.0f} min left",
            file=sys.stderr,
            flush=True,
        )
    return out


def _reference_key(site: Site) -> str:
    """What a direct computation depends on besides rays and seed: the scene, the area's
    origin and cells, the users' height and the solver's settings (not the UAV grid)."""
    import hashlib

    solver = {
        k: v for k, v in site.meta.get("solver", {}).items() if k not in ("seed", "samples_per_tx")
    }
    what = {
        "scene": site.meta.get("scene", {}).get("name") or site.meta.get("scene", {}).get("file"),
        "origin_m": site.meta.get("scene", {}).get("origin_m"),
        "size_m": [site.size_x_m, site.size_y_m],
        "cell_m": site.cell_m,
        "user_height_m": site.user_height_m,
        "solver": solver,
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:12]


def compare(reference: np.ndarray, other: np.ndarray, walkable: np.ndarray) -> dict[str, Any]:
    """Error statistics of ``other`` against ``reference`` (N, cells) over walkable cells."""
    ref = reference[:, walkable]
    est = other[:, walkable]
    has_ref, has_est = np.isfinite(ref), np.isfinite(est)
    both = has_ref & has_est
    error = np.abs(ref[both] - est[both])

    def stats(mask: np.ndarray) -> dict[str, Any]:
        e = np.abs(ref[mask & both] - est[mask & both])
        return {
            "cells": int((mask & both).sum()),
            "median_db": round(float(np.median(e)), 3) if e.size else None,
            "p90_db": round(float(np.percentile(e, 90)), 3) if e.size else None,
        }

    thresholds = {}
    for limit in CONNECT_LOSS_DB:
        below_ref = has_ref & (ref <= limit)
        below_est = has_est & (est <= limit)
        thresholds[f"le_{limit:g}_db"] = {
            "definition": f"reference loss <= {limit:g} dB; agreement: loss <= {limit:g} dB in "
            "both or in neither, over all walkable cells",
            **stats(below_ref),
            "agreement": round(float((below_ref == below_est).mean()), 4),
        }
    bands = {}
    for low, high in ((0, 100), (100, 110), (110, 120), (120, 130), (130, np.inf)):
        band = has_ref & (ref >= low) & (ref < high)
        bands[f"{low}-{high}"] = {
            **stats(band),
            "share_of_covered": round(float(band.sum() / max(has_ref.sum(), 1)), 4),
            "missed": round(float((band & ~has_est).sum() / max(band.sum(), 1)), 4),
        }
    return {
        "walkable_cells": int(ref.size),
        "covered_in_reference": round(float(has_ref.mean()), 4),
        "covered_in_other": round(float(has_est.mean()), 4),
        "covered_cells_compared": int(both.sum()),
        "median_abs_error_db": round(float(np.median(error)), 3),
        "p90_abs_error_db": round(float(np.percentile(error, 90)), 3),
        "coverage_agreement": round(float((has_ref == has_est).mean()), 4),
        "missed_paths": round(float((has_ref & ~has_est).mean()), 4),
        "extra_paths": round(float((~has_ref & has_est).mean()), 4),
        "links_by_loss_threshold": thresholds,
        "by_reference_loss_db": bands,
    }


def accuracy(
    site: Site, n: int, rays: int, cache: Path
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    positions = draw_positions(site, n)
    centres_x = (np.arange(site.cells_x) + 0.5) * site.cell_m
    centres_y = (np.arange(site.cells_y) + 0.5) * site.cell_m
    cx, cy = np.meshgrid(centres_x, centres_y)
    cells = np.stack([cx.ravel(), cy.ravel()], axis=1)
    walkable = site.walkable.ravel()
    first = references(site, positions, rays, 1, cache, "reference").reshape(n, -1)
    second = references(site, positions, rays + FLOOR_RAYS_OFFSET, 2, cache, "noise floor").reshape(
        n, -1
    )
    started = time.perf_counter()
    looked_up = path_loss_db(site, positions, cells)
    lookup_s = time.perf_counter() - started
    lookup = compare(first, looked_up, walkable)
    floor = compare(first, second, walkable)
    previous = compare(first, previous_lookup_db(site, positions), walkable)
    by_altitude = {}
    for low, high in Z_BANDS_M:
        rows = (positions[:, 2] >= low) & (positions[:, 2] < high)
        if rows.any():
            part = compare(first[rows], looked_up[rows], walkable)
            part_floor = compare(first[rows], second[rows], walkable)
            by_altitude[f"{low:g}-{high:g}"] = {
                "positions": int(rows.sum()),
                "lookup": {k: part[k] for k in _HEADLINE},
                "floor": {k: part_floor[k] for k in _HEADLINE},
            }
    setup = {
        "positions": n,
        "position_seed": POSITION_SEED,
        "flight_volume_m": [[0, site.size_x_m], [0, site.size_y_m], list(Z_RANGE_M)],
        "clearance_m": CLEARANCE_M,
        "reference_rays": rays,
        "reference_seed": 1,
        "floor_rays": rays + FLOOR_RAYS_OFFSET,
        "floor_seed": 2,
        "solver": {k: v for k, v in site.meta.get("solver", {}).items() if k != "seed"},
        "error_over": "walkable cells covered (a path) in both the reference and the lookup",
        "coverage_over": "all walkable cells: a path in both, or in neither",
        "lookup_seconds_all_positions": round(lookup_s, 3),
    }
    return setup, {**lookup, "by_altitude_m": by_altitude, "previous_lookup_db": previous}, floor


_HEADLINE = ("median_abs_error_db", "p90_abs_error_db", "coverage_agreement")


# ------------------------------------------------------------------------------ grid study

STUDY_PATCH_M = (200.0, 300.0)
"""The grid study's sub-area: UAV positions over this square (x and y), every ground cell."""
STUDY_STEP_M = 12.5
STUDY_SEED = 2024
"""The grid study's reference positions' seed (used nowhere else)."""
STUDY_CONFIGS = {
    "xy12.5_z12.5": (12.5, 12.5),
    "xy25_z12.5": (25.0, 12.5),
    "xy25_z25": (25.0, 25.0),
    "xy12.5_z25": (12.5, 25.0),
    "xy50_z12.5": (50.0, 12.5),
    "xy50_z25": (50.0, 25.0),
}


def _study_axes(xy_m: float, z_m: float) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(STUDY_PATCH_M[0], STUDY_PATCH_M[1] + 1e-9, xy_m), np.arange(
        Z_RANGE_M[0], Z_RANGE_M[1] + 1e-9, z_m
    )


def previous_lookup_db(site: Site, positions: np.ndarray) -> np.ndarray:
    """The lookup this study replaced, on ``site`` at ``positions`` (N, 3), to every ground
    cell: (N, cells) dB — trilinear in dB over the corners with a path, their weights
    renormalised, a path when they carry at least half of the weight."""
    from sim.sites.format import dequantise_loss_db

    xs, ys, zs = site.uav_x_m, site.uav_y_m, site.uav_z_m
    out = np.empty((positions.shape[0], site.cells_y * site.cells_x))
    for k, p in enumerate(positions):
        lower, fractions = [], []
        for axis, value in ((xs, p[0]), (ys, p[1]), (zs, p[2])):
            value = min(max(value, axis[0]), axis[-1])
            i = min(max(int(np.searchsorted(axis, value, side="right")) - 1, 0), axis.size - 2)
            lower.append(i)
            fractions.append((value - axis[i]) / (axis[i + 1] - axis[i]))
        total = np.zeros(out.shape[1])
        weight = np.zeros(out.shape[1])
        for corner in range(8):
            w, index = 1.0, []
            for bit in range(3):
                up = (corner >> bit) & 1
                w *= fractions[bit] if up else 1.0 - fractions[bit]
                index.append(lower[bit] + up)
            loss = dequantise_loss_db(site.loss_code[index[2], index[1], index[0]]).ravel()
            covered = np.isfinite(loss)
            total += np.where(covered, w * np.where(covered, loss, 0.0), 0.0)
            weight += np.where(covered, w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[k] = np.where(weight >= 0.5 - 1e-12, total / weight, np.inf)
    return out


def _study_site(
    site: Site, grid: dict[tuple[float, float, float], np.ndarray], xs: np.ndarray, zs: np.ndarray
) -> Site:
    """A site of the patch's grid points ``xs`` × ``xs`` × ``zs`` with the given maps,
    quantised and kept on walkable cells as the build does."""
    from sim.sites.format import NO_PATH_CODE, quantise_loss_db

    codes = np.empty((zs.size, xs.size, xs.size, site.cells_y, site.cells_x), np.uint16)
    for iz, z in enumerate(zs):
        for iy, y in enumerate(xs):
            for ix, x in enumerate(xs):
                codes[iz, iy, ix] = quantise_loss_db(
                    grid[(float(x), float(y), float(z))].reshape(site.cells_y, site.cells_x)
                )
    codes[..., ~site.walkable] = NO_PATH_CODE
    return replace(site, uav_x_m=xs, uav_y_m=xs.copy(), uav_z_m=zs, loss_code=codes)


def grid_study(site: Site, rays: list[int], rich_rays: int, cache: Path, n_refs: int) -> dict:
    """Which UAV grid, rays and interpolation (docs/sites.md): a fine grid (every 12.5 m in
    x, y and z) over the patch :data:`STUDY_PATCH_M` traced at each of ``rays`` (and at
    ``rich_rays`` on its 25 m points), ``n_refs`` reference positions in the patch with their
    noise floor as in (b), (c); every coarser grid of :data:`STUDY_CONFIGS` is a subset of the
    fine one. Errors over every walkable cell of the site, as (b). The cost of a whole 500 m
    site at each grid and ray count: traced points × the measured seconds a point, and points ×
    the measured compressed size a point."""
    import io

    from sim.sites.format import NO_PATH_CODE, quantise_loss_db

    fine_xy, fine_z = _study_axes(STUDY_STEP_M, STUDY_STEP_M)
    Z, Y, X = np.meshgrid(fine_z, fine_xy, fine_xy, indexing="ij")
    fine = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    positions = draw_positions(site, n_refs, STUDY_SEED, STUDY_PATCH_M)
    walkable = site.walkable.ravel()
    first = references(site, positions, STUDY_REF_RAYS, 1, cache, "study reference").reshape(
        n_refs, -1
    )
    second = references(
        site, positions, STUDY_REF_RAYS + FLOOR_RAYS_OFFSET, 2, cache, "study floor"
    ).reshape(n_refs, -1)
    out: dict[str, Any] = {
        "patch_m": list(STUDY_PATCH_M),
        "z_m": list(Z_RANGE_M),
        "fine_step_m": STUDY_STEP_M,
        "reference_positions": n_refs,
        "reference_seed": STUDY_SEED,
        "reference_rays": STUDY_REF_RAYS,
        "noise_floor": {k: v for k, v in compare(first, second, walkable).items() if k in _BRIEF},
        "runs": {},
    }
    area_points = {
        name: round(site.size_x_m / xy + 1) ** 2 * round((Z_RANGE_M[1] - Z_RANGE_M[0]) / z + 1)
        for name, (xy, z) in STUDY_CONFIGS.items()
    }
    for count in [*rays, rich_rays]:
        points = (
            fine
            if count != rich_rays
            else fine[
                np.isclose(np.mod(fine[:, 0] - STUDY_PATCH_M[0], 25.0), 0)
                & np.isclose(np.mod(fine[:, 1] - STUDY_PATCH_M[0], 25.0), 0)
            ]
        )
        maps = references(site, points, count, 1, cache, f"study grid {count:.3g} rays")
        grid = {tuple(float(v) for v in p): maps[k].ravel() for k, p in enumerate(points)}
        timing = seconds_per_point(site, count)
        codes = quantise_loss_db(maps.reshape(len(points), -1))
        codes[:, ~walkable] = NO_PATH_CODE
        buffer = io.BytesIO()
        np.savez_compressed(buffer, a=codes)
        bytes_per_point = len(buffer.getvalue()) / len(points)
        run: dict[str, Any] = {
            "rays": count,
            "seconds_per_point": timing,
            "compressed_kb_per_point": round(bytes_per_point / 1e3, 2),
            "configs": {},
        }
        for name, (xy, z) in STUDY_CONFIGS.items():
            xs, zs = _study_axes(xy, z)
            if not all((float(x), float(y), float(h)) in grid for x in xs for y in xs for h in zs):
                continue
            study = _study_site(site, grid, xs, zs)
            looked_up = path_loss_db(study, positions, _cell_centres(site))
            previous = previous_lookup_db(study, positions)
            row = {
                "lookup": {
                    k: v for k, v in compare(first, looked_up, walkable).items() if k in _BRIEF
                },
                "previous_lookup_db": {
                    k: v for k, v in compare(first, previous, walkable).items() if k in _BRIEF
                },
                "whole_site_points": area_points[name],
                "whole_site_minutes": None
                if timing is None
                else round(area_points[name] * timing / 60, 1),
                "whole_site_mb": round(area_points[name] * bytes_per_point / 1e6, 1),
            }
            run["configs"][name] = row
            print(
                f"grid study {count:.3g} rays {name}: lookup {_line(row['lookup'])}; "
                f"previous {_line(row['previous_lookup_db'])}; whole site "
                f"{row['whole_site_minutes']} min, {row['whole_site_mb']} MB",
                flush=True,
            )
        out["runs"][f"{count:.3g}"] = run
    return out


def seconds_per_point(site: Site, rays: int, points: int = 16, batch: int = 8) -> float:
    """Seconds a UAV grid point takes at ``rays``, as the build traces them (batches of
    ``batch`` points, one radio map call each): ``points`` points over the patch, timed."""
    from sim.sites import raytrace

    recorded = site.meta["scene"]
    scene = raytrace.load_scene(recorded.get("name"), recorded.get("file"))
    positions = draw_positions(site, points, 1, STUDY_PATCH_M)
    from sim.sites.build import direct_loss_db

    direct_loss_db(site, positions[:1], rays, 1, scene=scene)  # warm-up: the kernels compile
    started = time.monotonic()
    direct_loss_db(site, positions, rays, 1, scene=scene, batch=batch)
    return round((time.monotonic() - started) / points, 3)


STUDY_REF_RAYS = 32_000_000
_BRIEF = (
    "median_abs_error_db",
    "p90_abs_error_db",
    "coverage_agreement",
    "missed_paths",
    "extra_paths",
    "links_by_loss_threshold",
)


def _line(part: dict[str, Any]) -> str:
    return (
        f"median {part['median_abs_error_db']:.2f} dB, p90 {part['p90_abs_error_db']:.2f} dB, "
        f"coverage {part['coverage_agreement']:.1%}"
    )


def _cell_centres(site: Site) -> np.ndarray:
    cx, cy = np.meshgrid(
        (np.arange(site.cells_x) + 0.5) * site.cell_m, (np.arange(site.cells_y) + 0.5) * site.cell_m
    )
    return np.stack([cx.ravel(), cy.ravel()], axis=1)


# ---------------------------------------------------------------------------- (d) speed


def _runner(area: AreaConfig, world_name: str, scenarios: list, steps: int):
    from sim.envs import FapDiscreteEnv, ScenarioCycle
    from sim.world import get_world

    world = replace(get_world(world_name), area=area)
    env = FapDiscreteEnv(ScenarioCycle(scenarios), world=world)
    rng = np.random.default_rng(0)
    env.reset(seed=0)

    def run() -> None:
        _, info = env.reset()
        for _ in range(steps):
            valid = np.flatnonzero(info["action_mask"])
            _, _, _, truncated, info = env.step(int(valid[rng.integers(len(valid))]))
            if truncated:
                _, info = env.reset()

    run()  # numba kernels load from cache, the site loads once
    return run


def speed(environment: str, steps: int, repeats: int) -> dict[str, Any]:
    """Env steps/s on the site and in the open, interleaved rounds, best of ``repeats``; both
    environments play the same 20 scenarios, generated on the site (users on its walkable
    ground, where they may stand in the open field too), so that the users' places are not
    what differs."""
    from sim.scenarios import generate_scenarios

    out: dict[str, Any] = {}
    site_area = AreaConfig(environment=environment)
    for world_name in ("paper", "closed-loop"):
        for n_users in (3, 30):
            scenarios = generate_scenarios(20, n_users, seed=1, area=site_area)
            runners = {
                "open": _runner(AreaConfig(), world_name, scenarios, steps),
                "site": _runner(site_area, world_name, scenarios, steps),
            }
            best = dict.fromkeys(runners, float("inf"))
            for _ in range(repeats):
                for name, run in runners.items():
                    started = time.perf_counter()
                    run()
                    best[name] = min(best[name], time.perf_counter() - started)
            rate = {name: steps / seconds for name, seconds in best.items()}
            key = f"{world_name}_{n_users}_users"
            out[key] = {
                "open_steps_per_s": round(rate["open"]),
                "site_steps_per_s": round(rate["site"]),
                "site_over_open": round(rate["site"] / rate["open"], 3),
            }
            print(
                f"speed {key}: open {rate['open']:.0f}, site {rate['site']:.0f} steps/s, "
                f"ratio {rate['site'] / rate['open']:.2f}",
                flush=True,
            )
    return out


# ------------------------------------------------------------------------------------ main


def _sionna_available() -> bool:
    try:
        from sim.sites import raytrace

        raytrace.prepare_llvm()
        return raytrace.find_libllvm() is not None and bool(raytrace.versions())
    except Exception:
        return False


PARTS = ("build", "accuracy", "speed", "grid-study")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="12 positions, 4e6 rays, fewer steps")
    parser.add_argument("--site", default="munich", help="a shipped site's name or a directory")
    parser.add_argument(
        "--parts",
        default="build,accuracy,speed",
        help=f"which parts to run, comma-separated, of {', '.join(PARTS)} (default: all but the "
        "grid study); the others' results already in --out are kept",
    )
    parser.add_argument("--positions", type=int, default=200)
    parser.add_argument("--reference-rays", type=int, default=32_000_000)
    parser.add_argument("--build", action="store_true", help="build the site again first")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--study-rays", default="1e6,2e6,4e6", help="the grid study's ray counts")
    parser.add_argument("--study-rich-rays", type=float, default=16e6)
    parser.add_argument("--study-positions", type=int, default=48)
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    parts = [part.strip() for part in args.parts.split(",") if part.strip()]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        parser.error(f"--parts: unknown {', '.join(unknown)}; choose from {', '.join(PARTS)}")
    if args.quick:
        args.positions, args.reference_rays = 12, 4_000_000
        args.steps, args.repeats = 600, 2
    environment = f"site:{args.site}"
    directory = site_directory(environment)
    assert directory is not None
    site = load_site(directory)
    previous: dict[str, Any] = {}
    if args.out.exists() and not args.quick:
        previous = json.loads(args.out.read_text())
    result: dict[str, Any] = {
        **previous,
        "benchmark": "sites",
        "quick": args.quick,
        "machine": {
            "cpu": platform.machine(),
            "cpu_count": os.cpu_count(),
            "load_average_1min_at_start": round(os.getloadavg()[0], 2),
        },
        "python": platform.python_version(),
        "environment": environment,
        "build": build_record(site, directory),
    }
    if args.build:
        result["rebuild"] = rebuild(site, args.cache / "build")
    needs_rt = {"accuracy", "grid-study"} & set(parts)
    if needs_rt and not _sionna_available():
        raise SystemExit(
            f"{', '.join(sorted(needs_rt))}: needs sionna-rt (pip install 'tupa[sites]') and "
            "libllvm19; run with --parts build,speed without them"
        )
    if "accuracy" in parts:
        setup, lookup, floor = accuracy(site, args.positions, args.reference_rays, args.cache)
        result["accuracy_setup"] = setup
        result["lookup_vs_reference"] = lookup
        result["noise_floor"] = floor
        for name, part in (("lookup", lookup), ("noise floor", floor)):
            usable = part["links_by_loss_threshold"]["le_110_db"]
            print(
                f"{name}: {_line(part)} (links <= 110 dB: median {usable['median_db']} dB, p90 "
                f"{usable['p90_db']} dB, agreement {usable['agreement']:.1%})",
                flush=True,
            )
    if "speed" in parts:
        result["speed"] = speed(environment, args.steps, args.repeats)
    if "grid-study" in parts:
        rays = [int(float(r)) for r in args.study_rays.split(",")]
        result["grid_study"] = grid_study(
            site, rays, int(args.study_rich_rays), args.cache, args.study_positions
        )
    result["targets"] = targets(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


def targets(result: dict[str, Any]) -> dict[str, Any]:
    """The issue's targets against what was measured: met, or by how much not."""
    build = result["build"]
    out: dict[str, Any] = {
        "build_minutes_le_45": build["build_minutes"] is not None and build["build_minutes"] <= 45,
        "size_mb_le_15": build["size_mb"] <= 15,
    }
    lookup = result.get("lookup_vs_reference")
    if isinstance(lookup, dict):
        out["median_le_1_5_db"] = lookup["median_abs_error_db"] <= 1.5
        out["p90_le_5_db"] = lookup["p90_abs_error_db"] <= 5.0
        out["coverage_agreement_ge_97_percent"] = lookup["coverage_agreement"] >= 0.97
    if "speed" in result:
        ratios = [v["site_over_open"] for v in result["speed"].values()]
        out["speed_ratio_ge_0_8"] = min(ratios) >= 0.8
        out["speed_ratio_min"] = min(ratios)
    return out


if __name__ == "__main__":
    main()
