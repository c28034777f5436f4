"""Solving one collision episode: what every strategy shares, and the orientation-graph strategy.

An episode's *levels* are consecutive motion rows. ``Episode`` gives a strategy the programmed
poses, the machine (orientation → words, reachability), a batched conservative test of candidate
orientations, and the full re-check of a solution (end poses, sweeps, and the solution's own
beads). A strategy returns the words of every level and the rows it could not free.

Pivot (docs/contract.md): ``tip`` keeps the head tip C = P + h·N and moves the programmed point to
P′ = C − h·N′; ``point`` keeps P (the tip moves to P + h·N′).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ncfix.collision.deposit import BeadStore
from ncfix.collision.path import Moves
from ncfix.correct.blend import blend
from ncfix.correct.candidates import SphereGrid, level_candidates, nearest
from ncfix.correct.graph import LayeredGraph
from ncfix.geometry.frames import angle_between_deg, minimal_rotation, turn_rotations
from ncfix.kinematics.base import Unreachable

if TYPE_CHECKING:
    from ncfix.config import Options
    from ncfix.correct.stage import CorrectStage

# A step may exceed θ only where the program's own step did: by this much at most (degrees).
STEP_SLACK_DEG = 1e-6
# Rounds of "blend, re-check, keep the strategy's orientations where the blend collided".
BLEND_ROUNDS = 4


@dataclass
class Solution:
    words: np.ndarray  # (L, k) words of every level
    unresolved: list[int] = field(default_factory=list)  # row indices left colliding
    reasons: dict[int, str] = field(default_factory=dict)


class Strategy(Protocol):
    """What the correction stage asks of a strategy (``--strategy``): a Solution for each episode."""

    def solve(self, ep: Episode) -> Solution: ...


class Episode:
    """Levels ``first .. last`` of the stage's row table: the view a strategy works through.

    What a strategy reads: the levels (``rows``, ``lines``, ``programmed`` words, ``tcp``, the
    programmed poses ``P0 N0 R0 C0``, which levels are ``colliding``), the poses around them
    (``before_words`` / ``N_before``: the row before as it will be written; ``N_after``: the row
    after as programmed), the step rules (``max_step``, ``limits``, ``step_limits``, ``turning``,
    ``turns``), the material (``store``: laid before the episode; ``bead_pts``/``bead_seq``: the
    programmed levels' own), and ``report`` for notes. What it calls: ``orient``, ``rotations``,
    ``free``, ``programmed_free``, ``moves_hit_parts``, ``words_of`` and ``recheck``.
    """

    def __init__(self, stage: CorrectStage, first: int, last: int, colliding: np.ndarray) -> None:
        r = stage.rows
        self.stage = stage
        self.path = stage.path
        self.checker = stage.checker
        self.kin = stage.profile.kinematics
        self.is_vector = stage.profile.is_vector
        self.first, self.last = first, last
        self.rows = np.arange(first, last + 1)
        self.lines = r.line[self.rows]  # 1-based input line of each level
        self.colliding = np.asarray(colliding, dtype=np.int64)
        self.is_colliding = np.isin(self.rows, self.colliding)
        self.programmed = r.programmed[first:last + 1]
        self.tcp = r.tcp[first:last + 1]
        self.h = stage.path.standoff_mm
        self.pivot_tip = stage.options.pivot == "tip"
        self.P0, self.N0, self.R0 = self.path.forward(self.programmed, self.tcp)
        self.C0 = self.P0 + self.h * self.N0
        # The poses before and after: the row before as it will be written, the row after as
        # programmed (it is not part of the episode and must stay reachable within θ).
        moves = stage.moves(first, first + 1)
        self.start_known = bool(moves.known_start[0])
        self.before_words = moves.w_start[0] if self.start_known else None
        self.after_row = last + 1 if last + 1 < len(r) else None
        self.store = stage.store
        self.report = stage.report
        self.max_step = theta = float(stage.options.max_step)
        # Step limit into each level and into the row after: θ, or the program's own step.
        _, n_before, _ = self.path.forward(self._prev_programmed()[None, :], self.tcp[:1]) if self.start_known \
            else (None, self.N0[:1], None)
        chain = np.vstack([n_before, self.N0])
        if self.after_row is not None:
            _, n_after, _ = self.path.forward(r.programmed[self.after_row][None, :], r.tcp[self.after_row:self.after_row + 1])
            chain = np.vstack([chain, n_after])
        self.N_after = n_after[0] if self.after_row is not None else None
        self.N_before = self.path.forward(self.before_words[None, :], self.tcp[:1])[1][0] \
            if self.before_words is not None else None
        own = angle_between_deg(chain[1:], chain[:-1])
        # Where the program itself turns by more than θ between two blocks, ncfix keeps that turn
        # and adds at most θ to it: the step is measured against the previous orientation turned
        # as the program turns (``turns``), the turn being the change of the programmed vector's
        # tilt from +Z and of its azimuth about Z (as a tilt/rotary-table machine turns: a
        # correction "2° more upright" stays so around a corner). Elsewhere the absolute step is
        # at most θ. Entries: the step into each level, and into the row after when there is one.
        self.turning = own > theta
        self.turns = np.tile(np.eye(3), (len(own), 1, 1))
        turn_deg = np.zeros(len(own))
        if self.turning.any():
            q = turn_rotations(chain)
            self.turns[self.turning] = q[self.turning]
            turn_deg = np.degrees(np.arccos(np.clip((np.trace(q, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
        self.step_limits = np.full(len(own), theta + STEP_SLACK_DEG)  # of the (turned) step
        self.limits = np.where(self.turning, np.maximum(own, turn_deg) + theta, theta) + STEP_SLACK_DEG  # absolute step
        if not self.start_known:
            self.limits[0] = self.step_limits[0] = 180.0
        if self.after_row is not None and not r.known_start[self.after_row]:
            self.limits[-1] = self.step_limits[-1] = 180.0
        # Beads of the programmed moves, seen from their own level on (candidate tests only; the
        # re-check uses the solution's own beads).
        self.bead_pts, self.bead_seq = self._programmed_beads()
        self.tests = 0  # candidate poses tested
        # Re-checks, each reusing what the last one found (the first: what detection found).
        self.checks = stage.rechecks((first, last + 1 if self.after_row is None else last + 2))
        self._programmed_free: np.ndarray | None = None

    def _prev_programmed(self) -> np.ndarray:
        r = self.stage.rows
        return r.programmed[self.first - 1] if self.first > 0 else self.stage.prev_programmed

    def _programmed_beads(self) -> tuple[np.ndarray, np.ndarray]:
        """The beads (m, 3) of the levels' programmed moves (the first from the row before as it
        will be written), in laying order, and the level of each (m,): one batch of moves."""
        moves = self.stage.moves(self.first, self.last + 1)
        start = moves.w_start.copy()
        start[1:] = self.programmed[:-1]
        return self.path.bead_points(Moves(start, self.programmed, moves.tcp, moves.known_start, moves.deposit,
                                           moves.arc), movers=True)

    # -- the machine -----------------------------------------------------------------------------
    def point(self, level: np.ndarray, N: np.ndarray) -> np.ndarray:
        """(m, 3) the programmed point for orientation N (m, 3) at levels (m,): P′ = C − h·N′ (the
        tip stays, ``--pivot tip``) or P as programmed (``--pivot point``)."""
        level = np.asarray(level, dtype=np.int64)
        return self.C0[level] - self.h * N if self.pivot_tip else self.P0[level]

    def orient(self, level: np.ndarray, N: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Words (m, k), head rotation (m, 3, 3) and reachability (m,) of orientation N at levels."""
        level = np.asarray(level, dtype=np.int64)
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        P = self.point(level, N)
        m = len(level)
        k = self.programmed.shape[1]
        if self.is_vector:
            words = np.concatenate([P, N], axis=1)
            ok = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0))) <= self.kin.max_tilt_deg + 1e-9
            return words, minimal_rotation(N), ok
        words = np.full((m, k), np.nan)
        ok = np.zeros(m, dtype=bool)
        for i in range(m):
            lv = int(level[i])
            try:
                words[i] = self.kin.inverse(P[i], N[i], self.programmed[lv], tcp=bool(self.tcp[lv]))
                ok[i] = True
            except Unreachable:
                pass
        R = np.tile(np.eye(3), (m, 1, 1))
        if ok.any():
            for flag in (False, True):
                sel = ok & (self.tcp[level] == flag)
                if sel.any():
                    R[sel] = self.kin.forward(words[sel], tcp=flag)[2]
        return words, R, ok

    def rotations(self, level: np.ndarray, N: np.ndarray) -> np.ndarray:
        """(m, 3, 3): ``orient``'s head rotations alone (a vector machine needs no words for them)."""
        if self.is_vector:
            return minimal_rotation(N / np.linalg.norm(N, axis=1, keepdims=True))
        return self.orient(level, N)[1]

    def free(self, level: np.ndarray, N: np.ndarray, beads: bool = True) -> np.ndarray:
        """(m,) True where orientation N at that level is reachable and its end pose is free of the
        parts and of the (programmed) beads laid up to that level: the bounds first, the exact
        test where they cannot decide (``Checker.poses_free``). Without ``beads``, of the parts
        and the beads laid before the episode only (those no solution changes)."""
        words, R, ok = self.orient(level, N)
        out = np.zeros(len(level), dtype=bool)
        if not ok.any():
            return out
        idx = np.nonzero(ok)[0]
        lv = np.asarray(level)[idx]
        # A tool-vector machine's P is its XYZ words (``ToolVector.forward``): no rotations to compute.
        P = words[idx, :3] if self.is_vector else self.path.forward(words[idx], self.tcp[lv])[0]
        C = P + self.h * (N[idx] / np.linalg.norm(N[idx], axis=1, keepdims=True))
        pts, seq = (self.bead_pts, self.bead_seq) if beads else (self.bead_pts[:0], self.bead_seq[:0])
        out[idx] = self.checker.poses_free(C, R[idx], lv.astype(np.int64), self.stage.store, pts, seq)
        self.tests += len(idx)
        return out

    def programmed_free(self) -> np.ndarray:
        """(L,) bool: the levels' end poses as programmed are free (``free``; tested once)."""
        if self._programmed_free is None:
            self._programmed_free = self.free(np.arange(len(self.rows)), self.N0)
        return self._programmed_free

    def moves_hit_parts(self, level: int, start_words: np.ndarray, N: np.ndarray) -> np.ndarray:
        """(m,) bool: the moves into ``level`` from start_words (m, k) to orientation N (m, 3)
        (its words on the branch ``orient`` tests, unwound next to each start) hit a part, at the
        end pose or on the way.
        Beads are not looked at."""
        row = int(self.rows[level])
        r = self.stage.rows
        m = len(N)
        if self.is_vector:
            end = self.orient(np.full(m, level), N)[0]
        else:
            P = self.point(np.full(m, level), N)
            end = np.array([self.kin.inverse(P[j], N[j], start_words[j], tcp=bool(self.tcp[level]),
                                             branch=self.programmed[level]) for j in range(m)])
        moves = Moves(start_words, end, np.repeat(r.tcp[row:row + 1], m), np.repeat(r.known_start[row:row + 1], m),
                      np.zeros(m, dtype=bool), np.repeat(r.arc[row:row + 1], m, axis=0))
        hits, _ = self.path.check(moves, BeadStore(0.0), 0, commit=False)
        self.stage.samples += hits.samples
        return hits.part_hit.any(axis=1)

    def words_of(self, N: np.ndarray, programmed: np.ndarray) -> np.ndarray:
        """The words of a whole solution (L, 3) in program order: rows keeping their programmed
        orientation keep their words exactly; rotary axes take the branch ``orient`` tested (the
        one nearest the level's programmed words: the pose ``free`` found free), unwound next to
        the block before. (Chosen next to the block before, the branch flipped where the blocks
        before were tilted near the pole, and the block ended 180° from its tested spin.)"""
        words = self.programmed.copy()
        previous = self.before_words if self.before_words is not None else self.programmed[0]
        for i in range(len(N)):
            if not programmed[i]:
                if self.is_vector:
                    words[i] = self.orient(np.array([i]), N[i:i + 1])[0][0]
                else:
                    P = self.point(np.array([i]), N[i:i + 1])[0]
                    try:
                        words[i] = self.kin.inverse(P, N[i], previous, tcp=bool(self.tcp[i]), branch=self.programmed[i])
                    except Unreachable:
                        words[i] = self.orient(np.array([i]), N[i:i + 1])[0][0]
            previous = words[i]
        return words

    def recheck(self, words: np.ndarray) -> np.ndarray:
        """(L,) bool: levels whose move (end pose and sweep) collides with these words, with the
        solution's own beads; the row after, when its sweep from the last level collides, marks
        the last level. Moves that nothing changed since the last re-check keep its result
        (``Rechecks``)."""
        stage = self.stage
        r = stage.rows
        end = self.last + 1 if self.after_row is None else self.last + 2
        saved = r.words[self.first:end].copy()
        try:
            r.words[self.first:self.last + 1] = stage.as_printed(self.rows, words)  # checked as written
            bad = self.checks.check(stage.moves(self.first, end))
        finally:
            r.words[self.first:end] = saved
        out = bad[:len(self.rows)].copy()
        if self.after_row is not None and bad[-1]:
            out[-1] = True
        return out


