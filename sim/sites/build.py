"""Building a site with Sionna RT (``tupa site build``): resumable, atomic, batched.

The UAV grid is ``grid_xy_m`` apart in x and y over the whole area (both edges included) at
the altitudes ``grid_z_m``; ground cells are ``cell_m`` squares, users at ``user_height_m``
above the scene's lowest point. Grid points inside or on a building (at most
``CLEARANCE_M`` above the tallest top in its ground cell) are not traced: no path from there.

Work goes in batches of ``batch`` grid points, one radio-map call each (every point a
transmitter; Dr.Jit uses every core for it: that is the build's parallelism — separate
worker processes would only compete for the same cores). Each finished batch is saved
atomically under ``OUT/.parts/``; a build interrupted (Ctrl-C) and started again with the same
settings continues from the batches saved; with other settings it is refused. The finished
site is written with :func:`sim.sites.format.save_site` and ``.parts`` removed. Losses are kept
for walkable cells only (users stand nowhere else; a cell inside a building gets what rays
refracted through its walls deposit at 1.5 m, which no user sees): the others are stored as no
path, which halves the site's size in a dense district.

Only :mod:`sim.sites.raytrace` touches the ray tracer, and only when a build runs.
"""

from __future__ import annotations

import io
import json
import math
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from sim.atomic import atomic_write_bytes, atomic_write_json
from sim.errors import InputError
from sim.sites.format import NO_PATH_CODE, Site, quantise_loss_db, save_site

CLEARANCE_M = 2.0
"""A UAV grid point at most this far above a building top in its ground cell is not traced."""
WALKABLE_MAX_M = 1.0
"""A ground cell is walkable when every downward ray from above meets a surface no higher than
this above the scene's lowest point (kerbs, low walls; not a roof)."""
SUBSAMPLES = 3
"""Downward rays per cell side for the building heights and the walkable mask."""
PARTS = ".parts"


