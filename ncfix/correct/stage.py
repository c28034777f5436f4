"""The correction stage: finds collision episodes in the stream and tilts the head out of them.

It holds the chunks it has not finished and works forward through their motion rows in a fixed
order, so its decisions do not depend on how the input is split into chunks or windows; a row's
detection is reused until its move or the beads within its reach change. Design:
docs/correction.md#episodes; the order of work on ``CorrectStage``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ncfix.collision.checker import Checker
from ncfix.collision.deposit import BeadField, BeadStore
from ncfix.collision.path import MoveHits, Moves, PathChecker, join_beads
from ncfix.collision.stage import MotionRows, PlacementCheck, collision_entry
from ncfix.correct.extrusion import follow
from ncfix.correct.solve import Episode, Solution, Strategy
from ncfix.geometry.frames import angle_between_deg
from ncfix.nc.emit import printed_decimals, word_kind
from ncfix.nc.modal import MM_PER_INCH
from ncfix.profiles import Profile

if TYPE_CHECKING:
    from ncfix.config import Options
    from ncfix.geometry.mesh import LoadedMesh
    from ncfix.report import Report


@dataclass
class Rows:
    """The motion rows of the held chunks (every axis known), in program order."""

    chunk: np.ndarray  # (n,) int64: serial number of the chunk the row is in
    row: np.ndarray  # (n,) int64: line index in that chunk
    line: np.ndarray  # (n,) int64: 1-based input line
    programmed: np.ndarray  # (n, k) words as programmed (normalised tool vectors)
    words: np.ndarray  # (n, k) words as they will be written
    tcp: np.ndarray  # (n,) bool
    known_start: np.ndarray  # (n,) bool: the sweep from the previous row is checkable
    deposit: np.ndarray  # (n,) bool
    arc: np.ndarray  # (n, 5) Chunk.arc (NaN on straight moves)

    @classmethod
    def empty(cls, k: int) -> "Rows":
        z = np.zeros(0, dtype=np.int64)
        b = np.zeros(0, dtype=bool)
        return cls(z, z, z, np.zeros((0, k)), np.zeros((0, k)), b, b, b, np.zeros((0, 5)))

    def __len__(self) -> int:
        return len(self.row)

    def append(self, other: "Rows") -> "Rows":
        return Rows(*(np.concatenate([getattr(self, f), getattr(other, f)]) for f in self.__dataclass_fields__))

    def drop(self, count: int) -> "Rows":
        return Rows(*(getattr(self, f)[count:] for f in self.__dataclass_fields__))


# Runs of rows to check again that are at most this many reusable rows apart are checked as one
# (fewer calls; the rows between get the same result again).
MERGE_GAP = 4
# Lines whose decimals ``as_printed`` keeps (a line's words are parsed once, not at every re-check).
DECIMALS_KEPT = 4096


@dataclass
class Detected:
    """The last detection of each row of the table (aligned with ``Rows``) and what it saw: the
    words of its sweep start and end, its poses (samples and sweep start) and their largest
    sweep margin, and the box of the deposit tree's balls at those poses (world mm)."""

    valid: np.ndarray  # (n,) bool: the result below is the row's current one (until words change)
    start: np.ndarray  # (n, k) words of the sweep start used (as ``Moves.w_start``)
    end: np.ndarray  # (n, k)
    lo: np.ndarray  # (n, 3) head box
    hi: np.ndarray  # (n, 3)
    margin: np.ndarray  # (n,) MoveHits.margin
    part_hit: np.ndarray  # (n, n_parts) MoveHits.part_hit
    deposit_hit: np.ndarray  # (n,)
    deposit_clearance: np.ndarray  # (n,)
    has_sample: np.ndarray  # (n,) bool: MoveHits.sample >= 0
    C: np.ndarray  # (n, 3) tip of the deciding sample
    R: np.ndarray  # (n, 3, 3) its rotation
    poses: list  # per row: (tips (m, 3), rotations (m, 3, 3)) of its samples and sweep start, or None

    @classmethod
    def blank(cls, n: int, k: int, parts: int) -> "Detected":
        nan = np.full((n, k), np.nan)
        box = np.full((n, 3), np.nan)
        return cls(np.zeros(n, dtype=bool), nan, nan.copy(), box, box.copy(), np.zeros(n),
                   np.zeros((n, parts), dtype=bool), np.zeros(n, dtype=bool), np.full(n, np.inf),
                   np.zeros(n, dtype=bool), np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), [None] * n)

    def append(self, other: "Detected") -> "Detected":
        return Detected(*(getattr(self, f) + getattr(other, f) if f == "poses"
                          else np.concatenate([getattr(self, f), getattr(other, f)])
                          for f in self.__dataclass_fields__))

    def drop(self, count: int) -> "Detected":
        return Detected(*(getattr(self, f)[count:] for f in self.__dataclass_fields__))


