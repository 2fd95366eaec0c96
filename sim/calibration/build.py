"""Build the ns-3 calibration set and run it through ns-3.

Two steps, both deterministic::

    python -m sim.calibration.build cases          # -> sim/calibration/cases.json
    nice -n 19 python -m sim.calibration.build run # -> sim/calibration/ns3_*.json (ns-3 needed)

``cases`` writes a ``tupa-cases/1`` file of 114 cases in five families, with extra top-level
keys (ignored by ``load_cases``) that say what each case is for:

* ``single-*`` (16): one user, the UAV in the area's corner, 50–700 m horizontal distance,
  altitudes 25–100 m, 5–40 Mbit/s: the rate ladder and the saturated single link.
* ``p3-*`` (24): the paper's setting, 3 users from :func:`sim.scenarios.generate_scenarios`
  (Λ = 40 Mbit/s), each at three UAV positions (users' centroid, load-weighted centroid,
  a random grid point).
* ``many-*`` (30): 5, 8, 12, 16 and 20 users with Λ = 10, 20 and 40 Mbit/s (unsaturated to
  saturated), at the centroid and at a random grid point: contention and collisions.
* ``light-*`` (8): one light user (0.5–2 Mbit/s) beside backlogged ones, near and far: the case
  where ns-3 loses a light user's packets while its delay stays low.
* ``grp*-c*`` (6 groups × 6 candidates = 36): one scenario (3–20 users) at six candidate UAV
  positions each, for placement agreement (does the fast model pick the position ns-3 rates
  best?).

**Urban cases**: ``cases`` also writes one file per urban environment,
``cases_<environment>.json`` (its top-level ``environment`` set: ``suburban``, ``urban``,
``dense-urban``, ``highrise-urban``), 58 cases each (:func:`make_urban_cases`). The geometry
is scaled to each environment's coverage radius R (:func:`coverage_radius_m`: the farthest
ground distance at which a UAV at 100 m delivers a mean −85 dBm; suburban 466 m, urban 211 m,
dense urban 140 m, highrise urban 30 m at 5.18 GHz): with one geometry for all, the highrise
cases would have nobody connected and agree trivially (0 = 0). Same seeds in every
environment, so the files differ by that scale and their ``environment`` field:

* ``usingle-*`` (6): one user 0.3 R, 0.7 R or R from the UAV's ground point, at 25 and 100 m
  altitude, 40 Mbit/s (saturated: the rate ladder on the urban mean loss);
* ``ugrp*-c*`` (8 groups × 6 candidates = 48): a scenario of 3 or 8 users spread over up to R
  (``GeneratorConfig.position_scale_max_m`` = R), Λ = 10 to 40 Mbit/s, at six UAV positions:
  the users' centroid at 25, 50 and 100 m, the load-weighted centroid at 75 m, above the
  heaviest user at 50 m and a random grid point. Altitude is a real trade-off there (climbing
  raises P_LoS but lengthens the path), so the placement agreement ranks altitudes, not only
  ground positions;
* ``ucrowd-*`` (4): 12 or 20 users around one corner (exponential scale up to R/2, nearly all
  in range), Λ = 40 Mbit/s, the UAV over their centroid at 50 and 100 m: contention and
  saturation on the urban channel, which the groups (up to 8 users, many out of range) rarely
  reach.

Held out: ``usingle`` cases 3 and 6 (every 3rd), the odd groups (``ugrp1``, ``ugrp3``,
``ugrp5``, ``ugrp7``) and the 100 m ``ucrowd`` cases. Groups 4–7 and the ``ucrowd`` family were
appended after a first run of groups 0–3 (same rules; appended so that the first cases keep
their run numbers): two held-out groups per environment were too few to judge placement
agreement, and those first cases had few congested users in range.
The MAC constants are not refitted on them (``fit.py`` reads ``cases.json`` only); the
fidelity benchmark reports their errors per environment. ns-3 gets the fast model's per-user
mean path loss (:mod:`sim.ns3_backend`), so these cases check the MAC on the urban channel.

**Site cases**: ``site-cases`` writes ``cases_site_munich.json`` (its top-level
``environment`` ``site:munich``, the shipped ray-traced district; :func:`make_site_cases`), 52
cases, every user on the site's walkable ground (the scenario generator's rule on a site) and
every UAV at least :data:`SITE_ROOF_CLEARANCE_M` above the roof under it:

* ``ssingle-*`` (12): one user about 60, 150 or 300 m (``t60`` ...) from the UAV's ground
  point (the walkable cell farthest from any building, at least 100 m inside the area), on a
  walkable cell in line of sight of the UAV at 100 m and on one *behind a building* (out of
  sight even from 100 m: a reflected or transmitted ray-traced path), with a path at both
  altitudes where the site has such a cell, at 25 and 100 m altitude, 40 Mbit/s (saturated:
  the rate ladder on the site's loss);
* ``sgrp*-c*`` (6 groups × 6 candidates = 36): a scenario of 3 or 8 users from the site
  families ``streets``, ``squares`` and the paper's ``exponential`` on walkable ground,
  Λ = 10 to 40 Mbit/s, at the six candidate positions of the urban groups (the users' centroid
  at 25, 50 and 100 m, the load-weighted centroid at 75 m, above the heaviest user at 50 m, a
  random grid point; each lifted above its roof where it would be inside a building);
* ``scrowd-*`` (4): 12 or 20 users of the ``crowd`` family (most at one place), 40 Mbit/s, the
  UAV over their centroid at 50 and 100 m: contention on the site's channel.

Held out: ``ssingle`` cases 3, 6, 9 and 12 (every 3rd), the odd groups (``sgrp1``, ``sgrp3``,
``sgrp5``) and the 100 m ``scrowd`` cases. Nothing is fitted on this set (``fit.py`` reads
``cases.json`` only); the fidelity benchmark reports its held-out figures (``per_site``).
``run --environments site:munich`` simulates it (``ns3_site_munich_<queueing>.json``): ns-3 is
given the site's per-user loss (:mod:`sim.ns3_backend`). Seeds 3800–3806, 3812 and 3820 are
this set's own.

**Few-station cases**: ``few-stations-cases`` writes ``cases_few_stations.json``
(:func:`make_few_station_cases`: 1–4 stations, heavy users 250–500 m from the UAV, light ones
near or, ``fmid``, 150–400 m away; 152 cases, all held out, never fitted) and
``run-few-stations`` simulates it (both variants, seeds 0 and 1, every ns-3 counter kept;
``ns3_few_stations_<queueing>.json``).

``held_out`` lists the cases kept out of any fit: every 4th case of the first four families and
every case of the odd groups (grp1, grp3, grp5). ``long_runs`` lists six cases also simulated
for 10 s (1 s intervals), to show how FqCoDel delays grow.

``run`` (``--environments``, default all five: ``open`` is ``cases.json``) simulates every case
with both queueing variants and ``--seeds`` seeds (ns-3 varies by ±10 % from seed to seed on
overloaded cases), seed-major so an interrupted run still has every case once, then the long
runs (``open`` only). Results are rewritten atomically after every case and a rerun skips what
is already there: a crash loses one case at most. Output per variant, ``ns3_<queueing>.json``:
the ``tupa sim evaluate`` format (``tupa-case-results/1``) whose ``users`` are the means over
seeds (throughput, delay, loss) and ``utility`` the mean of the per-seed utilities, with
``backend``, ``ns3_version``, the ns-3 settings, ``per_seed`` results and a few ns-3 counters
per user (drops by cause, PPDUs, MCS, backoffs; see :data:`sim.ns3_worker.FIELDS`).
``ns3_long_<queueing>.json`` holds the 10 s runs; the urban results are
``ns3_<environment>_<queueing>.json``, the site's ``ns3_site_<name>_<queueing>.json``
(``site:NAME`` → ``site_NAME``: no ``:`` in file names).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_json
from sim.channel import area_site, mean_path_loss_db
from sim.config import ENVIRONMENTS, AreaConfig, RadioConfig, site_path
from sim.files import cases_document, load_cases
from sim.scenarios import Case, GeneratorConfig, Scenario, generate_scenarios, site_ground

HERE = Path(__file__).resolve().parent
CASES_PATH = HERE / "cases.json"
AREA = AreaConfig()
MBPS = 1e6
URBAN_ENVIRONMENTS: tuple[str, ...] = tuple(e for e in ENVIRONMENTS if e != "open")
SITE_ENVIRONMENTS: tuple[str, ...] = ("site:munich",)
"""The sites with a calibration set (:func:`make_site_cases`): the shipped district only."""
SITE_ROOF_CLEARANCE_M = 5.0
"""How far above the roof under it a site case's UAV flies at least (module doc)."""
# Town-sized scenarios: users within a few hundred metres of each other.
COVERAGE_RSSI_DBM = -85.0