@dataclass
class _Search:
    """One episode's lazy search (``GraphStrategy.solve``): the candidates and their graph, and
    what the rounds found."""

    ep: Episode
    cands: np.ndarray  # (L, K, 3) candidate orientations of each level
    valid: np.ndarray  # (L, K) bool: reachable, within Θ and the cone
    graph: LayeredGraph
    state: np.ndarray  # (L, K) int8: 0 untested, 1 free, 2 colliding
    # (level, vertex) -> the vertices before it whose moves into it failed the re-check
    fails: dict[tuple[int, int], set[int]] = field(default_factory=dict)
    # Levels given up because the level before was left colliding: their states before that.
    given_up: dict[int, np.ndarray] = field(default_factory=dict)
    reopens: int = 0  # times given-up levels were searched again
    # Levels left colliding that ``_prove_stuck`` tried, and why those it marked are stuck.
    proved: set[int] = field(default_factory=set)
    stuck: dict[int, str] = field(default_factory=dict)
    part_free: dict[int, np.ndarray] = field(default_factory=dict)  # ``GraphStrategy._part_free``
    failed_rechecks: dict[int, int] = field(default_factory=dict)  # level -> re-checks its move failed


class GraphStrategy:
    """Orientation graph + shortest path (seed steps 1–3, after Nishat et al.), searched lazily.

    Levels: the episode's rows, between the pose before (as written) and the row after (as
    programmed); vertices: candidates of the shared sphere grid within Θ of each programmed
    orientation that can still reach both ends in steps within the limits (the cone test).
    Testing every vertex would cost a collision test per candidate and level (thousands per
    block), so the search is lazy (as in Lazy PRM):

    1. A coarse subset of each level's candidates (about ``COARSE`` resolutions apart) is tested;
       an untested candidate is *promising* when its nearest tested neighbour is free.
    2. The cheapest path over free and promising vertices is found; its untested vertices are
       tested, with the ``BATCH`` untested candidates nearest to each, and the search runs
       again, until the path is made of tested free vertices only. Then every untested vertex
       becomes eligible, for a last few rounds, in case the coarse test missed a narrow passage.
    3. The path is re-checked whole (sweeps, its own beads); the edges of a move that fails there
       are removed (lazy edge evaluation: between the neighbourhoods of its two vertices), a
       vertex whose moves fail from ``FAIL_SOURCES`` vertices before it is dropped, and the
       search goes on.

    A colliding block may keep its programmed orientation at a cost ``UNRESOLVED_COST``: the path
    always exists (the programmed path is within the limits), and it leaves as few blocks
    colliding as the limits allow; those are reported as unresolved.
    """

    name = "graph"
    BATCH = 24  # untested candidates tested per level on the path, per round
    COARSE = 4.0  # spacing of the first tests, in resolutions
    MAX_ROUNDS = 200
    OPEN_ROUNDS = 3  # rounds with every untested vertex eligible, after the promising ones
    UNRESOLVED_COST = 1e4  # per block left colliding; far above any tilt or step cost
    FAIL_SOURCES = 3  # a vertex whose moves fail from this many vertices before it is dropped
    REOPENS = 2  # searches again with the levels given up after a level since freed
    PROOF_PAIRS = 4096  # moves checked at most to show that no move frees a level (``_prove_stuck``)
    PROOF_BATCH = 32  # moves checked at once there, until one is free

    def __init__(self, options: Options) -> None:
        self.max_tilt = float(options.max_tilt)
        self.max_step = float(options.max_step)
        self.grid = SphereGrid(float(options.resolution))
        self.coarse = SphereGrid(float(options.resolution) * self.COARSE)
        self.near_cos = float(np.cos(np.radians(1.5 * float(options.resolution))))

    def solve(self, ep: Episode) -> Solution:
        L = len(ep.rows)
        cands, valid = level_candidates(self.grid, ep.N0, self.max_tilt)
        valid &= _cone(cands, ep, L)
        ext_c, ext_v, ext_p, limits, turns = _with_anchors(ep, cands, valid)
        state = np.zeros(valid.shape, dtype=np.int8)
        state[:, 0] = np.where(ep.is_colliding, 2, 1)  # detection tested the programmed moves
        s = _Search(ep, cands, valid, LayeredGraph(ext_c, ext_v, ext_p, limits, turns=turns,
                                                      plain_limit=self.max_step + STEP_SLACK_DEG), state)
        promising = self._seed(ep, cands, valid, state)
        rows_l = np.arange(L)
        open_rounds = 0
        best = None
        capped = False  # the search ran out of rounds (MAX_ROUNDS) before it settled
        for _round in range(self.MAX_ROUNDS):
            eligible = (state == 1) | ((state == 0) & (promising | (open_rounds > 0)))
            allowed = valid & eligible
            allowed[:, 0] = True  # the programmed orientation: free, or left colliding at a cost
            penalty = np.zeros((L + 2, valid.shape[1]))
            penalty[1:L + 1, 0] = np.where(state[:, 0] == 2, self.UNRESOLVED_COST, 0.0)
            path = s.graph.cheapest(_anchored(allowed), penalty)
            if path is None:  # cannot happen while the programmed path is allowed; be safe
                break
            pick = path[1:L + 1]
            untested = state[rows_l, pick] == 0
            if untested.any():
                self._test_near(ep, cands, valid, state, np.nonzero(untested)[0], pick)
                continue
            left = (pick == 0) & (state[:, 0] == 2)  # blocks left colliding
            if self._prove_stuck(s, left):
                continue
            words = ep.words_of(cands[rows_l, pick], pick == 0)
            bad = ep.recheck(words) & ~left
            # A move that starts at a pose left colliding collides whatever its end.
            after_left = bad & np.concatenate([[False], left[:-1]])
            tilted = after_left & (pick != 0)
            if tilted.any():
                self._give_up(s, tilted)
                continue
            left |= after_left  # kept as programmed: left colliding with the level before
            bad &= ~after_left
            if bad.any():
                self._ban(s, bad, pick)
                continue
            if best is None or left.sum() < best[1].sum():
                best = (words, left)
            if self._reopen(s, left):
                open_rounds = 0
                continue
            if not left.any() or open_rounds == 1:
                break
            # Some blocks are left colliding: let every untested vertex in for a few rounds.
            open_rounds = self.OPEN_ROUNDS if open_rounds == 0 else open_rounds - 1
        else:
            capped = True
        if best is None:
            rows = [int(r) for r in ep.colliding]
            if capped:
                why = self._limit(s)
            elif s.failed_rechecks:  # the re-checks' bans took the last path
                why = ("every path within the limits that frees it makes a block collide that does not as programmed "
                       f"(the re-checks failed most often at the moves into lines {self._failed_lines(s)})")
            else:
                why = (f"no path keeps every step within {self.max_step:g}° (--max-step) "
                       f"and the tilt within {self.max_tilt:g}°")
            return Solution(ep.programmed.copy(), rows, {r: why for r in rows})
        words, left = best
        words = blend_episode(ep, words, left)
        rows = [int(ep.rows[i]) for i in np.nonzero(left)[0]]
        return Solution(words, rows, self._reasons(s, left, capped))

    def _prove_stuck(self, s: "_Search", levels: np.ndarray) -> bool:
        """Mark those of ``levels`` (L,) bool that no move can free: the search stops trying them
        (else its rounds go there, lazily, up to MAX_ROUNDS) and their reason says why.

        At such a level and the level before, every valid candidate is tested against the parts
        and the beads laid before the episode (what no solution changes); every move between a
        free candidate before and a free one at the level, within the step limits, is checked
        against the parts (end pose and sweep). When each collides, no path of candidates frees
        the level, whatever the beads do. Tried once per level, when at most PROOF_PAIRS moves
        are to be checked; whether any level was marked."""
        ep, marked = s.ep, False
        for i in np.nonzero(levels)[0].tolist():
            if i in s.proved or i in s.given_up or (i == 0 and not ep.start_known):
                continue
            s.proved.add(i)
            to = self._part_free(s, i)
            if len(to) > self.PROOF_PAIRS:
                continue
            if i == 0:
                starts, start_words = np.array([0]), ep.before_words[None, :]
            else:
                starts = self._part_free(s, i - 1)
                if not len(starts):  # held by the level before, not stuck on its own
                    continue
                start_words = ep.orient(np.full(len(starts), i - 1), s.cands[i - 1, starts])[0]
            sources = s.graph.candidates[i][starts]  # level i of the graph is episode level i - 1
            _, allowed = s.graph.steps(i + 1, sources, s.cands[i, to])
            b, a = np.nonzero(allowed)
            if len(a) > self.PROOF_PAIRS or not self._all_hit(s, i, start_words, sources, a, to[b]):
                continue
            if not len(to):
                s.stuck[i] = f"no free orientation within {self.max_tilt:g}° (--max-tilt) and the machine's limits"
            elif not len(a):
                s.stuck[i] = (f"no move frees it: none of its {len(to)} orientations free of the parts within "
                              f"{self.max_tilt:g}° (--max-tilt) is within {self.max_step:g}° (--max-step) of the "
                              f"{len(starts)} of the block before")
            else:
                s.stuck[i] = (f"no move frees it: its {len(to)} orientations free of the parts within "
                              f"{self.max_tilt:g}° (--max-tilt) are reached from the {len(starts)} of the block "
                              f"before, within {self.max_step:g}° (--max-step), only through the part (each such "
                              "move collides)")
            s.state[i, 1:] = 2
            marked = True
        return marked

    def _all_hit(self, s: "_Search", level: int, start_words: np.ndarray, sources: np.ndarray, a: np.ndarray,
                 targets: np.ndarray) -> bool:
        """Whether every move into ``level`` from start_words[a] (orientations sources[a]) to the
        candidates ``targets`` hits a part: checked PROOF_BATCH at a time, the shortest steps
        first, up to the first batch with a free move (one is enough to stop; a free move costs
        the most to check: every sample of its sweep)."""
        N = s.cands[level, targets]
        order = np.argsort(-np.einsum("ij,ij->i", N, sources[a]), kind="stable")
        for lo in range(0, len(order), self.PROOF_BATCH):
            pick = order[lo:lo + self.PROOF_BATCH]
            if not s.ep.moves_hit_parts(level, start_words[a[pick]], N[pick]).all():
                return False
        return True

    def _part_free(self, s: "_Search", level: int) -> np.ndarray:
        """The valid candidates of a level free of the parts and the beads laid before the episode
        (tested once per level)."""
        if level not in s.part_free:
            idx = np.flatnonzero(s.valid[level])
            s.part_free[level] = idx[s.ep.free(np.full(len(idx), level), s.cands[level, idx], beads=False)]
        return s.part_free[level]

    def _give_up(self, s: "_Search", tilted: np.ndarray) -> None:
        """The tilted levels whose moves start at a pose left colliding keep their programmed
        orientation (given up: searched again if the level before is freed later, ``_reopen``).
        Where that programmed pose itself collides, so does every move out of it: the level after
        goes with it, and so on (else the search gives them up one round at a time)."""
        programmed_free = s.ep.programmed_free()
        for i in np.nonzero(tilted)[0].tolist():
            while i < len(s.state) and i not in s.given_up:
                s.given_up[i] = s.state[i].copy()
                s.state[i, 1:] = 2
                if programmed_free[i]:
                    break
                i += 1

    def _ban(self, s: "_Search", bad: np.ndarray, pick: np.ndarray) -> None:
        """The end poses were tested free: the moves into them (their sweeps, the path's own beads)
        are in the way. The edges between the two vertices' neighbourhoods on the grid go (they
        sweep the same way); a vertex whose moves fail from FAIL_SOURCES different vertices before
        it goes too (its own beads, not the way in)."""
        L = len(pick)
        for i in np.nonzero(bad)[0].tolist():
            s.failed_rechecks[i] = s.failed_rechecks.get(i, 0) + 1
            targets = self._near(s.cands, s.valid, i, pick[i])
            sources = self._near(s.cands, s.valid, i - 1, pick[i - 1]) if i > 0 else np.array([0])
            # A tilted move's ban spares the programmed edge (vertex 0 to vertex 0) between the
            # neighbourhoods: it is the way to leave the blocks as programmed (before, the ban of
            # a move near the programmed orientations took it too, no path was left, and the whole
            # episode went back as programmed). Only the programmed move's own failure bans it
            # (the blocks changed before it make it collide: leaving it so is no answer).
            spare = not (pick[i] == 0 and (i == 0 or pick[i - 1] == 0))
            self._ban_edges(s.graph, i + 1, sources, targets, spare)
            if i == L - 1:  # or the move out of it, into the row after
                self._ban_edges(s.graph, L + 1, targets, np.array([0]), spare)
            failed = s.fails.setdefault((i, int(pick[i])), set())
            failed.add(int(pick[i - 1]) if i > 0 else -1)
            if len(failed) >= self.FAIL_SOURCES and not (pick[i] == 0 and s.state[i, 0] == 1):
                s.state[i, pick[i]] = 2

    @staticmethod
    def _ban_edges(graph: LayeredGraph, level: int, sources: np.ndarray, targets: np.ndarray, spare: bool) -> None:
        """``graph.ban`` of every edge from ``sources`` to ``targets``; with ``spare``, all but the
        programmed edge (vertex 0 to vertex 0)."""
        sources, targets = np.asarray(sources), np.asarray(targets)
        if not spare or not ((sources == 0).any() and (targets == 0).any()):
            graph.ban(level, sources, targets)
            return
        graph.ban(level, sources[sources != 0], targets)
        graph.ban(level, np.array([0]), targets[targets != 0])

    def _reopen(self, s: "_Search", left: np.ndarray) -> bool:
        """Levels given up after a level that this path frees are searched again, with the run
        given up after them (at most REOPENS times); whether any was."""
        stale = [i for i in s.given_up if not left[i - 1]]
        if not stale or s.reopens >= self.REOPENS:
            return False
        s.reopens += 1
        for i in sorted(stale):
            while i in s.given_up:
                s.state[i] = s.given_up.pop(i)
                i += 1
        return True

    def _limit(self, s: "_Search") -> str:
        """Why a level is left when the rounds ran out: the limit, and the lines whose moves failed
        the re-checks most often (where the search was stuck)."""
        why = (f"the search stopped at its {self.MAX_ROUNDS}-round limit (an episode of {len(s.ep.rows)} blocks) "
               "before a path freeing it passed the re-check")
        if s.failed_rechecks:
            why += f"; the moves into lines {self._failed_lines(s)} failed it most often"
        return why

    @staticmethod
    def _failed_lines(s: "_Search") -> str:
        """The (up to 4) input lines whose moves failed the re-checks most often, with the count."""
        top = sorted(s.failed_rechecks.items(), key=lambda kv: (-kv[1], kv[0]))[:4]
        return ", ".join(f"{int(s.ep.lines[i])} ({n}x)" for i, n in sorted(top))

    def _reasons(self, s: "_Search", left: np.ndarray, capped: bool) -> dict[int, str]:
        """Why each level left colliding is: by what its candidates' states say."""
        reasons = {}
        for i in np.nonzero(left)[0].tolist():
            row = int(s.ep.rows[i])
            if i in s.stuck:
                reasons[row] = s.stuck[i]
                continue
            if i > 0 and left[i - 1] and (i in s.given_up or s.state[i, 0] == 1):
                reasons[row] = "its move starts at the block before, which is left colliding"
                continue
            free_any = (s.valid[i] & (s.state[i] == 1)).any()
            untested = (s.valid[i] & (s.state[i] == 0)).any()
            if not free_any and not untested:
                why = f"no free orientation within {self.max_tilt:g}° (--max-tilt) and the machine's limits"
            elif capped:
                why = self._limit(s)
            elif free_any:
                why = (f"a free orientation exists, but no path to it keeps every step within {self.max_step:g}° "
                       f"(--max-step) while the blocks around it stay free")
            else:
                why = f"no free orientation found within {self.max_tilt:g}° (--max-tilt) among those tested"
            reasons[row] = why
        return reasons

    def _near(self, cands, valid, level: int, vertex: int) -> np.ndarray:
        """The valid candidates of a level within 1.5 resolutions of one of them (itself included)."""
        close = valid[level] & (cands[level] @ cands[level, vertex] >= self.near_cos)
        close[vertex] = True
        return np.flatnonzero(close)

    def _seed(self, ep: Episode, cands, valid, state) -> np.ndarray:
        """Test each level's candidates nearest to the coarse grid; (L, K) bool: untested
        candidates whose nearest tested candidate at the same level is free."""
        L, K = valid.shape
        lv_all, ci_all = [], []
        for lv in range(L):
            idx = np.flatnonzero(valid[lv])
            cap = self.coarse.cap(ep.N0[lv], self.max_tilt)
            if len(cap) == 0 or len(idx) == 0:
                continue
            near = nearest(self.coarse.points[cap], cands[lv, idx])
            take = np.unique(idx[near])
            take = take[state[lv, take] == 0]
            lv_all.append(np.full(len(take), lv)), ci_all.append(take)
        if lv_all:  # none where Θ is below the coarse grid's spacing
            lv, ci = np.concatenate(lv_all), np.concatenate(ci_all)
            state[lv, ci] = np.where(ep.free(lv, cands[lv, ci]), 1, 2)
        promising = np.zeros((L, K), dtype=bool)
        for lv in range(L):
            tested = np.flatnonzero(valid[lv] & (state[lv] > 0))
            todo = np.flatnonzero(valid[lv] & (state[lv] == 0))
            if len(tested) == 0 or len(todo) == 0:
                continue
            promising[lv, todo] = state[lv, tested[nearest(cands[lv, todo], cands[lv, tested])]] == 1
        return promising

    def _test_near(self, ep: Episode, cands, valid, state, levels: np.ndarray, pick: np.ndarray) -> None:
        """Test, at each level, the untested candidates nearest to the path's vertex there."""
        lv_all, ci_all = [], []
        for lv in levels:
            open_ = np.flatnonzero(valid[lv] & (state[lv] == 0))
            near = cands[lv, open_] @ cands[lv, pick[lv]]
            take = open_[np.argsort(-near, kind="stable")[:self.BATCH]]
            lv_all.append(np.full(len(take), lv)), ci_all.append(take)
        lv, ci = np.concatenate(lv_all), np.concatenate(ci_all)
        state[lv, ci] = np.where(ep.free(lv, cands[lv, ci]), 1, 2)


