"""Sionna RT behind four functions: the only module that imports ``sionna``, ``mitsuba`` or
``drjit``, and only inside its functions, so importing it costs nothing and a site can be
loaded and looked up without the ray tracer installed (``pip install 'tupa[sites]'``).

Dr.Jit's CPU backend needs a libLLVM it can JIT with: Debian 12's default LLVM 15 aborts
("Cannot select … fminimum"); ``libllvm19`` works. :func:`prepare_llvm` points
``DRJIT_LIBLLVM_PATH`` at it when the variable is unset. The Mitsuba variant is
``llvm_ad_mono_polarized`` (CPU, polarised, as Sionna's radio maps need).

Radio maps: every transmitter of a batch in one :class:`sionna.rt.RadioMapSolver` call (rays
are launched per transmitter; Dr.Jit spreads the work over every core, which is the build's
parallelism), isotropic vertically polarised antennas at both ends, so the path gain is the
channel's alone. The value of a cell is the mean over its area at the measurement height.
"""

from __future__ import annotations

import glob
import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sim.errors import InputError

VARIANT = "llvm_ad_mono_polarized"
FREQUENCY_HZ = 5.18e9  # 802.11ac channel 36, the model's (sim.config.NetworkConfig)
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19*",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19*",
    "/usr/lib/llvm-19/lib/libLLVM*.so*",
    "/usr/lib/*/libLLVM-1[6-9]*.so*",
    "/usr/lib/*/libLLVM.so.2*",
)
_OSM_SCENES = ("munich", "florence", "etoile", "san_francisco")
_OSM_ATTRIBUTION = (
    "Sionna RT example scene (NVIDIA, sionna-rt, Apache-2.0), built from OpenStreetMap data "
    "with Blender, Blender-OSM and Mitsuba Blender; map data © OpenStreetMap contributors"
)


@dataclass(frozen=True)
class SolverSettings:
    """The ray tracer's settings, recorded in a site's metadata. Diffraction is off by default:
    Sionna's radio maps model it at a large cost and the street-level error it fixes is in the
    deep-shadow cells that are out of coverage for Wi-Fi anyway."""

    samples_per_tx: int = 2_000_000
    max_depth: int = 3
    los: bool = True
    specular_reflection: bool = True
    diffuse_reflection: bool = False
    refraction: bool = True
    diffraction: bool = False
    seed: int = 42

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def find_libllvm() -> str | None:
    """A libLLVM that Dr.Jit can use (LLVM ≥ 16, 19 preferred), or None."""
    for pattern in _LLVM_GLOBS:
        found = sorted(p for p in glob.glob(pattern) if os.path.isfile(p))
        if found:
            return found[-1]
    return None