# ns-3 counters kept per user in the committed results (window differences or end levels).
KEPT_DETAIL = (
    "tx_pkts",
    "rx_pkts",
    "drop_qdisc",
    "drop_mac_expired",
    "drop_mac_retry_limit",
    "drop_mac_old_packet",
    "drop_tc",
    "drop_mac_tx",
    "drop_arp",
    "data_ppdus",
    "data_mpdus",
    "mcs_mpdu_sum",
    "response_timeouts",
    "ap_rx_ppdu_drops",
    "backoff_draws",
    "backoff_slots_sum",
    "backoff_long_draws",
    "expired_unsent",
    "max_tx_gap_s",
    "backlog_qdisc_pkts",
    "backlog_mac_pkts",
)


# --------------------------------------------------------------------------------------------
# Cases


def _grid_point(rng: np.random.Generator) -> np.ndarray:
    """A random zone centre at a random altitude level."""
    return AREA.grid_positions_m()[rng.integers(len(AREA.grid_positions_m()))]


def _centroid(xy_m: np.ndarray, weights: np.ndarray | None, z_m: float) -> np.ndarray:
    w = np.ones(len(xy_m)) if weights is None else weights
    centre = (xy_m * w[:, None]).sum(axis=0) / w.sum()
    return np.array([centre[0], centre[1], z_m])


def _group_candidates(scenario: Scenario, rng: np.random.Generator) -> list[np.ndarray]:
    """A placement-agreement group's six UAV positions: the users' centroid at 25, 50 and
    100 m, the load-weighted centroid at 75 m, above the heaviest user at 50 m and a random
    grid point (one draw of ``rng``)."""
    users, loads = scenario.users_xy_m, scenario.load_bps
    heavy = users[int(np.argmax(loads))]
    return [
        _centroid(users, None, 25.0),
        _centroid(users, None, 50.0),
        _centroid(users, None, 100.0),
        _centroid(users, loads, 75.0),
        np.array([heavy[0], heavy[1], 50.0]),
        _grid_point(rng),
    ]