class Rechecks:
    """The re-checks of one episode's moves with the words a strategy proposes (``Episode.recheck``).

    Each re-check reuses the last one's result of a move where nothing that result depends on
    changed (``CorrectStage``): its own words, and the beads within its reach. A move before the first
    changed one keeps its result (it does not see later beads); a later unchanged move keeps it
    unless its head came within reach (``reach_mm``) of a bead of a changed move, as laid before
    or after the change. The rest are checked, in runs, each with the beads of the moves before
    it (``PathChecker.check`` ``prior``), as detection reuses its results.

    ``rows`` (first, end): the table rows of the moves checked; the first re-check then starts
    from their detection (``Detected``) instead of checking them all: a move the strategy left
    as detected keeps detection's result by the same rule, so an episode costs the moves it
    changes, not its length."""

    def __init__(self, stage: "CorrectStage", rows: tuple[int, int] | None = None):
        self.stage = stage
        self.rows = rows
        self.last: Moves | None = None  # the moves of the last re-check (copies)
        self.bad = self.margin = self.lo = self.hi = None
        self.poses: list = []
        self.checked = 0  # moves checked (the others' results were reused)

    def check(self, moves: Moves) -> np.ndarray:
        """(n,) bool: the moves that collide (end pose or sweep, the parts and every bead laid
        before each: the store's and the earlier moves')."""
        stage, ck = self.stage, self.stage.checker
        n = len(moves)
        todo = np.ones(n, dtype=bool)
        stale = self._from_detection(moves) if self.last is None else np.zeros(n, dtype=bool)
        if self.last is None or len(self.last) != n or not stage.REUSE_DETECTION:
            self.bad, self.margin = np.zeros(n, dtype=bool), np.zeros(n)
            self.lo, self.hi = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
            self.poses = [None] * n
        else:
            last = self.last
            changed = ~(_same(last.w_start, moves.w_start) & _same(last.w_end, moves.w_end))
            todo = changed | stale
            if changed.any() and stage.head_corners is not None and moves.deposit[changed].any():
                later = np.nonzero((np.arange(n) > np.argmax(changed)) & ~todo)[0]
                beads = np.concatenate([stage.path.bead_points(_take(last, changed)),
                                        stage.path.bead_points(_take(moves, changed))])
                near = near_beads(ck, self.lo[later], self.hi[later], [self.poses[i] for i in later],
                                  reach_mm(ck, self.margin[later]), beads)
                todo[later[near]] = True
        for s, e in _runs(todo, MERGE_GAP):
            prior = stage.path.bead_points(_take(moves, slice(0, s)), radii=True) if s else None
            run = _take(moves, slice(s, e))
            hits, _ = stage.path.check(run, stage.store, 0, commit=False, prior=prior, clearances=False)
            stage.samples += hits.samples
            self.checked += e - s
            self.bad[s:e], self.margin[s:e] = hits.any, hits.margin
            poses, lo, hi = move_poses(stage.path, run, hits, stage.head_corners)
            self.poses[s:e] = poses
            if lo is not None:
                self.lo[s:e], self.hi[s:e] = lo, hi
        self.last = Moves(*(None if v is None else np.array(v) for v in (moves.w_start, moves.w_end, moves.tcp,
                                                                          moves.known_start, moves.deposit,
                                                                          moves.arc)))
        return self.bad.copy()

    def _from_detection(self, moves: Moves) -> np.ndarray:
        """Take the detection of the rows as the last re-check (``self.last`` and its results);
        (n,) bool: the moves whose detection is not current (checked whatever their words).
        Nothing is taken when the rows are not known, or the store retired beads since."""
        stage = self.stage
        n = len(moves)
        if self.rows is None or not stage.REUSE_DETECTION or stage.store.retired != stage.retired_seen:
            return np.zeros(n, dtype=bool)
        a, b = self.rows
        d = stage.detected
        if b - a != n or b > len(d.valid):
            return np.zeros(n, dtype=bool)
        stale = ~d.valid[a:b] | np.array([p is None for p in d.poses[a:b]], dtype=bool)
        # A stale move is checked; as "last" it stands with its current words (its beads did not move).
        start = np.where(stale[:, None], moves.w_start, d.start[a:b])
        end = np.where(stale[:, None], moves.w_end, d.end[a:b])
        self.last = Moves(start, end, np.array(moves.tcp), np.array(moves.known_start), np.array(moves.deposit),
                          None if moves.arc is None else np.array(moves.arc))
        self.bad = d.part_hit[a:b].any(axis=1) | d.deposit_hit[a:b]
        self.margin, self.lo, self.hi = d.margin[a:b].copy(), d.lo[a:b].copy(), d.hi[a:b].copy()
        self.poses = list(d.poses[a:b])
        return stale


