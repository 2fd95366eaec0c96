"""The oracle: the best static UAV position for a scenario, found with the network model itself.

It knows everything a policy cannot (the model, in its deterministic expected mode) and is the
upper bound every static placement policy is measured against. A position's *score* is what the
evaluation measures for a policy that holds it: the mean network utility over an episode of
``episode_steps`` steps at that position, queues carried from step to step, after the
environment's reset step at the same position (simulated, not scored) — see
:func:`episode_utility`. With FqCoDel the backlog of an underserved user keeps growing, so a
position's score depends on the episode length; the oracle optimises the length it is given.

The search, in three stages (:class:`OracleConfig` holds the knobs):

1. **Screen** every zone centre at every altitude level (20 × 20 × 4 = 1600 positions by
   default) over a short horizon of ``screen_steps`` steps, all positions in one batch per step,
   by successive halving: after the warm-up step only the best ``screen_keep[0]`` (600) go on,
   after the first scored step the best ``screen_keep[1]`` (200). The screen's ``top_k`` are
   those of the whole grid screened to the end (checked on 1,560 generated scenarios, 1 to 20
   users, both queueings: the whole grid's top 32 ranked at worst 256th after the warm-up step
   and 82nd after the first scored step).
2. **Score** the ``top_k`` best of the screen over the full episode, together with the
   ``min-distance`` and ``load-weighted`` positions (so the oracle is never beaten by them on the
   model it optimises: they are candidates, not just rivals), and, speculatively, the pattern
   search's first neighbours of the screen's best (nearly always the refinement's start).
3. **Refine** the best ``refine_starts`` candidates with a compass pattern search: try ± step
   along x, y and z (clipped to the volume), move to the best neighbour while it improves the
   full-episode score, halve the step when none does, stop below ``min_step_m``.

Every episode stops simulating a position once its queues settle (:func:`episode_utility`:
a step that leaves the queue state unchanged repeats forever, exactly), which is where most of
the time went. That and the speculative neighbours change no result; with the staged screen as
well, the search returned bit for bit what it returned before on every scenario compared (1,000
with 3 users, 200 each with 8 and 12, 200 with ``mac-only`` queueing).

**Tracking** (:meth:`OraclePlacement.track`) re-optimises every decision of a closed loop whose
users move a little between decisions, from the last answer: a pattern search from
``previous_m`` (first step ``track_step_m``, a quarter zone), scored in one batch with the
baselines and the best ``track_top_k`` of a coarse screen (every ``track_screen_stride``-th zone,
100 positions); a full search every ``track_full_every`` calls, and whenever one of those rivals
beats the refined position by more than ``track_jump_tol`` (the optimum moved elsewhere). An
exact-input cache answers a repeated input (static users) without simulating anything. Users
walking 1.5 m per decision, against a full search at every step: 3 users, never more than 4e-5
below it (600 decisions); 8 and 12 users, a few decisions in a hundred up to 4e-3 below it and
others above it (the pattern search keeps climbing from where it was), 3e-5 to 8e-5 above it on
average.

Positions and scores are all numpy; the per-step work is the model's compiled kernel. Timings in
ms on one core, ``python -m policies.placements.oracle --users U`` (500 generated scenarios, seed 3;
tracking on 50 of them, 20 decisions each, users walking 1.5 m per decision), on a shared 2-core
machine (a few ms of noise); "before" is the search without these shortcuts, timed interleaved with
it:

=====  ====================  ======================  ==================  ===============
users  search() median, p95  before: median, p95     track() cheap path  track() cached
=====  ====================  ======================  ==================  ===============
3      4.4, 17               20 to 24, 25 to 37      1.6, 5.9            0.01
8      25, 67                57 to 74, 85 to 125     5.8, 28             0.01
12     57, 89                86 to 89, 110 to 136    20, 36              0.02
=====  ====================  ======================  ==================  ===============

The slow tail is scenarios no position serves fully: their queues never settle (FqCoDel's drop
count keeps growing), so every episode runs all its steps, one model call per step.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from policies.interface import UsersLike
from policies.placements.baselines import MinDistancePlacement
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.geometry import clip_to_volume
from sim.network import NetworkModel, QueueState
from sim.utility import network_utility

# The compass directions of the pattern search: ±x, ±y, ±z.
_DIRECTIONS = np.concatenate([np.eye(3), -np.eye(3)])


@dataclass(frozen=True)
class OracleConfig:
    """Knobs of the oracle's search; the defaults are the evaluation's episode (100 × 1 s)."""

    episode_steps: int = 100  # steps scored per episode (the evaluation's T)
    step_s: float = 1.0  # seconds per step (the evaluation's S)
    warmup_steps: int = 1  # unscored steps at the position first (the environment's reset step)
    screen_steps: int = 3  # horizon of the grid screen
    # Successive halving of the screen: after the warm-up, and after each scored step, only the
    # best screen_keep[i] so far go on (i scored steps; their mean, the warm-up's for i = 0).
    screen_keep: tuple[int, ...] = (600, 200)
    top_k: int = 32  # screened positions scored over the full episode
    include_baselines: bool = True  # also score the min-distance and load-weighted positions
    refine_starts: int = 1  # best candidates refined by pattern search (0: no refinement)
    initial_step_m: float | None = None  # first pattern-search step; None: half a zone
    min_step_m: float = 1.0  # stop refining when the step falls below this
    max_refine_iterations: int = 40  # bound on pattern-search iterations
    improvement_tol: float = 1e-9  # a move must raise the score by more than this
    # Tracking (:meth:`OraclePlacement.track`).
    track_full_every: int = 10  # a full search every this many (uncached) calls; 1: always
    track_screen_stride: int = 4  # the cheap path screens every this many zones in x and y
    track_top_k: int = 4  # of that screen, positions scored over the full episode
    track_step_m: float | None = None  # first pattern-search step of the cheap path; None: zone/4
    track_jump_tol: float = 1e-6  # a rival better than the refined position by more: full search
    track_cache_size: int = 16  # inputs (users and loads) whose result is remembered; 0: none

    def __post_init__(self) -> None:
        for name in (
            "episode_steps",
            "screen_steps",
            "top_k",
            "track_full_every",
            "track_screen_stride",
            "track_top_k",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        object.__setattr__(self, "screen_keep", tuple(int(k) for k in self.screen_keep))
        if any(k < 1 for k in self.screen_keep):
            raise ValueError(f"screen_keep: every entry must be >= 1, got {self.screen_keep}")
        for name in (
            "warmup_steps",
            "refine_starts",
            "max_refine_iterations",
            "track_cache_size",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not self.step_s > 0:
            raise ValueError(f"step_s: must be > 0, got {self.step_s}")
        if not self.min_step_m > 0:
            raise ValueError(f"min_step_m: must be > 0, got {self.min_step_m}")
        for name in ("initial_step_m", "track_step_m"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name}: must be > 0 or None, got {value}")
        for name in ("improvement_tol", "track_jump_tol"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class OracleResult:
    """Outcome of one search: the best position (3,) in metres, its expected episode utility,
    the best grid position and its utility (before refinement), and the number of positions
    whose full episode was simulated (the screen not counted). ``source`` says how it was
    found: ``"search"`` (:meth:`OraclePlacement.search`, or a tracking call that ran one),
    ``"track"`` (the tracking's cheap re-search) or ``"cache"`` (a repeated input; the fields
    are the first answer's)."""

    position_m: np.ndarray
    utility: float
    grid_position_m: np.ndarray
    grid_utility: float
    episodes_simulated: int
    source: Literal["search", "track", "cache"] = "search"


def episode_utility(
    model: NetworkModel,
    positions_m: np.ndarray,
    scenario: UsersLike,
    steps: int,
    warmup_steps: int = 1,
    step_s: float = 1.0,
    utility: UtilityConfig = UtilityConfig(),
) -> np.ndarray:
    """Mean utility (B,) of holding each of ``positions_m`` (B, 3) for an episode, expected mode.

    From empty queues, ``warmup_steps`` unscored steps, then ``steps`` scored steps, queues
    carried throughout; all positions advance together, one batched model call per step. This
    is exactly the environment's episode (reset at the position, then ``steps`` steps there)
    with ``EnvConfig(expected=True)``.

    A position whose step leaves its queue state exactly as it found it has reached a fixed
    point: the model is deterministic, so every later step repeats that step's metrics, and its
    remaining steps are filled in without being simulated (exact, not an approximation: a
    well-placed UAV drains its queues at once, so most good positions settle in a step or two,
    while a backlog that keeps growing never settles).
    """
    episodes = _Episodes(model, positions_m, scenario, warmup_steps + steps, step_s)
    episodes.advance(warmup_steps + steps)
    return episodes.mean_utility(warmup_steps, utility)


# Steps after which :class:`_Episodes` looks for settled queues: every early step (where
# positions settle, if ever), then sparser (a check after the fact only re-simulates steps that
# were identical anyway).
_SETTLE_CHECKS = frozenset(
    [*range(12), 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 112, 128, 160, 192, 224]
) | frozenset(range(256, 1 << 20, 64))


class _Episodes:
    """Episodes of a batch of positions from empty queues, advanced together in stages.

    Metrics are kept for every step of the ``horizon`` (arrays (T, B, U)); a position that
    settles (see :func:`episode_utility`) gets its remaining steps filled in at once and leaves
    the batch, and :meth:`keep` drops positions no longer wanted, so later stages simulate only
    the rest.
    """

    def __init__(
        self,
        model: NetworkModel,
        positions_m: np.ndarray,
        scenario: UsersLike,
        horizon: int,
        step_s: float,
    ) -> None:
        self.model, self.step_s, self.horizon = model, step_s, horizon
        self.positions = np.atleast_2d(np.asarray(positions_m, dtype=float))
        self.users, self.load = scenario.users_xy_m, np.asarray(scenario.load_bps, dtype=float)
        shape = (horizon, self.positions.shape[0], len(self.load))
        self.throughput, self.delay, self.plr = np.empty(shape), np.empty(shape), np.empty(shape)
        self.index = np.arange(shape[1])  # the positions still simulated
        self.live: slice | np.ndarray = slice(None)  # the same, indexing the metric arrays
        self.queues = QueueState.empty(*shape[1:])
        self.t = 0  # steps simulated

    def advance(self, until: int) -> None:
        """Simulate the live positions up to step ``until`` (exclusive)."""
        model, users, load, step_s = self.model, self.users, self.load, self.step_s
        positions, index, live = self.positions, self.index, self.live
        queues = self.queues
        last = self.horizon - 1
        t = self.t
        while t < until and len(index):
            result = model.step(positions, users, load, queues, None, step_s)
            throughput, delay, plr = result.throughput_bps, result.delay_s, result.plr
            self.throughput[t, live], self.delay[t, live], self.plr[t, live] = (
                throughput,
                delay,
                plr,
            )
            new_queues = result.state
            if t < last and t in _SETTLE_CHECKS:
                settled = new_queues.same_as(queues)
                if settled.any():
                    # A fixed point: this step's metrics stand for every step left.
                    done = index[settled]
                    self.throughput[t + 1 :, done] = throughput[settled]
                    self.delay[t + 1 :, done] = delay[settled]
                    self.plr[t + 1 :, done] = plr[settled]
                    keep = ~settled
                    index = live = index[keep]
                    positions = positions[keep]
                    new_queues = new_queues.map(lambda a, keep=keep: a[keep])
            queues = new_queues
            t += 1
        self.positions, self.index, self.live = positions, index, live
        self.queues = queues
        self.t = until

    def keep(self, wanted: np.ndarray) -> None:
        """Simulate from now on only the positions ``wanted`` (indices into the batch)."""
        mask = np.isin(self.index, wanted)
        self.index = self.live = self.index[mask]
        self.positions = self.positions[mask]
        self.queues = self.queues.map(lambda a: a[mask])

    def mean_utility(
        self, warmup_steps: int, utility: UtilityConfig, rows: np.ndarray | slice = slice(None)
    ) -> np.ndarray:
        """Mean utility of the steps from ``warmup_steps`` to those simulated, per position
        (of ``rows`` only, if given)."""
        scored = slice(warmup_steps, self.t)
        values = network_utility(
            self.throughput[scored, rows],
            self.delay[scored, rows],
            self.plr[scored, rows],
            self.load,
            utility,
        )
        return values.mean(axis=0)


@dataclass
class OraclePlacement:
    """The oracle as a :class:`~policies.interface.Placement` (``name = "oracle"``).

    ``network`` must be the configuration the evaluation runs (queueing in particular), and
    ``config.episode_steps``/``step_s`` its episode, or the oracle optimises a different game.
    """

    area: AreaConfig = field(default_factory=AreaConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    config: OracleConfig = field(default_factory=OracleConfig)
    name: str = "oracle"

    def __post_init__(self) -> None:
        self.model = NetworkModel(self.network, self.area)
        self._grid_m = self.area.grid_positions_m()
        self._coarse_grid_m = coarse_grid_positions_m(self.area, self.config.track_screen_stride)
        self._baselines = (
            MinDistancePlacement(self.area),
            MinDistancePlacement(self.area, load_weighted=True),
        )
        self.reset_tracking()

    def place(self, scenario: UsersLike) -> np.ndarray:
        return self.search(scenario).position_m

    def _score(self, positions_m: np.ndarray, scenario: UsersLike, steps: int) -> np.ndarray:
        c = self.config
        return episode_utility(
            self.model, positions_m, scenario, steps, c.warmup_steps, c.step_s, self.utility
        )

    def _screen(self, positions_m: np.ndarray, scenario: UsersLike) -> np.ndarray:
        """Short-horizon (``screen_steps``) scores of ``positions_m``, by successive halving:
        after the warm-up and after each scored step only the best ``screen_keep[i]`` so far
        go on; those dropped score -inf."""
        c = self.config
        horizon = c.warmup_steps + c.screen_steps
        episodes = _Episodes(self.model, positions_m, scenario, horizon, c.step_s)
        kept = np.arange(len(positions_m))
        for scored, keep in enumerate(c.screen_keep):
            stop = c.warmup_steps + scored
            if not (0 < stop < horizon and keep < len(kept)):
                continue
            episodes.advance(stop)
            so_far = episodes.mean_utility(c.warmup_steps if scored else 0, self.utility, kept)
            kept = np.sort(kept[np.argsort(-so_far, kind="stable")[:keep]])
            episodes.keep(kept)
        episodes.advance(horizon)
        screen = np.full(len(positions_m), -np.inf)
        screen[kept] = episodes.mean_utility(c.warmup_steps, self.utility, kept)
        return screen

    def _baseline_positions(self, scenario: UsersLike) -> np.ndarray:
        return np.stack([p.place(scenario) for p in self._baselines])

    def search(self, scenario: UsersLike) -> OracleResult:
        """Screen the grid, score the best over the full episode, refine; see the module doc."""
        c = self.config
        grid = self._grid_m

        # 1. Screen. A stable sort keeps ties in grid order, so the search is deterministic.
        screen = self._screen(grid, scenario)
        top = np.argsort(-screen, kind="stable")[: min(c.top_k, len(grid))]
        n_grid = len(top)
        candidates = [grid[top]]
        if c.include_baselines:
            candidates.append(self._baseline_positions(scenario))
        candidates_m = np.concatenate(candidates)
        n_candidates = len(candidates_m)
        # The screen's best is nearly always the full episode's best too, so refinement's first
        # neighbours of it are scored along with the candidates: one batch fewer.
        refine = c.refine_starts > 0 and c.max_refine_iterations > 0
        speculate = refine and c.refine_starts == 1 and self._first_step_m() >= c.min_step_m
        if speculate:
            ring_m = self._ring(candidates_m[:1], self._first_step_m())[0]
            candidates_m = np.concatenate([candidates_m, ring_m])

        # 2. Score the candidates over the full episode.
        scores = self._score(candidates_m, scenario, c.episode_steps)
        simulated = len(candidates_m)
        scores, ring_scores = scores[:n_candidates], scores[n_candidates:]
        candidates_m = candidates_m[:n_candidates]
        grid_best = int(np.argmax(scores[:n_grid]))
        best = int(np.argmax(scores))
        best_m, best_score = candidates_m[best], float(scores[best])

        # 3. Refine the best few, all starts batched together.
        if refine:
            order = np.argsort(-scores, kind="stable")[: c.refine_starts]
            first = ring_scores[None] if speculate and order[0] == 0 else None
            refined_m, refined, n = self._refine(
                candidates_m[order], scores[order], scenario, first_values=first
            )
            simulated += n
            winner = int(np.argmax(refined))
            if refined[winner] > best_score:
                best_m, best_score = refined_m[winner], float(refined[winner])
        return OracleResult(
            position_m=best_m.copy(),
            utility=best_score,
            grid_position_m=grid[top[grid_best]].copy(),
            grid_utility=float(scores[grid_best]),
            episodes_simulated=simulated,
        )

    # ----------------------------------------------------------------------------------------
    # Tracking

    def reset_tracking(self) -> None:
        """Forget the tracking state: the input cache and the count toward the next full
        search (a new episode, or users that jumped)."""
        self._track_cache: OrderedDict[bytes, OracleResult] = OrderedDict()
        self._track_calls = 0  # uncached calls since the last full search

    def track(self, scenario: UsersLike, previous_m: np.ndarray | None = None) -> np.ndarray:
        """The best position for ``scenario`` (3,), re-optimised from ``previous_m``.

        For a closed loop that asks every step while users move a little; see
        :meth:`track_search` and the module doc.
        """
        return self.track_search(scenario, previous_m).position_m.copy()

    def track_search(
        self, scenario: UsersLike, previous_m: np.ndarray | None = None
    ) -> OracleResult:
        """:meth:`track`, with the score and how it was found (``OracleResult.source``).

        * Users and loads seen before (exactly, among the last ``track_cache_size`` inputs):
          the remembered result, ``previous_m`` ignored.
        * No ``previous_m``, or every ``track_full_every``-th uncached call: a full
          :meth:`search` (keeping the cheap result where the cheap path ran and did better).
        * Otherwise the cheap path: a pattern search from ``previous_m`` (first step
          ``track_step_m``), and, scored with it, the min-distance and load-weighted positions
          and the best ``track_top_k`` of a coarse screen (every ``track_screen_stride``-th
          zone), all in one batch. The best of them all is the answer, unless one of those
          rivals beats the refined position by more than ``track_jump_tol``: the optimum has
          moved elsewhere, and a full search runs instead.

        ``previous_m`` is the last answer (or where the UAV is); outside the volume, it is
        clipped into it. The answer is never worse than the baselines' positions on the model.
        """
        c = self.config
        if previous_m is not None:
            previous_m = np.asarray(previous_m, dtype=float)
            if previous_m.shape != (3,) or not np.all(np.isfinite(previous_m)):
                raise ValueError(f"previous_m: must be 3 finite numbers, got {previous_m!r}")
        key = _input_key(scenario)
        cached = self._track_cache.get(key)
        if cached is not None:
            self._track_cache.move_to_end(key)
            return _copied(cached, source="cache")
        self._track_calls += 1
        cheap = None
        if previous_m is not None and self._track_calls < c.track_full_every:
            cheap = self._track_cheap(scenario, previous_m)
        if cheap is None or cheap.source != "track":
            result = self.search(scenario)
            self._track_calls = 0
            if cheap is not None:
                if cheap.utility > result.utility:
                    result = replace(cheap, source="search")
                result = replace(
                    result, episodes_simulated=result.episodes_simulated + cheap.episodes_simulated
                )
        else:
            result = cheap
        if c.track_cache_size > 0:
            self._track_cache[key] = _copied(result)
            while len(self._track_cache) > c.track_cache_size:
                self._track_cache.popitem(last=False)
        return result

    def _track_cheap(self, scenario: UsersLike, previous_m: np.ndarray) -> OracleResult:
        """The cheap re-search; ``source="search"`` on the result asks for a full one."""
        c = self.config
        start_m = clip_to_volume(previous_m, self.area)
        coarse = self._coarse_grid_m
        screen = self._screen(coarse, scenario)
        top = np.argsort(-screen, kind="stable")[: min(c.track_top_k, len(coarse))]
        candidates = [start_m[None], coarse[top]]
        if c.include_baselines:
            candidates.append(self._baseline_positions(scenario))
        candidates_m = np.concatenate(candidates)
        n_candidates = len(candidates_m)
        # The pattern search's first neighbours are scored with the candidates: one batch.
        step_m = c.track_step_m or self.area.zone_m / 4.0
        refine = c.max_refine_iterations > 0 and step_m >= c.min_step_m
        ring_m = self._ring(start_m[None], step_m)[0] if refine else np.empty((0, 3))
        scores = self._score(np.concatenate([candidates_m, ring_m]), scenario, c.episode_steps)
        simulated = len(scores)
        scores, ring_scores = scores[:n_candidates], scores[n_candidates:]
        position_m, score = start_m, float(scores[0])
        if refine:
            refined_m, refined, n = self._refine(
                start_m[None], scores[:1], scenario, step_m, first_values=ring_scores[None]
            )
            simulated += n
            position_m, score = refined_m[0], float(refined[0])
        # The rivals: the coarse screen's best and the baselines. One far better than the
        # refined position means the optimum has moved elsewhere: ask for a full search.
        rivals = scores[1:]
        rival = int(np.argmax(rivals))
        source: Literal["search", "track"] = "track"
        if rivals[rival] > score + c.track_jump_tol:
            source = "search"
        elif rivals[rival] > score:
            position_m, score = candidates_m[1 + rival], float(rivals[rival])
        grid_best = int(np.argmax(rivals[: len(top)]))
        return OracleResult(
            position_m=position_m.copy(),
            utility=score,
            grid_position_m=coarse[top[grid_best]].copy(),
            grid_utility=float(rivals[grid_best]),
            episodes_simulated=simulated,
            source=source,
        )

    # ----------------------------------------------------------------------------------------
    # Refinement

    def _first_step_m(self, initial_step_m: float | None = None) -> float:
        return initial_step_m or self.config.initial_step_m or self.area.zone_m / 2.0

    def _ring(self, positions_m: np.ndarray, step_m: np.ndarray | float) -> np.ndarray:
        """(S, 6, 3) compass neighbours of each of ``positions_m`` (S, 3) at ``step_m`` (scalar
        or (S,)), kept inside the volume."""
        step = np.broadcast_to(np.asarray(step_m, dtype=float), (len(positions_m),))
        return clip_to_volume(
            positions_m[:, None, :] + step[:, None, None] * _DIRECTIONS, self.area
        )

    def _refine(
        self,
        starts_m: np.ndarray,
        start_scores: np.ndarray,
        scenario: UsersLike,
        initial_step_m: float | None = None,
        first_values: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Compass pattern search from each start (S, 3); returns positions, scores and the
        number of positions simulated. ``first_values`` (S, 6), if given, are the scores of
        the first iteration's neighbours (:meth:`_ring` of the starts at the first step),
        already simulated by the caller along with other positions."""
        c = self.config
        position = starts_m.astype(float).copy()
        score = start_scores.astype(float).copy()
        step_m = np.full(len(position), self._first_step_m(initial_step_m))
        simulated = 0
        for iteration in range(c.max_refine_iterations):
            active = np.flatnonzero(step_m >= c.min_step_m)
            if not len(active):
                break
            neighbours = self._ring(position[active], step_m[active])  # (A, 6, 3)
            if iteration == 0 and first_values is not None:
                values = first_values
            else:
                flat = neighbours.reshape(-1, 3)
                values = self._score(flat, scenario, c.episode_steps).reshape(len(active), 6)
                simulated += len(flat)
            best = np.argmax(values, axis=1)
            best_values = values[np.arange(len(active)), best]
            improved = best_values > score[active] + c.improvement_tol
            moved = active[improved]
            position[moved] = neighbours[improved, best[improved]]
            score[moved] = best_values[improved]
            step_m[active[~improved]] /= 2.0
        return position, score, simulated


def coarse_grid_positions_m(area: AreaConfig, stride: int) -> np.ndarray:
    """Every ``stride``-th zone centre in x and y (centred in the area), at every altitude
    level: the tracking's screen, (n_x' * n_y' * n_z, 3), x-major like the full grid."""

    def every(centres: np.ndarray) -> np.ndarray:
        span = (len(centres) - 1) // stride * stride  # from the first to the last one taken
        return centres[(len(centres) - 1 - span) // 2 :: stride]

    gx, gy, gz = np.meshgrid(
        every(area.zone_centres_x_m()),
        every(area.zone_centres_y_m()),
        area.altitude_levels_m(),
        indexing="ij",
    )
    return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)


def _copied(result: OracleResult, **changes: object) -> OracleResult:
    """``result`` with its own copies of the arrays (a cached result must not be shared)."""
    return replace(
        result,
        position_m=result.position_m.copy(),
        grid_position_m=result.grid_position_m.copy(),
        **changes,
    )


def _input_key(scenario: UsersLike) -> bytes:
    """Exact identity of a scenario's users and loads (positions, loads, their count)."""
    users = np.ascontiguousarray(scenario.users_xy_m, dtype=float)
    load = np.ascontiguousarray(scenario.load_bps, dtype=float)
    return len(load).to_bytes(4, "little") + users.tobytes() + load.tobytes()


def _benchmark(argv: list[str] | None = None) -> None:
    """Time :meth:`OraclePlacement.search` and :meth:`OraclePlacement.track` on generated scenarios
    (``python -m policies.placements.oracle --help``); the module doc's figures come from it."""
    import argparse
    import time

    from sim.scenarios import Scenario, generate_scenarios

    parser = argparse.ArgumentParser(
        prog="python -m policies.placements.oracle", description=__doc__, allow_abbrev=False
    )
    parser.add_argument("--scenarios", type=int, default=500)
    parser.add_argument("--users", type=int, default=3)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--track-steps", type=int, default=20, help="tracked steps per scenario")
    parser.add_argument("--walk-m", type=float, default=1.5, help="users' move per step")
    args = parser.parse_args(argv)

    oracle = OraclePlacement()
    scenarios = generate_scenarios(args.scenarios, args.users, seed=args.seed)
    oracle.search(scenarios[0])  # compiled kernels load from numba's cache
    rng = np.random.default_rng(args.seed)
    times: dict[str, list[float]] = {"search()": [], "search": [], "track": [], "cache": []}
    for scenario in scenarios:
        start = time.perf_counter()
        oracle.search(scenario)
        times["search()"].append(time.perf_counter() - start)
    for scenario in scenarios[: max(1, args.scenarios // 10)]:
        oracle.reset_tracking()
        users_xy_m, previous_m = np.array(scenario.users_xy_m), None
        for _ in range(args.track_steps):
            moved = Scenario(scenario.id, users_xy_m, scenario.load_bps)
            for _ in range(2):  # the second call repeats the input: the cache answers
                start = time.perf_counter()
                result = oracle.track_search(moved, previous_m)
                times[result.source].append(time.perf_counter() - start)
            previous_m = result.position_m
            heading = rng.uniform(0.0, 2.0 * np.pi, len(users_xy_m))
            step_m = args.walk_m * np.stack([np.cos(heading), np.sin(heading)], axis=1)
            area = oracle.area
            users_xy_m = np.clip(users_xy_m + step_m, 0.0, [area.size_x_m, area.size_y_m])
    print(f"{args.users} users, {args.scenarios} scenarios (seed {args.seed}), times in ms:")
    labels = {
        "search": "track(), full search",
        "track": "track(), cheap path",
        "cache": "track(), cached",
    }
    for name, values in times.items():
        if values:
            ms = 1e3 * np.array(values)
            print(
                f"  {labels.get(name, name):22} n={len(ms):5d} median {np.median(ms):7.3f} "
                f"p95 {np.percentile(ms, 95):7.3f} max {ms.max():7.3f}"
            )


if __name__ == "__main__":
    _benchmark()
