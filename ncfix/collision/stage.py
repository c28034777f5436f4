"""The --check stage: every motion block (end pose and sweep) checked, collisions reported.

Chunks go back at once and unchanged; memory holds one chunk, at most ``window`` blocks'
samples at a time, the grids and the beads laid so far.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from ncfix.collision.checker import Checker
from ncfix.collision.deposit import BeadStore, DepositRule, choose_rule, depositing, rule_text
from ncfix.collision.depth import move_poses
from ncfix.collision.implied import ImpliedBead
from ncfix.collision.path import MoveHits, Moves, PathChecker
from ncfix.geometry.mesh import LoadedMesh, check_part_overlaps
from ncfix.profiles import Profile

if TYPE_CHECKING:
    from ncfix.config import Options
    from ncfix.report import Report


class MotionRows:
    """Turns chunks into runs of moves: carries the previous motion block's words across chunks.
    With --filament-diameter it also measures the bead the program's extrusion implies, on the
    moves as programmed (``implied.ImpliedBead``)."""

    def __init__(self, path: PathChecker, profile: Profile, options: Options) -> None:
        self.path = path
        self.extrusion_letter = profile.extrusion_letter
        self.options = options
        self.rule = None
        self.prev_words: np.ndarray | None = None
        self.prev_tcp = False
        self.unchecked = 0
        self.arcs = 0
        self.implied = None
        if getattr(options, "filament_diameter", None) is not None and path.checker is not None:
            shape = path.checker.bead_shape if path.checker.bead_radius_mm > 0 else None
            self.implied = ImpliedBead(options.filament_diameter, shape.width_mm if shape else 0.0,
                                       shape.height_mm if shape else 0.0)

    def tcp(self, chunk, rows) -> np.ndarray:
        return self.path.poses.tcp(chunk, rows)

    def deposit(self, chunk) -> np.ndarray:
        if self.rule is None:
            self.rule = choose_rule(chunk.e_delta, self.options.deposit_codes is not None,
                                    self.path.checker.bead_radius_mm)
        return depositing(self.rule, chunk.motion, chunk.e_delta, chunk.deposit_on)

    def moves(self, chunk, rows: np.ndarray, dep: np.ndarray) -> tuple[np.ndarray, Moves]:
        """The checkable rows (every axis known) of ``rows`` (not empty) and their moves; counts the others."""
        tcp = self.tcp(chunk, rows)
        w_end = self.path.normalise(chunk.words[rows])
        w_start = np.empty_like(w_end)
        w_start[1:] = w_end[:-1]
        w_start[0] = self.prev_words if self.prev_words is not None else np.nan
        tcp_start = np.empty_like(tcp)
        tcp_start[1:] = tcp[:-1]
        tcp_start[0] = self.prev_tcp
        self.prev_words, self.prev_tcp = w_end[-1].copy(), bool(tcp[-1])
        arc = chunk.arc[rows].copy()
        chord = (chunk.motion[rows] >= 2) & np.isnan(arc[:, 0])
        arc[chord, 3] = -1.0  # an arc ncfix cannot follow: checked along its chord, never re-oriented
        self.arcs += int(chord.sum())
        known_end = np.isfinite(w_end).all(axis=1)
        known_start = np.isfinite(w_start).all(axis=1) & (tcp_start == tcp) & known_end
        self.unchecked += int((~known_end).sum())
        keep = known_end
        moves = Moves(w_start[keep], w_end[keep], tcp[keep], known_start[keep], dep[rows][keep], arc[keep])
        if self.implied is not None and self.rule is DepositRule.EXTRUSION:
            inch = chunk.inch[rows[keep]].astype(bool)  # E in the program's unit, as the path: mm
            self._observe(moves, np.where(inch, 25.4, 1.0) * chunk.e_delta[rows[keep]])
        return rows[keep], moves

    def rule_text(self) -> str | None:
        """The deposit rule the program was read with, as the report states it."""
        if self.rule is None:
            return None
        return rule_text(self.rule, self.extrusion_letter)

    def _observe(self, moves: Moves, e_delta: np.ndarray) -> None:
        """The programmed straight depositing moves with a known start, for ``ImpliedBead``."""
        sel = moves.deposit & moves.known_start & np.isnan(moves.arc[:, 0])
        sel &= np.isfinite(moves.w_start).all(axis=1) & (moves.arc[:, 3] != -1.0)
        if not sel.any():
            return
        Ps, Ns, _ = self.path.forward(moves.w_start[sel], moves.tcp[sel])
        Pe, Ne, _ = self.path.forward(moves.w_end[sel], moves.tcp[sel])
        self.implied.observe(Ps, Pe, Ns, Ne, e_delta[sel], np.ones(len(Ps), dtype=bool))

    def report_into(self, report) -> None:
        """The run's warnings, the deposit rule and the implied bead (with --filament-diameter)."""
        report.warnings.extend(self.warnings())
        report.summary["deposit_rule"] = self.rule_text()
        if self.implied is not None:
            report.summary["implied_bead"] = self.implied.summary()
            report.notes.append(self.implied.line())
            report.warnings.extend(self.implied.warnings())

    def warnings(self) -> list[str]:
        out = []
        if self.unchecked:
            out.append(f"{self.unchecked} motion blocks were not checked: an axis was unknown there "
                       "(after G28/G53 or an expression) or TCP switched on the block")
        if self.arcs:
            out.append(f"{self.arcs} G2/G3 arc blocks were checked along their chord, not along the arc: ncfix "
                       "follows arcs given by I J K (or G90.1 centres), R / CR= and Heidenhain CC + C / CR")
        return out


