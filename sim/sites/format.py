"""The site file: a district prepared for the fast model (``tupa-site/1``).

A site is a directory with two files, written atomically, the arrays first::

    DIR/site.npz   arrays (numpy ``savez_compressed``):
        uav_x_m, uav_y_m, uav_z_m   float64 (nx,), (ny,), (nz,)  the UAV grid, ascending, area frame
        loss_code                   uint16 (nz, ny, nx, cy, cx)  mean path loss in LOSS_STEP_DB
                                    steps from each UAV grid point to each ground cell's centre
                                    at ``user_height_m``; NO_PATH_CODE where no ray arrived
        building_height_m           float32 (cy, cx)  top of whatever stands on the cell (0: ground)
        walkable                    bool (cy, cx)     ground a user may stand on
    DIR/site.json  the metadata: ``format``, ``size_x_m``, ``size_y_m``, ``cell_m``,
        ``user_height_m``, ``loss_step_db``, ``no_path_code``, ``scene`` (name or file, its
        origin in the scene frame, attribution, licence), ``solver`` (the ray tracer's settings),
        ``versions`` (libraries), ``build`` (how long, how many positions) and
        ``content_sha256`` (:func:`content_hash`: the geometry fields and every array).

Frames: the area frame of the rest of the model (origin at the area's south-west corner, x
east, y north, z up, metres). Ground cell (j, i) is the square ``[i·cell_m, (i+1)·cell_m] ×
[j·cell_m, (j+1)·cell_m]``, its value taken at its centre; ``cx·cell_m = size_x_m``.

:func:`load_site` never returns half-valid data: a missing file, a wrong format, a shape that
does not match, or a hash that does not match the arrays is an :class:`sim.errors.InputError`
of one line naming the directory and the field.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_bytes, atomic_write_json
from sim.errors import InputError

SITE_FORMAT = "tupa-site/1"
LOSS_STEP_DB = 0.1
NO_PATH_CODE = np.iinfo(np.uint16).max  # 65535: no ray arrived
MAX_LOSS_DB = (int(NO_PATH_CODE) - 1) * LOSS_STEP_DB  # 6553.4 dB, far above any real link
DATA_FILE = "site.npz"
META_FILE = "site.json"
_ARRAYS = ("uav_x_m", "uav_y_m", "uav_z_m", "loss_code", "building_height_m", "walkable")
_GEOMETRY = ("size_x_m", "size_y_m", "cell_m", "user_height_m", "loss_step_db", "no_path_code")


@dataclass(frozen=True)
class Site:
    """A district prepared for the fast model (module doc). The arrays are made read-only;
    ``meta`` holds the non-geometric metadata (scene, solver, versions, build).
    :func:`check_site` says whether the arrays fit together (saving and loading call it)."""

    size_x_m: float
    size_y_m: float
    cell_m: float
    user_height_m: float
    uav_x_m: np.ndarray
    uav_y_m: np.ndarray
    uav_z_m: np.ndarray
    loss_code: np.ndarray
    building_height_m: np.ndarray
    walkable: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def cells_x(self) -> int:
        return int(self.building_height_m.shape[1])

    @property
    def cells_y(self) -> int:
        return int(self.building_height_m.shape[0])

    def __post_init__(self) -> None:
        codes = self.loss_code
        if codes.ndim == 5 and not _cell_major(codes):
            object.__setattr__(self, "loss_code", cell_major(codes))
        for name in _ARRAYS:
            getattr(self, name).setflags(write=False)


def cell_major(codes: np.ndarray) -> np.ndarray:
    """``codes`` (nz, ny, nx, cy, cx) with the same values, laid out in memory ground cell by
    ground cell: the UAV grid points of one cell are next to each other, so the lookup's
    eight corners of a link share a few cache lines (a layer-major array spreads them over
    eight maps far apart). Indexing, shape and content hash are unchanged."""
    stored = np.ascontiguousarray(np.moveaxis(codes, (3, 4), (0, 1)))
    return np.moveaxis(stored, (0, 1), (3, 4))


def _cell_major(codes: np.ndarray) -> bool:
    base = np.moveaxis(codes, (3, 4), (0, 1))
    return bool(base.flags.c_contiguous)


def quantise_loss_db(loss_db: np.ndarray) -> np.ndarray:
    """Path loss in dB → uint16 codes of LOSS_STEP_DB; +inf or NaN (no path) → NO_PATH_CODE.
    Losses are clipped to [0, MAX_LOSS_DB] (a negative loss, a gain, cannot occur)."""
    loss = np.asarray(loss_db, dtype=np.float64)
    covered = np.isfinite(loss)
    codes = np.full(loss.shape, NO_PATH_CODE, dtype=np.uint16)
    clipped = np.clip(loss[covered], 0.0, MAX_LOSS_DB)
    codes[covered] = np.rint(clipped / LOSS_STEP_DB).astype(np.uint16)
    return codes


def dequantise_loss_db(codes: np.ndarray) -> np.ndarray:
    """uint16 codes → path loss in dB (float64); NO_PATH_CODE → +inf."""
    codes = np.asarray(codes)
    loss = codes.astype(np.float64) * LOSS_STEP_DB
    loss[codes == NO_PATH_CODE] = np.inf
    return loss


def _geometry(site: Site) -> dict[str, float | int]:
    return {
        "size_x_m": float(site.size_x_m),
        "size_y_m": float(site.size_y_m),
        "cell_m": float(site.cell_m),
        "user_height_m": float(site.user_height_m),
        "loss_step_db": LOSS_STEP_DB,
        "no_path_code": int(NO_PATH_CODE),
    }


def content_hash(site: Site) -> str:
    """SHA-256 (hex) of the site's geometry fields (canonical JSON) and of every array's
    dtype, shape and bytes, in a fixed order: what the data is, not how the file stores it."""
    digest = hashlib.sha256()
    digest.update(json.dumps(_geometry(site), sort_keys=True).encode())
    for name in _ARRAYS:
        array = np.ascontiguousarray(getattr(site, name))
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def check_site(site: Site, where: str) -> None:
    """InputError naming ``where`` and the field for arrays that do not fit together."""

    def bad(name: str, problem: str) -> InputError:
        return InputError(f"{where}: {name}: {problem}")

    for name in ("size_x_m", "size_y_m", "cell_m"):
        value = getattr(site, name)
        if not (math.isfinite(value) and value > 0):
            raise bad(name, f"must be a finite number > 0, got {value}")
    for name in ("uav_x_m", "uav_y_m", "uav_z_m"):
        axis = getattr(site, name)
        if axis.ndim != 1 or axis.size < 1 or not np.all(np.isfinite(axis)):
            raise bad(name, "must be a non-empty 1-D array of finite numbers")
        if np.any(np.diff(axis) <= 0):
            raise bad(name, "must be strictly ascending")
    cells = (round(site.size_y_m / site.cell_m), round(site.size_x_m / site.cell_m))
    for name, dtype in (("building_height_m", np.float32), ("walkable", np.bool_)):
        array = getattr(site, name)
        if array.dtype != dtype or array.shape != cells:
            raise bad(
                name,
                f"must be {np.dtype(dtype).name} of shape {cells}, got "
                f"{array.dtype.name} {array.shape}",
            )
    grid = (site.uav_z_m.size, site.uav_y_m.size, site.uav_x_m.size)
    if site.loss_code.dtype != np.uint16 or site.loss_code.shape != (*grid, *cells):
        raise bad(
            "loss_code",
            f"must be uint16 of shape {(*grid, *cells)}, got "
            f"{site.loss_code.dtype.name} {site.loss_code.shape}",
        )


def save_site(site: Site, directory: Path) -> str:
    """Write ``site`` to ``directory`` (created if missing): the arrays, then the metadata with
    the content hash, each atomically, so a reader sees a complete site or an InputError.
    Returns the hash."""
    directory = Path(directory)
    check_site(site, str(directory))
    digest = content_hash(site)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{name: getattr(site, name) for name in _ARRAYS})
    atomic_write_bytes(directory / DATA_FILE, buffer.getvalue())
    meta = {"format": SITE_FORMAT, **_geometry(site), **site.meta, "content_sha256": digest}
    atomic_write_json(directory / META_FILE, meta)
    return digest


def load_site(directory: Path) -> Site:
    """Read and check a site directory (module doc); InputError of one line naming the
    directory and the field on any problem, the hash included."""
    directory = Path(directory)
    where = str(directory)
    try:
        meta = json.loads((directory / META_FILE).read_text())
    except FileNotFoundError:
        raise InputError(f"{where}: {META_FILE}: no such file (not a site directory)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{where}: {META_FILE}: not readable JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != SITE_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise InputError(f"{where}: format: must be {SITE_FORMAT!r}, got {got!r}")
    for name in _GEOMETRY:
        value = meta.get(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"{where}: {name}: must be a number, got {value!r}")
    if meta["loss_step_db"] != LOSS_STEP_DB or meta["no_path_code"] != NO_PATH_CODE:
        raise InputError(
            f"{where}: loss_step_db: this version reads {LOSS_STEP_DB} dB steps with "
            f"no_path_code {NO_PATH_CODE}, got {meta['loss_step_db']} and {meta['no_path_code']}"
        )
    try:
        with np.load(directory / DATA_FILE, allow_pickle=False) as data:
            arrays = {name: data[name] for name in _ARRAYS if name in data}
    except FileNotFoundError:
        raise InputError(f"{where}: {DATA_FILE}: no such file") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{where}: {DATA_FILE}: not a readable npz ({exc})") from None
    missing = [name for name in _ARRAYS if name not in arrays]
    if missing:
        raise InputError(f"{where}: {missing[0]}: missing from {DATA_FILE}")
    extra = {k: v for k, v in meta.items() if k not in (*_GEOMETRY, "format", "content_sha256")}
    site = Site(
        size_x_m=float(meta["size_x_m"]),
        size_y_m=float(meta["size_y_m"]),
        cell_m=float(meta["cell_m"]),
        user_height_m=float(meta["user_height_m"]),
        meta=extra,
        **arrays,
    )
    check_site(site, where)
    digest = content_hash(site)
    if meta.get("content_sha256") != digest:
        raise InputError(
            f"{where}: content_sha256: does not match the site's data (recorded "
            f"{str(meta.get('content_sha256'))[:12]}…, computed {digest[:12]}…)"
        )
    return site
