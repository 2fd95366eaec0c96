"""A tiny site built from scratch through the real Sionna RT path, checked against a direct
ray-tracer computation and the lookup. Skipped, saying why, without sionna-rt (``pip install
'tupa[sites]'``) or without a libLLVM Dr.Jit can use (``apt-get install libllvm19``)."""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
import pytest

from sim.errors import InputError
from sim.sites import load_site, path_loss_db, raytrace
from sim.sites.build import BuildSpec, build_site, direct_loss_db

pytestmark = pytest.mark.slow

INSTALL = "sionna-rt is not installed: pip install 'tupa[sites]'"


@pytest.fixture(scope="module")
def rt():
    raytrace.prepare_llvm()
    if raytrace.find_libllvm() is None:
        pytest.skip("no libLLVM >= 16 for Dr.Jit's CPU backend: apt-get install libllvm19")
    mi = pytest.importorskip("mitsuba", reason=INSTALL)
    if mi.variant() is None:
        mi.set_variant(raytrace.VARIANT)
    return pytest.importorskip("sionna.rt", reason=INSTALL)


SPEC = BuildSpec(
    scene="simple_street_canyon",
    size_m=40.0,
    cell_m=5.0,
    grid_xy_m=20.0,
    grid_z_m=(30.0, 60.0),
    batch=9,
    solver={"samples_per_tx": 200_000},
)


def test_a_tiny_site_built_through_sionna_matches_a_direct_computation(rt, tmp_path: Path):
    started = time.monotonic()
    built = build_site(SPEC, tmp_path / "site", stream=io.StringIO())
    seconds = time.monotonic() - started
    site = load_site(tmp_path / "site")
    assert site.loss_code.shape == (2, 3, 3, 8, 8)
    assert np.array_equal(site.loss_code, built.loss_code)
    assert site.meta["versions"]["sionna-rt"] == rt.__version__
    assert site.meta["scene"]["name"] == "simple_street_canyon"
    assert not (tmp_path / "site" / ".parts").exists()
    assert site.walkable.any() and not site.walkable.all()
    assert site.building_height_m.max() > 20
    assert seconds < 60, f"the CI site took {seconds:.0f} s"

    # The lookup at a grid point against the ray tracer run there on its own (what
    # benchmarks/sites.py measures at scale), over the walkable cells: losses are kept there
    # only, the cells inside buildings have none.
    uav = np.array([20.0, 20.0, 30.0])
    direct = direct_loss_db(site, uav[None], 200_000, seed=7)[0]
    assert direct.shape == (8, 8)
    centres = (np.arange(8) + 0.5) * 5.0
    cx, cy = np.meshgrid(centres, centres)
    looked_up = path_loss_db(site, uav, np.stack([cx.ravel(), cy.ravel()], 1)).reshape(8, 8)
    walk = site.walkable
    assert np.isinf(looked_up[~walk]).all()
    d, lk = direct[walk], looked_up[walk]
    both = np.isfinite(d) & np.isfinite(lk)
    assert np.mean(np.isfinite(d) == np.isfinite(lk)) >= 0.9
    assert np.median(np.abs(d[both] - lk[both])) <= 1.0
    # In the open street right below the UAV, close to free space (28.5 m at 5.18 GHz: 75.8 dB).
    assert 70 < looked_up[4, 4] < 82
    # Off the grid, the lookup follows the ray tracer too (a coarse 20 m grid: looser).
    uav = np.array([27.0, 13.0, 41.0])
    direct = direct_loss_db(site, uav[None], 200_000, seed=7)[0][walk]
    looked_up = path_loss_db(site, uav, np.stack([cx.ravel(), cy.ravel()], 1)).reshape(8, 8)
    lk = looked_up[walk]
    both = np.isfinite(direct) & np.isfinite(lk)
    assert both.sum() >= 10 and np.median(np.abs(direct[both] - lk[both])) <= 3.0


def test_unknown_scenes_and_areas_outside_the_scene_are_refused(rt, tmp_path: Path):
    with pytest.raises(InputError, match=r"--scene: unknown scene 'nowhere'; one of .*munich"):
        build_site(BuildSpec(scene="nowhere"), tmp_path / "a")
    with pytest.raises(InputError, match=r"--size-m: the 400 m area around .* leaves the scene"):
        build_site(BuildSpec(scene="simple_street_canyon", size_m=400), tmp_path / "b")
    with pytest.raises(InputError, match=r"--scene-file: no such file"):
        build_site(BuildSpec(scene_file=str(tmp_path / "none.xml")), tmp_path / "c")
