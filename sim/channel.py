"""Radio channel: geometry, path loss in open and urban environments, noise, fast fading.

**Environments** (:data:`ENVIRONMENTS`). ``open`` is the paper's channel: Friis free-space loss,
every link in line of sight, Rician fading with K = 13 dB. The four urban classes of ITU-R
Rec. P.1410 — ``suburban``, ``urban``, ``dense-urban``, ``highrise-urban`` — use the
air-to-ground model of A. Al-Hourani, S. Kandeepan and S. Lardner, "Optimal LAP Altitude for
Maximum Coverage", IEEE Wireless Communications Letters 3(6):569–572, 2014:

* a link is in line of sight (LoS) with probability ``P_LoS(θ) = 1 / (1 + a·exp(−b(θ − a)))``,
  θ the elevation angle from the user to the UAV in degrees, (a, b) the environment's S-curve
  (their Table I: suburban 4.88, 0.43; urban 9.61, 0.16; dense urban 12.08, 0.11; highrise
  urban 27.23, 0.08);
* a LoS link loses free-space loss plus η_LoS dB, a non-LoS one free-space loss plus η_NLoS dB
  (their Table I at 700 MHz, 2 GHz and 5.8 GHz; between and beyond those frequencies η is
  interpolated linearly in log-frequency and held at the end values, which the letter does not
  cover: it is an assumption of ours);
* the mean path loss is ``FSPL(d) + P_LoS·η_LoS + (1 − P_LoS)·η_NLoS``
  (:func:`mean_path_loss_db`): climbing raises P_LoS but lengthens d, so each environment has
  a best elevation angle (:func:`optimal_elevation_deg`).

Fading: Rician with the configured K on LoS links, Rayleigh on non-LoS ones. In the model's
stochastic mode each link's LoS state is drawn afresh every step (a Bernoulli of ``P_LoS`` at
the step's geometry; :func:`draw_link_channel`), like the step's fading draws: the simplest model
that has the right mean, chosen over spatially consistent states because a decision period of
1 s moves the UAV up to 10 m, and because the policy acts on the step's report, not on a
link's history. Its cost: a hovering UAV's links flip state from step to step more often than
3GPP TR 38.901's LoS-state correlation distance (~50 m outdoors) would have them. The expected
mode uses the mean path loss.

**Sites** (``site:PATH``, :mod:`sim.sites`): a ray-traced district. A link's mean path loss is
the site's, interpolated at the UAV's exact position (:func:`sim.sites.lookup.path_loss_db`;
no path: ``+inf``, out of coverage); its line-of-sight state is not drawn but found, over the
site's building-height map (:func:`sim.sites.los.line_of_sight`), and its fading is Rician with
the configured K in line of sight, Rayleigh otherwise (:func:`site_link_channel`). Ray tracing
already gives the mean loss of each state, so no excess loss is added. :func:`area_site` loads
the area's site once per file version and checks that it covers the area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from sim.config import ENVIRONMENTS, AreaConfig, RadioConfig, site_directory, site_path
from sim.errors import InputError

if TYPE_CHECKING:
    from sim.sites.format import Site

SPEED_OF_LIGHT_MPS = 299_792_458.0
NO_LINK_LOSS_DB = 1000.0
"""The loss the network model gives a site's link with no path at all (``+inf`` in the
lookup): far beyond any real link (received power ~ −980 dBm, disconnected, no throughput)
but finite, so SNRs, sums and differences downstream stay numbers."""
MIN_FREQUENCY_HZ = 1e9
MAX_FREQUENCY_HZ = 7e9


@dataclass(frozen=True)
class AirToGround:
    """One environment's parameters (Al-Hourani et al. 2014, Table I)."""

    a: float
    b: float
    eta_los_db: tuple[float, float, float]  # at TABLE_FREQUENCIES_HZ
    eta_nlos_db: tuple[float, float, float]

    def excess_db(self, frequency_hz: float) -> tuple[float, float]:
        """(η_LoS, η_NLoS) at ``frequency_hz``: interpolated in log-frequency, held at the ends."""
        x = np.log10(TABLE_FREQUENCIES_HZ)
        f = math.log10(frequency_hz)
        return float(np.interp(f, x, self.eta_los_db)), float(np.interp(f, x, self.eta_nlos_db))