def blend_episode(ep: Episode, words: np.ndarray, left: np.ndarray) -> np.ndarray:
    """The solution's ramps and runs eased with Bezier curves (``ncfix.correct.blend``): the
    colliding levels keep the orientation the strategy found for them, unchanged levels stay
    exactly as programmed, the levels between are replaced by a smooth curve within the step
    limits. The blended episode is re-checked whole; when it collides, the spans around each
    failing level go back to the strategy's orientations and it is checked again (up to
    ``BLEND_ROUNDS`` times, else the strategy's words are kept)."""
    L = len(ep.rows)
    if L < 3:
        return words
    N = ep.path.forward(words, ep.tcp)[1]
    unchanged = np.all(words == ep.programmed, axis=1)
    keep = ep.is_colliding | unchanged | left
    keep[0] = keep[-1] = True
    for _ in range(BLEND_ROUNDS):
        if keep.all():
            return words
        Nb = blend(ep.N0, N, keep, ep.max_step, limits_deg=ep.limits[:L])
        same = np.all(Nb == ep.N0, axis=1)
        out = ep.words_of(Nb, same)
        out[keep] = words[keep]
        bad = ep.recheck(out) & ~left
        if not bad.any():
            return out
        keep |= bad
        keep[np.maximum(np.nonzero(bad)[0] - 1, 0)] = True
    return words


