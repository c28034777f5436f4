"""The correction stage: finds collision episodes in the stream and tilts the head out of them.

The stage holds the chunks it has not finished and a table of their motion rows. It works forward
through the rows in a fixed order, so that its decisions do not depend on how the input is split
into chunks or windows:

1. *Detect*: check the rows after the last final one (ends and sweeps, against the parts and the
   beads laid before each, the current outputs of earlier rows) without committing beads.
2. No collision: the rows up to ``ramp`` before the end of what was checked become final (their
   beads go into the store, their chunks go out once every row of them is final). The last
   ``ramp`` rows wait, so that a later episode can still ramp in over them.
3. A collision at row f: the *episode* runs from f to the last colliding row e that follows a
   colliding row by at most ``2·ramp + 1`` rows (closer episodes are one); rows are checked
   (input is awaited) until ``e + 2·ramp + 1`` is known to be free. The episode is solved whole
   over the levels ``max(final, f − ramp) .. e + ramp`` (the strategy), checked again with sweeps
   and its own beads, and becomes final. Detection resumes after it.

``ramp`` = ⌈Θ/θ⌉ + 1 blocks: enough to tilt from the programmed orientation to Θ in steps of θ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ncfix.collision.checker import Checker
from ncfix.collision.deposit import BeadStore
from ncfix.collision.path import MoveHits, Moves, PathChecker
from ncfix.collision.stage import MotionRows, check_placement
from ncfix.geometry.frames import angle_between_deg


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


class CorrectStage:
    """Pipeline stage: checks every motion block and rewrites the colliding ones (module doc)."""

    def __init__(self, checker: Checker, profile, options, report, strategy, placed_parts=()):
        self.checker = checker
        self.profile = profile
        self.options = options
        self.report = report
        self.strategy = strategy
        self.placed_parts = list(placed_parts)
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

    # -- stage protocol ------------------------------------------------------------------------
    def push(self, chunk):
        rows = np.nonzero(chunk.motion >= 0)[0]
        self.placed_parts = check_placement(self.path, self.motion, self.placed_parts, chunk, rows, self.report)
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
        self._advance(end=False)
        return self._release()

    def flush(self):
        self._advance(end=True)
        out = self._release(everything=True)
        self.report.warnings.extend(self.motion.warnings())
        self.report.summary["checked_samples"] = self.samples
        rule = self.motion.rule
        self.report.summary["deposit_rule"] = rule.value if rule else None
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
            self.final -= count
            self.first_serial += 1
        return out

    def _moves(self, a: int, b: int) -> Moves:
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
        moves = self._moves(self.final, b)
        self.store.add(self.path.bead_points(moves))
        self._trace(self.final, b)
        self.prev_words = self.rows.words[b - 1].copy()
        self.prev_programmed = self.rows.programmed[b - 1].copy()
        self.final = b

    def _trace(self, a: int, b: int) -> None:
        r = self.rows
        P, N, _ = self.path.forward(r.words[a:b], r.tcp[a:b])
        _, N0, _ = self.path.forward(r.programmed[a:b], r.tcp[a:b])
        previous = N[:-1]
        if a > 0 or self.prev_words is not None:
            w = r.words[a - 1:a] if a > 0 else self.prev_words[None, :]
            t = r.tcp[a - 1:a] if a > 0 else r.tcp[a:a + 1]
            previous = np.vstack([self.path.forward(w, t)[1], previous])
        step = np.zeros(b - a)
        step[b - a - len(previous):] = angle_between_deg(N[b - a - len(previous):], previous)
        add_trace = getattr(self.report, "add_trace", None)  # TODO: report.add_trace lands with the HTML report
        if add_trace is not None:
            add_trace(r.line[a:b], P, angle_between_deg(N, N0), step)

    # -- the work --------------------------------------------------------------------------------
    def _advance(self, end: bool) -> None:
        while self.final < len(self.rows):
            n = len(self.rows)
            span_end = min(n, self.final + max(self.window, 2 * self.gap))
            while True:
                hits = self._detect(self.final, span_end)
                colliding = self.final + np.nonzero(hits.any)[0]
                if len(colliding) == 0:
                    if span_end == n:
                        self._commit(n if end else max(self.final, n - self.ramp))
                        return
                    self._commit(span_end - self.ramp)
                    break
                f = int(colliding[0])
                e = f
                for c in colliding[1:]:
                    if c - e > self.gap:
                        break
                    e = int(c)
                if e + self.gap >= span_end and span_end < n:
                    span_end = min(n, e + self.gap + 1 + self.window)
                    continue  # the episode may go on: look further
                if e + self.gap >= span_end and not end:
                    self._commit(max(self.final, f - self.ramp))
                    return  # wait for more input to see where the episode ends
                first, last = max(self.final, f - self.ramp), min(n - 1, e + self.ramp)
                entries = self._collision_entries(colliding[colliding <= e], hits)
                self._commit(first)
                self._solve(first, last, entries)
                self._commit(last + 1)
                break

    def _detect(self, a: int, b: int) -> MoveHits:
        hits, _ = self.path.check(self._moves(a, b), self.store, 0, commit=False)
        self.samples += hits.samples
        return hits

    def _solve(self, first: int, last: int, collided: dict[int, dict]) -> None:
        """Solve the episode (levels first..last), record its collisions, apply its words."""
        from ncfix.correct.solve import Episode

        # An arc's centre is tied to its end points and (I J K) to its start: ncfix does not move
        # them, so an episode that holds an arc, or ends where one starts, stays as programmed.
        if np.isfinite(self.rows.arc[first:min(last + 2, len(self.rows)), 3]).any():
            from ncfix.correct.solve import Solution

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
                                               "penetration_mm": entry["penetration_mm"],
                                               "reason": solution.reasons.get(row, "no free orientation found")})
        for row in sorted(unresolved - set(collided)):  # a move that collides only as rewritten
            s["unresolved_blocks"] += 1
            self.report.unresolved.append({"line": int(self.rows.line[row]), "bodies": [], "penetration_mm": None,
                                           "reason": solution.reasons.get(row, "collides after the blocks around it")})
        self._apply(first, last, solution.words, collided)

    def _collision_entries(self, rows: np.ndarray, hits: MoveHits) -> dict[int, dict]:
        """Report entries of colliding rows (hits: detection from row ``self.final`` on)."""
        out = {}
        for row in rows:
            i = int(row) - self.final
            s = hits.sample[i]
            bodies = [p.name for j, p in enumerate(self.checker.parts) if hits.part_hit[i, j]]
            clearance = np.inf
            if bodies:
                per_part = self.checker.reference.part_clearances(hits.C[s], hits.R[s])
                clearance = min(per_part[b] for b in bodies)
            if hits.deposit_hit[i]:
                bodies.append("deposit")
                clearance = min(clearance, float(hits.deposit_clearance[i]))
            out[int(row)] = {"line": int(self.rows.line[row]), "bodies": bodies,
                             "penetration_mm": round(max(0.0, -float(clearance)), 4),
                             "clearance_mm": round(float(clearance), 4)}
        return out

    def _apply(self, first: int, last: int, words: np.ndarray, collided: dict[int, dict]) -> None:
        """Write the solved words of rows first..last into the table and their chunks."""
        r = self.rows
        rows = np.arange(first, last + 1)
        changed = ~np.all(np.isclose(words, r.words[rows], rtol=0.0, atol=1e-9), axis=1)
        if not changed.any():
            return
        h = self.path.standoff_mm
        P0, N0, R0 = self.path.forward(r.programmed[rows], r.tcp[rows])
        P1, N1, R1 = self.path.forward(words, r.tcp[rows])
        tilt = angle_between_deg(N1, N0)
        prev = np.vstack([self.path.forward(self._moves(first, first + 1).w_start,
                                            r.tcp[rows[:1]])[1], N1[:-1]])
        step = angle_between_deg(N1, prev)
        ref = self.checker.reference
        for i in np.nonzero(changed)[0]:
            row = int(rows[i])
            chunk = self.held[int(r.chunk[row]) - self.first_serial]
            line_index = int(r.row[row])
            reason = "collision" if row in collided else "blend"
            chunk.new_words[line_index] = words[i].copy()
            chunk.reasons[line_index] = reason
            r.words[row] = words[i]
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


def _finite(value: float) -> float | None:
    return round(float(value), 4) if math.isfinite(value) else None