TABLE_FREQUENCIES_HZ = (700e6, 2e9, 5.8e9)
AIR_TO_GROUND: dict[str, AirToGround | None] = {
    "open": None,
    "suburban": AirToGround(4.88, 0.43, (0.0, 0.1, 0.2), (18.0, 21.0, 24.0)),
    "urban": AirToGround(9.61, 0.16, (0.6, 1.0, 1.2), (17.0, 20.0, 23.0)),
    "dense-urban": AirToGround(12.08, 0.11, (1.0, 1.6, 1.8), (20.0, 23.0, 26.0)),
    "highrise-urban": AirToGround(27.23, 0.08, (1.5, 2.3, 2.5), (29.0, 34.0, 41.0)),
}
assert tuple(AIR_TO_GROUND) == ENVIRONMENTS


def air_to_ground(environment: str) -> AirToGround | None:
    """The environment's parameters (``None`` for ``open``); InputError for an unknown name,
    and for a site, which has no statistical parameters (:func:`site_link_channel`)."""
    if site_path(environment) is not None:
        raise InputError(
            f"environment: {environment!r} is a site: this part of the model takes only "
            f"{', '.join(ENVIRONMENTS)} so far"
        )
    try:
        return AIR_TO_GROUND[environment]
    except (KeyError, TypeError):
        raise InputError(
            f"environment: must be one of {', '.join(ENVIRONMENTS)}, got {environment!r}"
        ) from None


def elevation_deg(ground_distance_m: np.ndarray, height_m: np.ndarray) -> np.ndarray:
    """The elevation angle from the user to the UAV, degrees (90 straight overhead)."""
    return np.degrees(np.arctan2(height_m, ground_distance_m))


def los_probability(environment: str, elevation: np.ndarray) -> np.ndarray:
    """``P_LoS`` at elevation angles in degrees (1 everywhere in ``open``)."""
    params = air_to_ground(environment)
    theta = np.asarray(elevation, dtype=float)
    if params is None:
        return np.ones_like(theta)
    return 1.0 / (1.0 + params.a * np.exp(-params.b * (theta - params.a)))


def mean_path_loss_db(
    environment: str,
    ground_distance_m: np.ndarray | float,
    height_m: np.ndarray | float,
    frequency_hz: float,
) -> np.ndarray:
    """Mean path loss (dB) from a UAV ``height_m`` above the user and ``ground_distance_m``
    away: free-space loss plus the environment's expected excess loss (module doc). Arrays
    broadcast. InputError naming the argument for an unknown environment, a frequency outside
    1–7 GHz, negative or non-finite distances and heights."""
    params = air_to_ground(environment)
    if not (MIN_FREQUENCY_HZ <= frequency_hz <= MAX_FREQUENCY_HZ):
        raise InputError(f"frequency_hz: must lie in 1–7 GHz, got {frequency_hz!r}")
    ground = np.asarray(ground_distance_m, dtype=float)
    height = np.asarray(height_m, dtype=float)
    for name, values in (("ground_distance_m", ground), ("height_m", height)):
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            raise InputError(f"{name}: must be finite and non-negative")
    loss = friis_path_loss_db(np.hypot(ground, height), frequency_hz)
    if params is None:
        return loss
    eta_los, eta_nlos = params.excess_db(frequency_hz)
    p_los = los_probability(environment, elevation_deg(ground, height))
    return loss + p_los * eta_los + (1.0 - p_los) * eta_nlos


def optimal_elevation_deg(environment: str, frequency_hz: float) -> float:
    """The elevation angle that maximises the coverage radius for any fixed maximum path loss:
    the root of Al-Hourani et al.'s eq. (13),
    ``π/(9 ln 10)·tan θ + a·b·(η_LoS − η_NLoS)·e^(−b(θ−a)) / (a·e^(−b(θ−a)) + 1)² = 0``."""
    params = air_to_ground(environment)
    if params is None:
        raise InputError("environment: 'open' has no optimal elevation (lowest flies best)")
    eta_los, eta_nlos = params.excess_db(frequency_hz)
    a, b, excess = params.a, params.b, eta_los - eta_nlos

    def slope(theta: float) -> float:
        e = math.exp(-b * (theta - a))
        return math.pi / (9.0 * math.log(10.0)) * math.tan(math.radians(theta)) + (
            a * b * excess * e / (a * e + 1.0) ** 2
        )

    low, high = 0.01, 89.9  # slope(low) < 0 < slope(high): bisect
    for _ in range(80):
        mid = 0.5 * (low + high)
        if slope(mid) < 0:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def draw_link_channel(
    rng: np.random.Generator,
    p_los: np.ndarray,
    k_db: float,
    draws: int,
) -> tuple[np.ndarray, np.ndarray]:
    """One step's channel of every link in an urban environment, stochastic mode.

    ``p_los`` (N, U): each link's LoS probability now. Returns (LoS state (N, U) bool, power
    gains (N, U, draws)): Rician with factor ``k_db`` on LoS links, Rayleigh on the others.
    Draw order: N·U uniforms for the states, then the normals :func:`rician_power_gain`
    draws for shape (N, U, draws), shared by both fading laws.
    """
    los = rng.random(p_los.shape) < p_los
    re, im = rng.standard_normal((2, *p_los.shape, draws))
    los_amplitude, sigma = _rician_parameters(k_db)
    # Per link: the Rician law on LoS links, Rayleigh (no line-of-sight part) on the others.
    amplitude = np.where(los, los_amplitude, 0.0)[..., None]
    scatter = np.where(los, sigma, math.sqrt(0.5))[..., None]
    return los, (amplitude + scatter * re) ** 2 + (scatter * im) ** 2