class PlacementCheck:
    """The parts' placement check (wrong frame or units), on the program's box: the whole
    program's (its points and tips, ``pipeline.program_box``) when the input could be read ahead,
    else the first chunk that moves (a pipe: a streaming filter does not know the whole program
    yet). A part too far to reach is an error there and then; a part that only misses the box is
    a warning, given at the end unless some block hit the part (the head reaches it, so it is
    where the program works: a wall or fixture beside the path). The box is grown by where the
    material lies (the beads reach ``bead_drop_mm + bead_radius_mm`` from P) and a pitch, the
    checker's resolution: a platform that the first layer is printed on touches it."""

    def __init__(self, parts: Iterable[LoadedMesh], program_box: np.ndarray | None = None) -> None:
        self.parts = list(parts)
        self.program_box = program_box  # (2, 3) mm, or None: the first moving chunk's
        self.pending: list[tuple[str, str]] = []  # (the checker's name of the part, warning)

    def push(self, path: PathChecker, motion: MotionRows, chunk, rows) -> None:
        if not self.parts or not len(rows):
            return
        if self.program_box is not None:
            lo, hi = self.program_box
        else:
            P, _, _ = path.forward(path.normalise(chunk.words[rows]), motion.tcp(chunk, rows))
            P = P[np.isfinite(P).all(axis=1)]
            if len(P) == 0:
                return
            lo, hi = P.min(axis=0), P.max(axis=0)
        ck = path.checker
        grow = ck.pitch_mm + (ck.bead_drop_mm + ck.bead_radius_mm if ck.bead_radius_mm > 0 else 0.0)
        for part, body in zip(self.parts, ck.parts, strict=True):  # both in load_parts' order
            self.pending += [(body.name, w) for w in check_part_overlaps(part, lo - grow, hi + grow)]
        self.parts = []

    def report_into(self, report) -> None:
        hit = {body for entry in report.collisions for body in entry["bodies"]}
        report.warnings.extend(w for name, w in self.pending if name not in hit)


