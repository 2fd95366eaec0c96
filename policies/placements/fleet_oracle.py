"""The fleet's search oracle: the best static placement of K UAVs found with the fleet model.

The upper bound the fleet's policies and baselines are measured against, as
:mod:`policies.placements.oracle` is for one UAV. A fleet placement's *score* is the mean network
utility over an episode of ``episode_steps`` steps holding it, expected mode, queues and
associations carried from step to step after ``warmup_steps`` unscored steps
(:func:`fleet_episode_utility`; the environment's reset step). The joint space (1,600 grid points
per UAV, 1600^K placements) is too large to enumerate, so the search is **coordinate descent with
restarts**:

1. **Starts**: the two k-means placements (:mod:`policies.placements.fleet_baselines`, so the oracle
   is never below them on its own objective), and ``restarts`` more from ``default_rng(seed)``,
   alternately K users drawn by load (a UAV above each at the lowest level) and K candidate
   positions drawn uniformly. Given explicit ``candidates_m`` (a search restricted to a set of
   positions, as the exhaustive comparison needs), every start is first snapped onto them.
2. **Sweeps**: for each UAV in turn, the others held, every position of a coarse grid (every
   ``screen_stride``-th zone in x and y, every altitude level) is screened over a short
   horizon (``screen_steps``), the ``top_k`` best scored over the full episode, and the UAV moves
   to the best if that raises the score; sweeps repeat until one changes nothing (at most
   ``sweeps``). This is the single-UAV oracle's screen-then-score search, one UAV at a time.
3. **Refinement**: a compass pattern search over all UAVs at once — every UAV's ±x, ±y, ±z
   neighbour at the current step scored in one batch, the best single move taken while it
   improves, the step halved when none does, down to ``min_step_m``.
4. **Pair moves** (on the best start's result): coordinate descent stalls where two UAVs must
   move together (one leaves a hot spot only if the other takes its users), so for every pair
   of UAVs every placement of the two on a coarse grid (every ``pair_stride``-th zone, all
   levels: 100 positions, 4,950 pairs), the others held, is screened and the best ``top_k``
   scored; the best improvement is taken and stages 2–3 resume from it.

**From where the fleet is** (:meth:`FleetOracle.place_from`, a :class:`FleetStart`: what a
closed loop and the service use): the search above runs as it is, then the placement it ends on
from every start, and the k-means placements, each given to the vehicles by least total flight,
are scored again over the episode a closed loop flies (:func:`fleet_episode_utility` with the
start: the vehicles fly there at the world's speeds, the users stay on the APs they are on until
another is stronger by the hysteresis), and the best is refined on that score. It matters: a
placement that splits a hot spot's users between two UAVs a few tens of metres apart scores
0.99 held from a fresh association, but flown from the fleet's homes the users join the first
UAV that comes near and stay (3 dB hysteresis): 0.50 flown (K = 2, 20 users); the flown
search's choice flies 0.91 there, against load-weighted k-means' 0.82.

Placements that put two UAVs closer than ``separation_m`` are never candidates, so the answer
is separated; it is passed through :func:`sim.geometry.enforce_separation` anyway. The best
start's result wins. Everything is deterministic given ``seed`` (stable sorts, ties to the
first). How close this is to the true optimum: ``benchmarks/fleet_oracle.py`` solves small
cases (K = 2 and 3, 3 and 6 users, coarse grids) exhaustively and compares; on its 64 cases the
search restricted to the same grid reached the optimum every time, and coordinate descent
without the pair moves fell as low as 0.41 of it (docs/network-model.md, "Several access
points"). A restricted search snaps the k-means starts onto its candidates, so only the
unrestricted oracle is guaranteed to be at least the k-means placements.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from policies.interface import UsersLike
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.oracle import coarse_grid_positions_m
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel, FleetState
from sim.flight import Flight, fly_many
from sim.geometry import assign_targets, clip_to_volume, enforce_separation

__all__ = [
    "FLEET_ORACLE",
    "FleetOracle",
    "FleetOracleConfig",
    "FleetOracleResult",
    "FleetStart",
    "fleet_episode_utility",
    "separated",
]

_DIRECTIONS = np.concatenate([np.eye(3), -np.eye(3)])
# A restricted search with at most this many candidates moves pairs on the candidates.
_PAIR_GRID_MAX = 150


@dataclass(frozen=True)
class FleetOracleConfig:
    """Knobs of the fleet oracle's search (module doc); defaults: the evaluation's episode."""

    episode_steps: int = 100
    step_s: float = 1.0
    warmup_steps: int = 1
    screen_steps: int = 2
    screen_stride: int = 2
    top_k: int = 4
    restarts: int = 2
    sweeps: int = 3  # coordinate-descent sweeps over the grid; 0: local refinement only
    refine: bool = True
    initial_step_m: float | None = None  # None: half a zone
    min_step_m: float = 2.0
    max_refine_iterations: int = 30
    improvement_tol: float = 1e-9
    pair_stride: int = 4  # joint moves of two UAVs on every 4th zone; 0: none
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("episode_steps", "screen_steps", "screen_stride", "top_k"):
            if getattr(self, name) < 1:
                raise InputError(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("warmup_steps", "restarts", "sweeps", "max_refine_iterations", "pair_stride"):
            if getattr(self, name) < 0:
                raise InputError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not self.min_step_m > 0:
            raise InputError(f"min_step_m: must be > 0, got {self.min_step_m}")


@dataclass(frozen=True)
class FleetOracleResult:
    """The best placement (K, 3), its score, the best start's score before the search (flown
    from a start: the better k-means placement's), and how many placements were scored over
    the full episode."""

    positions_m: np.ndarray
    utility: float
    start_utility: float
    episodes_simulated: int


def separated(fleets_m: np.ndarray, separation_m: float) -> np.ndarray:
    """Which of the placements (B, K, 3) keep every two UAVs ``separation_m`` apart (B,)."""
    gap = fleets_m[:, :, None, :] - fleets_m[:, None, :, :]
    d2 = np.sum(gap * gap, axis=-1)
    k = fleets_m.shape[1]
    d2[:, np.arange(k), np.arange(k)] = np.inf
    return np.all(d2 >= separation_m * separation_m, axis=(1, 2))


def fleet_episode_utility(
    model: FleetModel,
    fleets_m: np.ndarray,
    users: UsersLike,
    steps: int,
    warmup_steps: int = 1,
    step_s: float = 1.0,
    start: FleetStart | None = None,
) -> np.ndarray:
    """Mean utility (B,) of holding each placement of ``fleets_m`` (B, K, 3) for an episode,
    expected mode: ``warmup_steps`` unscored steps, then ``steps`` scored, all placements
    advanced together. A placement whose step leaves its queues and associations as it found
    them has reached a fixed point (the model is deterministic and the users static), so its
    remaining steps repeat that step's utility and are not simulated.

    With ``start`` the episode is the one a closed loop flies: it begins where the fleet is,
    with the users on the APs they are on, and every step after the first the vehicles fly
    toward the placement (:func:`sim.flight.fly_many`, the environments' flight) before it is
    simulated; a placement is settled only once it is reached. (The environments also hold a
    vehicle whose flight would end too close to another; this score does not.)"""
    fleets = np.asarray(fleets_m, dtype=float)
    xy = np.asarray(users.users_xy_m, dtype=float)
    load = np.asarray(users.load_bps, dtype=float)
    batch, k = fleets.shape[0], fleets.shape[1]
    total = np.zeros(batch)
    live = np.arange(batch)
    state = None if start is None else start.state(batch, len(xy))
    here = fleets if start is None else np.broadcast_to(start.positions_m, fleets.shape).copy()
    horizon = warmup_steps + steps
    for t in range(horizon):
        if not len(live):
            break
        if start is not None and t > 0:
            flown = fly_many(here[live].reshape(-1, 3), fleets[live].reshape(-1, 3),
                             start.flight, step_s)  # fmt: skip
            here[live] = flown.reshape(len(live), k, 3)
        result = model.step(here[live], xy, load, state, None, step_s)
        if t >= warmup_steps:
            total[live] += result.utility
        new = result.state
        if state is not None and t < horizon - 1:
            settled = new.queues.same_as(state.queues) & np.all(
                new.association == state.association, axis=1
            )
            if start is not None:
                settled &= np.all(here[live] == fleets[live], axis=(1, 2))
            if settled.any():
                left = horizon - 1 - t
                scored_left = min(left, horizon - max(t + 1, warmup_steps))
                total[live[settled]] += result.utility[settled] * scored_left
                keep = ~settled
                live = live[keep]
                new = _take(new, keep)
        state = new
    return total / steps


@dataclass(frozen=True)
class FleetStart:
    """Where a closed loop's fleet is when it decides: the vehicles' positions (K, 3), the AP
    each user is on (U,; ``-1`` none, ``None`` nobody yet) and how the vehicles fly. The fleet
    oracle scores placements from here (:func:`fleet_episode_utility`)."""

    positions_m: np.ndarray
    association: np.ndarray | None
    flight: Flight

    @classmethod
    def at(
        cls,
        positions_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> FleetStart:
        """The start of a fleet at ``positions_m`` (K, 3; any array-like), as a ``place_from``
        gets it: ``association`` ``None`` for none yet, ``flight`` ``None`` for the default."""
        return cls(np.asarray(positions_m, dtype=float), association, flight or Flight())

    def state(self, batch: int, n_users: int) -> FleetState | None:
        """The fleet state each of ``batch`` episodes starts from (fresh queues)."""
        if self.association is None:
            return None
        association = np.asarray(self.association, dtype=np.int64)
        if association.shape != (n_users,):
            raise InputError(
                f"association: must hold one AP per user ({n_users}), got {association.shape}"
            )
        empty = FleetState.empty(batch, n_users)
        return FleetState(empty.queues, np.repeat(association[None], batch, axis=0),
                          empty.handovers)  # fmt: skip


def _take(state: FleetState, keep: np.ndarray) -> FleetState:
    return FleetState(
        state.queues.map(lambda a: a[keep]),
        state.association[keep],
        state.handovers[keep],
    )


FLEET_ORACLE = "fleet-oracle"
"""The fleet oracle's name, to evaluate (``tupa eval --uavs K``) and to serve."""


@dataclass
class FleetOracle:
    """The search oracle as a fleet placement (``name = "fleet-oracle"``): ``place(users)``
    gives (K, 3). ``network`` and ``config.episode_steps``/``step_s`` must be the evaluation's."""

    fleet: FleetConfig = field(default_factory=FleetConfig)
    area: AreaConfig = field(default_factory=AreaConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    config: FleetOracleConfig = field(default_factory=FleetOracleConfig)
    candidates_m: np.ndarray | None = None  # a UAV's candidate positions; None: coarse grid
    name: str = "fleet-oracle"

    def __post_init__(self) -> None:
        self.model = FleetModel(self.fleet, self.network, self.area, self.utility)
        self._restricted = self.candidates_m is not None
        if self.candidates_m is None:
            self.candidates_m = _coarse_grid(self.area, self.config.screen_stride)
        self.candidates_m = clip_to_volume(np.asarray(self.candidates_m, dtype=float), self.area)
        stride = self.config.pair_stride
        if self._restricted and len(self.candidates_m) <= _PAIR_GRID_MAX:
            self._pair_grid = self.candidates_m
        else:
            self._pair_grid = _coarse_grid(self.area, max(stride, 1))
        self._starts = (
            KMeansPlacement(self.fleet.n_uavs, self.area, False, self.fleet.separation_m),
            KMeansPlacement(self.fleet.n_uavs, self.area, True, self.fleet.separation_m),
        )

    def place(self, users: UsersLike) -> np.ndarray:
        return self.search(users).positions_m

    def place_from(
        self,
        users: UsersLike,
        positions_m: np.ndarray,
        association: np.ndarray | None = None,
        flight: Flight | None = None,
    ) -> np.ndarray:
        """:meth:`place` for a fleet that is at ``positions_m`` (K, 3) with the users on
        ``association`` (U,; ``None``: on none yet) and flies as ``flight`` (the world's
        default): the placement that scores best flown from there (:meth:`search`)."""
        return self.search(users, FleetStart.at(positions_m, association, flight)).positions_m

    def score(
        self,
        fleets_m: np.ndarray,
        users: UsersLike,
        steps: int | None = None,
        start: FleetStart | None = None,
    ) -> np.ndarray:
        """Episode scores (B,) of placements (B, K, 3); ``steps`` defaults to the episode;
        with ``start``, flown from there (:func:`fleet_episode_utility`)."""
        c = self.config
        return fleet_episode_utility(
            self.model, fleets_m, users, steps or c.episode_steps, c.warmup_steps, c.step_s, start
        )

    def search(self, users: UsersLike, start: FleetStart | None = None) -> FleetOracleResult:
        """The search of the module doc. With ``start`` (a closed loop's fleet where it is),
        the placements it ends on from every start, the k-means placements among them, are
        scored again flown from there, and the best is refined on that score: a placement
        that wins only with a fresh association (users split between two close UAVs, which
        stations that joined one on the way, with the roaming hysteresis, do not follow) loses
        to one that holds once flown."""
        c = self.config
        starts = [self._snap(s.place(users)) for s in self._starts] + self._random_starts(users)
        start_scores = self.score(np.stack(starts), users)
        simulated = len(starts)
        best_m, best = starts[0], -np.inf
        ends = list(starts[:2])  # the k-means placements, as they are
        for begin, score in zip(starts, start_scores, strict=True):
            position, value, n = self._descend(begin, float(score), users)
            simulated += n
            if c.refine:
                position, value, n = self._refine(position, value, users)
                simulated += n
            ends.append(position)
            if value > best + c.improvement_tol:
                best_m, best = position, value
        if c.pair_stride > 0 and self.fleet.n_uavs > 1:
            best_m, best, n = self._pairs(best_m, best, users)
            simulated += n
            ends.append(best_m)
        start_best = float(np.max(start_scores))
        if start is not None:
            # Flown as a controller flies them: each vehicle to the target nearest in total.
            ends = [assign_targets(start.positions_m, end) for end in ends]
            flown = self.score(np.stack(ends), users, start=start)
            simulated += len(ends)
            start_best = float(np.max(flown[:2]))
            winner = int(np.argmax(flown))
            best_m, best = ends[winner], float(flown[winner])
            if c.refine:
                best_m, best, n = self._refine(best_m, best, users, start)
                simulated += n
        final = enforce_separation(best_m, self.fleet.separation_m, self.area)
        if not np.array_equal(final, best_m):  # never expected: candidates are separated
            best = float(self.score(final[None], users, start=start)[0])
            simulated += 1
        return FleetOracleResult(final, float(best), start_best, simulated)

    def _random_starts(self, users: UsersLike) -> list[np.ndarray]:
        """``restarts`` starts from ``default_rng(seed)``, alternately K users drawn by load
        (a UAV above each, lowest level) and K distinct candidate positions drawn uniformly."""
        c, area = self.config, self.area
        grid = self.candidates_m
        assert grid is not None
        rng = np.random.default_rng(c.seed)
        xy = np.asarray(users.users_xy_m, dtype=float)
        load = np.asarray(users.load_bps, dtype=float)
        p = load / load.sum() if load.sum() > 0 else None
        k = self.fleet.n_uavs
        out = []
        for restart in range(c.restarts):
            if restart % 2 == 0:
                picks = rng.choice(len(xy), size=k, replace=len(xy) < k, p=p)
                start = np.column_stack([xy[picks], np.full(k, area.z_min_m)])
            else:
                start = grid[rng.choice(len(grid), size=k, replace=len(grid) < k)]
            out.append(self._snap(enforce_separation(start, self.fleet.separation_m, area)))
        return out

    def _snap(self, start: np.ndarray) -> np.ndarray:
        """With candidates given (a restricted search), each UAV of a start moved to the
        nearest candidate at least ``separation_m`` from those already moved (in UAV order);
        otherwise the start as it is."""
        if not self._restricted:
            return start
        grid = self.candidates_m
        assert grid is not None
        out = start.copy()
        taken: list[np.ndarray] = []
        for k, point in enumerate(start):
            order = np.argsort(np.sum((grid - point) ** 2, axis=1), kind="stable")
            for i in order:
                if all(np.linalg.norm(grid[i] - q) >= self.fleet.separation_m for q in taken):
                    out[k] = grid[i]
                    taken.append(grid[i])
                    break
        return out

    def _descend(
        self, position: np.ndarray, score: float, users: UsersLike
    ) -> tuple[np.ndarray, float, int]:
        """Coordinate descent: each UAV over the candidate grid, the others held."""
        c = self.config
        grid = self.candidates_m
        assert grid is not None
        simulated = 0
        for _ in range(c.sweeps):
            moved = False
            for k in range(self.fleet.n_uavs):
                fleets = np.repeat(position[None], len(grid), axis=0)
                fleets[:, k] = grid
                ok = separated(fleets, self.fleet.separation_m)
                fleets = fleets[ok]
                if not len(fleets):
                    continue
                screen = self.score(fleets, users, c.screen_steps)
                top = np.argsort(-screen, kind="stable")[: c.top_k]
                full = self.score(fleets[top], users)
                simulated += len(top)
                winner = int(np.argmax(full))
                if full[winner] > score + c.improvement_tol:
                    position, score, moved = fleets[top[winner]].copy(), float(full[winner]), True
            if not moved:
                break
        return position, score, simulated

    def _pairs(
        self, position: np.ndarray, score: float, users: UsersLike
    ) -> tuple[np.ndarray, float, int]:
        """Joint moves of two UAVs: for each pair, every placement of the two on the pair grid
        (the others held) screened, the best ``top_k`` scored; the best improvement is taken
        and coordinate descent (and refinement) resumes from it, at most ``sweeps`` times."""
        c = self.config
        grid = self._pair_grid
        i_idx, j_idx = np.triu_indices(len(grid), k=1)
        simulated = 0
        for _ in range(c.sweeps):
            best_fleet, best_value = None, score
            for i in range(self.fleet.n_uavs):
                for j in range(i + 1, self.fleet.n_uavs):
                    fleets = np.repeat(position[None], len(i_idx), axis=0)
                    fleets[:, i], fleets[:, j] = grid[i_idx], grid[j_idx]
                    fleets = fleets[separated(fleets, self.fleet.separation_m)]
                    if not len(fleets):
                        continue
                    screen = np.concatenate(
                        [
                            self.score(chunk, users, c.screen_steps)
                            for chunk in np.array_split(fleets, max(1, len(fleets) // 2000))
                        ]
                    )
                    top = np.argsort(-screen, kind="stable")[: c.top_k]
                    full = self.score(fleets[top], users)
                    simulated += len(top)
                    winner = int(np.argmax(full))
                    if full[winner] > best_value + c.improvement_tol:
                        best_fleet, best_value = fleets[top[winner]].copy(), float(full[winner])
            if best_fleet is None:
                break
            position, score, n = self._descend(best_fleet, best_value, users)
            simulated += n
            if c.refine:
                position, score, n = self._refine(position, score, users)
                simulated += n
        return position, score, simulated

    def _refine(
        self, position: np.ndarray, score: float, users: UsersLike, start: FleetStart | None = None
    ) -> tuple[np.ndarray, float, int]:
        """Compass pattern search: every UAV's six neighbours at the step, the best move
        (scored flown from ``start`` when given)."""
        c = self.config
        k = self.fleet.n_uavs
        step = c.initial_step_m or self.area.zone_m / 2.0
        simulated = 0
        for _ in range(c.max_refine_iterations):
            if step < c.min_step_m:
                break
            fleets = np.repeat(position[None], 6 * k, axis=0)
            for i in range(k):
                fleets[6 * i : 6 * i + 6, i] = clip_to_volume(
                    position[i] + step * _DIRECTIONS, self.area
                )
            fleets = fleets[separated(fleets, self.fleet.separation_m)]
            if start is not None:  # scored as flown: each vehicle to the target least travel gives
                fleets = np.array([assign_targets(start.positions_m, f) for f in fleets])
            values = self.score(fleets, users, start=start) if len(fleets) else np.empty(0)
            simulated += len(fleets)
            if len(values) and values.max() > score + c.improvement_tol:
                winner = int(np.argmax(values))
                position, score = fleets[winner].copy(), float(values[winner])
            else:
                step /= 2.0
        return position, score, simulated


def _coarse_grid(area: AreaConfig, stride: int) -> np.ndarray:
    """Every ``stride``-th zone centre in x and y (centred in the area), every altitude level."""
    return coarse_grid_positions_m(area, stride)
