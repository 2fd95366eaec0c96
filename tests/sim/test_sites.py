"""Sites without the ray tracer: the tupa-site/1 format, its hash, the lookup, the build's
numpy parts and ``tupa site build``'s refusals (sim/sites/)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

import sim.sites
from service.cli import main
from sim.channel import friis_path_loss_db
from sim.errors import InputError
from sim.sites import Site, load_site, path_loss_db, raytrace, save_site
from sim.sites.build import BuildSpec, Progress, _parts_dir, build_site, ground_maps
from sim.sites.format import (
    DATA_FILE,
    META_FILE,
    NO_PATH_CODE,
    content_hash,
    dequantise_loss_db,
    quantise_loss_db,
)


def _site(loss_db: np.ndarray | None = None) -> Site:
    """A 20 m × 20 m site of 5 m cells; UAV grid x, y ∈ {0, 10, 20}, z ∈ {25, 50}."""
    xs = np.array([0.0, 10.0, 20.0])
    zs = np.array([25.0, 50.0])
    if loss_db is None:
        rng = np.random.default_rng(3)
        loss_db = rng.uniform(60, 120, (2, 3, 3, 4, 4))
        loss_db[1, 2, 2, 0, 0] = np.inf
    height = np.zeros((4, 4), np.float32)
    height[2:, 2:] = 12.5
    return Site(
        size_x_m=20.0,
        size_y_m=20.0,
        cell_m=5.0,
        user_height_m=1.5,
        uav_x_m=xs,
        uav_y_m=xs.copy(),
        uav_z_m=zs,
        loss_code=quantise_loss_db(loss_db),
        building_height_m=height,
        walkable=height == 0,
        meta={"scene": {"name": "test", "licence": "CC0"}, "solver": {"max_depth": 3}},
    )


def _linear_site() -> Site:
    """Loss linear in the UAV's x, y, z (exactly representable in 0.1 dB steps)."""
    x = np.array([0.0, 10.0, 20.0])
    z = np.array([25.0, 50.0])
    Z, Y, X = np.meshgrid(z, x, x, indexing="ij")
    loss = 80 + 0.5 * X + 0.2 * Y + 0.4 * (Z - 25)
    return _site(np.broadcast_to(loss[..., None, None], (*loss.shape, 4, 4)).copy())


# ---------------------------------------------------------------------------------- format


def test_quantisation_round_trip_and_no_path_sentinel() -> None:
    loss = np.array([0.0, 61.23, 119.96, np.inf, np.nan, -3.0])
    codes = quantise_loss_db(loss)
    assert codes.dtype == np.uint16
    assert codes[3] == codes[4] == NO_PATH_CODE
    back = dequantise_loss_db(codes)
    assert np.allclose(back[:3], loss[:3], atol=0.05)
    assert np.isinf(back[3]) and np.isinf(back[4]) and back[5] == 0.0


def test_round_trip_keeps_arrays_metadata_and_hash(tmp_path: Path) -> None:
    site = _site()
    digest = save_site(site, tmp_path / "s")
    loaded = load_site(tmp_path / "s")
    assert digest == content_hash(loaded) == content_hash(site)
    for name in ("uav_x_m", "uav_y_m", "uav_z_m", "loss_code", "building_height_m", "walkable"):
        assert np.array_equal(getattr(loaded, name), getattr(site, name)), name
        assert getattr(loaded, name).dtype == getattr(site, name).dtype
    assert loaded.meta == site.meta
    assert (loaded.size_x_m, loaded.cell_m, loaded.user_height_m) == (20.0, 5.0, 1.5)
    meta = json.loads((tmp_path / "s" / META_FILE).read_text())
    assert meta["format"] == "tupa-site/1" and meta["content_sha256"] == digest


def test_a_site_whose_data_does_not_match_its_hash_is_refused(tmp_path: Path) -> None:
    save_site(_site(), tmp_path / "s")
    with np.load(tmp_path / "s" / DATA_FILE) as data:
        arrays = dict(data)
    arrays["loss_code"] = arrays["loss_code"].copy()
    arrays["loss_code"][0, 0, 0, 0, 0] += 1
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    (tmp_path / "s" / DATA_FILE).write_bytes(buffer.getvalue())
    with pytest.raises(InputError, match=r"content_sha256: does not match") as caught:
        load_site(tmp_path / "s")
    assert "\n" not in str(caught.value) and str(tmp_path / "s") in str(caught.value)