class CorrectStage:
    """Pipeline stage: checks every motion block and rewrites the colliding ones.

    The stage holds the chunks it has not finished and a table of their motion rows, and works
    forward through the rows in a fixed order (``_advance``):

    1. *Detect*: check the rows after the last final one (ends and sweeps, against the parts and the
       beads laid before each, the current outputs of earlier rows) without committing beads.
    2. No collision: the rows up to ``ramp`` before the end of what was checked become final (their
       beads go into the store, their chunks go out once every row of them is final). The last
       ``ramp`` rows wait, so that a later episode can still ramp in over them.
    3. A collision at row f: the *episode* runs from f to the last colliding row e that follows a
       colliding row by at most ``2·ramp + 1`` rows (closer episodes are one); rows are checked
       (input is awaited) until ``e + 2·ramp + 1`` is known to be free. The episode is solved whole
       over the levels ``max(final, f − ramp) .. e + ramp`` (the strategy), checked again with
       sweeps and its own beads, and becomes final. Detection resumes after it.

    ``ramp`` = ⌈Θ/θ⌉ + 1 blocks: enough to tilt from the programmed orientation to Θ in steps of θ.

    Detection is kept per row (``Detected``) and reused. A row's result is decided sample by sample
    (a sample collides when its exact test says so; the bounds only choose which samples get an
    exact test), so it depends only on its own move (the words of the row before and its own, its
    flags), the parts, and the beads within reach of its head at its samples (the store and the
    pending beads of the rows before it and its own). An episode changes the words of some of its
    rows: the moves that start or end at a changed row are checked again (their words differ), and
    so is every row whose head (the deposit tree's balls, at every sample and at the sweep start)
    came within its reach of a bead those moves laid, before or after the change (``_forget``). The
    rest keeps its result: the next detection checks only the runs of rows it cannot reuse, each
    with the pending beads of the rows before it (``PathChecker.check`` ``prior``); past an episode
    it has seen whole (``_closed``), the stale rows wait for it to be solved, since it may make
    them stale again (``_detect``). Beads the store
    retires change what every row sees: nothing is reused across that. A strategy's re-checks of
    one episode reuse each other's results by the same rule (``Rechecks``).
    """

    # Reuse detection results where nothing they depend on changed (the class doc); False checks
    # every row again at every detection (the reference the reuse is tested against).
    REUSE_DETECTION = True

    def __init__(self, checker: Checker, profile: Profile, options: Options, report: Report,
                 strategy: Strategy, placed_parts: Iterable[LoadedMesh] = (),
                 program_box: np.ndarray | None = None) -> None:
        self.checker = checker
        self.profile = profile
        self.options = options
        self.report = report
        self.strategy = strategy
        self.placement = PlacementCheck(placed_parts, program_box)
        self.path = PathChecker(checker, profile, options.standoff, options.pitch)
        self.motion = MotionRows(self.path, profile, options)
        self.window = int(options.window)
        self.ramp = int(math.ceil(options.max_tilt / options.max_step)) + 1
        self.gap = 2 * self.ramp + 1
        self.store = BeadStore(checker.bead_radius_mm)
        self.held: list = []  # chunks not given back yet, oldest first
        self.first_serial = 0  # serial number of held[0]
        self.rows = Rows.empty(len(profile.kinematics.letters))
        self.final = 0  # rows before this index are final
        self.prev_words: np.ndarray | None = None  # last final row (sweep start of the next)
        self.prev_programmed: np.ndarray | None = None
        self.samples = 0
        self.checked_rows = 0  # rows detection checked (reused ones not counted)
        self.detected = Detected.blank(0, len(profile.kinematics.letters), len(checker.parts))
        self.retired_seen = 0  # store.retired when the cached results were found
        self.head_corners = _head_corners(checker)
        self._decimals: dict[bytes, dict[str, int]] = {}  # as_printed: a line's decimals per kind of word
        # line -> [(first, last)] lines of changed moves whose beads moved within its reach (``_forget``):
        # a collision found there was found after ncfix's own change (``_detected_after``).
        self._beads_moved_by: dict[int, list[tuple[int, int]]] = {}
        report.summary.setdefault("freed_blocks", 0)
        report.summary.setdefault("found_after_changes", 0)
        self.progress = None  # set by the pipeline: progress(line) as the work reaches a line

    # -- stage protocol ------------------------------------------------------------------------
    def push(self, chunk):
        rows = np.nonzero(chunk.motion >= 0)[0]
        self.placement.push(self.path, self.motion, chunk, rows)
        dep = self.motion.deposit(chunk)
        serial = self.first_serial + len(self.held)
        self.held.append(chunk)
        if len(rows):
            kept, moves = self.motion.moves(chunk, rows, dep)
            # A row whose start follows an unchecked row has no known start (MotionRows).
            new = Rows(np.full(len(kept), serial, dtype=np.int64), kept.astype(np.int64),
                       chunk.first_lineno + kept.astype(np.int64), moves.w_end.copy(), moves.w_end.copy(),
                       moves.tcp, moves.known_start, moves.deposit, moves.arc)
            self.rows = self.rows.append(new)
            self.detected = self.detected.append(Detected.blank(len(kept), self.rows.words.shape[1],
                                                                len(self.checker.parts)))
        self._advance(end=False)
        return self._release()

    def flush(self):
        self._advance(end=True)
        out = self._release(everything=True)
        self.report.summary["checked_samples"] = self.samples
        self.placement.report_into(self.report)
        self.motion.report_into(self.report)
        return out

    # -- bookkeeping ---------------------------------------------------------------------------
    def _release(self, everything: bool = False) -> list:
        """Chunks whose rows are all final, oldest first; their rows leave the table."""
        out = []
        while self.held:
            serial = self.first_serial
            if not everything and self.final < len(self.rows) and self.rows.chunk[self.final] <= serial:
                break
            out.append(self.held.pop(0))
            count = int(np.searchsorted(self.rows.chunk, serial, side="right"))
            self.rows = self.rows.drop(count)
            self.detected = self.detected.drop(count)
            self.final -= count
            self.first_serial += 1
        if self._beads_moved_by:  # lines already written cannot collide again
            first = int(self.rows.line[0]) if len(self.rows) else None
            self._beads_moved_by = {k: v for k, v in self._beads_moved_by.items() if first is not None and k >= first}
        return out

    def rechecks(self, rows: tuple[int, int] | None = None) -> Rechecks:
        """A fresh re-check of one episode's moves, rows[0] .. rows[1] - 1 (``Episode.checks``):
        its first check takes what detection found for them."""
        return Rechecks(self, rows)

    def moves(self, a: int, b: int) -> Moves:
        """Rows a..b-1 as moves from their current (possibly corrected) predecessors."""
        r = self.rows
        start = np.empty_like(r.words[a:b])
        start[1:] = r.words[a:b - 1]
        start[0] = r.words[a - 1] if a > 0 else (self.prev_words if self.prev_words is not None else np.nan)
        return Moves(start, r.words[a:b], r.tcp[a:b], r.known_start[a:b], r.deposit[a:b], r.arc[a:b])

    def _commit(self, b: int) -> None:
        """Rows final .. b-1 become final: their beads go into the store."""
        if b <= self.final:
            return
        moves = self.moves(self.final, b)
        if self.checker.bead_radius_mm > 0 and moves.deposit.any():  # no kinematics for no beads
            self.store.add(*self.path.bead_points(moves, radii=True))
        self._trace(self.final, b)
        d = self.detected  # final rows are not detected again: their poses can go
        d.valid[self.final:b] = False
        d.poses[self.final:b] = [None] * (b - self.final)
        self.prev_words = self.rows.words[b - 1].copy()
        self.prev_programmed = self.rows.programmed[b - 1].copy()
        self.final = b
        if self.progress is not None:
            self.progress(int(self.rows.line[b - 1]) + 1)

    def _trace(self, a: int, b: int) -> None:
        r = self.rows
        P, N, _ = self.path.forward(r.words[a:b], r.tcp[a:b])
        # Rows as programmed (most of a program) have their programmed orientation: no second pass.
        N0 = N if _same(r.words[a:b], r.programmed[a:b]).all() else self.path.forward(r.programmed[a:b], r.tcp[a:b])[1]
        previous = N[:-1]
        if a > 0 or self.prev_words is not None:
            w = r.words[a - 1:a] if a > 0 else self.prev_words[None, :]
            t = r.tcp[a - 1:a] if a > 0 else r.tcp[a:a + 1]
            previous = np.vstack([self.path.forward(w, t)[1], previous])
        step = np.zeros(b - a)
        step[b - a - len(previous):] = angle_between_deg(N[b - a - len(previous):], previous)
        self.report.add_trace(r.line[a:b], P, angle_between_deg(N, N0), step)

    # -- the work --------------------------------------------------------------------------------
    def _advance(self, end: bool) -> None:
        while self.final < len(self.rows):
            n = len(self.rows)
            span_end = min(n, self.final + max(self.window, 2 * self.gap))
            while True:
                hits, known = self._detect(self.final, span_end)
                span_end = known  # rows past ``known`` wait for the episode before them (``_detect``)
                colliding = self.final + np.nonzero(hits.any[:known - self.final])[0]
                if len(colliding) == 0:
                    if span_end == n:
                        self._commit(n if end else max(self.final, n - self.ramp))
                        return
                    self._commit(span_end - self.ramp)
                    break
                f, e = int(colliding[0]), self._episode_end(colliding)
                if e + self.gap >= span_end and span_end < n:
                    span_end = min(n, e + self.gap + 1 + self.window)
                    continue  # the episode may go on: look further
                if e + self.gap >= span_end and not end:
                    self._commit(max(self.final, f - self.ramp))
                    return  # wait for more input to see where the episode ends
                first, last = max(self.final, f - self.ramp), min(n - 1, e + self.ramp)
                entries = self._collision_entries(colliding[colliding <= e], hits)
                self._commit(first)
                upto = min(n, last + 2)  # the row after the episode starts at its last level
                before = self.moves(first, upto)
                before.w_end = before.w_end.copy()  # a view of the table, which _apply rewrites
                self._solve(first, last, entries)
                self._forget(before, first, upto)
                self._commit(last + 1)
                break

    def _detect(self, a: int, b: int) -> tuple[MoveHits, int]:
        """Detection of rows a..b-1 and ``known``: rows a..known-1 have a current result. The
        rows whose result cannot be reused are checked in order (runs of them, each with the
        pending beads of the rows a.. before it); the others keep theirs. Past an episode seen
        whole (``_closed``), a run of rows detected before (stale since) waits: that episode is
        solved first, and its beads may make those rows stale again, so they are checked once,
        when detection reaches them. Rows never detected are checked (``_forget`` needs their
        poses to note the beads that move near them)."""
        if not self.REUSE_DETECTION:
            hits, _ = self.path.check(self.moves(a, b), self.store, 0, commit=False)
            self.samples += hits.samples
            self.checked_rows += b - a
            self._remember(a, b, hits)  # the poses, for ``_forget``'s note of moved beads
            return hits, b
        d = self.detected
        if self.store.retired != self.retired_seen:  # the beads every row sees changed
            d.valid[:] = False
            self.retired_seen = self.store.retired
        moves = self.moves(a, b)
        ok = d.valid[a:b] & _same(d.start[a:b], moves.w_start) & _same(d.end[a:b], moves.w_end)
        d.valid[a:b] = ok
        prior, covered = [], a  # pending beads of rows a .. covered-1
        samples = 0
        known = b
        for s, e in _runs(~ok, MERGE_GAP):
            s, e = a + s, a + e
            if known == b and self._closed(a, s):
                known = s
            if known < b and all(p is not None for p in d.poses[s:e]):
                continue
            if s > covered:
                if self.checker.bead_radius_mm > 0:
                    prior.append(self.path.bead_points(self.moves(covered, s), radii=True))
                covered = s
            pts = join_beads(prior, self.checker.bead_radius_mm) if prior else None
            hits, _ = self.path.check(self.moves(s, e), self.store, 0, commit=False, prior=pts,
                                      progress=self._detecting(s, e))
            samples += hits.samples
            self.checked_rows += e - s
            self._remember(s, e, hits)
        self.samples += samples
        n = b - a
        sample = np.where(d.has_sample[a:b], np.arange(n), -1)
        return MoveHits(d.part_hit[a:b].copy(), d.deposit_hit[a:b].copy(), d.deposit_clearance[a:b].copy(),
                        sample, d.C[a:b].copy(), d.R[a:b].copy(), samples), known

    def _episode_end(self, colliding: np.ndarray) -> int:
        """The last row of the episode that starts at colliding[0]: the chain of colliding rows
        (ascending) each at most ``gap`` after the one before."""
        e = int(colliding[0])
        for c in colliding[1:]:
            if c - e > self.gap:
                break
            e = int(c)
        return e

    def _closed(self, a: int, s: int) -> bool:
        """Whether rows a..s-1 (every one with a current result) hold a whole episode: its chain
        (``_episode_end``) ends ``gap`` or more rows before s. ``_advance`` then finds the same
        episode, whatever the rows from s on hold."""
        d = self.detected
        colliding = a + np.nonzero(d.part_hit[a:s].any(axis=1) | d.deposit_hit[a:s])[0]
        return len(colliding) > 0 and self._episode_end(colliding) + self.gap < s

    def _detecting(self, a: int, b: int):
        """A progress hook for the detection of rows a..b-1: it moves the bar over the first half
        of their lines, since fixing the episodes among them takes the rest (commits move it)."""
        if self.progress is None or b <= a:
            return None
        first, end = float(self.rows.line[a]), float(self.rows.line[b - 1]) + 1
        return lambda f: self.progress(first + 0.5 * f * (end - first))

    def _remember(self, a: int, b: int, hits: MoveHits) -> None:
        """Keep the detection of rows a..b-1 (``hits``, from a check of exactly these moves)."""
        d = self.detected
        moves = self.moves(a, b)
        rows = np.arange(a, b)
        d.start[rows], d.end[rows] = moves.w_start, moves.w_end
        d.part_hit[rows], d.deposit_hit[rows] = hits.part_hit, hits.deposit_hit
        d.deposit_clearance[rows] = hits.deposit_clearance
        has = hits.sample >= 0
        d.has_sample[rows] = has
        d.C[rows[has]], d.R[rows[has]] = hits.C[hits.sample[has]], hits.R[hits.sample[has]]
        d.margin[rows] = hits.margin
        poses, lo, hi = move_poses(self.path, moves, hits, self.head_corners)
        d.poses[a:b] = poses
        if lo is not None:
            d.lo[rows], d.hi[rows] = lo, hi
        d.valid[rows] = True

    def _forget(self, before: Moves, first: int, end: int) -> None:
        """After an episode rewrote rows of first..end-1: forget the detection of the rows whose
        head came within their reach (``reach_mm``) of a bead of a changed move, as laid before
        or after the change (the changed moves themselves have other words now: checked again)."""
        after = self.moves(first, end)
        changed = ~(_same(before.w_start, after.w_start) & _same(before.w_end, after.w_end))
        if not changed.any() or not after.deposit[changed].any() or self.head_corners is None:
            return
        beads = np.concatenate([self.path.bead_points(_take(before, changed)),
                                self.path.bead_points(_take(after, changed))])
        d = self.detected
        rows = end - 1 + np.arange(len(d.valid) - (end - 1))  # the rows before become final now
        poses = [d.poses[r] for r in rows]
        known = np.array([p is not None for p in poses], dtype=bool)
        rows, poses = rows[known], [p for p in poses if p is not None]
        if not len(rows):
            return
        near = near_beads(self.checker, d.lo[rows], d.hi[rows], poses, reach_mm(self.checker, d.margin[rows]), beads)
        if self.REUSE_DETECTION:
            d.valid[rows[near]] = False
        moved = first + np.nonzero(changed)[0]
        span = (int(self.rows.line[moved[0]]), int(self.rows.line[moved[-1]]))
        for line in self.rows.line[rows[near]].tolist():
            spans = self._beads_moved_by.setdefault(int(line), [])
            if span not in spans:
                spans.append(span)

    def _solve(self, first: int, last: int, collided: dict[int, dict]) -> None:
        """Solve the episode (levels first..last), record its collisions, apply its words."""
        # An arc's centre is tied to its end points and (I J K) to its start: ncfix does not move
        # them, so an episode that holds an arc, or ends where one starts, stays as programmed.
        if np.isfinite(self.rows.arc[first:min(last + 2, len(self.rows)), 3]).any():
            solution = Solution(self.rows.words[first:last + 1].copy(), sorted(collided),
                                {row: "an arc (G2/G3) is in the way: ncfix does not re-orient arc blocks "
                                 "or the blocks next to them" for row in collided})
        else:
            solution = self.strategy.solve(Episode(self, first, last, np.array(sorted(collided), dtype=np.int64)))
        unresolved = set(solution.unresolved)
        s = self.report.summary
        for row, entry in collided.items():
            s["colliding_blocks_before"] += 1
            self.report.collisions.append(entry)
            if row in unresolved:
                s["unresolved_blocks"] += 1
                self.report.unresolved.append({"line": entry["line"], "bodies": entry["bodies"],
                                               "penetration_mm": entry["penetration_mm"], "where": entry["where"],
                                               "reason": solution.reasons.get(row, "no free orientation found")})
        for row in sorted(unresolved - set(collided)):  # a move that collides only as rewritten
            s["unresolved_blocks"] += 1
            self.report.unresolved.append({"line": int(self.rows.line[row]), "bodies": [], "penetration_mm": None,
                                           "reason": solution.reasons.get(row, "collides after the blocks around it")})
        self._apply(first, last, solution.words, collided)
        self._outcomes(collided, unresolved)

    def _outcomes(self, collided: dict[int, dict], unresolved: set) -> None:
        """Say in each collision entry of an episode what became of it (``outcome``): "tilted",
        "unresolved", or "freed": left as programmed, its move is free once the blocks before it
        are rewritten (``note`` says how); the summary counts the freed (``freed_blocks``)."""
        r = self.rows
        for row, entry in collided.items():
            if row in unresolved:
                entry["outcome"] = "unresolved"
            elif not _same(r.words[row:row + 1], r.programmed[row:row + 1])[0]:
                entry["outcome"] = "tilted"
            else:
                entry["outcome"] = "freed"
                before = self.moves(row, row + 1).w_start
                programmed = r.programmed[row - 1:row] if row > 0 else self.prev_programmed
                if row > 0 and programmed is not None and not _same(before, np.reshape(programmed, (1, -1)))[0]:
                    entry["note"] = (f"left as programmed: its move now starts from line {int(r.line[row - 1])} "
                                     "as rewritten, and is free")
                else:
                    entry["note"] = ("left as programmed: free with the beads of the rewritten blocks before it "
                                     "laid where they are now")
                self.report.summary["freed_blocks"] += 1

    def _detected_after(self, row: int, bodies: list[str]) -> str | None:
        """Why a collision found at ``row`` may not be one of the program as written, or None:
        its move starts from the block before as ncfix rewrote it (an earlier episode's last
        level), or it hits only beads and beads of rewritten blocks moved within its reach (the
        tip pivot moves a re-oriented block's programmed point, and its beads with it)."""
        r = self.rows
        line = int(r.line[row])
        before = self.moves(row, row + 1).w_start
        programmed = r.programmed[row - 1:row] if row > 0 else (
            None if self.prev_programmed is None else self.prev_programmed[None])
        if programmed is not None and not _same(before, programmed)[0]:
            where = f"line {int(r.line[row - 1])}" if row > 0 else "the block before it"
            return f"found after ncfix rewrote {where}: its move starts there"
        moved = self._beads_moved_by.get(line)
        if moved and bodies == ["deposit"]:
            lines = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in moved)
            return f"found with the beads of lines {lines} as ncfix rewrote them, which moved within its reach"
        return None

    def _collision_entries(self, rows: np.ndarray, hits: MoveHits) -> dict[int, dict]:
        """Report entries of colliding rows (hits: detection from row ``self.final`` on;
        ``collision_entry``): the move's poses are the detection's (``Detected.poses``)."""
        out = {}
        ends = np.append(hits.first[1:], len(hits.C)) if hits.first is not None else None
        for row in rows:
            i = int(row) - self.final
            s = hits.sample[i]
            c, r = hits.C[s], hits.R[s]
            if ends is not None:  # a fresh check of every row (REUSE_DETECTION off)
                move_C, move_R = hits.C[hits.first[i]:ends[i]], hits.R[hits.first[i]:ends[i]]
            else:
                move_C, move_R = self.detected.poses[int(row)]
                if self.rows.known_start[row]:  # its first pose is the sweep start: the block before's
                    move_C, move_R = move_C[1:], move_R[1:]
            at_end = bool(np.array_equal(move_C[-1], c) and np.array_equal(move_R[-1], r))
            entry = collision_entry(self.checker, int(self.rows.line[row]), hits.part_hit[i],
                                    bool(hits.deposit_hit[i]), float(hits.deposit_clearance[i]), c, r,
                                    at_end, move_C, move_R)
            after = self._detected_after(int(row), entry["bodies"])
            if after is not None:
                entry["detected"] = after
                self.report.summary["found_after_changes"] += 1
            out[int(row)] = entry
        return out

    def as_printed(self, rows: np.ndarray, words: np.ndarray) -> np.ndarray:
        """``words`` (one row each of ``rows``) as the output will state them. The writer writes
        a value only where it differs from the programmed one (all of a vector's components
        when one does), rounded to the decimals of its line (``emit.printed_decimals``) in the
        line's units: those values are rounded the same way here, the rest are the programmed. Solutions are
        checked, and later rows detected, as written, so a fresh check of the output decides as
        the fix did. Incremental (G91) rows are left as computed (the writer prints increments)."""
        out = np.array(words, dtype=np.float64)
        profile = self.profile
        letters = profile.kinematics.letters
        kinds = [word_kind(profile, letter) for letter in letters]
        linear = np.array([letter in ("X", "Y", "Z") for letter in letters])
        vector = np.array([profile.is_vector and letter in profile.kinematics.orientation_letters
                           for letter in letters])
        r = self.rows
        rows = np.asarray(rows, dtype=np.int64)
        with np.errstate(invalid="ignore"):
            written = np.isfinite(out) & ~np.isclose(out, r.programmed[rows], rtol=0.0, atol=1e-12)
        written |= (written & vector).any(axis=1, keepdims=True) & vector & np.isfinite(out)
        out = np.where(written | np.isnan(out), out, r.programmed[rows])  # a value not written stays as read
        for i in np.nonzero(written.any(axis=1))[0].tolist():
            row = int(rows[i])
            chunk = self.held[int(r.chunk[row]) - self.first_serial]
            line = int(r.row[row])
            if chunk.incremental[line]:
                continue
            raw = chunk.lines[line]
            decimals = self._decimals.get(raw)
            if decimals is None:  # re-checks ask again for the same lines
                if len(self._decimals) >= DECIMALS_KEPT:
                    self._decimals.clear()
                decimals = self._decimals[raw] = printed_decimals(raw.decode("latin-1"), profile)
            inch = MM_PER_INCH if chunk.inch[line] else 1.0
            for k in np.nonzero(written[i])[0].tolist():
                scale = inch if linear[k] else 1.0
                out[i, k] = float(f"{out[i, k] / scale:.{decimals[kinds[k]]}f}") * scale
        return out

    def _apply(self, first: int, last: int, words: np.ndarray, collided: dict[int, dict]) -> None:
        """Write the solved words of rows first..last into the table and their chunks."""
        r = self.rows
        rows = np.arange(first, last + 1)
        printed = self.as_printed(rows, words)  # the table holds the rows as written
        changed = ~np.all(np.isclose(printed, r.words[rows], rtol=0.0, atol=1e-9), axis=1)
        if not changed.any():
            return
        h = self.path.standoff_mm
        P0, N0, R0 = self.path.forward(r.programmed[rows], r.tcp[rows])
        P1, N1, R1 = self.path.forward(words, r.tcp[rows])
        tilt = angle_between_deg(N1, N0)
        start = self.moves(first, first + 1).w_start
        # The program's first motion block has no block before it: its step is 0.
        before = self.path.forward(start, r.tcp[rows[:1]])[1] if np.isfinite(start).all() else N1[:1]
        prev = np.vstack([before, N1[:-1]])
        step = angle_between_deg(N1, prev)
        ref = self.checker.exact
        for i in np.nonzero(changed)[0]:
            row = int(rows[i])
            chunk = self.held[int(r.chunk[row]) - self.first_serial]
            line_index = int(r.row[row])
            reason = "collision" if row in collided else "blend"
            chunk.new_words[line_index] = words[i].copy()
            chunk.reasons[line_index] = reason
            r.words[row] = printed[i]
            entry = collided.get(row)
            after = ref.clearance(P1[i] + h * N1[i], R1[i])[0] if ref.parts else math.inf
            before = entry["clearance_mm"] if entry else (
                ref.clearance(P0[i] + h * N0[i], R0[i])[0] if ref.parts else math.inf)
            self.report.changes.append({
                "line": int(r.line[row]),
                "before": chunk.lines[line_index].decode("latin-1").rstrip("\r\n"),
                "after": None,  # filled when the writer renders the chunk
                "reason": reason,
                "tilt_deg": round(float(tilt[i]), 4),
                "step_deg": round(float(step[i]), 4),
                "bodies": entry["bodies"] if entry else [],
                "clearance_before_mm": _finite(before),
                "clearance_after_mm": _finite(after),
                "point": [round(float(v), 4) for v in P1[i]],
            })
            self.report.summary["changed_blocks"] += 1
            s = self.report.summary
            s["max_tilt_deg"] = max(s["max_tilt_deg"], round(float(tilt[i]), 4))
            s["max_step_deg"] = max(s["max_step_deg"], round(float(step[i]), 4))
        if self.options.pivot == "tip":  # P moved: E and inverse-time F of the moves whose length changed
            follow(self, first, last)