def make_cases() -> tuple[list[Case], dict[str, Any]]:
    """The calibration cases and the metadata (families, held-out split, groups, long runs)."""
    rng = np.random.default_rng(20250301)
    cases: list[Case] = []
    family: dict[str, str] = {}

    def add(case: Case, kind: str) -> None:
        cases.append(case)
        family[case.id] = kind

    # single: (horizontal distance m, altitude m, load Mbit/s), UAV in the south-west corner.
    singles = [
        (50, 25, 40), (200, 25, 40), (300, 25, 40), (450, 25, 40), (550, 25, 40), (650, 25, 40),
        (700, 25, 40), (200, 100, 40), (450, 100, 40), (650, 100, 40), (300, 50, 40),
        (450, 75, 40), (450, 25, 10), (650, 25, 10), (650, 75, 20), (100, 50, 5),
    ]  # fmt: skip
    for d_m, z_m, load in singles:
        xy = np.array([[d_m / math.sqrt(2.0), d_m / math.sqrt(2.0)]])
        add(Case(f"single-d{d_m}-z{z_m}-L{load}", [0.0, 0.0, z_m], xy, [load * MBPS]), "single")

    # p3: the paper's 3-user scenarios.
    for s in generate_scenarios(8, 3, seed=31, area=AREA):
        positions = {
            "centroid": _centroid(s.users_xy_m, None, 25.0),
            "loadw": _centroid(s.users_xy_m, s.load_bps, 50.0),
            "random": _grid_point(rng),
        }
        for name, uav in positions.items():
            add(Case(f"p3-{s.id}-{name}", uav, s.users_xy_m, s.load_bps), "p3")

    # many: contention with 5-20 users, unsaturated to saturated.
    for n_users in (5, 8, 12, 16, 20):
        for total_mbps in (10, 20, 40):
            (s,) = generate_scenarios(
                1, n_users, seed=1000 + 10 * n_users + total_mbps, total_load_bps=total_mbps * MBPS
            )
            base = f"many-u{n_users}-L{total_mbps}"
            add(Case(f"{base}-centroid", _centroid(s.users_xy_m, None, 25.0), s.users_xy_m,
                     s.load_bps), "many")  # fmt: skip
            add(Case(f"{base}-random", _grid_point(rng), s.users_xy_m, s.load_bps), "many")

    # light: one light user beside backlogged ones.
    centre = [250.0, 250.0, 25.0]
    lights = {
        "light-far-2far": ([[0, 0], [500, 500], [0, 500]], [2, 19, 19]),
        "light-far-2near": ([[0, 0], [250, 260], [260, 250]], [2, 19, 19]),
        "light-mid-2far": ([[250, 100], [500, 500], [0, 500]], [2, 19, 19]),
        "light-near-2far": ([[255, 250], [480, 480], [20, 480]], [1, 19.5, 19.5]),
        "light-far-4mid": ([[10, 10], [400, 250], [100, 250], [250, 400], [250, 100]],
                           [0.5, 9.875, 9.875, 9.875, 9.875]),
        "light-near-4far": ([[240, 240], [480, 250], [20, 250], [250, 480], [250, 20]],
                            [1, 9.75, 9.75, 9.75, 9.75]),
        "light-two-3far": ([[200, 200], [300, 300], [490, 10], [10, 490], [490, 490]],
                           [1, 1, 12.67, 12.67, 12.66]),
        "light-far-unsat": ([[0, 0], [500, 500], [0, 500]], [2, 9, 9]),
    }  # fmt: skip
    for name, (xy, loads) in lights.items():
        add(Case(name, centre, np.array(xy, float), np.array(loads) * MBPS), "light")

    # groups: one scenario, six candidate UAV positions.
    groups: dict[str, list[str]] = {}
    for g, (n_users, total_mbps) in enumerate([(3, 40), (3, 40), (3, 20), (6, 40), (10, 40),
                                               (20, 40)]):  # fmt: skip
        (s,) = generate_scenarios(1, n_users, seed=2000 + g, total_load_bps=total_mbps * MBPS)
        heavy = s.users_xy_m[int(np.argmax(s.load_bps))]
        candidates = [
            _centroid(s.users_xy_m, None, 25.0),
            _centroid(s.users_xy_m, s.load_bps, 25.0),
            np.array([heavy[0], heavy[1], 25.0]),
            np.array([250.0, 250.0, 25.0]),
            np.array([250.0, 250.0, 100.0]),
            _grid_point(rng),
        ]
        ids = []
        for c, uav in enumerate(candidates):
            case_id = f"grp{g}-c{c}"
            add(Case(case_id, uav, s.users_xy_m, s.load_bps), "group")
            ids.append(case_id)
        groups[f"grp{g}"] = ids

    individual = [c.id for c in cases if family[c.id] != "group"]
    held_out = [case_id for i, case_id in enumerate(individual) if i % 4 == 3]
    held_out += [case_id for g, ids in groups.items() if int(g[3:]) % 2 == 1 for case_id in ids]
    meta = {
        "description": "ns-3 calibration set; see sim/calibration/build.py",
        "family": family,
        "held_out": held_out,
        "groups": groups,
        "long_runs": [
            "single-d450-z25-L40",
            "p3-s0002-centroid",
            "many-u12-L40-centroid",
            "many-u20-L40-centroid",
            "light-far-2far",
            "many-u8-L20-centroid",
        ],
    }
    return cases, meta


def file_label(environment: str) -> str:
    """An environment as a file-name part: ``site:munich`` → ``site_munich`` (no ``:``)."""
    name = site_path(environment)
    return environment if name is None else f"site_{name}"


def cases_path(environment: str = "open") -> Path:
    """The calibration case file of an environment (``open``: the original ``cases.json``)."""
    if environment == "open":
        return CASES_PATH
    return HERE / f"cases_{file_label(environment)}.json"