def _anchored(allowed: np.ndarray) -> np.ndarray:
    """The allowed mask with the two anchor levels (candidate 0 only) around it."""
    L, K = allowed.shape
    out = np.zeros((L + 2, K), dtype=bool)
    out[1:L + 1] = allowed
    out[0, 0] = out[-1, 0] = True
    return out


def _with_anchors(ep: Episode, cands, allowed):
    """Candidates with an anchor level before and after: the pose before (or, at the program's
    start, the first programmed orientation with no step limit) and the row after; with the step
    limits and turns of the graph's levels (``Episode.turns``)."""
    L, K = allowed.shape
    before = ep.N_before if ep.N_before is not None else ep.N0[0]
    if ep.N_after is not None:
        after = ep.N_after
        after_limit, after_turn = ep.step_limits[-1], ep.turns[-1]
    else:
        after, after_limit, after_turn = ep.N0[-1], 180.0, np.eye(3)
    ext_c = np.concatenate([np.repeat(before[None, None, :], K, axis=1), cands,
                            np.repeat(after[None, None, :], K, axis=1)])
    ext_f = np.concatenate([np.zeros((1, K), dtype=bool), allowed, np.zeros((1, K), dtype=bool)])
    ext_f[0, 0] = ext_f[-1, 0] = True
    ext_p = np.vstack([before, ep.N0, after])
    limits = np.concatenate([[0.0], ep.step_limits[:L], [after_limit]])
    turns = np.concatenate([np.eye(3)[None], ep.turns[:L], after_turn[None]])
    return ext_c, ext_f, ext_p, limits, turns


def _cone(cands: np.ndarray, ep: Episode, L: int) -> np.ndarray:
    """(L, K) bool: candidates that can be reached from the pose before and can still reach the
    row after, within the steps' limits (spherical triangle inequality)."""
    ok = np.ones(cands.shape[:2], dtype=bool)
    if ep.N_before is not None:
        reach = np.cumsum(ep.limits[:L])
        ok &= angle_between_deg(cands, ep.N_before[None, None, :]) <= reach[:, None] + 1e-9
    if ep.N_after is not None:
        reach = np.cumsum(ep.limits[1:L + 1][::-1])[::-1]
        ok &= angle_between_deg(cands, ep.N_after[None, None, :]) <= reach[:, None] + 1e-9
    ok[:, 0] = True  # the programmed orientation itself is always a candidate
    return ok
