"""The ns-3 backend on a site (issue 38): ``site:NAME`` / ``site:PATH`` accepted, a bad one
refused in one line naming ``environment``, ns-3 given exactly the fast model's expected-mode
per-user loss on the site (a finite stand-in, ``NO_PATH_LOSS_DB``, where the site has no path)
and one case of the site's calibration set simulated.

The ns-3 case uses the run's one worker (``ns3_runner`` in tests/conftest.py: skipped when ns-3
is not installed) and is marked ``slow``, as the urban cases of test_ns3_backend.py are; the
rest needs no ns-3.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.calibration.build import cases_path
from sim.channel import NO_LINK_LOSS_DB
from sim.config import AreaConfig, NetworkConfig
from sim.errors import InputError
from sim.evaluate import evaluate_case
from sim.files import load_cases
from sim.network import NetworkModel
from sim.ns3_backend import (
    NO_PATH_LOSS_DB,
    FleetCase,
    Ns3Runner,
    Ns3Settings,
    _request,
    fleet_link_losses_db,
    link_losses_db,
)
from sim.scenarios import Case

MUNICH = "site:munich"
SHORT = {"warmup_s": 0.2, "measure_s": 0.5}


@pytest.fixture(scope="module")
def site_cases() -> list[Case]:
    area, cases = load_cases(cases_path(MUNICH))
    assert area.environment == MUNICH
    return cases


def test_settings_take_a_shipped_site_and_a_site_directory() -> None:
    assert Ns3Settings(environment=MUNICH).environment == MUNICH
    shipped = Path(__file__).resolve().parents[2] / "sim" / "sites" / "data" / "munich"
    by_path = Ns3Settings(environment=f"site:{shipped}")
    assert by_path.to_dict()["environment"] == f"site:{shipped}"


@pytest.mark.parametrize(
    ("environment", "message"),
    [
        ("site:paris", r"^environment: 'site:paris': no shipped site 'paris'"),
        ("site:/nowhere/at/all", r"^environment: 'site:/nowhere/at/all': no site there"),
        ("site:", r"^environment: 'site:' needs the site directory's path"),
        ("moon", r"^environment: must be one of open, .*site:NAME or site:PATH"),
    ],
)
def test_a_bad_site_is_refused_in_one_line_naming_environment(
    environment: str, message: str
) -> None:
    with pytest.raises(InputError, match=message) as info:
        Ns3Settings(environment=environment)
    assert "\n" not in str(info.value)


def test_a_broken_site_directory_is_refused_naming_environment(tmp_path: Path) -> None:
    (tmp_path / "site.json").write_text("{}")
    (tmp_path / "site.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=rf"^environment: 'site:{tmp_path}': ") as info:
        Ns3Settings(environment=f"site:{tmp_path}")
    assert "\n" not in str(info.value)


def test_link_losses_are_the_fast_models_expected_loss_on_the_site(
    site_cases: list[Case],
) -> None:
    """Every case of the site's calibration set: ns-3's per-user loss is the loss the fast
    model's expected-mode step uses (read back from its SNR), the stand-in where no path."""
    settings = Ns3Settings(environment=MUNICH)
    config = NetworkConfig()
    model = NetworkModel(config, AreaConfig(environment=MUNICH))
    radio = config.radio
    no_path = 0
    for case in site_cases:
        to_uav, between = link_losses_db(case, settings)
        step = model.step(case.uav_xyz_m, case.users_xy_m, case.load_bps)
        model_loss_db = radio.tx_power_dbm - radio.noise_dbm - step.snr_db[0]
        np.testing.assert_allclose(to_uav, model_loss_db, atol=1e-9, err_msg=case.id)
        assert np.all(np.isfinite(to_uav)) and np.all(to_uav <= NO_PATH_LOSS_DB)
        assert between.shape == (case.n_users, case.n_users)
        no_path += int(np.sum(to_uav == NO_PATH_LOSS_DB))
        # A user with no path is out of coverage in the fast model: not connected.
        assert not np.any(step.connected[0][to_uav == NO_PATH_LOSS_DB])
    assert NO_PATH_LOSS_DB == NO_LINK_LOSS_DB
    assert no_path > 0  # the set has users the site gives no path: the stand-in is exercised


def test_the_request_carries_the_site_losses_as_json_numbers(site_cases: list[Case]) -> None:
    case = next(c for c in site_cases if c.id == "sgrp0-c1")
    request = _request(case, Ns3Settings(environment=MUNICH), index=0)
    assert (
        request["ap_loss_db"] == link_losses_db(case, Ns3Settings(environment=MUNICH))[0].tolist()
    )
    assert NO_PATH_LOSS_DB in request["ap_loss_db"]
    assert all(np.isfinite(request["ap_loss_db"]))


def test_fleet_losses_on_a_site_are_each_aps_single_losses(site_cases: list[Case]) -> None:
    a, b = (next(c for c in site_cases if c.id == i) for i in ("sgrp1-c2", "sgrp1-c4"))
    fleet = FleetCase(
        "two", np.stack([a.uav_xyz_m, b.uav_xyz_m]), a.users_xy_m, a.load_bps, [0, 1] * 4
    )
    settings = Ns3Settings(environment=MUNICH)
    to_uavs, ap_ap, between = fleet_link_losses_db(fleet, settings)
    np.testing.assert_array_equal(to_uavs[0], link_losses_db(a, settings)[0])
    np.testing.assert_array_equal(to_uavs[1], link_losses_db(b, settings)[0])
    assert ap_ap.shape == (2, 2) and between.shape == (8, 8)


def mean_ap_rx_dbm(result) -> np.ndarray:
    d = result.detail
    return d["ap_rx_dbm_sum"] / np.maximum(d["ap_rx_mpdus"], 1)


@pytest.mark.slow
def test_a_site_case_runs_in_ns3_with_the_sites_losses(
    ns3_runner: Ns3Runner, site_cases: list[Case]
) -> None:
    """sgrp0-c1: two users in range, one with no path on the site. ns-3 receives the two at
    20 dBm minus the site's loss (within 1 dB: Nakagami's mean in dB), the third never
    associates and loses what it sends, as in the fast model; the served users' throughput
    agrees with the fast model's expected mode on the site within 15 %."""
    case = next(c for c in site_cases if c.id == "sgrp0-c1")
    settings = Ns3Settings(queueing="fq-codel", environment=MUNICH, **SHORT)
    loss_db = link_losses_db(case, settings)[0]
    blocked = loss_db == NO_PATH_LOSS_DB
    assert blocked.sum() == 1 and np.all(20.0 - loss_db[~blocked] > -90.0)
    result = ns3_runner.run(case, settings, index=1)
    np.testing.assert_allclose(mean_ap_rx_dbm(result)[~blocked], 20.0 - loss_db[~blocked], atol=1.0)
    assert result.detail["ap_rx_mpdus"][blocked] == 0
    assert result.association_s[blocked] == -1.0
    m = result.metrics
    assert m.throughput_bps[blocked] == 0.0
    assert m.plr[blocked] == pytest.approx(1.0, abs=0.01)
    model = NetworkModel(NetworkConfig().with_queueing("fq-codel"), AreaConfig(environment=MUNICH))
    reference = evaluate_case(model, case, None, SHORT["warmup_s"], SHORT["measure_s"])
    assert reference.throughput_bps[blocked] == 0.0
    np.testing.assert_allclose(
        m.throughput_bps[~blocked], reference.throughput_bps[~blocked], rtol=0.15
    )