def results_path(environment: str, queueing: str) -> Path:
    """The committed ns-3 results of an environment and queueing variant."""
    if environment == "open":
        return HERE / f"ns3_{queueing}.json"
    return HERE / f"ns3_{file_label(environment)}_{queueing}.json"


def coverage_radius_m(environment: str, area: AreaConfig = AREA) -> float:
    """The farthest ground distance (1 m steps, at most the area's diagonal) at which a UAV at
    the top of the altitude band delivers a mean received power of at least
    :data:`COVERAGE_RSSI_DBM` (the fast model's mean path loss, 20 dBm transmitted)."""
    radio = RadioConfig()
    ground_m = np.arange(0.0, area.diagonal_m, 1.0)
    height_m = area.z_max_m - area.user_height_m
    rssi_dbm = radio.tx_power_dbm - mean_path_loss_db(
        environment, ground_m, height_m, radio.frequency_hz
    )
    covered = ground_m[rssi_dbm >= COVERAGE_RSSI_DBM]
    return float(covered.max()) if covered.size else 0.0


def make_urban_cases(environment: str) -> tuple[list[Case], dict[str, Any]]:
    """The urban calibration cases of ``environment`` and their metadata (module doc).

    Fixed seeds: the geometry differs between environments only by the coverage radius it is
    scaled to (module doc).
    """
    if environment not in URBAN_ENVIRONMENTS:
        raise ValueError(f"environment: must be one of {', '.join(URBAN_ENVIRONMENTS)}")
    radius_m = coverage_radius_m(environment)
    generator = GeneratorConfig(
        position_scale_min_m=min(10.0, radius_m / 3.0), position_scale_max_m=radius_m
    )
    rng = np.random.default_rng(20261115)
    cases: list[Case] = []
    family: dict[str, str] = {}
    for fraction in (0.3, 0.7, 1.0):
        d_m = round(fraction * radius_m)
        for z_m in (25, 100):
            xy = np.array([[d_m / math.sqrt(2.0), d_m / math.sqrt(2.0)]])
            case = Case(f"usingle-d{d_m}-z{z_m}-L40", [0.0, 0.0, z_m], xy, [40 * MBPS])
            cases.append(case)
            family[case.id] = "usingle"
    groups: dict[str, list[str]] = {}
    shapes = [(3, 40), (3, 20), (8, 40), (8, 20), (3, 30), (8, 30), (3, 10), (8, 10)]
    for g, (n_users, total_mbps) in enumerate(shapes):
        (s,) = generate_scenarios(
            1,
            n_users,
            seed=3000 + g,
            total_load_bps=total_mbps * MBPS,
            config=generator,
        )
        ids = []
        for c, uav in enumerate(_group_candidates(s, rng)):
            case = Case(f"ugrp{g}-c{c}", uav, s.users_xy_m, s.load_bps)
            cases.append(case)
            family[case.id] = "ugroup"
            ids.append(case.id)
        groups[f"ugrp{g}"] = ids
    # Contention: 12 and 20 users near one corner, exponential scale up to R/2 (nearly all in
    # range of their centroid), 40 Mbit/s in all.
    crowd = replace(generator, position_scale_max_m=radius_m / 2.0, scatter_probability=0.0)
    for n_users in (12, 20):
        (s,) = generate_scenarios(
            1, n_users, seed=3100 + n_users, total_load_bps=40 * MBPS, config=crowd
        )
        for z_m in (50.0, 100.0):
            case = Case(
                f"ucrowd-u{n_users}-z{z_m:.0f}",
                _centroid(s.users_xy_m, None, z_m),
                s.users_xy_m,
                s.load_bps,
            )
            cases.append(case)
            family[case.id] = "ucrowd"
    singles = [c.id for c in cases if family[c.id] == "usingle"]
    held_out = [case_id for i, case_id in enumerate(singles) if i % 3 == 2]
    crowds = [c.id for c in cases if family[c.id] == "ucrowd"]
    held_out += [case_id for i, case_id in enumerate(crowds) if i % 2 == 1]
    held_out += [case_id for g, ids in groups.items() if int(g[4:]) % 2 == 1 for case_id in ids]
    meta = {
        "description": f"ns-3 calibration set, {environment}; see sim/calibration/build.py",
        "coverage_radius_m": radius_m,
        "family": family,
        "held_out": held_out,
        "groups": groups,
        "long_runs": [],
    }
    return cases, meta


