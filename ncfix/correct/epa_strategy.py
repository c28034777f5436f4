"""The ``--strategy epa`` correction: tilt each colliding block along its GJK/EPA extraction vector, then ramp.

Four parts, in this order: the required tilts (``EpaModel.tilt`` until ``Episode.free`` accepts),
the ramps between them as offsets carried along the programmed path (``OffsetFrames``,
``fill_offsets``, ``keep_chain``), the verification rounds (tilt further, pin, give up), and the
orientation graph on the episodes the walk leaves colliding. Approximate by design: the walk is
greedy; every kept orientation passed the conservative checker.
Design: docs/correction.md, "The walk's four parts".
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from ncfix.config import EpaOptions, Options
from ncfix.correct.epa import VARIANTS, EpaModel, run_tilts
from ncfix.correct.solve import Episode, GraphStrategy, Solution
from ncfix.errors import ConfigError
from ncfix.geometry.cells import first_of_each_cell
from ncfix.geometry.frames import angle_between_deg, rotation_between, rotation_from_z

# The seed's second method (E recomputed each rotation, Lami's theorem) is the default: it bends
# around corners where the first E points into a second obstacle (tests/test_epa.py, corner case).
DEFAULT_VARIANT = EpaOptions.variant
# Rounds of "re-check the episode, tilt the failing levels further"; once a solution is kept, the
# rounds stop when it has not improved for PATIENCE rounds (a re-check of a long episode with
# beads costs seconds).
ROUNDS = 8
PATIENCE = 2
# Layouts (fill the offsets, test the ramp levels, fix the failing ones) over all rounds.
MAX_LAYOUTS = 4 * ROUNDS
# Times the blocks still colliding with a tilt are given up (left as programmed) and the rest laid
# out again, with this many more rounds each.
GIVEUPS = 2
GIVEUP_ROUNDS = 2
# Rounds of shrinking the step budgets where the measured steps exceed the limits.
BUDGET_ROUNDS = 6
# Times one layout may move a fixed level to settle a conflict before dropping it instead.
MAX_MOVES = 4
# Angles below this (radians) are zero: an offset this small is the programmed orientation.
_TINY_RAD = 1e-12
# Tilt walks run in step (``_searches``): each round tests up to 32 x 8 orientations in one call.
TILTS_IN_STEP = 32
# Budgets stay this far (degrees) under the limits, so float noise never crosses them.
_MARGIN_DEG = 1e-7


class EpaStrategy:
    """GJK/EPA tilts about the tip, ramped within the step limit (module doc).

    options : ``Options``: max_tilt Θ, max_step θ, resolution, and ``options.epa``
        (``EpaOptions``: the variant, the walk's step, CoACD's threshold and cache, the graph fallback).
    The hull model is built on the first ``solve`` (parts and head of the episode's checker) and
    kept: ``decompose_seconds``, ``cached`` and ``pieces_count`` describe it; ``episodes``,
    ``solve_seconds`` and ``last`` (stats of the last episode) are for benchmarks.
    """

    name = "epa"

    def __init__(self, options: Options) -> None:
        self.max_tilt = float(options.max_tilt)
        self.max_step = float(options.max_step)
        epa = options.epa
        self.variant = str(epa.variant)
        if self.variant not in VARIANTS:
            raise ConfigError(f"unknown EPA variant {self.variant!r}", fix=f"use one of: {', '.join(VARIANTS)}")
        self.step_deg = float(0.5 * float(options.resolution) if epa.step_deg is None else epa.step_deg)
        if not self.step_deg > 0:
            raise ConfigError(f"the EPA walk's step_deg must be above 0, not {self.step_deg:g}")
        # A level failing the re-check is tilted this much further per failure (degrees).
        self.bump_deg = 2.0 * self.step_deg
        self.threshold = float(epa.threshold)
        self.cache_dir = epa.cache_dir
        fallback = epa.graph_fallback
        if not isinstance(fallback, bool):
            raise ConfigError(f"the EPA graph_fallback has a bad value {fallback!r}", fix="use true or false")
        # The orientation graph for the episodes the walk leaves colliding (None: the walk alone).
        self.graph = GraphStrategy(options) if fallback else None
        self.graph_episodes = 0  # episodes the graph searched after the walk
        self.graph_kept = 0  # of those, the episodes whose answer is the graph's
        self.model: EpaModel | None = None
        self._model_of: int | None = None  # id of the checker the model was built from
        self.decompose_seconds = 0.0
        self.cached: bool | None = None
        self.pieces_count = 0
        self.episodes = 0
        self.solve_seconds = 0.0
        self.last: dict = {}

    def model_for(self, checker, report=None) -> EpaModel:
        """The hull model of this checker's parts and head, built once (CoACD cached on disk); a
        part decomposed now (not read from the cache) is noted in ``report`` with its time."""
        if self.model is None or self._model_of != id(checker):
            parts = [(p.name, p.mesh) for p in checker.parts]
            radius = float(checker.bead_radius_mm)
            # The beads' clearance is part of the checker's sphere radius; steer with the same.
            if radius > 0:
                radius += float(getattr(checker, "clearance_mm", 0.0))
            self.model = EpaModel(checker.head, parts, threshold=self.threshold, cache_dir=self.cache_dir,
                                  bead_radius_mm=radius, tip_allowance_mm=float(checker.tip_allowance_mm))
            self._model_of = id(checker)
            self.decompose_seconds += self.model.decompose_seconds
            self.cached = self.model.cached if self.cached is None else (self.cached and self.model.cached)
            self.pieces_count = self.model.pieces_count
            for name, result in self.model.decompositions:
                if report is not None and not result.cached:
                    report.notes.append(f"CoACD: {name} cut into {len(result.pieces)} convex pieces in "
                                        f"{result.seconds:.2f} s (not cached before this run)")
        return self.model

    def solve(self, ep: Episode) -> Solution:
        started = time.perf_counter()
        solver = _EpisodeSolver(self, self.model_for(ep.checker, ep.report), ep)
        solution = solver.run()
        left_by_epa = len(solution.unresolved)
        by_graph = False
        if solution.unresolved and self.graph is not None:
            # The walk is greedy: where it leaves blocks colliding, the orientation graph searches
            # the episode (its answer is the graph strategy's) and is kept when it leaves fewer.
            graph = self.graph.solve(ep)
            if len(graph.unresolved) < len(solution.unresolved):
                solution, by_graph = graph, True
            self.graph_episodes += 1
            self.graph_kept += by_graph
        seconds = time.perf_counter() - started
        self.episodes += 1
        self.solve_seconds += seconds
        self.last = {"levels": len(ep.rows), "colliding": int(np.count_nonzero(ep.is_colliding)),
                     "unresolved": len(solution.unresolved), "left_by_epa": left_by_epa, "by_graph": by_graph,
                     **solver.stats(), "seconds": round(seconds, 4)}
        return solution


class OffsetFrames:
    """The layout of one episode's offsets: frames, fixed ends and step budgets (the set-up).

    An orientation at level l is an offset (2,) radians from the programmed N0_l in the frame
    ``Q[l]`` (z axis N0_l), carried along the programmed path: as the program turns where the step
    limit is relative (``turn``), by the minimal rotation elsewhere, so a constant offset follows
    the program. Step entries j = 0..L: the step into level j (j = 0: from the pose before), j = L:
    into the row after; ``limit_deg`` is each one's limit, ``base`` and ``safe`` its budgets.
    """

    def __init__(self, ep: Episode) -> None:
        self.L = L = len(ep.rows)
        self.N0 = N0 = ep.N0 / np.linalg.norm(ep.N0, axis=1, keepdims=True)
        # ``turn[j]`` maps the previous programmed orientation as the program turns (the identity
        # where the absolute step is limited).
        n = len(ep.limits)
        turning = np.zeros(L + 1, dtype=bool)
        turning[:n] = ep.turning
        self.turn = np.tile(np.eye(3), (L + 1, 1, 1))
        if turning.any():
            self.turn[:n][turning[:n]] = ep.turns[turning[:n]]
        limit = np.full(L + 1, 180.0)
        limit[:n] = np.where(turning[:n], ep.step_limits, ep.limits)
        self.limit_deg = limit
        # Frames: Q_l's z axis is N0_l; carried as the program turns, or by the minimal rotation.
        Q = np.empty((L, 3, 3))
        Q[0] = rotation_from_z(N0[0])
        own = np.zeros(L + 1)
        for j in range(1, L):
            own[j] = float(angle_between_deg(N0[j], N0[j - 1]))
            carry = self.turn[j] if turning[j] else rotation_between(N0[j - 1], N0[j])
            q = carry @ Q[j - 1]
            Q[j] = rotation_between(q[:, 2], N0[j]) @ q  # remove the rounding drift
        self.Q = Q
        # The fixed ends, each in the frame of its neighbouring level, so that the bound
        # |Δoffset| >= step is exact there: the pose before as written, the row after as programmed.
        self.anchors: dict[int, np.ndarray] = {}
        self.N_before = self.N_after = None
        if ep.before_words is not None and limit[0] < 180.0:
            self.N_before = ep.N_before
            self.anchors[-1] = _log(Q[0], self.turn[0] @ self.N_before)
        if ep.after_row is not None and limit[L] < 180.0:
            self.N_after = ep.N_after
            self.anchors[L] = _log(Q[L - 1], self.turn[L].T @ self.N_after)
        # Budgets (radians): optimistic at the limit; ``safe`` holds whatever the offsets do (the
        # frames turn by ``own`` where the absolute step is limited).
        base = np.radians(np.maximum(limit - _MARGIN_DEG, 0.0))
        safe = base.copy()
        inner = np.arange(1, L)
        safe[inner] = np.where(turning[inner], base[inner], np.radians(np.maximum(limit[inner] - own[inner] - _MARGIN_DEG, 0.0)))
        if -1 not in self.anchors:
            base[0] = safe[0] = 0.0  # nothing before: this entry links nothing
        if L not in self.anchors:
            base[L] = safe[L] = 0.0
        self.base, self.safe = base, safe
        # Where the bound is not exact (the frame turns by ``own`` under the offsets).
        self.own_deg = np.where(turning, 0.0, own)

    def normals(self, d: np.ndarray, levels: np.ndarray | None = None) -> np.ndarray:
        """Tool vectors of offsets d (m, 2) at levels (all by default); a zero offset is N0 exactly."""
        levels = np.arange(self.L) if levels is None else np.asarray(levels)
        out = self.N0[levels].copy()
        for i, l in enumerate(levels):
            if np.linalg.norm(d[i]) > _TINY_RAD:
                out[i] = _exp(self.Q[l], d[i])
        return out

    def steps(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(L + 1,) each step of these offsets as the limits measure it (degrees; turned by the
        program where it turns), and (L + 1,) the change of the offsets there (radians); 0 for
        an entry that links nothing (no pose before, or no row after)."""
        L = self.L
        N = self.normals(d)
        prev, nxt = np.vstack([N[:1], N[:-1]]), N
        d_prev = np.vstack([d[:1], d[:-1]])
        if self.N_before is not None:
            prev[0], d_prev[0] = self.N_before, self.anchors[-1]
        if self.N_after is not None:
            prev, nxt = np.vstack([prev, N[-1:]]), np.vstack([nxt, self.N_after[None]])
        k = len(nxt)
        step = np.zeros(L + 1)
        step[:k] = angle_between_deg(nxt, np.einsum("nij,nj->ni", self.turn[:k], prev))
        change = np.zeros(L + 1)
        change[:L] = np.linalg.norm(d - d_prev, axis=1)
        if self.N_after is not None:
            change[L] = np.linalg.norm(self.anchors[L] - d[-1])
        if self.N_before is None:
            step[0] = change[0] = 0.0
        return step, change

    def within_limits(self, resolve) -> np.ndarray:
        """(L, 2) offsets laid out by ``resolve`` (budgets -> offsets, or None when the fixed ones
        cannot be joined), every measured step within its limit.

        A step whose offsets change by δ measures s(δ), own at δ = 0 (the program's own step),
        and s is convex in δ, so the chord through (0, own) and (δ, s) never underestimates it:
        an over-limit budget becomes the δ where that chord meets the limit. After
        ``BUDGET_ROUNDS`` such rounds, a budget still over takes its safe value (always within).
        """
        budgets = self.base.copy()
        for attempt in range(BUDGET_ROUNDS + self.L + 2):
            d = resolve(budgets)
            if d is None:  # the two ends alone cannot be joined (cannot happen: they are ≤ θ apart)
                return np.zeros((self.L, 2))
            step, change = self.steps(d)
            over = step > self.limit_deg
            if not over.any():
                return d
            if attempt < BUDGET_ROUNDS:
                own = self.own_deg[over]
                rise = np.maximum(step[over] - own, 1e-9)
                chord = np.minimum(budgets[over], change[over]) * (self.limit_deg[over] - _MARGIN_DEG - own) / rise
                budgets[over] = np.maximum(self.safe[over], np.minimum(budgets[over], chord) * (1.0 - 1e-6))
            else:
                budgets[over] = self.safe[over]
        return d


@dataclass
class _Rounds:
    """The rounds' progress: the best answer so far (words, colliding levels, levels left
    colliding among them), layouts made, rounds since the best fell, the caps, give-ups."""

    words: np.ndarray
    bad: np.ndarray
    left: np.ndarray
    layouts: int = 0
    stale: int = 0
    round_cap: int = ROUNDS
    layout_cap: int = MAX_LAYOUTS
    giveups: int = 0


class _EpisodeSolver:
    """The state of one episode's solve (``EpaStrategy.solve``).

    ``run``: the required tilts (step 1), then rounds (``_round``) of: lay the offsets out within
    the budgets, settling conflicts between fixed levels (step 2); test the ramp levels, re-check
    the episode, pin or give up the levels left colliding, bump the failing ones (step 3). The
    offsets' set-up (frames, fixed ends, budgets) is ``frames`` (``OffsetFrames``); the answer is
    ``_solution`` (rows left colliding, with reasons), what it took is ``stats``.
    """

    def __init__(self, strategy: EpaStrategy, model: EpaModel, ep):
        self.s = strategy
        self.model = model
        self.ep = ep
        self.frames = OffsetFrames(ep)
        self.L = self.frames.L
        self.max_tilt_rad = np.radians(strategy.max_tilt)
        self.rounds = 0
        self.searches = 0
        # settle outcomes: conflicts, moved by the walk, moved by the grid, dropped levels
        self.settles = {"conflicts": 0, "walk": 0, "grid": 0, "dropped": 0}
        # Level state: required (fixed) offsets, levels left colliding, with why.
        self.fixed: dict[int, np.ndarray] = {}
        self.end_free: set[int] = set()  # colliding only through the move into them (free end pose)
        self.hopeless: dict[int, str] = {}  # no free orientation within Θ along E
        self.dropped: dict[int, str] = {}  # free orientations, none within the steps of its neighbours
        self.gave_up: dict[int, str] = {}  # still colliding after the rounds: left as programmed
        self.fails = np.zeros(self.L, dtype=np.int64)  # re-check failures per level
        self._free_cache: dict[tuple, bool] = {}
        self._settle_failed: set[tuple] = set()
        self.holds: set[int] = set()  # fixed at the programmed orientation for good (``_hold``)
        self._bead_cache: dict[int, np.ndarray | None] = {}
        self._reach_mm = model.head_reach_mm + model.bead_radius_mm
        self.fallback = True  # the answer is the program as written (no verified solution yet)

    # -- the rounds -----------------------------------------------------------------------------
    def run(self) -> Solution:
        """The required tilts, then passes (``_round``) until they stop; the best answer kept."""
        self._required()
        bad = self.ep.is_colliding.copy()
        rounds = _Rounds(self.ep.programmed.copy(), bad, self._left_mask() & bad)
        while self._round(rounds):
            pass
        return self._solution(rounds)

    def _round(self, r: _Rounds) -> bool:
        """One pass: lay the offsets out and test the ramp levels; where one fails, it gets its own
        tilt and the pass ends there (the next lays out again, within ``layout_cap``). Else a
        round: re-check the episode, then pin the tilted levels left colliding, or keep the answer
        if it is the best and give up or bump the failing levels. False: stop."""
        d = self._layout()
        r.layouts += 1
        if r.layouts < r.layout_cap and self._test_ramps(d):
            return True
        self.rounds += 1
        changed = np.linalg.norm(d, axis=1) > _TINY_RAD
        words, bad, left = self._recheck(d, changed)
        # Blocks left colliding are left as programmed (docs/contract.md): one that a ramp passes
        # through (a dropped level, a block whose move starts at one left colliding) is pinned
        # at its programmed orientation for good, and the ramps are laid out around it again.
        tilted = bad & left & changed
        if tilted.any():
            self._pin_left(tilted)
            return True
        self._keep_best(r, words, bad, left, changed)
        retry = bad & ~left
        if not retry.any() or self.rounds >= r.round_cap or r.layouts >= r.layout_cap or r.stale >= PATIENCE:
            return self._give_up(r, retry & changed)
        self._bump(np.nonzero(retry)[0], d)
        return True

    def _recheck(self, d: np.ndarray, changed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(words, colliding, left) of the episode with offsets d: the whole episode re-checked
        (sweeps, the solution's own beads); ``left``: the levels left colliding (``_held``)."""
        ep = self.ep
        words = ep.words_of(self.frames.normals(d), ~changed)
        bad = ep.recheck(words)
        left = self._held(self._left_mask(), bad)
        _debug(f"epa round {self.rounds}: {int(bad.sum())} colliding ({int((bad & ~ep.is_colliding).sum())} new), "
               f"{int(left.sum())} left, fixed {len(self.fixed)}, dropped {len(self.dropped)}, "
               f"hopeless {len(self.hopeless)}, searches {self.searches}, new at {np.nonzero(bad & ~ep.is_colliding)[0].tolist()} "
               f"(after a block left colliding: {np.nonzero(bad & ~ep.is_colliding & left)[0].tolist()})")
        return words, bad, left

    def _pin_left(self, tilted: np.ndarray) -> None:
        """Pin the tilted levels left colliding at their programmed orientation. Where the pinned
        pose collides itself, so does every move out of it: the level after is pinned with it, and
        so on (else one round each)."""
        for l in np.nonzero(tilted)[0].tolist():
            self._pin(l)
            while l + 1 < self.L and not self.ep.programmed_free()[l] and l + 1 not in self.holds:
                l += 1
                self._pin(l)

    def _keep_best(self, r: _Rounds, words, bad: np.ndarray, left: np.ndarray, changed: np.ndarray) -> None:
        """Keep this round's answer if it leaves fewer blocks colliding. Never hand back a solution
        that makes a block collide that did not, unless its move starts at a block left colliding
        (as GraphStrategy; the stage reports it), nor one whose colliding blocks are not as programmed."""
        if not (bad & ~self.ep.is_colliding & ~left).any() and not (bad & changed).any() and bad.sum() < r.bad.sum():
            r.words, r.bad, r.left, self.fallback = words, bad, left & bad, False
            r.stale = 0
        elif not self.fallback:  # patience runs once there is an answer to keep
            r.stale += 1

    def _give_up(self, r: _Rounds, stuck: np.ndarray) -> bool:
        """The rounds are over: blocks still colliding with a tilt are given up (pinned at the
        programmed orientation, reported unresolved) and the rest laid out around them with
        ``GIVEUP_ROUNDS`` more rounds, at most ``GIVEUPS`` times. False: stop."""
        if not stuck.any() or r.giveups >= GIVEUPS:
            return False
        r.giveups += 1
        for l in np.nonzero(stuck)[0]:
            self._pin(int(l), self._stuck(int(l)))
        r.round_cap, r.layout_cap = self.rounds + GIVEUP_ROUNDS, r.layouts + 2 * GIVEUP_ROUNDS
        r.stale = 0
        return True

    # -- step 1: the required tilts -------------------------------------------------------------
    def _required(self) -> None:
        """Step 1: the EPA tilt of every colliding level, from its programmed orientation."""
        levels = [int(l) for l in np.nonzero(self.ep.is_colliding)[0]]
        for l, (found, bodies) in zip(levels, self._searches([(l, None, None) for l in levels])):
            if found is None:
                what = f" ({', '.join(bodies)})" if bodies else ""
                self.hopeless[l] = (f"no free orientation within {self.s.max_tilt:g}° (--max-tilt) found along "
                                    f"the EPA extraction direction{what}")
                self._pin(l)  # left as programmed: the ramps go around it
            elif np.linalg.norm(found) > _TINY_RAD:
                self._fix(l, found)
            else:  # free as programmed: only the move into it collides (the re-check tilts it)
                self.end_free.add(l)

    # -- step 2: offsets within the step budgets ------------------------------------------------
    def _layout(self) -> np.ndarray:
        """(L, 2) offsets through the fixed ones, every measured step within its limit."""
        return self.frames.within_limits(self._resolve)

    def _resolve(self, budgets: np.ndarray) -> np.ndarray | None:
        """Offsets filled between the fixed ones; where two are too far apart, the larger wins.
        Each settle moves a level (at most ``MAX_MOVES`` times per level) or drops one, so this ends."""
        moves = np.zeros(self.L, dtype=np.int64)
        while True:
            points = {**self.frames.anchors, **self.fixed}
            d, conflict = fill_offsets(points, budgets, self.L)
            if conflict is None:
                return d
            if not any(k in self.fixed and k not in self.holds for k in conflict):
                return None
            self._settle(*conflict, points, budgets, moves)

    def _settle(self, a: int, c: int, points: dict, budgets: np.ndarray, moves: np.ndarray) -> None:
        """Fixed levels a < c too far apart: move the smaller tilt into the ball the larger one
        reaches, staying within reach of its own fixed neighbour on the other side (``_within``),
        else the larger into the smaller's; failing both, keep the most fixed levels that can be
        joined (``_prune``) and drop the others."""
        self.settles["conflicts"] += 1
        pos = np.concatenate([[0.0], np.cumsum(budgets)])
        keys = sorted(points)
        movable = sorted((k for k in (a, c) if k in self.fixed and k not in self.holds),
                         key=lambda k: np.linalg.norm(points[k]))
        for s in movable:
            if moves[s] >= MAX_MOVES:
                continue
            o = c if s == a else a
            balls = [(points[o], float(abs(pos[o + 1] - pos[s + 1])))]
            # Its fixed neighbour on the other side from o: the move must keep that link.
            i = keys.index(s)
            beyond = (keys[i - 1] if i > 0 else None) if s == a else (keys[i + 1] if i + 1 < len(keys) else None)
            if beyond is not None:
                balls.append((points[beyond], float(abs(pos[beyond + 1] - pos[s + 1]))))
            found = self._within(s, points[s], balls)
            if found is not None:
                self._fix(s, found)
                moves[s] += 1
                return
        self._prune(points, pos)

    def _prune(self, points: dict, pos: np.ndarray) -> None:
        """Drop the fixed levels off the best joinable chain (``keep_chain``): the anchors and
        ``holds`` must stay; each colliding level kept counts 1; a level that was not colliding
        counts 0 (let go, it is a ramp level again: keeping such levels on ties constrains the
        ramps and frees fewer blocks on the bathtub sample)."""
        keys = sorted(points)
        must = [k in self.frames.anchors or k in self.holds for k in keys]
        gain = [int(not m and 0 <= k < self.L and bool(self.ep.is_colliding[k])) for k, m in zip(keys, must)]
        keep = keep_chain([points[k] for k in keys], [pos[k + 1] for k in keys], must, gain)
        for i, k in enumerate(keys):
            if not keep[i] and k in self.fixed and k not in self.holds:
                self._drop(k)

    def _within(self, s: int, offset: np.ndarray, balls: list[tuple[np.ndarray, float]]) -> np.ndarray | None:
        """A free offset at level s inside every ball (centre offset, radius in radians), or None.

        The start is the point of the balls' intersection nearest ``offset`` (alternating
        projections); the EPA walk goes from there, kept inside the balls, then the balls' points on
        a grid (about 8 across) are tested in one batch, nearest ``offset`` first. Failures are
        remembered (the layout asks again)."""
        key = (_key(s, offset),) + tuple((_key(s, c), round(r, 12)) for c, r in balls)
        if key in self._settle_failed:
            return None
        target = np.asarray(offset, dtype=np.float64)
        for _ in range(50):
            for centre, radius in balls:
                gap = target - centre
                n = float(np.linalg.norm(gap))
                if n > radius:
                    target = centre + gap * (radius / n)
        inside = all(np.linalg.norm(target - c) <= r + 1e-10 for c, r in balls)
        found = None
        if inside:
            # The walk tests its start first: a free target is kept as it is.
            found, _ = self._search(s, start=target, balls=balls)
            self.settles["walk"] += found is not None
        if found is None:
            # E leads out of the balls: try the balls' points on a grid instead, nearest first.
            centre, radius = balls[0]
            spacing = max(np.radians(self.s.step_deg), radius / 4.0)
            ticks = np.arange(-radius, radius + 1e-12, spacing)
            grid = centre + np.stack(np.meshgrid(ticks, ticks), axis=-1).reshape(-1, 2)
            keep = np.linalg.norm(grid, axis=1) <= self.max_tilt_rad
            for c, r in balls:
                keep &= np.linalg.norm(grid - c, axis=1) <= r + 1e-10
            grid = grid[keep]
            if len(grid):
                grid = grid[np.argsort(np.linalg.norm(grid - offset, axis=1), kind="stable")]
                free = self.ep.free(np.full(len(grid), s), self.frames.normals(grid, np.full(len(grid), s)))
                if free.any():
                    found = grid[np.flatnonzero(free)[0]]
                    self.settles["grid"] += 1
        if found is None:
            self._settle_failed.add(key)
        return found

    # -- step 3: verification -------------------------------------------------------------------
    def _test_ramps(self, d: np.ndarray) -> bool:
        """Test the ramp levels' end poses; a failing one gets a new fixed offset. True if any did."""
        norms = np.linalg.norm(d, axis=1)
        todo = [l for l in range(self.L) if norms[l] > _TINY_RAD and l not in self.fixed
                and l not in self.hopeless and l not in self.dropped and self._cached(l, d[l]) is None]
        if not todo:
            return False
        levels = np.array(todo)
        free = self.ep.free(levels, self.frames.normals(d[levels], levels))
        for l, ok in zip(todo, free):
            self._free_cache[_key(l, d[l])] = bool(ok)
        changed = False
        for l in levels[~free]:
            l = int(l)
            found, _ = self._search(l, start=d[l])
            if found is not None and np.linalg.norm(found) > _TINY_RAD:
                self._fix(l, found)
            else:
                # No way out along E from the ramp: the level holds its programmed pose (free: it
                # is not colliding, or only its move is) and its neighbours settle around it.
                self._fix(l, np.zeros(2))
            changed = True
        return changed

    def _bump(self, levels: np.ndarray, d: np.ndarray) -> None:
        """Tilt levels failing the re-check further along their offset (or the move's E); a level
        failing again takes its predecessor with it (the move between them is in the way)."""
        for l in levels:
            l = int(l)
            self.fails[l] += 1
            if not self.ep.is_colliding[l] and self.fails[l] > 1:
                self._hold(l)
                continue
            targets = [l] + ([l - 1] if self.fails[l] > 1 and l > 0 else [])
            for k in targets:
                if k in self.hopeless or k in self.dropped or k in self.holds:
                    continue
                current = float(np.linalg.norm(d[k]))
                direction = d[k] / current if current > _TINY_RAD else self._move_direction(l, k, d)
                if direction is None:
                    continue
                size = min(current + np.radians(self.s.bump_deg) * self.fails[l], self.max_tilt_rad)
                if size <= current + _TINY_RAD:
                    continue
                target = direction * size
                found, _ = self._search(k, start=target)  # a free target is kept as it is
                if found is not None and np.linalg.norm(found) > current + _TINY_RAD:
                    self._fix(k, found)

    def _hold(self, l: int) -> None:
        """A block that did not collide keeps failing the re-check (a ramp's sweep): it and the
        block before go back to the program (the programmed move between them was free), for good;
        a colliding block before is left colliding instead (the move from it is excused)."""
        self._fix(l, np.zeros(2))
        self.holds.add(l)
        if l > 0:
            if not self.ep.is_colliding[l - 1]:
                self._fix(l - 1, np.zeros(2))
                self.holds.add(l - 1)
            elif l - 1 in self.fixed and l - 1 not in self.holds:
                self._drop(l - 1)

    def _move_direction(self, l: int, k: int, d: np.ndarray) -> np.ndarray | None:
        """A unit offset direction at level k for the move into level l: a neighbour's offset, else
        E at the middle of that move (rotating N toward E's perpendicular part moves the head along E)."""
        norms = np.linalg.norm(d, axis=1)
        for j in (k - 1, k + 1):
            if 0 <= j < self.L and norms[j] > _TINY_RAD:
                return d[j] / norms[j]
        N = self.frames.normals(d)
        ep = self.ep
        C = 0.5 * (ep.C0[l - 1] + ep.C0[l]) if l > 0 else ep.C0[l]
        n = N[l - 1] + N[l] if l > 0 else N[l]
        n = n / np.linalg.norm(n)
        e = self.model.extraction_vector(C, self._rotation_of(l)(n[None])[0], self._beads(l)).vector
        u = (self.frames.Q[k].T @ e)[:2]
        norm = float(np.linalg.norm(u))
        return u / norm if norm > _TINY_RAD else None

    # -- the levels' state ----------------------------------------------------------------------
    def _fix(self, level: int, offset: np.ndarray) -> None:
        self.fixed[level] = offset

    def _pin(self, level: int, why: str | None = None) -> None:
        """Fix a level at its programmed orientation for good (offset 0, never moved: ramps bend
        around it or stop at it); ``why``: it is given up, left colliding for that reason."""
        self._fix(level, np.zeros(2))
        self.holds.add(level)
        if why is not None:
            self.gave_up[level] = why

    def _drop(self, level: int) -> None:
        self.settles["dropped"] += 1
        tilt = np.degrees(np.linalg.norm(self.fixed.pop(level)))
        if self.ep.is_colliding[level]:
            self.dropped[level] = (f"a free orientation exists ({tilt:.1f}° from programmed), but none was found "
                                   f"within {self.s.max_step:g}° steps (--max-step) of its neighbours'")

    def _left_mask(self) -> np.ndarray:
        out = np.zeros(self.L, dtype=bool)
        out[list(self.hopeless) + list(self.dropped) + list(self.gave_up)] = True
        return out

    @staticmethod
    def _held(left: np.ndarray, bad: np.ndarray) -> np.ndarray:
        """``left`` with every colliding level whose move starts at a level left colliding (a
        move that starts at a pose left colliding collides whatever its end), and the colliding
        levels after it in a row (their moves start where it is pinned: left with it)."""
        out = left.copy()
        for i in range(1, len(out)):
            out[i] |= bad[i] & out[i - 1]
        return out

    # -- the result -----------------------------------------------------------------------------
    def _solution(self, r: _Rounds) -> Solution:
        """The best answer kept, its colliding blocks' rows and why each is left."""
        ep = self.ep
        rows = [int(ep.rows[i]) for i in np.nonzero(r.bad)[0]]
        reasons = {int(ep.rows[i]): self._reason(i, r.bad, r.left) for i in np.nonzero(r.bad)[0]}
        return Solution(r.words, rows, reasons)

    def stats(self) -> dict:
        """What the solve took: rounds, walks, end-pose tests and the settles' outcomes."""
        return {"rounds": self.rounds, "searches": self.searches, "tests": self.ep.tests, **self.settles}

    def _reason(self, i: int, bad: np.ndarray, left: np.ndarray | None = None) -> str:
        if i in self.hopeless:
            return self.hopeless[i]
        if i in self.dropped:
            return self.dropped[i]
        if i in self.gave_up and not self.fallback:
            return self.gave_up[i]
        if i > 0 and bad[i - 1] and left is not None and left[i - 1]:
            return "its move starts at the block before, which is left colliding"
        if self.fallback:
            return (f"no EPA tilt within {self.s.max_tilt:g}° (--max-tilt), ramped in "
                    f"{self.s.max_step:g}° steps (--max-step), kept every block around it free; "
                    "the episode is left as programmed")
        return self._stuck(i)

    def _stuck(self, i: int) -> str:
        """Why a level still colliding with a tilt after the rounds is given up."""
        what = "the move into it" if i in self.end_free else "its sweep or the solution's own beads"
        return (f"still collides ({what}) after {self.rounds} rounds of larger EPA tilts within "
                f"{self.s.max_tilt:g}° (--max-tilt); left as programmed")

    # -- the EPA walk and the tests ------------------------------------------------------------
    def _search(self, l: int, start: np.ndarray | None = None, balls: list[tuple[np.ndarray, float]] | None = None):
        """(offset (2,) or None, bodies): the EPA tilt at level l from ``start`` (an offset; None:
        the programmed orientation), accepted by ``Episode.free`` within Θ of N0 (and inside every
        ball (centre offset, radius) of ``balls`` when given)."""
        return self._searches([(l, start, balls)])[0]

    def _searches(self, asks: list[tuple]) -> list[tuple]:
        """``_search`` of each (level, start, balls), the walks run in step, ``TILTS_IN_STEP`` at a
        time: each round's orientations of every walk are tested in one ``Episode.free`` call (a
        batch large enough for the kernels' threads). Each walk asks and gets what it would alone."""
        out = []
        for first in range(0, len(asks), TILTS_IN_STEP):
            walks = [self._walk(*ask) for ask in asks[first:first + TILTS_IN_STEP]]

            def test(asked: list[tuple[int, np.ndarray]], walks=walks) -> list[np.ndarray]:
                ok = [walks[i][2](normals) for i, normals in asked]
                levels = np.concatenate([np.full(int(k.sum()), walks[i][1]) for (i, _), k in zip(asked, ok)])
                normals = np.concatenate([n[k] for (_, n), k in zip(asked, ok)])
                free = self.ep.free(levels, normals) if len(levels) else np.zeros(0, dtype=bool)
                answers, at = [], 0
                for k in ok:
                    answer = np.zeros(len(k), dtype=bool)
                    answer[k] = free[at:at + int(k.sum())]
                    at += int(k.sum())
                    answers.append(answer)
                return answers

            results = run_tilts([w[0] for w in walks], test)
            for (_, l, _, Q), result in zip(walks, results):
                if result.normal is None:
                    out.append((None, result.bodies))
                    continue
                found = _log(Q, result.normal)
                self._free_cache[_key(l, found)] = True
                out.append((found, result.bodies))
        return out

    def _walk(self, l: int, start: np.ndarray | None, balls: list[tuple[np.ndarray, float]] | None):
        """(tilt walk, level, allowed: (k, 3) normals -> (k,) bool (within Θ and the balls), frame Q)."""
        self.searches += 1
        Q = self.frames.Q[l]
        n0 = self.frames.N0[l]
        start_n = n0 if start is None else _exp(Q, start)
        # The walk may cross the whole cap from its start, but never leaves the ball: no farther
        # than its diameter (every step outside would cost a hull test for nothing).
        reach_deg = self.s.max_tilt + (0.0 if start is None else float(np.degrees(np.linalg.norm(start))))
        if balls:
            reach_deg = min(reach_deg, float(np.degrees(2.0 * min(r for _, r in balls))) + self.s.step_deg)

        def allowed(normals: np.ndarray) -> np.ndarray:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
            ok = angle_between_deg(normals, n0[None]) <= self.s.max_tilt + 1e-9
            if balls:
                local = _log_many(Q, normals)
                for centre, radius in balls:
                    ok &= np.linalg.norm(local - centre, axis=1) <= radius + 1e-10
            return ok

        walk = self.model.tilt_steps(self.ep.C0[l], start_n, self._rotation_of(l),
                                     max_tilt_deg=min(reach_deg, 180.0), step_deg=self.s.step_deg,
                                     variant=self.s.variant, beads_mm=self._beads(l))
        return walk, l, allowed, Q

    def _rotation_of(self, l: int):
        ep = self.ep
        return lambda normals: ep.rotations(np.full(len(normals), l), np.asarray(normals).reshape(-1, 3))

    def _beads(self, l: int) -> np.ndarray | None:
        """Bead centres the level sees, near its tip: the store's and the episode's laid up to it."""
        if self.model.bead_radius_mm <= 0:
            return None
        if l not in self._bead_cache:
            ep = self.ep
            c = ep.C0[l]
            found = []
            if ep.store.count:
                found.extend(ep.store.near(c, self._reach_mm))
            mine = ep.bead_pts[ep.bead_seq <= l]
            found.append(mine[np.linalg.norm(mine - c, axis=1) <= self._reach_mm])
            beads = np.concatenate(found)
            # E only steers: one bead per cell of the bead radius gives its direction, at a
            # fraction of the hull tests (the beads are laid at the pitch, closer than that).
            cell = np.floor(beads / self.model.bead_radius_mm).astype(np.int64)
            self._bead_cache[l] = beads[first_of_each_cell(cell)]
        return self._bead_cache[l]

    def _cached(self, l: int, offset: np.ndarray) -> bool | None:
        return self._free_cache.get(_key(l, offset))


# -- offsets ---------------------------------------------------------------------------------------


def fill_offsets(points: dict[int, np.ndarray], steps_rad: np.ndarray, L: int, tol_rad: float = 1e-9):
    """Offsets (L, 2) of levels 0..L-1 through fixed ones, each changing by at most its step.

    points : level -> fixed offset (2,); level -1 (the pose before) and L (the row after) allowed
    steps_rad : (L + 1,) the largest change into level j (j = 0: from level -1; j = L: into L)
    returns (offsets, None), or (zeros, (a, c)) for the first neighbouring fixed levels a < c
    whose offsets differ by more than the steps between them allow.

    Between fixed a and c (offsets r_a, r_c; steps D between them): when D >= |r_a| + |r_c| the
    levels ramp from r_a straight down to 0 at full steps, stay at exactly 0, and ramp up to r_c
    (so far levels keep their programmed orientation exactly); else they run at full steps along
    r_a → p → r_c, p on the line from 0 to the point of segment r_a r_c nearest 0, placed so the
    path's length is D. Beyond the first or last fixed level with no anchor, a ramp down to 0.
    The path's points are never farther from 0 than its ends.
    """
    pos = np.concatenate([[0.0], np.cumsum(np.asarray(steps_rad, dtype=np.float64))])  # level j at pos[j + 1]
    d = np.zeros((L, 2))
    keys = sorted(points)
    if not keys:
        return d, None
    at = {k: np.asarray(points[k], dtype=np.float64) for k in keys}
    for a, c in zip(keys, keys[1:]):
        if np.linalg.norm(at[a] - at[c]) > pos[c + 1] - pos[a + 1] + tol_rad:
            return d, (a, c)
    first, last = keys[0], keys[-1]
    for j in range(0, min(first, L)):
        d[j] = _shrink(at[first], pos[first + 1] - pos[j + 1])
    for j in range(max(last + 1, 0), L):
        d[j] = _shrink(at[last], pos[j + 1] - pos[last + 1])
    for a, c in zip(keys, keys[1:]):
        if c - a < 2:
            continue
        ra, rc = at[a], at[c]
        span = pos[c + 1] - pos[a + 1]
        na, nc = np.linalg.norm(ra), np.linalg.norm(rc)
        if span >= na + nc:
            for j in range(a + 1, c):
                s, t = pos[j + 1] - pos[a + 1], pos[c + 1] - pos[j + 1]
                d[j] = _shrink(ra, s) if s < na else (_shrink(rc, t) if t < nc else 0.0)
            continue
        p = _bend_point(ra, rc, span)
        first_leg = np.linalg.norm(p - ra)
        second_leg = np.linalg.norm(rc - p)
        for j in range(a + 1, c):
            s = pos[j + 1] - pos[a + 1]
            if s <= first_leg:
                d[j] = ra + (p - ra) * (s / first_leg if first_leg > 0 else 0.0)
            else:
                d[j] = p + (rc - p) * (min(1.0, (s - first_leg) / second_leg) if second_leg > 0 else 0.0)
    for k in keys:
        if 0 <= k < L:
            d[k] = at[k]
    return d, None


def keep_chain(values, positions, must, gain) -> np.ndarray:
    """Which fixed levels to keep so that every two neighbours among the kept can be joined.

    values : offsets (2,) radians of the fixed levels, in level order; positions : their positions
    (summed step budgets, radians); must : levels that stay whatever; gain : what keeping each is
    worth. Filling between two fixed levels works exactly when their offsets differ by no more
    than the steps between them (``fill_offsets``), so the answer is the chain through every
    ``must`` level, each member joinable to the next, of the largest total gain: a longest path
    over the levels in order (dynamic programming, O(n²)). Where runs of opposite tilts meet at a
    sharp turn this keeps whole runs rather than eroding both. Returns (n,) bool; all False when
    two ``must`` levels cannot be joined.
    """
    n = len(values)
    value = np.asarray(values, dtype=np.float64).reshape(n, 2)
    at = np.asarray(positions, dtype=np.float64)
    must = np.asarray(must, dtype=bool)
    musts_before = np.concatenate([[0], np.cumsum(must)])  # musts among levels[:j]
    score = np.full(n, -1)
    back = np.full(n, -1)
    for j in range(n):
        if musts_before[j] == 0:  # the chain may start here: no level before must stay
            score[j] = gain[j]
        for i in range(j):
            if score[i] < 0 or musts_before[j] > musts_before[i + 1]:
                continue  # i unreachable, or a level between them must stay
            if np.linalg.norm(value[j] - value[i]) <= at[j] - at[i] + 1e-9 and score[i] + gain[j] > score[j]:
                score[j], back[j] = score[i] + gain[j], i
    keep = np.zeros(n, dtype=bool)
    ends = [j for j in range(n) if score[j] >= 0 and musts_before[n] == musts_before[j + 1]]
    if ends:
        j = max(ends, key=lambda e: score[e])
        while j >= 0:
            keep[j] = True
            j = back[j]
    return keep


def _bend_point(ra: np.ndarray, rc: np.ndarray, length: float) -> np.ndarray:
    """The point p = t·m (m: the point of segment ra rc nearest 0, 0 <= t <= 1) with
    |ra - p| + |p - rc| = length (between |ra - rc| and |ra| + |rc|; bisection, the sum falls with t)."""
    seg = rc - ra
    den = float(seg @ seg)
    m = ra + seg * (np.clip(-(ra @ seg) / den, 0.0, 1.0) if den > 0 else 0.0)
    lo, hi = 0.0, 1.0
    for _ in range(60):
        t = 0.5 * (lo + hi)
        if np.linalg.norm(ra - t * m) + np.linalg.norm(t * m - rc) > length:
            lo = t
        else:
            hi = t
    return hi * m


def _shrink(r: np.ndarray, by: float) -> np.ndarray:
    """r shortened by ``by`` toward 0; exactly 0 when nothing is left (the programmed orientation)."""
    n = float(np.linalg.norm(r))
    return r * (1.0 - by / n) if n - by > _TINY_RAD else np.zeros(2)


def _log(Q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The offset (2,) radians of unit vector n in frame Q (z axis = N0): direction and angle from N0."""
    v = Q.T @ (n / np.linalg.norm(n))
    side = float(np.hypot(v[0], v[1]))
    if side < _TINY_RAD:
        return np.zeros(2)
    return v[:2] * (np.arctan2(side, v[2]) / side)


def _log_many(Q: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.array([_log(Q, n) for n in normals]).reshape(-1, 2)


def _exp(Q: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The unit vector of an offset (2,) radians in frame Q."""
    a = float(np.linalg.norm(offset))
    if a < _TINY_RAD:
        return Q[:, 2].copy()
    local = np.array([offset[0] * np.sin(a) / a, offset[1] * np.sin(a) / a, np.cos(a)])
    return Q @ local


def _debug(text: str) -> None:
    if os.environ.get("NCFIX_DEBUG"):
        print(text, file=sys.stderr)


def _key(level: int, offset: np.ndarray) -> tuple:
    return (int(level), round(float(offset[0]), 12), round(float(offset[1]), 12))
