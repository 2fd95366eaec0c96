"""The fit of the fast model's free constants (sim/calibration/fit.py) and its committed result.

No ns-3 needed: the fit reads the committed ns-3 results of the calibration set.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import pytest

from sim.calibration import fit
from sim.config import NetworkConfig


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