def distances_m(uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, user_height_m: float) -> np.ndarray:
    """3-D distances between each UAV position (B, 3) and each ground user (U, 2): shape (B, U)."""
    dx = uav_xyz_m[:, None, 0] - users_xy_m[None, :, 0]
    dy = uav_xyz_m[:, None, 1] - users_xy_m[None, :, 1]
    dz = uav_xyz_m[:, None, 2] - user_height_m
    return np.sqrt(dx * dx + dy * dy + dz * dz)


def friis_path_loss_db(distance_m: np.ndarray, frequency_hz: float) -> np.ndarray:
    """Free-space path loss; distances under 1 m count as 1 m (the near field is not modelled)."""
    d = np.maximum(distance_m, 1.0)
    return 20.0 * np.log10(4.0 * np.pi * d * frequency_hz / SPEED_OF_LIGHT_MPS)


def mean_rssi_dbm(distance_m: np.ndarray, radio: RadioConfig) -> np.ndarray:
    """Received power before fading (the average over Rician fading is the Friis value)."""
    return radio.tx_power_dbm - friis_path_loss_db(distance_m, radio.frequency_hz)


def rician_power_gain(rng: np.random.Generator, k_db: float, size: tuple[int, ...]) -> np.ndarray:
    """Unit-mean power gains |h|² of a Rician channel with factor K (linear power ratio).

    Draw order: ``size`` standard normals for the real parts (C order), then ``size`` for the
    imaginary parts, from one ``standard_normal`` call of shape ``(2, *size)`` (the same numbers
    two calls of ``size`` would give).
    """
    los, sigma = _rician_parameters(k_db)
    if type(size) is not tuple:
        size = () if size is None else tuple(np.atleast_1d(size))  # an int, a list, None
    draws = rng.standard_normal((2, *size))
    _combine_parts(draws.reshape(2, -1), los, sigma)
    return draws[0]


@njit(cache=True, nogil=True)
def _combine_parts(draws: np.ndarray, los: float, sigma: float) -> None:
    """``draws[0] = (los + sigma·draws[0])² + (sigma·draws[1])²`` in place, (2, N)."""
    for i in range(draws.shape[1]):
        re = los + sigma * draws[0, i]
        im = sigma * draws[1, i]
        draws[0, i] = re * re + im * im


@lru_cache(maxsize=8)
def _rician_parameters(k_db: float) -> tuple[float, float]:
    """(line-of-sight amplitude, scatter standard deviation per component) for K in dB."""
    k = 10.0 ** (k_db / 10.0)
    return float(np.sqrt(k / (k + 1.0))), float(np.sqrt(1.0 / (2.0 * (k + 1.0))))


@lru_cache(maxsize=8)
def rician_quadrature_db(k_db: float, n_points: int = 32) -> np.ndarray:
    """Deterministic equal-probability quadrature of the Rician power gain, in dB.

    Point i is the mean gain of the i-th of ``n_points`` equally likely slices of the
    distribution, estimated once from 2**18 draws with a fixed seed; averaging a function over
    these points approximates its expectation over the fading (used by the expected mode).
    """
    rng = np.random.default_rng(20240601)
    samples = np.sort(rician_power_gain(rng, k_db, (2**18,)))
    gains_db = 10.0 * np.log10(samples.reshape(n_points, -1).mean(axis=1))
    gains_db.setflags(write=False)  # cached: shared by every caller
    return gains_db