def _finite(value: float) -> float | None:
    return round(float(value), 4) if math.isfinite(value) else None


def _same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) bool: rows of words (n, k) that are equal, NaN equal to NaN."""
    return np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)


def _runs(mask: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """[start, end) runs of True in mask; runs at most ``gap`` False apart are one."""
    idx = np.nonzero(mask)[0]
    if len(idx) == 0:
        return []
    cut = np.nonzero(np.diff(idx) > gap + 1)[0]
    starts = np.concatenate([[idx[0]], idx[cut + 1]])
    ends = np.concatenate([idx[cut], [idx[-1]]]) + 1
    return list(zip(starts.tolist(), ends.tolist()))


def _take(moves: Moves, sel: np.ndarray) -> Moves:
    return Moves(moves.w_start[sel], moves.w_end[sel], moves.tcp[sel], moves.known_start[sel], moves.deposit[sel],
                 None if moves.arc is None else moves.arc[sel])


def _head_corners(checker: Checker) -> np.ndarray | None:
    """(8, 3) corners of a head-frame box holding the balls of the checker's deposit tree (the
    head above the tip allowance: all that beads are tested against); None without beads."""
    tree = getattr(checker, "dep_tree", None)
    if tree is None or checker.bead_radius_mm <= 0:
        return None
    start = int(tree.level_start[-2])  # the balls
    c, r = tree.host.center[start:], tree.host.radius[start:]
    lo, hi = (c - r[:, None]).min(axis=0), (c + r[:, None]).max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _boxes(C: np.ndarray, R: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World boxes (n, 3) lo and hi of the head-frame box ``corners`` at poses (tip C, rotation R)."""
    w = C[:, None, :] + np.einsum("nij,kj->nki", R, corners)
    return w.min(axis=1), w.max(axis=1)


