"""Solving one collision episode: what every strategy shares, and the orientation-graph strategy.

An episode's *levels* are consecutive motion rows. ``Episode`` gives a strategy the programmed
poses, the machine (orientation → words, reachability), a batched conservative test of candidate
orientations, and the full re-check of a solution (end poses, sweeps, and the solution's own
beads). A strategy returns the words of every level and the rows it could not free.

Pivot (CONTRACT.md): ``tip`` keeps the head tip C = P + h·N and moves the programmed point to
P′ = C − h·N′; ``point`` keeps P (the tip moves to P + h·N′).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ncfix.correct.candidates import SphereGrid, level_candidates
from ncfix.correct.graph import cheapest_path
from ncfix.geometry.frames import angle_between_deg, minimal_rotation
from ncfix.kinematics.base import Unreachable

# A step may exceed θ only where the program's own step did: by this much at most (degrees).
STEP_SLACK_DEG = 1e-6
# Rounds of "solve, re-check with sweeps, drop the candidates that failed" before giving up.
VERIFY_ROUNDS = 8


@dataclass
class Solution:
    words: np.ndarray  # (L, k) words of every level
    unresolved: list[int] = field(default_factory=list)  # row indices left colliding
    reasons: dict[int, str] = field(default_factory=dict)


class Episode:
    """Levels ``first .. last`` of the stage's row table, with everything a strategy needs."""

    def __init__(self, stage, first: int, last: int, colliding: np.ndarray):
        r = stage.rows
        self.stage = stage
        self.path = stage.path
        self.checker = stage.checker
        self.kin = stage.profile.kinematics
        self.is_vector = stage.profile.is_vector
        self.first, self.last = first, last
        self.rows = np.arange(first, last + 1)
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
        moves = stage._moves(first, first + 1)
        self.start_known = bool(moves.known_start[0])
        self.before_words = moves.w_start[0] if self.start_known else None
        self.after_row = last + 1 if last + 1 < len(r) else None
        theta = float(stage.options.max_step)
        # Step limit into each level and into the row after: θ, or the program's own step.
        _, n_before, _ = self.path.forward(self._prev_programmed()[None, :], self.tcp[:1]) if self.start_known \
            else (None, self.N0[:1], None)
        chain = np.vstack([n_before, self.N0])
        if self.after_row is not None:
            _, n_after, _ = self.path.forward(r.programmed[self.after_row][None, :], r.tcp[self.after_row:self.after_row + 1])
            chain = np.vstack([chain, n_after])
        own = angle_between_deg(chain[1:], chain[:-1])
        self.limits = np.maximum(theta, own) + STEP_SLACK_DEG  # (L,) or (L+1,) with the row after
        if not self.start_known:
            self.limits[0] = 180.0
        if self.after_row is not None and not r.known_start[self.after_row]:
            self.limits[-1] = 180.0
        # Beads of the programmed moves, seen from their own level on (candidate tests only; the
        # re-check uses the solution's own beads).
        self.bead_pts, self.bead_seq = self._programmed_beads()

    def _prev_programmed(self) -> np.ndarray:
        r = self.stage.rows
        return r.programmed[self.first - 1] if self.first > 0 else self.stage.prev_programmed

    def _programmed_beads(self):
        stage = self.stage
        pts, seq = [], []
        for i, row in enumerate(self.rows):
            moves = stage._moves(int(row), int(row) + 1)
            moves.w_end = self.programmed[i:i + 1]
            if i > 0:
                moves.w_start = self.programmed[i - 1:i]
            b = self.path.bead_points(moves)
            pts.append(b)
            seq.append(np.full(len(b), i, dtype=np.int64))
        return np.concatenate(pts) if pts else np.zeros((0, 3)), np.concatenate(seq) if seq else np.zeros(0, np.int64)

    # -- the machine -----------------------------------------------------------------------------
    def orient(self, level: np.ndarray, N: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Words (m, k), head rotation (m, 3, 3) and reachability (m,) of orientation N at levels."""
        level = np.asarray(level, dtype=np.int64)
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        P = self.C0[level] - self.h * N if self.pivot_tip else self.P0[level]
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

    def free(self, level: np.ndarray, N: np.ndarray) -> np.ndarray:
        """Conservative: (m,) True where orientation N at that level is reachable and its end pose
        is free of the parts and of the (programmed) beads laid up to that level."""
        words, R, ok = self.orient(level, N)
        out = np.zeros(len(level), dtype=bool)
        if not ok.any():
            return out
        idx = np.nonzero(ok)[0]
        lv = np.asarray(level)[idx]
        P = self.path.forward(words[idx], self.tcp[lv])[0]
        C = P + self.h * (N[idx] / np.linalg.norm(N[idx], axis=1, keepdims=True))
        out[idx] = self.checker.free_poses(C, R[idx], lv.astype(np.int64), self.stage.store,
                                          self.bead_pts, self.bead_seq)
        return out

    def words_of(self, N: np.ndarray, programmed: np.ndarray) -> np.ndarray:
        """The words of a whole solution (L, 3) in program order: rows keeping their programmed
        orientation keep their words exactly; rotary axes take the branch nearest the block before."""
        words = self.programmed.copy()
        previous = self.before_words if self.before_words is not None else self.programmed[0]
        for i in range(len(N)):
            if not programmed[i]:
                if self.is_vector:
                    words[i] = self.orient(np.array([i]), N[i:i + 1])[0][0]
                else:
                    P = self.C0[i] - self.h * N[i] if self.pivot_tip else self.P0[i]
                    try:
                        words[i] = self.kin.inverse(P, N[i], previous, tcp=bool(self.tcp[i]))
                    except Unreachable:
                        words[i] = self.orient(np.array([i]), N[i:i + 1])[0][0]
            previous = words[i]
        return words

    def recheck(self, words: np.ndarray) -> np.ndarray:
        """(L,) bool: levels whose move (end pose and sweep) collides with these words, with the
        solution's own beads; the row after, when its sweep from the last level collides, marks
        the last level."""
        stage = self.stage
        r = stage.rows
        end = self.last + 1 if self.after_row is None else self.last + 2
        saved = r.words[self.first:end].copy()
        try:
            r.words[self.first:self.last + 1] = words
            hits, _ = self.path.check(stage._moves(self.first, end), stage.store, 0, commit=False)
        finally:
            r.words[self.first:end] = saved
        stage.samples += hits.samples
        bad = hits.any
        out = bad[:len(self.rows)].copy()
        if self.after_row is not None and bad[-1]:
            out[-1] = True
        return out


class GraphStrategy:
    """Orientation graph + shortest path (seed steps 1–3, after Nishat et al.).

    Levels: the episode's rows, between the pose before (as written) and the row after (as
    programmed); vertices: free candidates of the shared sphere grid within Θ of each programmed
    orientation, and only those that can still reach both ends in steps within the limits (the
    cone test); candidates are tested lazily, the nearest to the programmed orientation first
    (tilt bounds of Θ/3, 2Θ/3, Θ); the cheapest path is re-checked with sweeps and its own beads,
    and the candidates that fail are dropped until it holds.
    """

    name = "graph"

    def __init__(self, options):
        self.max_tilt = float(options.max_tilt)
        self.grid = SphereGrid(float(options.resolution))

    def solve(self, ep: Episode) -> Solution:
        L = len(ep.rows)
        cands, valid = level_candidates(self.grid, ep.N0, self.max_tilt)
        dev = angle_between_deg(cands, ep.N0[:, None, :])
        valid &= _cone(cands, ep, L)
        free = np.zeros_like(valid)
        tested = np.zeros_like(valid)
        forced = np.zeros(L, dtype=bool)  # levels left as programmed (no free orientation)
        reasons: dict[int, str] = {}
        bounds = sorted({min(self.max_tilt, b) for b in (self.max_tilt / 3, 2 * self.max_tilt / 3, self.max_tilt)})
        for bound in bounds:
            need = valid & ~tested & (dev <= bound + 1e-9)
            lv, ci = np.nonzero(need)
            if len(lv):
                free[lv, ci] = ep.free(lv, cands[lv, ci])
                tested |= need
            found = self._search(ep, cands, free, forced)
            if found is not None:
                return Solution(found, [], {})
        # Nothing holds within Θ: levels with no free candidate at all stay as programmed.
        blocked = ep.is_colliding & ~(free & valid)[:, 1:].any(axis=1) & ~free[:, 0]
        for i in np.nonzero(blocked)[0]:
            forced[i] = True
            reasons[int(ep.rows[i])] = (f"no free orientation within {self.max_tilt:g}° "
                                        "(--max-tilt) and the machine's limits")
        if forced.any():
            found = self._search(ep, cands, free, forced)
            if found is not None:
                return Solution(found, [int(ep.rows[i]) for i in np.nonzero(forced)[0]], reasons)
        rows = [int(r) for r in ep.colliding]
        why = (f"no path keeps every step within {ep.stage.options.max_step:g}° (--max-step) "
               f"and the tilt within {self.max_tilt:g}°")
        return Solution(ep.programmed.copy(), rows, {r: reasons.get(r, why) for r in rows})

    def _search(self, ep: Episode, cands, free, forced) -> np.ndarray | None:
        """Cheapest path on the free candidates, re-checked; None when none holds."""
        L = len(ep.rows)
        allowed = free.copy()
        allowed[forced] = False
        allowed[forced, 0] = True
        for _ in range(VERIFY_ROUNDS):
            ext_c, ext_f, ext_p, limits = _with_anchors(ep, cands, allowed)
            path = cheapest_path(ext_c, ext_f, ext_p, limits)
            if path is None:
                return None
            pick = path[1:L + 1]
            N = cands[np.arange(L), pick]
            words = ep.words_of(N, pick == 0)
            bad = ep.recheck(words) & ~forced
            if not bad.any():
                return words
            allowed[np.nonzero(bad)[0], pick[bad]] = False
        return None


def _with_anchors(ep: Episode, cands, allowed):
    """Candidates with an anchor level before and after: the pose before (or, at the program's
    start, the first programmed orientation with no step limit) and the row after."""
    L, K = allowed.shape
    before = ep.path.forward(ep.before_words[None, :], ep.tcp[:1])[1][0] if ep.before_words is not None else ep.N0[0]
    if ep.after_row is not None:
        r = ep.stage.rows
        after = ep.path.forward(r.programmed[ep.after_row][None, :], r.tcp[ep.after_row:ep.after_row + 1])[1][0]
        after_limit = ep.limits[-1]
    else:
        after, after_limit = ep.N0[-1], 180.0
    ext_c = np.concatenate([np.repeat(before[None, None, :], K, axis=1), cands,
                            np.repeat(after[None, None, :], K, axis=1)])
    ext_f = np.concatenate([np.zeros((1, K), dtype=bool), allowed, np.zeros((1, K), dtype=bool)])
    ext_f[0, 0] = ext_f[-1, 0] = True
    ext_p = np.vstack([before, ep.N0, after])
    limits = np.concatenate([[0.0], ep.limits[:L], [after_limit]])
    return ext_c, ext_f, ext_p, limits


def _cone(cands: np.ndarray, ep: Episode, L: int) -> np.ndarray:
    """(L, K) bool: candidates that can be reached from the pose before and can still reach the
    row after, within the steps' limits (spherical triangle inequality)."""
    ok = np.ones(cands.shape[:2], dtype=bool)
    if ep.before_words is not None:
        before = ep.path.forward(ep.before_words[None, :], ep.tcp[:1])[1][0]
        reach = np.cumsum(ep.limits[:L])
        ok &= angle_between_deg(cands, before[None, None, :]) <= reach[:, None] + 1e-9
    if ep.after_row is not None:
        r = ep.stage.rows
        after = ep.path.forward(r.programmed[ep.after_row][None, :], r.tcp[ep.after_row:ep.after_row + 1])[1][0]
        reach = np.cumsum(ep.limits[1:L + 1][::-1])[::-1]
        ok &= angle_between_deg(cands, after[None, None, :]) <= reach[:, None] + 1e-9
    ok[:, 0] = True  # the programmed orientation itself is always a candidate
    return ok


def make_strategy(options):
    if options.strategy == "graph":
        return GraphStrategy(options)
    raise NotImplementedError(options.strategy)