def environment_site(environment: str) -> Site | None:
    """The site an environment names (None unless it is ``site:NAME``, a shipped site, or
    ``site:PATH``: :func:`sim.config.site_directory`), loaded once per version of its files;
    InputError naming ``environment`` for a missing or broken site. Whether it covers an area
    is :func:`area_site`'s check."""
    found = site_directory(environment)
    if found is None:
        return None
    from sim.sites.format import DATA_FILE, META_FILE

    directory = found.resolve()
    try:
        stamp = tuple((directory / name).stat().st_mtime_ns for name in (META_FILE, DATA_FILE))
    except FileNotFoundError:
        raise InputError(
            f"environment: {environment!r}: no site there ({META_FILE} and {DATA_FILE})"
        ) from None
    return _load_site(str(directory), stamp, environment)


def area_site(area: AreaConfig) -> Site | None:
    """The area's site (None unless its environment is ``site:NAME``, a shipped site, or
    ``site:PATH``: :func:`sim.config.site_directory`), loaded once per version of its files;
    InputError naming ``environment`` for a missing or broken site, or one that does not cover
    the area's ground and flight volume."""
    site = environment_site(area.environment)
    if site is None:
        return None
    short = [
        f"{name} {have:g} m < {need:g} m"
        for name, have, need in (
            ("size_x_m", site.size_x_m, area.size_x_m),
            ("size_y_m", site.size_y_m, area.size_y_m),
            ("uav_x_m", site.uav_x_m[-1], area.size_x_m),
            ("uav_y_m", site.uav_y_m[-1], area.size_y_m),
            ("uav_z_m", site.uav_z_m[-1], area.z_max_m),
        )
        if have < need - 1e-9
    ]
    if site.uav_x_m[0] > 1e-9 or site.uav_y_m[0] > 1e-9 or site.uav_z_m[0] > area.z_min_m:
        short.append("its UAV grid starts inside the area's flight volume")
    if short:
        raise InputError(
            f"environment: {area.environment!r} is smaller than the area ({', '.join(short)})"
        )
    return site


@lru_cache(maxsize=4)
def _load_site(directory: str, stamp: tuple[int, ...], environment: str) -> Site:
    from sim.sites.format import load_site

    try:
        return load_site(Path(directory))
    except InputError as exc:
        raise InputError(f"environment: {environment!r}: {exc}") from None


def site_link_channel(
    site: Site,
    uav_xyz_m: np.ndarray,
    users_xy_m: np.ndarray,
    k_db: float,
    rng: np.random.Generator | None,
    draws: int,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The links' channel on a site (module doc): path loss (dB, (N, U); ``+inf`` without a
    path) for UAV positions (N, 3) and users (U, 2) — or (N, U, 2), each position its own users
    (:func:`sim.sites.los.site_links`) — and fading power gains (N, U, draws) — Rician with
    factor ``k_db`` on links in line of sight, Rayleigh on the others — or None in expected
    mode (``rng`` None). Draw order: :func:`draw_link_channel`'s, with each link's state given
    (its uniforms are drawn and do not change it); the same gains it gives."""
    from sim.sites.los import site_links

    loss, los = site_links(site, uav_xyz_m, users_xy_m, rng is not None)
    if rng is None:
        return loss, None
    assert los is not None
    rng.random(los.shape)  # draw_link_channel's state uniforms: the states are known here
    parts = rng.standard_normal((2, *los.shape, draws))
    los_amplitude, sigma = _rician_parameters(k_db)
    _combine_by_state(parts.reshape(2, los.size, draws), los.ravel(), los_amplitude, sigma)
    return loss, parts[0]


@njit(cache=True, nogil=True)
def _combine_by_state(
    parts: np.ndarray, los: np.ndarray, los_amplitude: float, sigma: float
) -> None:
    """:func:`draw_link_channel`'s gains in place into ``parts[0]`` (2, L, draws): Rician
    (``los_amplitude``, ``sigma``) on links in line of sight, Rayleigh on the others."""
    rayleigh = math.sqrt(0.5)
    for link in range(parts.shape[1]):
        amplitude = los_amplitude if los[link] else 0.0
        scatter = sigma if los[link] else rayleigh
        for d in range(parts.shape[2]):
            re = amplitude + scatter * parts[0, link, d]
            im = scatter * parts[1, link, d]
            parts[0, link, d] = re * re + im * im