def collision_entry(checker: Checker, line: int, part_hit: np.ndarray, deposit_hit: bool, deposit_clearance: float,
                    c: np.ndarray, r: np.ndarray, at_end: bool, move_C: np.ndarray, move_R: np.ndarray) -> dict:
    """The report entry of one colliding move: the bodies hit, ``where`` it collides ("end": its
    end pose; "sweep": a pose along the move from the block before, its end pose being free),
    the exact clearance at the deciding pose (c, r: the end pose, or the last colliding pose of
    the sweep) and the penetration: the deepest the head goes into a body hit, over the poses
    of the move (``move_C`` (m, 3), ``move_R`` (m, 3, 3); ``depth.DepthProbe`` for the parts,
    the deepest bead for the beads, never less than the deciding pose's exact overlap)."""
    hit = [j for j, p in enumerate(checker.parts) if part_hit[j]]
    bodies = [checker.parts[j].name for j in hit]
    clearance = np.inf
    if bodies:
        per_part = checker.exact.part_clearances(c, r)
        clearance = min(per_part[b] for b in bodies)
    if deposit_hit:
        bodies.append("deposit")
        clearance = min(clearance, float(deposit_clearance))
    penetration = max(0.0, -clearance)
    if hit:
        probe = checker.depth_probe()
        poses = move_poses(move_C, move_R)
        penetration = max([penetration] + [probe.depth_mm(j, *poses) for j in hit])
    where = "end" if at_end and clearance < checker.clearance_mm else "sweep"
    return {"line": int(line), "bodies": bodies, "penetration_mm": round(penetration, 4),
            "clearance_mm": round(float(clearance), 4), "where": where}


def record_collisions(report, checker: Checker, lines: np.ndarray, hits: MoveHits, *, resolved: bool) -> None:
    """One report entry per colliding move (``collision_entry``)."""
    ends = np.append(hits.first[1:], len(hits.C)) if hits.first is not None else None
    for r in np.nonzero(hits.any)[0]:
        s = hits.sample[r]
        lo, hi = (hits.first[r], ends[r]) if ends is not None else (s, s + 1)
        entry = collision_entry(checker, lines[r], hits.part_hit[r], bool(hits.deposit_hit[r]),
                                float(hits.deposit_clearance[r]), hits.C[s], hits.R[s], s == hi - 1,
                                hits.C[lo:hi], hits.R[lo:hi])
        report.summary["colliding_blocks_before"] += 1
        report.collisions.append(entry)
        if not resolved:
            report.unresolved.append({"line": entry["line"], "bodies": entry["bodies"],
                                      "penetration_mm": entry["penetration_mm"], "where": entry["where"],
                                      "reason": "collides as programmed"})
            report.summary["unresolved_blocks"] += 1


class CheckStage:
    """Pipeline stage: checks every motion block (end pose and sweep) and fills the report."""

    def __init__(self, checker: Checker, profile: Profile, options: Options, report: Report,
                 placed_parts: Iterable[LoadedMesh] = (), program_box: np.ndarray | None = None) -> None:
        self.placement = PlacementCheck(placed_parts, program_box)
        self.checker = checker
        self.path = PathChecker(checker, profile, options.standoff, options.pitch)
        self.motion = MotionRows(self.path, profile, options)
        self.options = options
        self.report = report
        self.window = int(options.window)
        self.seq = 0
        self.store = BeadStore(checker.bead_radius_mm)
        self.samples = 0
        self.progress = None  # set by the pipeline: progress(line) as the work reaches a line

    def push(self, chunk):
        rows = np.nonzero(chunk.motion >= 0)[0]
        self.placement.push(self.path, self.motion, chunk, rows)
        dep = self.motion.deposit(chunk)
        for a in range(0, len(rows), self.window):
            rows_w, moves = self.motion.moves(chunk, rows[a:a + self.window], dep)
            if len(moves) == 0:
                continue
            tick = None
            if self.progress is not None:
                first, end = chunk.first_lineno + rows_w[0], chunk.first_lineno + rows_w[-1] + 1

                def tick(f, first=first, end=end):
                    return self.progress(first + f * (end - first))
            hits, self.seq = self.path.check(moves, self.store, self.seq, progress=tick)
            self.samples += hits.samples
            record_collisions(self.report, self.checker, chunk.first_lineno + rows_w, hits,
                              resolved=bool(self.options.check))
        return [chunk]

    def flush(self):
        self.report.summary["checked_samples"] = self.samples
        self.placement.report_into(self.report)
        self.motion.report_into(self.report)
        return []