def prepare_llvm() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` to :func:`find_libllvm` unless it is set already."""
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        path = find_libllvm()
        if path:
            os.environ["DRJIT_LIBLLVM_PATH"] = path


def _rt() -> Any:
    """``sionna.rt`` on the CPU variant; InputError saying what to install when it is missing."""
    prepare_llvm()
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            "--scene: building a site needs Sionna RT: pip install 'tupa[sites]' "
            "(and apt-get install libllvm19)"
        ) from None
    if mi.variant() is None:
        try:
            mi.set_variant(VARIANT)
        except Exception as exc:  # Dr.Jit's own errors: no usable LLVM
            raise InputError(
                f"--scene: Mitsuba's {VARIANT} variant does not start ({exc}); install "
                "libllvm19 and set DRJIT_LIBLLVM_PATH to its libLLVM.so"
            ) from None
    import sionna.rt as rt

    return rt


def versions() -> dict[str, str]:
    """The ray tracer's library versions, for a site's metadata."""
    import drjit
    import mitsuba

    rt = _rt()
    return {
        "sionna-rt": rt.__version__,
        "mitsuba": mitsuba.__version__,
        "drjit": drjit.__version__,
        "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH", ""),
    }


def scene_names() -> list[str]:
    """The scenes shipped in the sionna-rt package."""
    rt = _rt()
    return sorted(
        name
        for name, value in vars(rt.scene).items()
        if isinstance(value, str) and value.endswith(".xml") and not name.startswith("_")
    )


def scene_attribution(name: str | None) -> dict[str, str]:
    """Where a scene's geometry comes from and under what licence (a site is derived data)."""
    if name in _OSM_SCENES:
        return {
            "attribution": _OSM_ATTRIBUTION,
            "licence": "ODbL-1.0 (https://openstreetmap.org/copyright)",
        }
    if name is not None:
        return {
            "attribution": "Sionna RT example scene (NVIDIA, sionna-rt)",
            "licence": "Apache-2.0",
        }
    return {"attribution": "the user's own scene file", "licence": "as the scene file's"}


def load_scene(name: str | None, path: str | None) -> Any:
    """A Sionna scene by package name or from a Mitsuba XML file, set up at FREQUENCY_HZ with
    isotropic antennas; InputError naming ``--scene`` or ``--scene-file``."""
    rt = _rt()
    if name is not None:
        known = scene_names()
        if name not in known:
            raise InputError(f"--scene: unknown scene {name!r}; one of {', '.join(known)}")
        path, option = getattr(rt.scene, name), "--scene"
    else:
        option = "--scene-file"
        if path is None or not os.path.isfile(path):
            raise InputError(f"--scene-file: no such file: {path}")
    try:
        scene = rt.load_scene(path)
    except Exception as exc:  # Mitsuba's parser raises RuntimeError with a long message
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{option}: cannot load {path}: {first}") from None
    scene.frequency = FREQUENCY_HZ
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    return scene


def scene_bounds_m(scene: Any) -> tuple[np.ndarray, np.ndarray]:
    """The scene's bounding box, (min xyz, max xyz) in the scene frame."""
    box = scene.mi_scene.bbox()
    return (
        np.array([box.min.x, box.min.y, box.min.z], dtype=np.float64).ravel(),
        np.array([box.max.x, box.max.y, box.max.z], dtype=np.float64).ravel(),
    )


def top_surface_m(scene: Any, points_xy: np.ndarray) -> np.ndarray:
    """The height (scene frame z) of the first surface a ray cast straight down meets above
    each point; the scene's lowest z where nothing is hit."""
    import mitsuba as mi

    low, high = scene_bounds_m(scene)
    xy = np.asarray(points_xy, dtype=np.float32)
    start_z = float(high[2]) + 10.0
    origin = mi.Point3f(xy[:, 0], xy[:, 1], np.full(len(xy), start_z, dtype=np.float32))
    hit = scene.mi_scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0.0, 0.0, -1.0)))
    distance = np.array(hit.t, dtype=np.float64)
    valid = np.array(hit.is_valid(), dtype=bool)
    return np.where(valid, start_z - distance, float(low[2]))


def radio_maps(
    scene: Any,
    tx_xyz: np.ndarray,
    center_xyz: tuple[float, float, float],
    size_xy_m: tuple[float, float],
    cell_m: float,
    settings: SolverSettings,
) -> np.ndarray:
    """Path gain (linear, 0 where no ray arrived) from each transmitter position (scene frame)
    to every cell of a horizontal plane: shape ``(B, cells_y, cells_x)``, row 0 the
    southernmost (lowest y), column 0 the westernmost."""
    import mitsuba as mi

    rt = _rt()
    for name in list(scene.transmitters):
        scene.remove(name)
    for k, (x, y, z) in enumerate(np.asarray(tx_xyz, dtype=np.float64)):
        scene.add(rt.Transmitter(f"uav{k}", position=mi.Point3f(float(x), float(y), float(z))))
    solver = rt.RadioMapSolver()
    radio_map = solver(
        scene,
        center=mi.Point3f(*(float(c) for c in center_xyz)),
        orientation=mi.Point3f(0.0, 0.0, 0.0),
        size=mi.Point2f(float(size_xy_m[0]), float(size_xy_m[1])),
        cell_size=mi.Point2f(float(cell_m), float(cell_m)),
        **settings.as_dict(),
    )
    gain = np.array(radio_map.path_gain, dtype=np.float64)
    centers = np.array(radio_map.cell_centers, dtype=np.float64)
    if gain.shape[0] != len(tx_xyz) or centers[0, 0, 1] > centers[-1, 0, 1]:
        raise RuntimeError(f"unexpected radio map layout: gain {gain.shape}")
    return gain
