"""The fit of the fast model's free constants (sim/calibration/fit.py) and its committed result,
and the committed calibration case files (sim/calibration/build.py), open and urban.

No ns-3 needed: the fit reads the committed ns-3 results of the calibration set.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from sim.calibration import build, fit
from sim.config import NetworkConfig
from sim.files import load_cases


@pytest.fixture(scope="module")
def calib() -> fit.Calibration:
    return fit.load_calibration()


def test_hand_set_values_give_the_hand_set_configuration():
    assert fit.make_config(fit.HAND_SET_VALUES) == fit.HAND_SET
    assert fit.make_config({}) == fit.HAND_SET


def test_the_model_defaults_are_the_committed_fit():
    """Refitting without copying the result into sim/config.py fails here."""
    assert fit.fitted_config() == NetworkConfig()
    assert NetworkConfig() != fit.HAND_SET


def test_make_config_moves_only_the_free_constants():
    config = fit.make_config(
        {"per_offset_db": -0.5, "threshold_offset_db": 1.0, "contention_cw_min": 31}
    )
    base = fit.HAND_SET
    assert config.phy.per_mid_snr_db == tuple(x - 0.5 for x in base.phy.per_mid_snr_db)
    assert config.phy.ideal_threshold_db == tuple(x + 1.0 for x in base.phy.ideal_threshold_db)
    assert config.mac.contention_cw_min == 31 and config.mac.cw_min == base.mac.cw_min
    assert replace(config, phy=base.phy, mac=base.mac) == base


def test_constants_under_which_a_slower_mcs_carries_more_are_rejected():
    assert fit.falls_monotonically(NetworkConfig())
    # Switching MCS 1 dB early at a shallow waterfall: the faster MCS loses more than it gains.
    bad = {"threshold_offset_db": -1.0, "per_offset_db": -0.5, "per_slope_per_db": 0.875}
    assert not fit.falls_monotonically(fit.make_config(bad))


def test_fit_and_held_out_parts_are_disjoint_and_cover_the_set(calib):
    fit_ids, held = set(calib.ids("fit")), set(calib.ids("held_out"))
    assert not fit_ids & held
    assert fit_ids | held == set(calib.cases)
    assert len(held) == 37 and len(fit_ids) == 77


def test_committed_fit_is_within_bounds_and_reproduces_its_figures(calib):
    doc = fit.load_fitted()
    assert set(doc["fitted"]) == {c.name for c in fit.FREE}
    for c in fit.FREE:
        assert c.lo <= doc["fitted"][c.name] <= c.hi
    config = fit.fitted_config()
    assert fit.falls_monotonically(config)
    for part in ("fit", "held_out"):
        for name, cfg in (("fitted", config), ("hand_set", fit.HAND_SET)):
            got = fit.figures(calib, cfg, part)
            for variant, committed in doc["errors"][part][name].items():
                assert got[variant] == pytest.approx(committed, abs=2e-4), (part, name)
    assert doc["objective"]["fitted"] < doc["objective"]["hand_set"]


def test_fit_never_reads_the_held_out_results(calib, tmp_path):
    """Scrambling the held-out ns-3 results changes nothing in what the fit finds."""
    tampered = copy.deepcopy(calib.ns3)
    for variant in fit.VARIANTS:
        for case_id in calib.held_out:
            for user in tampered[variant][case_id]["users"]:
                user["throughput_bps"] *= 7.0
    scrambled = replace(calib, ns3=tampered)
    quiet = lambda *a, **k: None  # noqa: E731
    a = fit.run_fit(tmp_path / "a.json", rounds=1, log=quiet, calib=calib)
    b = fit.run_fit(tmp_path / "b.json", rounds=1, log=quiet, calib=scrambled)
    assert a["fitted"] == b["fitted"]
    assert a["objective"] == b["objective"]
    assert a["errors"]["fit"] == b["errors"]["fit"]
    assert a["errors"]["held_out"] != b["errors"]["held_out"]


def test_rescoring_keeps_the_committed_values_and_reproduces_its_figures(calib, tmp_path):
    """``--start fitted --rounds 0``: the constants stay, the figures are recomputed, and the
    search that found them is kept beside the (empty) new one."""
    path = tmp_path / "fitted.json"
    path.write_bytes(fit.FITTED_PATH.read_bytes())
    committed = fit.load_fitted()
    doc = fit.run_fit(path, rounds=0, log=lambda *a: None, calib=calib, start="fitted")
    assert doc["fitted"] == committed["fitted"]
    assert doc["start"] == {"from": "fitted", "values": committed["fitted"], "rounds": 0}
    assert doc["errors"] == committed["errors"]
    assert len(doc["history"]) == 1 and doc["earlier_history"] == committed["earlier_history"]
    assert len(doc["earlier_history"]) > 1  # the search that found the constants
    assert fit.load_fitted(path)["config_fields"] == committed["config_fields"]


def test_fit_refuses_a_bad_start_or_round_count(tmp_path, capsys):
    with pytest.raises(ValueError, match="start"):
        fit.run_fit(tmp_path / "x.json", start="best")
    with pytest.raises(SystemExit) as exit_info:
        fit.main(["--out", str(tmp_path / "x.json"), "--rounds", "-1"])
    assert exit_info.value.code == 2
    assert "--rounds: must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def assert_same_cases(committed: list, generated: list) -> None:
    """The same cases, floats to 1e-9 relative: numpy's SIMD power and exponential differ in
    the last bits between CPUs (AVX-512 or not), and the files were written on one of them."""
    assert [c.id for c in committed] == [c.id for c in generated]
    for a, b in zip(committed, generated, strict=True):
        for name in ("uav_xyz_m", "users_xy_m", "load_bps"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, err_msg=a.id)


@pytest.mark.parametrize("environment", build.URBAN_ENVIRONMENTS)
def test_urban_case_files_are_the_generated_sets(environment):
    """``python -m sim.calibration.build cases`` rewrites these files; a hand edit fails here."""
    area, committed = load_cases(build.cases_path(environment))
    assert area.environment == environment
    cases, meta = build.make_urban_cases(environment)
    assert_same_cases(committed, cases)
    assert build.load_meta(build.cases_path(environment))["held_out"] == meta["held_out"]
    ids = {c.id for c in cases}
    held = set(meta["held_out"])
    assert held < ids and len(held) == 28
    by_id = {c.id: c for c in cases}
    for group in meta["groups"].values():
        # The candidates of a group differ in altitude, not only in ground position.
        assert len({by_id[i].uav_xyz_m[2] for i in group}) >= 3
        assert {i in held for i in group} in ({True}, {False})  # a group is held out whole


def test_urban_sets_are_scaled_to_their_coverage_radius():
    radii = [build.coverage_radius_m(e) for e in build.URBAN_ENVIRONMENTS]
    assert radii == sorted(radii, reverse=True)  # suburban reaches farthest, highrise least
    assert build.coverage_radius_m("open") > 500.0
    for environment, radius in zip(build.URBAN_ENVIRONMENTS, radii, strict=True):
        cases, _ = build.make_urban_cases(environment)
        singles = [c for c in cases if c.id.startswith("usingle")]
        farthest = max(float(np.hypot(*(c.users_xy_m[0] - c.uav_xyz_m[:2]))) for c in singles)
        assert farthest == pytest.approx(radius, abs=1.0)


def test_the_fit_reads_only_the_open_set(calib):
    assert not any(case_id.startswith("u") for case_id in calib.cases)


def test_few_station_case_file_is_the_generated_set(calib):
    """``python -m sim.calibration.build few-stations-cases`` rewrites this file (issue 19); a
    hand edit fails here. It is held out whole, in issue 19's regime, and no fit reads it."""
    area, committed = load_cases(build.FEW_STATIONS_PATH)
    assert area.environment == "open"
    cases, meta = build.make_few_station_cases()
    assert_same_cases(committed, cases)
    stored = build.load_meta(build.FEW_STATIONS_PATH)
    assert stored["held_out"] == meta["held_out"] == [c.id for c in cases]
    assert stored["groups"] == meta["groups"] and stored["family"] == meta["family"]
    for case in cases:
        ground_m = np.hypot(*(case.users_xy_m - case.uav_xyz_m[:2]).T)
        heavy = case.load_bps >= 15e6
        assert 1 <= case.n_users <= 4 and 1 <= heavy.sum() <= 2
        assert np.all(case.load_bps[~heavy] <= 3e6)
        if meta["family"][case.id] == "few":
            assert np.all((ground_m[heavy] >= 250.0) & (ground_m[heavy] <= 500.0))
            assert np.all(ground_m[~heavy] <= 100.0)
        elif meta["family"][case.id] == "fmid":
            assert np.all(ground_m[~heavy] <= 400.0)
    assert {meta["family"][c.id] for c in cases} == {"few", "fgroup", "fmid"}
    assert not set(meta["held_out"]) & set(calib.cases)