def test_a_geometry_field_changed_in_the_metadata_breaks_the_hash(tmp_path: Path) -> None:
    save_site(_site(), tmp_path / "s")
    meta_path = tmp_path / "s" / META_FILE
    meta = json.loads(meta_path.read_text())
    meta["user_height_m"] = 2.0
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="content_sha256"):
        load_site(tmp_path / "s")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda m: m.update(format="tupa-site/9"), "format"),
        (lambda m: m.update(size_x_m=25.0), "building_height_m"),
        (lambda m: m.update(cell_m="5"), "cell_m"),
        (lambda m: m.pop("size_y_m"), "size_y_m"),
    ],
)
def test_bad_metadata_is_refused_naming_the_field(tmp_path: Path, change, field: str) -> None:
    save_site(_site(), tmp_path / "s")
    meta_path = tmp_path / "s" / META_FILE
    meta = json.loads(meta_path.read_text())
    change(meta)
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match=f": {field}: "):
        load_site(tmp_path / "s")


def test_a_missing_site_and_a_missing_array_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"site.json: no such file"):
        load_site(tmp_path / "nothing")
    save_site(_site(), tmp_path / "s")
    buffer = io.BytesIO()
    np.savez_compressed(buffer, uav_x_m=np.zeros(3))
    (tmp_path / "s" / DATA_FILE).write_bytes(buffer.getvalue())
    with pytest.raises(InputError, match=r"uav_y_m: missing from site.npz"):
        load_site(tmp_path / "s")


def test_a_wrong_shape_is_refused_before_writing(tmp_path: Path) -> None:
    site = _site()
    bad = Site(**{**site.__dict__, "walkable": np.ones((3, 4), bool)})
    with pytest.raises(InputError, match=r"walkable: must be bool of shape \(4, 4\)"):
        save_site(bad, tmp_path / "s")
    assert not (tmp_path / "s").exists()


def test_arrays_are_read_only() -> None:
    with pytest.raises(ValueError, match="read-only"):
        _site().loss_code[0, 0, 0, 0, 0] = 1


# ---------------------------------------------------------------------------------- lookup


def test_lookup_is_exact_at_grid_points_for_every_cell() -> None:
    site = _site()
    stored = dequantise_loss_db(site.loss_code)
    centres = (np.arange(4) + 0.5) * 5.0
    cx, cy = np.meshgrid(centres, centres)
    users = np.stack([cx.ravel(), cy.ravel()], axis=1)  # row-major: (row j, column i)
    for iz, z in enumerate(site.uav_z_m):
        for iy, y in enumerate(site.uav_y_m):
            for ix, x in enumerate(site.uav_x_m):
                got = path_loss_db(site, np.array([x, y, z]), users)
                assert np.array_equal(got, stored[iz, iy, ix].ravel())


def _free_space_site(excess_db: float = 0.0) -> Site:
    """Friis at 5.18 GHz from each grid point to each cell's centre (at 1.5 m), plus
    ``excess_db``: what an open field's site stores."""
    site = _site()
    centres = (np.arange(4) + 0.5) * 5.0
    Z, Y, X, CY, CX = np.meshgrid(
        site.uav_z_m, site.uav_y_m, site.uav_x_m, centres, centres, indexing="ij"
    )
    distance = np.sqrt((X - CX) ** 2 + (Y - CY) ** 2 + (Z - 1.5) ** 2)
    return Site(
        **{
            **site.__dict__,
            "loss_code": quantise_loss_db(friis_path_loss_db(distance, 5.18e9) + excess_db),
        }
    )