def _above_roof(site: Any, xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """``xyz_m`` lifted to :data:`SITE_ROOF_CLEARANCE_M` above the roof of its ground cell
    when it is lower (at most the area's ceiling), kept inside the area."""
    x = float(np.clip(xyz_m[0], 0.0, area.size_x_m))
    y = float(np.clip(xyz_m[1], 0.0, area.size_y_m))
    column = min(int(x // site.cell_m), site.cells_x - 1)
    row = min(int(y // site.cell_m), site.cells_y - 1)
    roof_m = float(site.building_height_m[row, column])
    z = min(max(float(xyz_m[2]), roof_m + SITE_ROOF_CLEARANCE_M), area.z_max_m)
    return np.array([x, y, z])


def make_site_cases(environment: str = "site:munich") -> tuple[list[Case], dict[str, Any]]:
    """The calibration cases of a site and their metadata (module doc). Fixed seeds
    (3800–3806, 3812, 3820: used nowhere else); the users stand on the site's walkable ground."""
    from sim.scenarios import FamilyConfig
    from sim.sites.lookup import path_loss_db
    from sim.sites.los import line_of_sight

    area = AreaConfig(environment=environment)
    site = area_site(area)
    if site is None:
        raise ValueError(f"environment: must be a site (site:NAME or site:PATH), got {environment}")
    ground = site_ground(site, area, FamilyConfig())
    cell_m = float(site.cell_m)
    rows, columns = np.nonzero(ground.walkable)
    centres = np.stack([(columns + 0.5) * cell_m, (rows + 0.5) * cell_m], axis=1)
    cases: list[Case] = []
    family: dict[str, str] = {}
    # Singles: the UAV's ground point is the walkable cell farthest from any building among
    # those at least 100 m inside the area (its edge is no wall: the clearance ignores it).
    inner = (np.minimum(centres, [area.size_x_m, area.size_y_m] - centres) >= 100.0).all(axis=1)
    best = int(np.argmax(np.where(inner, ground.clearance_m[rows, columns], -1.0)))
    hub = centres[best]
    distance_m = np.hypot(*(centres - hub).T)
    # Line of sight from the UAV at 100 m (at 25 m almost nothing beyond 120 m is in sight);
    # a path at both altitudes where there is such a cell, else at 100 m.
    seen = line_of_sight(site, np.array([hub[0], hub[1], 100.0]), centres)
    uavs = np.array([[hub[0], hub[1], 25.0], [hub[0], hub[1], 100.0]])
    has_path = np.isfinite(path_loss_db(site, uavs, centres))
    singles: list[tuple[str, np.ndarray]] = []
    single_distance_m: dict[str, float] = {}
    for target_m in (60, 150, 300):
        for label, wanted in (("los", True), ("blocked", False)):
            pool = np.flatnonzero((seen == wanted) & has_path.all(axis=0))
            if pool.size == 0:
                pool = np.flatnonzero((seen == wanted) & has_path[1])
            if pool.size == 0:
                raise ValueError(f"{environment}: no walkable {label} cell with a path")
            pick = pool[int(np.argmin(np.abs(distance_m[pool] - target_m)))]
            singles.append((f"t{target_m}-{label}", centres[pick]))
            single_distance_m[f"t{target_m}-{label}"] = round(float(distance_m[pick]), 1)
    for z_m in (25.0, 100.0):
        for name, xy in singles:
            case = Case(f"ssingle-{name}-z{z_m:.0f}-L40", [hub[0], hub[1], z_m], [xy], [40 * MBPS])
            cases.append(case)
            family[case.id] = "ssingle"
    rng = np.random.default_rng(3800)
    groups: dict[str, list[str]] = {}
    shapes = [
        ("streets", 3, 40),
        ("squares", 8, 20),
        ("exponential", 3, 20),
        ("streets", 8, 30),
        ("squares", 3, 10),
        ("exponential", 8, 40),
    ]
    for g, (kind, n_users, total_mbps) in enumerate(shapes):
        (s,) = generate_scenarios(
            1, n_users, seed=3801 + g, area=area, total_load_bps=total_mbps * MBPS, family=kind
        )
        ids = []
        for c, uav in enumerate(_group_candidates(s, rng)):
            case = Case(f"sgrp{g}-c{c}", _above_roof(site, uav, area), s.users_xy_m, s.load_bps)
            cases.append(case)
            family[case.id] = "sgroup"
            ids.append(case.id)
        groups[f"sgrp{g}"] = ids
    for n_users in (12, 20):
        (s,) = generate_scenarios(
            1, n_users, seed=3800 + n_users, area=area, total_load_bps=40 * MBPS, family="crowd"
        )
        for z_m in (50.0, 100.0):
            uav = _above_roof(site, _centroid(s.users_xy_m, None, z_m), area)
            case = Case(f"scrowd-u{n_users}-z{z_m:.0f}", uav, s.users_xy_m, s.load_bps)
            cases.append(case)
            family[case.id] = "scrowd"
    single_ids = [c.id for c in cases if family[c.id] == "ssingle"]
    held_out = [case_id for i, case_id in enumerate(single_ids) if i % 3 == 2]
    crowds = [c.id for c in cases if family[c.id] == "scrowd"]
    held_out += [case_id for i, case_id in enumerate(crowds) if i % 2 == 1]
    held_out += [case_id for g, ids in groups.items() if int(g[4:]) % 2 == 1 for case_id in ids]
    meta = {
        "description": f"ns-3 calibration set, {environment} over the site; see "
        "sim/calibration/build.py",
        "single_ground_point_m": [float(hub[0]), float(hub[1])],
        "single_distance_m": single_distance_m,
        "family": family,
        "held_out": held_out,
        "groups": groups,
        "long_runs": [],
    }
    return cases, meta


def write_site_cases(environments: tuple[str, ...] = SITE_ENVIRONMENTS) -> None:
    """Write ``cases_site_<name>.json`` per site of ``environments`` (:func:`make_site_cases`)."""
    for environment in environments:
        cases, meta = make_site_cases(environment)
        doc = cases_document(AreaConfig(environment=environment), cases)
        doc.update(meta)
        target = cases_path(environment)
        atomic_write_json(target, doc)
        area, _ = load_cases(target)  # validates: users on walkable ground, the site covers
        assert area.environment == environment
        print(f"wrote {len(cases)} cases ({len(meta['held_out'])} held out) to {target}")


FEW_STATIONS_PATH = HERE / "cases_few_stations.json"


def _few_station_users(
    rng: np.random.Generator,
    uav_xy_m: np.ndarray,
    n_heavy: int,
    n_light: int,
    light_m: tuple[float, float] = (10.0, 100.0),
) -> tuple[np.ndarray, np.ndarray] | None:
    """Users around ``uav_xy_m``: ``n_heavy`` heavy ones 250–500 m away (15–45 Mbit/s) and
    ``n_light`` light ones ``light_m`` away (0.5–3 Mbit/s; clipped to the area), or None if a
    heavy one would fall outside it (the caller draws again). Positions to 0.1 m, loads
    (bit/s) to 1 kbit/s."""
    xy, loads = [], []
    for _ in range(n_heavy):
        d_m, bearing = rng.uniform(250.0, 500.0), rng.uniform(0.0, 2.0 * math.pi)
        xy.append(uav_xy_m + d_m * np.array([math.cos(bearing), math.sin(bearing)]))
        loads.append(rng.uniform(15.0, 45.0))
    for _ in range(n_light):
        d_m, bearing = rng.uniform(*light_m), rng.uniform(0.0, 2.0 * math.pi)
        xy.append(uav_xy_m + d_m * np.array([math.cos(bearing), math.sin(bearing)]))
        loads.append(rng.uniform(0.5, 3.0))
    users = np.round(np.array(xy), 1)
    if n_heavy and not np.all((users[:n_heavy] >= 0.0) & (users[:n_heavy] <= AREA.size_x_m)):
        return None
    users = np.clip(users, 0.0, [AREA.size_x_m, AREA.size_y_m])
    return users, np.round(np.array(loads) * 1e3) * (MBPS / 1e3)


def make_few_station_cases() -> tuple[list[Case], dict[str, Any]]:
    """The few-station regime: 1–4 stations, one or two heavy users 250–500 m from the UAV, light
    ones near it (or, ``fmid``, not near). Held out entirely (no fit reads it); 152 cases:

    * ``few-n<U>-h<H>-<i>`` (80): U = 1..4 stations, H = 1 or 2 heavy (15–45 Mbit/s, 250–500 m
      from the UAV's ground point), the rest light (0.5–3 Mbit/s, 10–100 m), the UAV at a
      random point of the area's inner part, 25–100 m (altitude levels);
    * ``fgrp<g>-c<c>`` (8 groups × 4 candidates = 32): one such scenario (2–4 stations) at four
      UAV positions, for placement agreement in the regime: above the light users' centroid
      at 25 and 75 m, the load-weighted centroid of all users at 25 m, and halfway between
      the lights' centroid and the (first) heavy user at 50 m;
    * ``fmid-n<U>-h<H>-<i>`` (40): as ``few`` with U = 2..4, but the light users 150–400 m
      from the UAV (appended after the first run: the open set's congested light users that
      the model misses are of this kind, not near ones).
    """
    rng = np.random.default_rng(20261124)
    cases: list[Case] = []
    family: dict[str, str] = {}
    levels = (25.0, 50.0, 75.0, 100.0)

    def draw(
        n_stations: int, n_heavy: int, light_m: tuple[float, float] = (10.0, 100.0)
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        for _ in range(10_000):
            uav_xy = np.round(rng.uniform(50.0, 450.0, size=2), 1)
            users = _few_station_users(rng, uav_xy, n_heavy, n_stations - n_heavy, light_m)
            if users is not None:
                return uav_xy, *users
        raise RuntimeError("no scenario fits in the area")  # pragma: no cover

    for i in range(80):
        n_stations = 1 + i % 4
        n_heavy = 1 if n_stations == 1 else 1 + (i // 4) % 2
        uav_xy, xy, load_bps = draw(n_stations, n_heavy)
        z_m = levels[int(rng.integers(len(levels)))]
        case = Case(f"few-n{n_stations}-h{n_heavy}-{i:02d}", [*uav_xy, z_m], xy, load_bps)
        cases.append(case)
        family[case.id] = "few"
    groups: dict[str, list[str]] = {}
    for g in range(8):
        n_stations = 2 + g % 3
        n_heavy = 1 if n_stations == 2 else 1 + (g // 3) % 2
        _, xy, load_bps = draw(n_stations, n_heavy)
        lights = xy[n_heavy:]
        light_c = lights.mean(axis=0)
        heavy = xy[0]
        candidates = [
            np.array([*light_c, 25.0]),
            np.array([*light_c, 75.0]),
            _centroid(xy, load_bps, 25.0),
            np.array([*(0.5 * (light_c + heavy)), 50.0]),
        ]
        ids = []
        for c, uav in enumerate(candidates):
            case = Case(f"fgrp{g}-c{c}", np.round(uav, 1), xy, load_bps)
            cases.append(case)
            family[case.id] = "fgroup"
            ids.append(case.id)
        groups[f"fgrp{g}"] = ids
    # Appended after a first run (same rules otherwise): light users 150-400 m away, not near;
    # in the open set it is such light users that ns-3 congests and the model does not.
    for i in range(40):
        n_stations = 2 + i % 3
        n_heavy = 1 if n_stations == 2 else 1 + (i // 3) % 2
        uav_xy, xy, load_bps = draw(n_stations, n_heavy, (150.0, 400.0))
        z_m = levels[int(rng.integers(len(levels)))]
        case = Case(f"fmid-n{n_stations}-h{n_heavy}-{i:02d}", [*uav_xy, z_m], xy, load_bps)
        cases.append(case)
        family[case.id] = "fmid"
    meta = {
        "description": "the few-station regime (1-4 stations, heavy users 250-500 m away, light "
        "ones near), held out entirely; see sim/calibration/build.py make_few_station_cases",
        "family": family,
        "held_out": [c.id for c in cases],
        "groups": groups,
        "long_runs": [],
    }
    return cases, meta


def write_few_station_cases(path: Path = FEW_STATIONS_PATH) -> None:
    """Write ``cases_few_stations.json`` (:func:`make_few_station_cases`)."""
    cases, meta = make_few_station_cases()
    doc = cases_document(AREA, cases)
    doc.update(meta)
    atomic_write_json(path, doc)
    load_cases(path)  # validates
    print(f"wrote {len(cases)} cases (all held out) to {path}")


def write_cases(path: Path = CASES_PATH) -> None:
    """Write ``cases.json`` (open) and one ``cases_<environment>.json`` per urban class."""
    cases, meta = make_cases()
    doc = cases_document(AREA, cases)
    doc.update(meta)
    atomic_write_json(path, doc)
    load_cases(path)  # validates
    print(f"wrote {len(cases)} cases ({len(meta['held_out'])} held out) to {path}")
    if path != CASES_PATH:
        return
    for environment in URBAN_ENVIRONMENTS:
        cases, meta = make_urban_cases(environment)
        doc = cases_document(AreaConfig(environment=environment), cases)
        doc.update(meta)
        target = cases_path(environment)
        atomic_write_json(target, doc)
        area, _ = load_cases(target)  # validates
        assert area.environment == environment
        print(f"wrote {len(cases)} cases ({len(meta['held_out'])} held out) to {target}")


def load_meta(path: Path = CASES_PATH) -> dict[str, Any]:
    """The extra top-level keys of the calibration case file (family, held_out, groups ...)."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    return {k: v for k, v in doc.items() if k not in ("format", "area", "cases")}


# --------------------------------------------------------------------------------------------
# Running ns-3


def _mean_entry(case_id: str, per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over seeds of each user's metrics; utility: the mean of the per-seed utilities."""
    n_users = len(per_seed[0]["users"])
    users = []
    for u in range(n_users):
        users.append(
            {
                key: float(np.mean([s["users"][u][key] for s in per_seed]))
                for key in ("throughput_bps", "delay_s", "plr")
            }
        )
    return {
        "id": case_id,
        "utility": float(np.mean([s["utility"] for s in per_seed])),
        "users": users,
        "wall_s": float(np.mean([s["wall_s"] for s in per_seed])),
        "per_seed": per_seed,
    }


def _round(value: Any) -> Any:
    """Floats to 6 significant digits, recursively (keeps the committed files small)."""
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, dict):
        return {k: _round(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_round(v) for v in value]
    return value


def _compact(
    result_dict: dict[str, Any], seed: int, kept: tuple[str, ...] = KEPT_DETAIL
) -> dict[str, Any]:
    out = {
        "seed": seed,
        "utility": result_dict["utility"],
        "wall_s": result_dict["wall_s"],
        "association_max_s": max(result_dict["association_s"]),
    }
    out["users"] = [
        {
            "throughput_bps": user["throughput_bps"],
            "delay_s": user["delay_s"],
            "plr": user["plr"],
            "ns3": {k: v for k, v in user.get("ns3", {}).items() if k in kept},
        }
        for user in result_dict["users"]
    ]
    if "intervals" in result_dict:
        out["intervals"] = result_dict["intervals"]
    return _round(out)


def run_variant(
    out_path: Path,
    cases: list[Case],
    indices: list[int],
    settings_kwargs: dict[str, Any],
    seeds: list[int],
    niceness: int,
    deadline: float,
    source: Path = CASES_PATH,
    kept: tuple[str, ...] = KEPT_DETAIL,
) -> None:
    """Simulate ``cases`` for every seed, rewriting ``out_path`` after each case (resumable).

    ``settings_kwargs`` are :class:`~sim.ns3_backend.Ns3Settings` fields (``environment`` among
    them for the urban sets); ``source`` is the case file named in the results; ``kept``: the
    ns-3 counters kept per user and seed."""
    from sim.ns3_backend import Ns3CaseError, Ns3Runner, Ns3Settings

    doc: dict[str, Any] = {}
    if out_path.exists():
        doc = json.loads(out_path.read_text(encoding="utf-8"))
    done: dict[str, dict[int, dict[str, Any]]] = {}
    for entry in doc.get("cases", []):
        done[entry["id"]] = {s["seed"]: s for s in entry["per_seed"]}
    failed: list[dict[str, str]] = doc.get("failed", [])
    base = Ns3Settings(**settings_kwargs)
    with Ns3Runner(niceness=niceness) as runner:
        for seed in seeds:
            settings = Ns3Settings(**{**settings_kwargs, "seed": seed})
            for case, index in zip(cases, indices, strict=True):
                if seed in done.get(case.id, {}):
                    continue
                if time.monotonic() > deadline:
                    print("time budget spent; stopping (rerun to resume)", flush=True)
                    return
                started = time.perf_counter()
                try:
                    result = runner.run(case, settings, index)
                except Ns3CaseError as exc:
                    failed.append({"id": case.id, "seed": str(seed), "error": exc.reason})
                    print(f"  FAILED {exc}", flush=True)
                    continue
                done.setdefault(case.id, {})[seed] = _compact(result.to_dict(), seed, kept)
                print(
                    f"  {out_path.name} seed {seed} {case.id}: utility "
                    f"{result.metrics.utility:.3f}, {time.perf_counter() - started:.1f} s",
                    flush=True,
                )
                entries = [
                    _mean_entry(c.id, [done[c.id][s] for s in sorted(done[c.id])])
                    for c in cases
                    if c.id in done
                ]
                seeds_done = sorted({s for per_case in done.values() for s in per_case})
                atomic_write_json(
                    out_path,
                    {
                        "format": "tupa-case-results/1",
                        "source": str(source.relative_to(HERE.parent.parent)),
                        "backend": "ns3",
                        "ns3_version": runner.version,
                        "mode": "stochastic",
                        "seed": seeds_done[0],
                        "seeds": seeds_done,
                        "queueing": base.queueing,
                        "warmup_s": base.warmup_s,
                        "measure_s": base.measure_s,
                        "ns3": {k: v for k, v in base.to_dict().items() if k != "seed"},
                        "cases": entries,
                        "failed": failed,
                    },
                )


def run_all(
    seeds: list[int],
    niceness: int,
    budget_s: float,
    environments: tuple[str, ...] = ENVIRONMENTS,
) -> None:
    """Simulate every calibration set in ``environments`` (``open`` first, with its long runs),
    resumable, within ``budget_s`` seconds."""
    deadline = time.monotonic() + budget_s
    started = time.perf_counter()
    if "open" in environments:
        run_open(seeds, niceness, deadline)
    for environment in environments:
        if environment == "open":
            continue
        source = cases_path(environment)
        area, cases = load_cases(source)
        assert area.environment == environment, source
        indices = list(range(len(cases)))
        for seed in seeds:
            for queueing in ("fq-codel", "mac-only"):
                print(f"{environment}, {queueing}, seed {seed}", flush=True)
                run_variant(
                    results_path(environment, queueing),
                    cases,
                    indices,
                    {
                        "queueing": queueing,
                        "environment": environment,
                        "user_height_m": area.user_height_m,
                    },
                    [seed],
                    niceness,
                    deadline,
                    source,
                )
    print(f"done in {time.perf_counter() - started:.0f} s", flush=True)


def few_stations_results_path(queueing: str) -> Path:
    """The ns-3 results of the few-station set (:func:`make_few_station_cases`)."""
    return HERE / f"ns3_few_stations_{queueing}.json"


def run_few_stations(seeds: list[int], niceness: int, budget_s: float) -> None:
    """Simulate the few-station set, both variants, seed-major, resumable, every ns-3 counter
    of :data:`sim.ns3_worker.FIELDS` kept per user and seed (the mechanism needs them)."""
    from sim.ns3_worker import FIELDS

    deadline = time.monotonic() + budget_s
    started = time.perf_counter()
    _, cases = load_cases(FEW_STATIONS_PATH)
    indices = list(range(len(cases)))
    for seed in seeds:
        for queueing in ("fq-codel", "mac-only"):
            print(f"few stations, {queueing}, seed {seed}", flush=True)
            run_variant(
                few_stations_results_path(queueing),
                cases,
                indices,
                {"queueing": queueing},
                [seed],
                niceness,
                deadline,
                FEW_STATIONS_PATH,
                kept=FIELDS,
            )
    print(f"done in {time.perf_counter() - started:.0f} s", flush=True)


def run_open(seeds: list[int], niceness: int, deadline: float) -> None:
    """The original (open) set, both variants, then its long runs."""
    _, cases = load_cases(CASES_PATH)
    meta = load_meta()
    indices = list(range(len(cases)))
    # Seed-major across both variants: every case once before any case twice.
    for seed in seeds:
        for queueing in ("fq-codel", "mac-only"):
            print(f"{queueing}, seed {seed}", flush=True)
            run_variant(
                HERE / f"ns3_{queueing}.json",
                cases,
                indices,
                {"queueing": queueing},
                [seed],
                niceness,
                deadline,
            )
    by_id = {c.id: (i, c) for i, c in enumerate(cases)}
    long_cases = [by_id[i][1] for i in meta["long_runs"]]
    long_indices = [by_id[i][0] for i in meta["long_runs"]]
    for queueing in ("fq-codel", "mac-only"):
        print(f"long runs, {queueing}", flush=True)
        run_variant(
            HERE / f"ns3_long_{queueing}.json",
            long_cases,
            long_indices,
            {"queueing": queueing, "measure_s": 10.0, "interval_s": 1.0},
            [seeds[0]],
            niceness,
            deadline,
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("cases", help="write sim/calibration/cases.json", allow_abbrev=False)
    sub.add_parser(
        "site-cases",
        help="write sim/calibration/cases_site_munich.json (the site set)",
        allow_abbrev=False,
    )
    sub.add_parser(
        "few-stations-cases",
        help="write sim/calibration/cases_few_stations.json",
        allow_abbrev=False,
    )
    few = sub.add_parser(
        "run-few-stations", help="simulate the few-station set in ns-3", allow_abbrev=False
    )
    few.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    few.add_argument("--nice", type=int, default=10, help="worker niceness (default 10)")
    few.add_argument("--budget-s", type=float, default=20 * 60, help="stop after this long")
    run = sub.add_parser("run", help="simulate the cases in ns-3 (resumable)", allow_abbrev=False)
    run.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    run.add_argument("--nice", type=int, default=19, help="worker niceness (default 19)")
    run.add_argument("--budget-s", type=float, default=40 * 60, help="stop after this long")
    run.add_argument(
        "--environments",
        nargs="+",
        choices=ENVIRONMENTS + SITE_ENVIRONMENTS,
        default=list(ENVIRONMENTS),
        help="which calibration sets (default: the five classes; open is cases.json; "
        "site:munich, the site set, only when named)",
    )
    args = parser.parse_args(argv)
    if args.command == "cases":
        write_cases()
    elif args.command == "site-cases":
        write_site_cases()
    elif args.command == "few-stations-cases":
        write_few_station_cases()
    elif args.command == "run-few-stations":
        run_few_stations(args.seeds, args.nice, args.budget_s)
    else:
        run_all(args.seeds, args.nice, args.budget_s, tuple(args.environments))
    return 0


if __name__ == "__main__":
    sys.exit(main())