def move_poses(path: PathChecker, moves: Moves, hits: MoveHits, corners: np.ndarray | None):
    """The poses of each move (a list of (tips (m, 3), rotations (m, 3, 3))): its samples, and
    its sweep start where that is known; and the world boxes (n, 3) lo and hi of the deposit
    tree's balls at them (``corners``: ``_head_corners``; None, None without beads).

    Whole arrays at once: each move's poses are views of one array of every move's poses (a
    fix pays this for every row it detects, so it costs what the check costs, not a loop)."""
    n = len(moves)
    known = moves.known_start
    Cs, Rs = np.full((n, 3), np.nan), np.tile(np.eye(3), (n, 1, 1))
    if known.any():
        Ps, Ns, Rs[known] = path.forward(moves.w_start[known], moves.tcp[known])
        Cs[known] = Ps + path.standoff_mm * Ns
    counts = np.diff(np.append(hits.first, len(hits.C)))
    # Move i's poses start at first[i] + (sweep starts of the moves up to it); its sweep start first.
    shift = np.cumsum(known) - known
    begin = hits.first + shift
    size = counts + known
    total = int(size.sum())
    C, R = np.empty((total, 3)), np.empty((total, 3, 3))
    own = np.ones(total, dtype=bool)
    own[begin[known]] = False
    C[own], R[own] = hits.C, hits.R
    C[begin[known]], R[begin[known]] = Cs[known], Rs[known]
    ends = (begin + size).tolist()
    poses = [(C[a:b], R[a:b]) for a, b in zip(begin.tolist(), ends)]
    lo = hi = None
    if corners is not None:
        wlo, whi = _boxes(C, R, corners)
        lo, hi = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
        has = size > 0
        lo[has] = np.minimum.reduceat(wlo, begin[has], axis=0)
        hi[has] = np.maximum.reduceat(whi, begin[has], axis=0)
    return poses, lo, hi