@dataclass(frozen=True)
class BuildSpec:
    """What to build. ``center_xy_m`` is in the scene frame (None: the scene's bounding box
    centre); the area is ``size_m`` square around it."""

    scene: str | None = None
    scene_file: str | None = None
    center_xy_m: tuple[float, float] | None = None
    size_m: float = 500.0
    cell_m: float = 5.0
    grid_xy_m: float = 25.0
    grid_z_m: tuple[float, ...] = (25.0, 37.5, 50.0, 62.5, 75.0, 87.5, 100.0)
    user_height_m: float = 1.5
    batch: int = 8
    solver: dict[str, Any] = field(default_factory=dict)

    def check(self) -> None:
        """InputError naming the command-line option for a spec that cannot be built."""
        if (self.scene is None) == (self.scene_file is None):
            raise InputError("--scene: give exactly one of --scene NAME and --scene-file FILE")
        if not (math.isfinite(self.size_m) and self.size_m > 0):
            raise InputError(f"--size-m: must be a finite number > 0, got {self.size_m}")
        for option, step in (("--cell-m", self.cell_m), ("--grid-xy-m", self.grid_xy_m)):
            if not (math.isfinite(step) and step > 0):
                raise InputError(f"{option}: must be a finite number > 0, got {step}")
            if abs(self.size_m / step - round(self.size_m / step)) > 1e-9:
                raise InputError(f"{option}: must divide --size-m {self.size_m:g}, got {step:g}")
        if self.cell_m > 5.0:
            raise InputError(f"--cell-m: must be at most 5 m, got {self.cell_m:g}")
        z = np.asarray(self.grid_z_m, dtype=np.float64)
        if z.size == 0 or not np.all(np.isfinite(z)) or np.any(z <= self.user_height_m):
            raise InputError(f"--grid-z-m: altitudes must be above the users, got {self.grid_z_m}")
        if np.any(np.diff(z) <= 0):
            raise InputError(f"--grid-z-m: must be strictly ascending, got {self.grid_z_m}")
        if self.batch < 1:
            raise InputError(f"--batch: must be at least 1, got {self.batch}")
        if self.center_xy_m is not None and not all(map(math.isfinite, self.center_xy_m)):
            raise InputError(f"--center: must be two finite numbers, got {self.center_xy_m}")

    def command(self, out: str | Path) -> str:
        """The ``tupa site build`` command line that builds this spec into ``out`` (recorded in
        the site's metadata, so that a site says how to build it again)."""
        parts = ["tupa site build"]
        if self.scene is not None:
            parts.append(f"--scene {self.scene}")
        else:
            parts.append(f"--scene-file {self.scene_file}")
        if self.center_xy_m is not None:
            parts.append(f"--center {self.center_xy_m[0]:g},{self.center_xy_m[1]:g}")
        from sim.sites.raytrace import SolverSettings  # a dataclass: no ray tracer imported

        solver = SolverSettings(**self.solver)
        parts += [
            f"--size-m {self.size_m:g}",
            f"--cell-m {self.cell_m:g}",
            f"--grid-xy-m {self.grid_xy_m:g}",
            f"--grid-z-m {','.join(f'{z:g}' for z in self.grid_z_m)}",
            f"--samples {solver.samples_per_tx}",
            f"--max-depth {solver.max_depth}",
            f"--batch {self.batch}",
            f"--out {out}",
        ]
        return " ".join(parts)

    def uav_axes_m(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The UAV grid's x, y and z in the area frame."""
        n = round(self.size_m / self.grid_xy_m) + 1
        xy = np.linspace(0.0, self.size_m, n)
        return xy, xy.copy(), np.asarray(self.grid_z_m, dtype=np.float64)


class Progress:
    """Positions done, elapsed and time left on standard error: rewritten in place on a
    terminal, a line every ``every_s`` otherwise."""

    def __init__(self, total: int, done: int, stream: TextIO | None = None, every_s: float = 10):
        self.total, self.start_done, self.done = total, done, done
        self.stream = stream or sys.stderr
        self.every_s = every_s
        self.t0 = time.monotonic()
        self.last = -math.inf
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def advance(self, n: int) -> None:
        self.done += n
        now = time.monotonic()
        if not self.tty and now - self.last < self.every_s and self.done < self.total:
            return
        self.last = now
        elapsed = now - self.t0
        rate = (self.done - self.start_done) / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        eta = _clock(left) if math.isfinite(left) else "?"
        width = 30
        filled = int(width * self.done / max(self.total, 1))
        line = (
            f"site build [{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total}"
            f" positions, {_clock(elapsed)} elapsed, about {eta} left"
        )
        end = "\r" if self.tty and self.done < self.total else "\n"
        self.stream.write(line + end)
        self.stream.flush()


def _clock(seconds: float) -> str:
    minutes, s = divmod(round(seconds), 60)
    return f"{minutes}:{s:02d}"


def _spec_record(spec: BuildSpec, center_xy_m: tuple[float, float]) -> dict[str, Any]:
    record = asdict(spec)
    record["center_xy_m"] = [float(c) for c in center_xy_m]
    record["grid_z_m"] = [float(z) for z in spec.grid_z_m]
    return record


def _parts_dir(out: Path, record: dict[str, Any]) -> Path:
    """``OUT/.parts`` for this spec: made if missing; InputError if it holds another build."""
    parts = out / PARTS
    spec_file = parts / "spec.json"
    if spec_file.exists():
        try:
            saved = json.loads(spec_file.read_text())
        except (OSError, ValueError):
            saved = None
        if saved != json.loads(json.dumps(record)):
            raise InputError(
                f"--out: {out} holds an interrupted build with other settings; "
                f"remove {parts} or choose another --out"
            )
    else:
        atomic_write_json(spec_file, record)
    return parts


def ground_maps(
    top_surface: Callable[[np.ndarray], np.ndarray],
    origin_xy_m: np.ndarray,
    size_m: float,
    cell_m: float,
    ground_z_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Building height (m above the ground, the tallest of SUBSAMPLES² downward rays) and the
    walkable mask, ``(cells, cells)`` each, from ``top_surface`` (scene-frame xy → z)."""
    n = round(size_m / cell_m)
    offsets = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES * cell_m
    along = (np.arange(n)[:, None] * cell_m + offsets[None, :]).ravel()  # n * SUBSAMPLES
    xs, ys = np.meshgrid(along + origin_xy_m[0], along + origin_xy_m[1])
    tops = top_surface(np.stack([xs.ravel(), ys.ravel()], axis=1)).reshape(xs.shape) - ground_z_m
    tops = np.maximum(tops, 0.0).reshape(n, SUBSAMPLES, n, SUBSAMPLES)
    height = tops.max(axis=(1, 3)).astype(np.float32)
    walkable = np.all(tops <= WALKABLE_MAX_M, axis=(1, 3))
    return height, walkable


def build_site(spec: BuildSpec, out: Path, stream: TextIO | None = None) -> Site:
    """Build ``spec`` into the site directory ``out`` (module doc) and return the site."""
    from sim.sites import raytrace  # the only way in to the ray tracer

    spec.check()
    out = Path(out)
    started = time.monotonic()
    settings = raytrace.SolverSettings(**spec.solver)
    scene = raytrace.load_scene(spec.scene, spec.scene_file)
    low, high = raytrace.scene_bounds_m(scene)
    center = spec.center_xy_m or (float(low[0] + high[0]) / 2, float(low[1] + high[1]) / 2)
    origin = np.array(center, dtype=np.float64) - spec.size_m / 2
    if np.any(origin < low[:2] - 1e-6) or np.any(origin + spec.size_m > high[:2] + 1e-6):
        raise InputError(
            f"--size-m: the {spec.size_m:g} m area around {center[0]:g},{center[1]:g} leaves the "
            f"scene (x {low[0]:.0f}..{high[0]:.0f}, y {low[1]:.0f}..{high[1]:.0f} m)"
        )
    record = _spec_record(spec, center)
    parts = _parts_dir(out, record)
    ground_z = float(low[2])
    height, walkable = ground_maps(
        lambda xy: raytrace.top_surface_m(scene, xy), origin, spec.size_m, spec.cell_m, ground_z
    )
    xs, ys, zs = spec.uav_axes_m()
    cells = height.shape[0]
    grid = np.stack(np.meshgrid(zs, ys, xs, indexing="ij"), axis=-1).reshape(-1, 3)[:, ::-1]
    column = np.minimum((grid[:, 0] // spec.cell_m).astype(int), cells - 1)
    row = np.minimum((grid[:, 1] // spec.cell_m).astype(int), cells - 1)
    traced = np.flatnonzero(grid[:, 2] > height[row, column] + CLEARANCE_M)
    batches = [traced[i : i + spec.batch] for i in range(0, traced.size, spec.batch)]
    done = [k for k in range(len(batches)) if (parts / f"batch_{k:05d}.npy").exists()]
    progress = Progress(traced.size, sum(batches[k].size for k in done), stream)
    plane = (float(center[0]), float(center[1]), ground_z + spec.user_height_m)
    for k, positions in enumerate(batches):
        path = parts / f"batch_{k:05d}.npy"
        if path.exists():
            continue
        tx = grid[positions] + np.array([origin[0], origin[1], ground_z])
        gain = raytrace.radio_maps(
            scene, tx, plane, (spec.size_m, spec.size_m), spec.cell_m, settings
        )
        with np.errstate(divide="ignore"):
            loss = np.where(gain > 0, -10.0 * np.log10(gain), np.inf)
        buffer = _npy_bytes(quantise_loss_db(loss))
        atomic_write_bytes(path, buffer)
        progress.advance(positions.size)
    codes = np.full((grid.shape[0], cells, cells), NO_PATH_CODE, dtype=np.uint16)
    for k, positions in enumerate(batches):
        codes[positions] = np.load(parts / f"batch_{k:05d}.npy")
    codes[:, ~walkable] = NO_PATH_CODE  # users stand on walkable ground only (module doc)
    site = Site(
        size_x_m=spec.size_m,
        size_y_m=spec.size_m,
        cell_m=spec.cell_m,
        user_height_m=spec.user_height_m,
        uav_x_m=xs,
        uav_y_m=ys,
        uav_z_m=zs,
        loss_code=codes.reshape(zs.size, ys.size, xs.size, cells, cells),
        building_height_m=height,
        walkable=walkable,
        meta={
            "scene": {
                "name": spec.scene,
                "file": spec.scene_file,
                "origin_m": [float(origin[0]), float(origin[1]), ground_z],
                **raytrace.scene_attribution(spec.scene),
            },
            "solver": {
                **settings.as_dict(),
                "frequency_hz": raytrace.FREQUENCY_HZ,
                "antennas": "isotropic, vertical polarisation",
            },
            "grid": {
                "xy_m": spec.grid_xy_m,
                "z_m": list(record["grid_z_m"]),
                "clearance_m": CLEARANCE_M,
                "walkable_max_m": WALKABLE_MAX_M,
            },
            "versions": raytrace.versions(),
            "build": {
                "seconds": round(time.monotonic() - started, 1),
                "positions": int(grid.shape[0]),
                "traced": int(traced.size),
                "batch": spec.batch,
                "command": spec.command(out),
            },
        },
    )
    save_site(site, out)
    shutil.rmtree(parts, ignore_errors=True)
    return site


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def direct_loss_db(
    site: Site,
    uav_xyz_m: np.ndarray,
    samples_per_tx: int,
    seed: int,
    scene: Any | None = None,
    batch: int = 2,
) -> np.ndarray:
    """What the ray tracer itself gives at UAV positions ``uav_xyz_m`` (N, 3), area frame, off
    the grid or on it: path loss in dB from each position to each of the site's ground cells,
    ``(N, cells_y, cells_x)``, ``+inf`` where no ray arrived, computed as the build computes a
    grid point (the site's scene, origin, cells, user height and solver settings, from its
    metadata) but with ``samples_per_tx`` rays and ``seed``, unquantised. ``scene`` is the
    loaded scene (:func:`sim.sites.raytrace.load_scene`) or None to load the site's. For the
    lookup's error against direct computation (``benchmarks/sites.py``, the build's test)."""
    from sim.sites import raytrace

    recorded = site.meta.get("scene", {})
    if scene is None:
        scene = raytrace.load_scene(recorded.get("name"), recorded.get("file"))
    solver = {
        k: v
        for k, v in site.meta.get("solver", {}).items()
        if k in raytrace.SolverSettings.__dataclass_fields__
    }
    settings = raytrace.SolverSettings(**{**solver, "samples_per_tx": samples_per_tx, "seed": seed})
    origin = np.asarray(recorded["origin_m"], dtype=np.float64)
    plane = (
        float(origin[0] + site.size_x_m / 2),
        float(origin[1] + site.size_y_m / 2),
        float(origin[2] + site.user_height_m),
    )
    uav = np.atleast_2d(np.asarray(uav_xyz_m, dtype=np.float64))
    out = np.empty((uav.shape[0], site.cells_y, site.cells_x))
    for start in range(0, uav.shape[0], batch):
        gain = raytrace.radio_maps(
            scene,
            uav[start : start + batch] + origin,
            plane,
            (site.size_x_m, site.size_y_m),
            site.cell_m,
            settings,
        )
        with np.errstate(divide="ignore"):
            out[start : start + batch] = np.where(gain > 0, -10.0 * np.log10(gain), np.inf)
    return out