def _interpolated_squared_distance(uav: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Σ w·d² over the eight corners for ``_site``'s grid (steps 10, 10 and 25 m): the squared
    distance plus f(1 − f)·h² on each axis (trilinear interpolation of a quadratic)."""
    squared = ((uav[:, None, :2] - centres[None]) ** 2).sum(axis=2) + (uav[:, None, 2] - 1.5) ** 2
    bend = 0.0
    for axis, step, low in ((0, 10.0, 0.0), (1, 10.0, 0.0), (2, 25.0, 25.0)):
        f = np.mod(uav[:, axis] - low, step) / step
        bend = bend + f * (1 - f) * step**2
    return squared + bend[:, None]


@pytest.mark.parametrize("excess_db", [0.0, 23.4])
def test_lookup_follows_free_space_between_grid_points(excess_db: float) -> None:
    """Power relative to free-space spreading is interpolated and spread over the interpolated
    squared distance: a site that stores Friis (plus a constant) gives Friis (plus it) at the
    interpolated squared distance — exact at the grid points, within the module doc's bound
    between them — to the 0.1 dB steps."""
    site = _free_space_site(excess_db)
    rng = np.random.default_rng(0)
    uav = rng.uniform([0, 0, 25], [20, 20, 50], (200, 3))
    users = rng.uniform(0, 20, (7, 2))
    got = path_loss_db(site, uav, users)
    centres = (np.floor(users / 5.0) + 0.5) * 5.0  # the users' cells' centres
    spread = _interpolated_squared_distance(uav, centres)
    assert got.shape == (200, 7)
    assert np.allclose(got, friis_path_loss_db(np.sqrt(spread), 5.18e9) + excess_db, atol=0.051)


def test_a_constant_loss_stays_constant_between_grid_points() -> None:
    site = _site(np.full((2, 3, 3, 4, 4), 97.3))
    rng = np.random.default_rng(1)
    got = path_loss_db(site, rng.uniform([0, 0, 25], [20, 20, 50], (100, 3)), [[3, 3], [17, 9]])
    assert np.allclose(got, 97.3, atol=1e-9)


def test_lookup_averages_power_not_decibels() -> None:
    """Half-way between two grid points, 10 dB and 30 dB above free space, the loss is Friis'
    at the interpolated squared distance plus the mean excess *power*, −10·log10((10⁻¹ +
    10⁻³) / 2) = 12.96 dB, not the mean of the decibels, 20 dB (to the 0.1 dB steps)."""
    site = _free_space_site()
    codes = site.loss_code.copy()
    codes[:, :, 0] += 100  # +10 dB from every grid point at x = 0
    codes[:, :, 1] += 300  # +30 dB at x = 10
    site = Site(**{**site.__dict__, "loss_code": codes})
    user = np.array([[7.5, 12.5]])  # the cell centred at (7.5, 12.5)
    at_0, at_10 = path_loss_db(site, [[0.0, 10.0, 25.0], [10.0, 10.0, 25.0]], user)[:, 0]
    mid = path_loss_db(site, [5.0, 10.0, 25.0], user)[0]
    d0, d1 = 7.5**2 + 2.5**2 + 23.5**2, 2.5**2 + 2.5**2 + 23.5**2
    spread = (d0 + d1) / 2
    want = friis_path_loss_db(np.sqrt(spread), 5.18e9) - 10 * np.log10((10**-1.0 + 10**-3.0) / 2)
    assert mid == pytest.approx(want, abs=0.06)
    assert mid < (at_0 + at_10) / 2  # the stronger corner weighs more than in decibels


def test_lookup_uses_the_users_ground_cell_and_clamps_the_uav_to_the_grid() -> None:
    site = _site()
    a = path_loss_db(site, [10, 10, 25], [[5.1, 0.2], [9.9, 4.9]])
    assert a[0] == a[1]  # both in cell (row 0, column 1)
    assert np.array_equal(
        path_loss_db(site, [-5, 30, 10], [[1, 1]]), path_loss_db(site, [0, 20, 25], [[1, 1]])
    )
    edge = path_loss_db(site, [0, 0, 25], [[20.0, 20.0]])  # the far edge is the last cell
    assert edge[0] == dequantise_loss_db(site.loss_code)[0, 0, 0, 3, 3]


def test_no_path_is_infinite_loss_and_wins_only_with_most_of_the_weight() -> None:
    site = _free_space_site()
    codes = site.loss_code.copy()
    codes[1, 2, 2] = NO_PATH_CODE  # no path from (20, 20, 50) to any cell
    site = Site(**{**site.__dict__, "loss_code": codes})
    users = [[2.5, 2.5]]
    assert np.isinf(path_loss_db(site, [20, 20, 50], users)[0])
    # Three quarters of the way to the no-path corner along x: its weight is 0.75.
    assert np.isinf(path_loss_db(site, [17.5, 20, 50], users)[0])
    # A quarter of the way: the covered corner's power, with a zero for the other's quarter.
    near = path_loss_db(site, [12.5, 20, 50], users)[0]
    d1, d2 = 10**2 + 17.5**2 + 48.5**2, 20**2 + 17.5**2 + 48.5**2  # to x = 10 and x = 20
    gain = 10 ** (-friis_path_loss_db(np.sqrt(d1), 5.18e9) / 10)
    want = -10 * np.log10(0.75 * d1 * gain / (0.75 * d1 + 0.25 * d2))
    assert near == pytest.approx(want, abs=0.06)
    # Half-way: weight 0.5 with a path, so a path.
    assert np.isfinite(path_loss_db(site, [15, 20, 50], users)[0])


def test_lookup_refuses_bad_shapes_and_users_off_the_site() -> None:
    site = _site()
    with pytest.raises(InputError, match=r"users_xy\[1\]: .* outside the site's area"):
        path_loss_db(site, [10, 10, 25], [[1, 1], [21, 1]])
    with pytest.raises(InputError, match=r"uav_xyz: must be finite with shape"):
        path_loss_db(site, [10, 10], [[1, 1]])
    with pytest.raises(InputError, match=r"users_xy: must have shape \(M, 2\)"):
        path_loss_db(site, [10, 10, 25], [1, 1])


# ---------------------------------------------------------------------------------- build


def test_ground_maps_from_downward_rays() -> None:
    def top_surface(xy: np.ndarray) -> np.ndarray:  # a 20 m block on x, y ∈ [10, 17]
        inside = (xy[:, 0] >= 10) & (xy[:, 0] <= 17) & (xy[:, 1] >= 10) & (xy[:, 1] <= 17)
        return np.where(inside, 19.0, -1.0)  # ground at z = -1

    height, walkable = ground_maps(top_surface, np.array([0.0, 0.0]), 20.0, 5.0, -1.0)
    assert height.dtype == np.float32 and height.shape == (4, 4)
    assert height[2, 2] == 20.0 and height[3, 3] == 20.0 and height[0, 0] == 0.0
    assert walkable.sum() == 12 and not walkable[2, 2] and not walkable[3, 3]


def test_an_interrupted_build_with_other_settings_is_refused(tmp_path: Path) -> None:
    spec = BuildSpec(scene="munich")
    record = {"scene": "munich", "size_m": 500.0}
    parts = _parts_dir(tmp_path, record)
    assert _parts_dir(tmp_path, record) == parts
    with pytest.raises(InputError, match=r"--out: .* interrupted build with other settings"):
        _parts_dir(tmp_path, {**record, "size_m": 400.0})
    xs, ys, zs = spec.uav_axes_m()  # the default grid: every 25 m, 12.5 m up from 25 to 100
    assert xs.tolist() == ys.tolist() == [25.0 * i for i in range(21)]
    assert zs.tolist() == [25.0, 37.5, 50.0, 62.5, 75.0, 87.5, 100.0]


def test_progress_says_the_time_left() -> None:
    stream = io.StringIO()
    progress = Progress(10, 2, stream, every_s=0)
    progress.advance(4)
    progress.advance(4)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("site build [") and "6/10 positions" in lines[0]
    assert "left" in lines[0] and "10/10" in lines[-1]


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--grid-xy-m", "30"], "--grid-xy-m: must divide --size-m 500, got 30"),
        (["--cell-m", "10"], "--cell-m: must be at most 5 m, got 10"),
        (["--cell-m", "3"], "--cell-m: must divide --size-m 500, got 3"),
        (["--size-m", "-5"], "--size-m: must be a finite number > 0"),
        (["--grid-z-m", "50,25"], "--grid-z-m: must be strictly ascending"),
        (["--grid-z-m", "1,25"], "--grid-z-m: altitudes must be above the users"),
        (["--grid-z-m", "25,x"], "--grid-z-m: must be comma-separated numbers"),
        (["--center", "1"], "--center: must be 2 finite numbers, got '1'"),
        (["--center", "1,nan"], "--center: must be 2 finite numbers"),
        (["--batch", "0"], "--batch: must be at least 1, got 0"),
        (["--samples", "0"], "--samples: must be at least 1, got 0"),
    ],
)
def test_site_build_refuses_bad_options_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], said: str
) -> None:
    out = tmp_path / "site"
    assert main(["site", "build", "--scene", "munich", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert said in err and "\n" not in err
    assert not out.exists()


def test_site_build_needs_exactly_one_scene(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as caught:
        main(["site", "build", "--scene", "munich", "--scene-file", "x.xml", "--out", "o"])
    assert caught.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


class _FakeTracer:
    """Stands in for sim.sites.raytrace: a 40 m flat scene with a 20 m block in its north-east
    quarter; loss = 60 dB + the UAV's height in dB·m⁻¹; counts the positions it traced."""

    SolverSettings = raytrace.SolverSettings
    FREQUENCY_HZ = 5.18e9

    def __init__(self, fail_after: int | None = None) -> None:
        self.traced = 0
        self.fail_after = fail_after

    def load_scene(self, name, path):
        return "scene"

    def scene_bounds_m(self, scene):
        return np.array([-20.0, -20.0, 0.0]), np.array([20.0, 20.0, 20.0])

    def top_surface_m(self, scene, xy):
        return np.where((xy[:, 0] > 0) & (xy[:, 1] > 0), 20.0, 0.0)

    def radio_maps(self, scene, tx, centre, size, cell_m, settings):
        if self.fail_after is not None and self.traced >= self.fail_after:
            raise KeyboardInterrupt
        self.traced += len(tx)
        cells = round(size[0] / cell_m)
        return np.broadcast_to(10 ** (-(60 + tx[:, 2:3, None]) / 10), (len(tx), cells, cells))

    def versions(self):
        return {"sionna-rt": "fake"}

    def scene_attribution(self, name):
        return {"attribution": "a test", "licence": "CC0"}


def test_the_build_skips_blocked_points_saves_batches_and_resumes(tmp_path, monkeypatch):
    spec = BuildSpec(scene="fake", size_m=40, grid_xy_m=20, grid_z_m=(10.0, 30.0), batch=4)
    fake = _FakeTracer(fail_after=8)
    monkeypatch.setattr(sim.sites, "raytrace", fake)  # build_site's `from sim.sites import`
    with pytest.raises(KeyboardInterrupt):
        build_site(spec, tmp_path / "s", stream=io.StringIO())
    assert sorted(p.name for p in (tmp_path / "s" / ".parts").iterdir()) == [
        "batch_00000.npy", "batch_00001.npy", "spec.json"
    ]  # fmt: skip
    assert not (tmp_path / "s" / META_FILE).exists()
    with pytest.raises(InputError, match=r"--out: .* interrupted build with other settings"):
        build_site(BuildSpec(**{**spec.__dict__, "batch": 3}), tmp_path / "s")
    fake.fail_after = None
    site = build_site(spec, tmp_path / "s", stream=io.StringIO())
    # 18 grid points; the 4 at z = 10 m over the block (x, y ∈ {20, 40}) are not traced.
    assert fake.traced == 14 and site.meta["build"]["traced"] == 14
    assert not (tmp_path / "s" / ".parts").exists()
    assert load_site(tmp_path / "s").meta["scene"]["licence"] == "CC0"
    loss = dequantise_loss_db(site.loss_code)
    walk = site.walkable
    assert np.isinf(loss[0, 1:, 1:]).all() and np.isfinite(loss[0, 0][:, walk]).all()
    assert np.allclose(loss[1][..., walk], 90.0) and np.allclose(loss[0, 0][:, walk], 70.0)
    assert site.walkable.sum() == 48 and site.building_height_m.max() == 20.0
    # Losses are kept on walkable ground only: inside the block, no path from anywhere.
    assert np.isinf(loss[..., ~walk]).all()
    assert site.meta["build"]["command"] == (
        f"tupa site build --scene fake --size-m 40 --cell-m 5 --grid-xy-m 20 --grid-z-m 10,30 "
        f"--samples 2000000 --max-depth 3 --batch 4 --out {tmp_path / 's'}"
    )