def reach_mm(checker: Checker, margin: np.ndarray) -> np.ndarray:
    """How far (mm) beyond the deposit tree's balls bead material can be and still change the
    result of moves with these largest sweep margins (``MoveHits.margin``): a sample's exact
    test looks within the clearance and its sweep margin of the clipped head (which the balls
    cover); its finer samples lie within that margin and add their own (smaller) one: twice the
    margin, and two pitches more.

    Not counted: the reach of the bounds (groups of samples up to GROUP_LEVELS_MM long, the bead
    field's cells and box). They do not decide a sample, they only choose which samples get an
    exact test; that choice can change the deposit clearance a colliding row reports (the
    smallest of its tested hits), but it changes with where a check starts as well (the groups
    are counted from the first sample of a check), so no reach would pin it."""
    return 2.0 * np.asarray(margin) + 2.0 * checker.pitch_mm + checker.clearance_mm


def near_beads(checker: Checker, lo: np.ndarray, hi: np.ndarray, poses: list, reach: np.ndarray,
               beads: np.ndarray) -> np.ndarray:
    """(n,) bool: moves whose head (the deposit tree's balls at ``poses``, inside the boxes lo..hi)
    comes within ``reach`` (n,) of one of ``beads`` (a bead's surface). The boxes sort most moves
    out; the rest are tested as the checker tests poses against beads, with a field of these
    beads only (a lower bound: conservative, never "far" for a move that is near)."""
    n = len(lo)
    out = np.zeros(n, dtype=bool)
    if n == 0 or len(beads) == 0:
        return out
    box_reach = reach + checker.bead_radius_mm  # from a ball to a bead's centre
    gap = np.maximum(np.maximum(lo - beads.max(axis=0), beads.min(axis=0) - hi), 0.0)
    idx = np.nonzero(np.einsum("ri,ri->r", gap, gap) <= box_reach ** 2)[0]  # near the beads' box
    near = np.zeros(len(idx), dtype=bool)
    step = max(1, (1 << 20) // len(beads))  # moves per batch of (move, bead) gaps
    for a in range(0, len(idx), step):
        sel = idx[a:a + step]
        gap = np.maximum(np.maximum(lo[sel, None, :] - beads[None], beads[None] - hi[sel, None, :]), 0.0)
        near[a:a + step] = (np.einsum("rbi,rbi->rb", gap, gap) <= box_reach[sel, None] ** 2).any(axis=1)
    idx = idx[near]
    if len(idx) == 0:
        return out
    bead_field = BeadField(checker.bead_radius_mm, checker.pitch_mm)
    bead_field.add(beads)
    count = np.array([len(poses[i][0]) for i in idx])
    C = np.concatenate([poses[i][0] for i in idx])
    R = np.concatenate([poses[i][1] for i in idx])
    lin = np.repeat(reach[idx], count)
    touched = checker.deposit_balls_near(bead_field.lower_bound, C, R, lin)
    out[idx[np.logical_or.reduceat(touched, np.cumsum(count) - count)]] = True
    return out
