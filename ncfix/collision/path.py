"""Checking runs of consecutive motion blocks: end poses, sweeps between them, and their beads.

The words are interpolated as the controller moves (axis angles linearly, tool vectors on the
great circle, arcs about their centre) and sampled so that no head point moves more than the
pitch between samples; each sample is checked with that step as margin, which covers the
continuous sweep (docs/collision.md#sweeps). Beads are laid as docs/deposit.md says; a bead
exists from the first sample at or after its place on the move (sequence numbers).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ncfix.collision.checker import Checker, rotation_angle
from ncfix.collision.deposit import (LOOP_PROBE, LOOP_RATIO, LOOP_SPACING_MIN, BeadStore, axial_moves, bead_samples, held_radius,
                                     loop_samples, strand_along, strand_at_rest)
from ncfix.collision.plough import ploughing_moves
from ncfix.geometry.frames import half_turn_direction
from ncfix.kinematics.poses import PoseMap
from ncfix.kinematics.tool_vector import ToolVector
from ncfix.profiles import Profile

# A sample hit with its sweep margin is checked again as this many finer samples (REFINE_LEVELS deep).
REFINE_PARTS = 4
# Unit tool vectors whose sum is this short are opposite: their linear blend would pass through
# (or next to) zero, where no direction is defined (``PathChecker._half_turns``).
_HALF_TURN = 1e-9


@dataclass
class Moves:
    """Consecutive motion blocks: words at the start and end of each move (normalised tool
    vectors), TCP flag, whether the start is known (else only the end pose is checked) and
    whether the move deposits."""

    w_start: np.ndarray  # (n, k)
    w_end: np.ndarray  # (n, k)
    tcp: np.ndarray  # (n,) bool
    known_start: np.ndarray  # (n,) bool
    deposit: np.ndarray  # (n,) bool
    arc: np.ndarray | None = None  # (n, 5) Chunk.arc of each move (NaN: a straight move)

    def arc_rows(self) -> np.ndarray:
        """(n,) bool: moves followed along an arc (the start must be known)."""
        if self.arc is None:
            return np.zeros(len(self), dtype=bool)
        return np.isfinite(self.arc[:, 0]) & self.known_start

    def __len__(self) -> int:
        return len(self.w_end)


@dataclass
class MoveHits:
    """Per move: parts hit (n, n_parts), deposit hit (n,), the deposit clearance the exact test
    found (n,) (+inf where not tested), the sample that decides the reported clearance (n,)
    (the end pose when it collides, else the last colliding sample; -1 when free), and the
    samples' tip C and rotation R (for the report's exact clearances). When known: ``first`` (n,),
    the index of each move's first sample (move i has samples first[i] .. first[i+1]-1), and
    ``margin`` (n,), the largest sweep margin of its samples (mm: lin + ρ·ang; no head point is
    farther than that from where it is at the sample, between the sample and the one before)."""

    part_hit: np.ndarray
    deposit_hit: np.ndarray
    deposit_clearance: np.ndarray
    sample: np.ndarray
    C: np.ndarray
    R: np.ndarray
    samples: int
    first: np.ndarray | None = None
    margin: np.ndarray | None = None

    @property
    def any(self) -> np.ndarray:
        return self.part_hit.any(axis=1) | self.deposit_hit


class PathChecker:
    """The swept check of runs of moves against parts and beads; poses come from ``poses``."""

    def __init__(self, checker: Checker, profile: Profile, standoff_mm: float, pitch_mm: float) -> None:
        self.checker = checker
        self.poses = PoseMap(profile)
        self.kin, self.is_vector = self.poses.kin, self.poses.is_vector
        self.standoff_mm = float(standoff_mm)
        self.pitch_mm = float(pitch_mm)
        self.xyz = [list(self.kin.letters).index(a) for a in "XYZ"]

    def normalise(self, words: np.ndarray) -> np.ndarray:
        return self.poses.normalise(words)

    def forward(self, words: np.ndarray, tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Programmed point P (n, 3), tool vector N (n, 3) and rotation R (n, 3, 3) of words."""
        return self.poses.forward(words, tcp)

    def check(self, moves: Moves, store: BeadStore, seq0: int, *, commit: bool = True,
              prior: np.ndarray | None = None, clearances: bool = True,
              progress: Callable[[float], None] | None = None) -> tuple[MoveHits, int]:
        """Check every move (end pose and sweep) against the parts and the beads laid before it.

        store : the beads of every earlier move; seq0 : the sequence number of the first sample.
        With ``commit`` the moves' beads go into the store; without, the store is left as it was
        (the beads are then checked as pending, with their sequence numbers).
        prior : (m, 3) beads laid before the first move but not in the store (pending moves
        before these; without ``commit`` only): every sample sees them, none as its own.
        clearances : False when only the hits are wanted: the deposit hits' clearances (the
        deepest bead of each, for the report) are then not computed (``deposit_clearance`` -inf).
        progress : called with the fraction of the check done (0..1) as it goes (a progress bar).
        Returns the hits and the sequence number after the last sample.
        """
        if prior is not None and len(prior) and commit:
            raise ValueError("prior beads are for checks without commit")
        ck = self.checker
        h = self.standoff_mm
        ws, we, tcp, known = moves.w_start, moves.w_end, moves.tcp, moves.known_start
        ws = np.where(known[:, None], ws, we)
        Pe, Ne, Re = self.forward(we, tcp)
        Ps, Ns, Rs = self.forward(ws, tcp)
        Ce, Cs = Pe + h * Ne, Ps + h * Ns
        d_est = np.linalg.norm(Ce - Cs, axis=1) + ck.rho_mm * rotation_angle(Rs, Re)
        m = np.where(known, np.maximum(np.ceil(d_est / self.pitch_mm - 1e-9), 1), 1).astype(np.int64)
        arcs = moves.arc_rows()
        if arcs.any():
            sweep, length = arc_extent(ws[arcs][:, self.xyz], we[arcs][:, self.xyz], moves.arc[arcs])
            chord = np.linalg.norm(we[arcs][:, self.xyz] - ws[arcs][:, self.xyz], axis=1)
            longer = d_est[arcs] + np.maximum(length - chord, 0.0)
            m[arcs] = np.maximum(np.ceil(longer / self.pitch_mm - 1e-9),
                                 np.ceil(np.abs(sweep) / (0.5 * np.pi) - 1e-9)).astype(np.int64)
        total = int(m.sum())
        first = np.cumsum(m) - m  # index of each move's first sample
        row_of = np.repeat(np.arange(len(m)), m)
        k = np.arange(total) - first[row_of] + 1
        t = k / m[row_of]
        words = self._along(moves, ws, we, row_of, t, arcs)
        P, N, R = self.forward(self.normalise(words), tcp[row_of])
        C = P + h * N
        # Margin: how far any head point may be between this sample and the previous one.
        prev_C = np.where((k == 1)[:, None], Cs[row_of], np.roll(C, 1, axis=0))
        prev_R = np.where((k == 1)[:, None, None], Rs[row_of], np.roll(R, 1, axis=0))
        prev_P = prev_N = None  # needed on arcs only
        if arcs.any():
            prev_P = np.where((k == 1)[:, None], Ps[row_of], np.roll(P, 1, axis=0))
            prev_N = np.where((k == 1)[:, None], Ns[row_of], np.roll(N, 1, axis=0))
        step, turn = self.margins(P, N, C, R, prev_P, prev_N, prev_C, prev_R, arcs[row_of])
        first_only = (k == 1) & ~known[row_of]
        step[first_only], turn[first_only] = 0.0, 0.0
        margin = np.maximum.reduceat(step + ck.rho_mm * turn, first) if total else np.zeros(len(moves))
        seq = seq0 + np.arange(total)
        # Distances between consecutive samples of the array (whatever the moves), for groups.
        chain_lin = np.zeros(total)
        chain_ang = np.zeros(total)
        if total > 1:
            chain_lin[1:] = np.linalg.norm(C[1:] - C[:-1], axis=1)
            chain_ang[1:] = rotation_angle(R[:-1], R[1:])
        cum_lin, cum_ang = np.cumsum(chain_lin), np.cumsum(chain_ang)

        pend, pend_seq, pend_r = self._beads(moves, ws, Ps, Pe, Ns, Ne, m, first, seq0)
        if prior is not None and len(prior) and ck.bead_radius_mm > 0:
            # Laid before sample seq0: seen by every sample, never fresh; first in laying order.
            prior_r = None
            if isinstance(prior, tuple):  # (beads, radii) of ``bead_points(..., radii=True)``
                prior, prior_r = prior
            prior = np.asarray(prior, dtype=np.float64).reshape(-1, 3)
            if prior_r is not None or pend_r is not None:
                pend_r = np.concatenate([np.full(len(prior), ck.bead_radius_mm) if prior_r is None else prior_r,
                                         np.full(len(pend), ck.bead_radius_mm) if pend_r is None else pend_r])
            pend = np.concatenate([prior, pend])
            pend_seq = np.concatenate([np.full(len(prior), seq0 - 1, dtype=np.int64), pend_seq])
        refine = Refiner(self, moves, ws, we, arcs, row_of, (k - 1) / m[row_of], t)
        # The parts take the first half of the bar, the beads the second (a guess that only moves it).
        part_hit = ck.sweep_parts(C, R, step, turn, cum_lin, cum_ang, move_of=row_of, refine=refine,
                                  progress=None if progress is None else lambda f: progress(0.5 * f))
        dep_hit = np.zeros(total, dtype=bool)
        dep_clear = np.full(total, np.inf)
        if ck.bead_radius_mm > 0 and (store.count or len(pend)):
            # With commit the window's beads go into the field for good before the test: every
            # sample sees all of them there (a superset, conservative); the exact test keeps the
            # sequence. Without commit they are overlaid for the call.
            stamped = commit and len(pend) > 0
            if stamped:
                store.field(ck.pitch_mm).add(pend)
            dep_hit, dep_clear = ck.sweep_deposit(C, R, step, turn, cum_lin, cum_ang, seq, store, pend, pend_seq,
                                                  stamped=stamped, move_of=row_of, refine=refine,
                                                  clearances=clearances, pending_r=pend_r,
                                                  progress=None if progress is None else lambda f: progress(0.5 + 0.5 * f))
            if stamped:
                store._add_exact(pend, pend_r)
        elif commit:
            store.add(pend, pend_r)
        ck.stats.poses += total

        n = len(moves)
        any_hit = part_hit.any(axis=1) | dep_hit
        sample = np.full(n, -1, dtype=np.int64)
        hit_idx = np.nonzero(any_hit)[0]
        sample[row_of[hit_idx]] = hit_idx  # the last colliding sample of each move (ascending)
        part_rows = np.logical_or.reduceat(part_hit, first, axis=0) if total else part_hit[:0]
        dep_rows = np.logical_or.reduceat(dep_hit, first)
        dep_clear_rows = np.minimum.reduceat(dep_clear, first)
        hits = MoveHits(part_rows, dep_rows, dep_clear_rows, sample, C, R, total, first, margin)
        if progress is not None:
            progress(1.0)
        return hits, seq0 + total

    def margins(self, P, N, C, R, prev_P, prev_N, prev_C, prev_R, on_arc) -> tuple[np.ndarray, np.ndarray]:
        """Sweep margins of samples from the sample before each: lin = |ΔC| and ang = the head's
        turn (rad); a head point at distance d from the tip moves at most lin + ang·d between them
        (the sphere tree knows each node's d). On arcs lin = |ΔP| + h·|ΔN|: samples are at most a
        quarter turn apart, and no point of an arc of less than half a turn is farther from its
        end than its chord (prev_P / prev_N are read only there)."""
        lin = np.linalg.norm(C - prev_C, axis=1)
        if on_arc.any():
            alt = np.linalg.norm(P - prev_P, axis=1) + self.standoff_mm * np.linalg.norm(N - prev_N, axis=1)
            lin[on_arc] = alt[on_arc]
        return lin, rotation_angle(prev_R, R)

    def _along(self, moves: Moves, ws, we, row, t, arcs) -> np.ndarray:
        """Words at parameter t (m,) of moves ``row`` (m,): linear, the point along the arc on arcs."""
        words = ws[row] + t[:, None] * (we[row] - ws[row])
        on_arc = arcs[row]
        if on_arc.any():
            r = row[on_arc]
            pts = arc_points(ws[r][:, self.xyz], we[r][:, self.xyz], moves.arc[r], t[on_arc])
            sel = np.nonzero(on_arc)[0]
            for j, col in enumerate(self.xyz):
                words[sel, col] = pts[:, j]
        if self.is_vector:
            self._half_turns(words, ws[row], we[row], t)
        return words

    @staticmethod
    def _half_turns(words, ws, we, t) -> None:
        """Tool vectors of moves that turn them by 180° (``K1`` then ``K-1``), in place: the
        linear blend passes through zero there, so such a move turns in the plane through
        ``half_turn_direction`` instead (a half turn has no unique shortest way; README)."""
        a, b = ws[:, 3:6], we[:, 3:6]
        flip = np.linalg.norm(a + b, axis=1) <= _HALF_TURN
        flip &= np.isfinite(a).all(axis=1)
        if not flip.any():
            return
        a = a[flip] / np.linalg.norm(a[flip], axis=1, keepdims=True)
        angle = np.pi * t[flip]
        words[flip, 3:6] = np.cos(angle)[:, None] * a + np.sin(angle)[:, None] * half_turn_direction(a)

    def bead_points(self, moves: Moves, radii: bool = False, movers: bool = False):
        """The beads the moves lay (m, 3), as ``check`` lays them (for committing without a check);
        with ``radii`` (beads, radius of each (m,) or None: all the bead radius), which
        ``BeadStore.add`` and ``check``'s ``prior`` take; with ``movers`` (beads, index of the
        move that lays each (m,)). A move's beads do not depend on the other moves given."""
        ws = np.where(moves.known_start[:, None], moves.w_start, moves.w_end)
        Ps, Ns, _ = self.forward(ws, moves.tcp)
        Pe, Ne, _ = self.forward(moves.w_end, moves.tcp)
        n = len(moves)
        # Each move one sample long: a bead's sequence number is then its move's index.
        first = np.arange(n, dtype=np.int64) if movers else np.zeros(n, dtype=np.int64)
        pend, seq, pend_r = self._beads(moves, ws, Ps, Pe, Ns, Ne, np.ones(n, dtype=np.int64), first, 0)
        if movers:
            return pend, np.asarray(seq, dtype=np.int64)
        return (pend, pend_r) if radii else pend

    def _beads(self, moves: Moves, ws, Ps, Pe, Ns, Ne, m, first, seq0):
        """Beads of the depositing moves, from start to end point, <= pitch/2 apart (a plunge or
        lift: one, at its lower end), each ``bead_drop_mm`` below P along the tool axis, with the
        sequence number of the first sample that sees each, and their radii (None: all the bead
        radius; a looping move's beads are thinner, ``_looping_beads``)."""
        depo = moves.deposit
        if not depo.any() or self.checker.bead_radius_mm <= 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), None
        di = np.nonzero(depo)[0]
        arcs = moves.arc_rows()
        length = np.linalg.norm(Pe[di] - Ps[di], axis=1)
        if arcs[di].any():
            sel = di[arcs[di]]
            length[arcs[di]] = arc_extent(ws[sel][:, self.xyz], moves.w_end[sel][:, self.xyz], moves.arc[sel])[1]
        counts, tb = bead_samples(Ps[di], Pe[di], 0.5 * self.pitch_mm, length_mm=length)
        axial = (axial_moves(Ps[di], Pe[di], Ns[di], Ne[di]) | self._ploughing(moves, ws, di)) & ~arcs[di]
        if axial.any():
            # The lower end along the axis: the end point of a plunge (P·N falls), else the start.
            lower = np.where(np.einsum("ij,ij->i", Pe[di] - Ps[di], Ns[di] + Ne[di]) < 0, 1.0, 0.0)
            own = np.repeat(np.arange(len(di)), counts)
            keep = ~axial[own] | (tb == lower[own])  # t is exactly 0.0 and 1.0 at the ends
            tb = tb[keep]
            counts = np.where(axial, 1, counts)
        brow = np.repeat(di, counts)
        bw = self._along(moves, ws, moves.w_end, brow, tb, arcs)
        drop = float(getattr(self.checker, "bead_drop_mm", 0.0))  # a checker without it lays beads on P
        if isinstance(self.kin, ToolVector):  # P is the XYZ words: no rotations to compute
            pend = bw[:, :3].copy()
            if drop:
                v = bw[:, 3:6]
                pend -= drop * v / np.linalg.norm(v, axis=1, keepdims=True)
        else:
            pend, nb, _ = self.forward(self.normalise(bw), moves.tcp[brow])
            if drop:
                pend -= drop * nb
        kb = np.maximum(np.ceil(tb * m[brow] - 1e-9), 1).astype(np.int64)
        pend_seq = seq0 + first[brow] + kb - 1
        radii = None
        if not isinstance(self.kin, ToolVector):  # XYZ words: P runs straight, never loops
            loops = self._looping_beads(moves, ws, Ps, Pe, di[~axial & ~arcs[di]], m, first, seq0)
            if loops:
                pend, pend_seq, radii = self._with_loops(pend, pend_seq, di, counts, loops)
        return pend, pend_seq, radii

    def _linear_words(self, moves: Moves, ws, row: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The words at fractions ``t`` along the moves ``row`` (both (q,)), as the controller
        moves with TCP off (linear in the words)."""
        return self._along(moves, ws, moves.w_end, row, t, np.zeros(len(moves), dtype=bool))

    def _tip_paths(self, moves: Moves, ws, rows: np.ndarray, samples: list[int]) -> list:
        """P at ``samples[i]`` + 1 even steps of t along each move ``rows[i]`` (``_linear_words``),
        the poses of all in one batch (a pose does not depend on the others of its batch):
        [(P (samples + 1, 3), t (samples + 1,)), ...]."""
        ts = [np.arange(s + 1) / s for s in samples]
        counts = np.array([len(t) for t in ts], dtype=np.int64)
        row = np.repeat(rows, counts)
        words = self._linear_words(moves, ws, row, np.concatenate(ts) if ts else np.zeros(0))
        P, _, _ = self.forward(self.normalise(words), moves.tcp[row])
        return list(zip(np.split(P, np.cumsum(counts)[:-1]), ts))

    def _looping_beads(self, moves: Moves, ws, Ps, Pe, rows, m, first, seq0) -> dict:
        """Beads of the depositing moves ``rows`` whose tip runs a path LOOP_RATIO or more longer
        than the programmed one (TCP off, the axes interpolated linearly: a C flip near the pole):
        {row: (beads (q, 3), sequence numbers (q,), radii (q,))}. The move's material is spread
        along the longer path: a strand of (programmed length / tip path length) times the stated
        section (``BeadShape.strand``), laid along the tip's path at most min(pitch/2, its radius)
        apart, each held as a sphere covering the strand out to the next bead, where it comes to
        rest (``deposit.strand_at_rest``: no higher than the move's ends along the machine's
        vertical, and along the straight line between them) (deposit.md, "Looping tips"). The tip path's length is that of a polyline through points on it (never
        longer than the path: the strand is never made thinner than the rule says)."""
        ck = self.checker
        shape = getattr(ck, "bead_shape", None)
        if shape is None or len(rows) == 0:
            return {}
        chord = np.linalg.norm(Pe[rows] - Ps[rows], axis=1)
        P = np.stack([P for P, _ in self._tip_paths(moves, ws, rows, [LOOP_PROBE] * len(rows))])
        probe = np.linalg.norm(np.diff(P, axis=1), axis=2).sum(axis=1)
        loop = (chord > 0) & (probe > LOOP_RATIO * chord)
        if not loop.any():
            return {}
        # The tip paths of the looping moves, then the strands' beads, each in one batch of poses.
        paths = self._tip_paths(moves, ws, rows[loop], [loop_samples(rough) for rough in probe[loop]])
        strands = []
        for row, c, (P, t) in zip(rows[loop], chord[loop], paths):
            got = strand_along(P, t, c, shape, 0.5 * self.pitch_mm)
            if got is not None:
                strands.append((row, got))
        if not strands:
            return {}
        row_b = np.concatenate([np.full(len(got[0]), row) for row, got in strands])
        bw = self._linear_words(moves, ws, row_b, np.concatenate([got[0] for _, got in strands]))
        pb_all, nb_all, _ = self.forward(self.normalise(bw), moves.tcp[row_b])
        ends = np.cumsum([len(got[0]) for _, got in strands])
        out = {}
        for (row, (tb, r, drop)), b in zip(strands, ends):
            a = b - len(tb)
            beads = pb_all[a:b] - drop * nb_all[a:b]
            if held_radius(r, beads, ck.bead_radius_mm) >= ck.bead_radius_mm:  # laid as the stated bead
                continue
            middle = self._linear_words(moves, ws, np.array([row]), np.array([0.5]))
            step = min(0.5 * self.pitch_mm, max(r, LOOP_SPACING_MIN * 0.5 * self.pitch_mm))
            lowered, taut = strand_at_rest(beads, self.kin.vertical(self.normalise(middle))[0], step)
            beads = np.concatenate([lowered, taut])
            held = max(held_radius(r, lowered, ck.bead_radius_mm), held_radius(r, taut, ck.bead_radius_mm))
            kb = np.maximum(np.ceil(tb * m[row] - 1e-9), 1).astype(np.int64)
            kb = np.concatenate([kb, np.full(len(taut), m[row])])  # pulled taut: at the move's end
            out[int(row)] = (beads, seq0 + first[row] + kb - 1, np.full(len(beads), held))
        return out

    def _with_loops(self, pend, pend_seq, di, counts, loops: dict):
        """The beads with each looping move's replaced by ``loops``' (laying order kept), and the
        radius of every bead."""
        r = self.checker.bead_radius_mm
        ends = np.cumsum(counts)
        parts, seqs, radii = [], [], []
        done = 0  # pend[:done] is placed
        # The looping moves (few) in laying order; the runs of ordinary moves between them are
        # taken whole.
        for j in np.flatnonzero(np.isin(di, np.fromiter(loops, dtype=np.int64, count=len(loops)))):
            a, b = ends[j] - counts[j], ends[j]
            got = loops[int(di[j])]
            parts += [pend[done:a], got[0]]
            seqs += [pend_seq[done:a], got[1]]
            radii += [np.full(a - done, r), got[2]]
            done = b
        parts.append(pend[done:]), seqs.append(pend_seq[done:]), radii.append(np.full(len(pend) - done, r))
        return np.concatenate(parts), np.concatenate(seqs), np.concatenate(radii)

    def _ploughing(self, moves: Moves, ws: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) bool: the moves whose nozzle ploughs through what they extrude
        (``plough.ploughing_moves``: the head's shape decides; their material ends at the lower end)."""
        tris = getattr(self, "_head_triangles", None)
        if tris is None:
            head = getattr(self.checker, "head", None)  # a checker for the beads alone has no head
            if head is None:
                return np.zeros(len(rows), dtype=bool)
            tris = self._head_triangles = np.asarray(head.triangles, dtype=np.float64)
        Ps, Ns, Rs = self.forward(ws[rows], moves.tcp[rows])
        Pe, Ne, Re = self.forward(moves.w_end[rows], moves.tcp[rows])
        h = self.standoff_mm
        return ploughing_moves(tris, Ps + h * Ns, Pe + h * Ne, Rs, Re)


def join_beads(parts: list, radius_mm: float):
    """(beads, radii) of ``PathChecker.bead_points(..., radii=True)`` parts, joined in order (radii
    None when every bead has ``radius_mm``)."""
    pts = np.concatenate([p for p, _ in parts])
    if all(r is None for _, r in parts):
        return pts, None
    return pts, np.concatenate([np.full(len(p), radius_mm) if r is None else r for p, r in parts])


class Refiner:
    """Splits samples into finer ones: a sample stands for its move from parameter t0 to t1, and
    a hit found with its sweep margin may be a false alarm of that margin. ``split(idx)`` gives
    REFINE_PARTS samples per sample idx over the same stretch, each with its own (smaller)
    margins, and a Refiner of them for the next level. The checker calls a sample colliding only
    when a sub-sample collides (each sub-sample's margin covers its own stretch: conservative)."""

    def __init__(self, path: PathChecker, moves: Moves, ws: np.ndarray, we: np.ndarray, arcs: np.ndarray,
                 row: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> None:
        self.path, self.moves, self.ws, self.we, self.arcs = path, moves, ws, we, arcs
        self.row, self.t0, self.t1 = row, t0, t1

    def split(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, "Refiner"]:
        """Sub-samples of samples idx: C (q, 3), R (q, 3, 3), lin (q,), ang (q,), parent (q,) (index into idx)."""
        idx = np.asarray(idx, dtype=np.int64)
        parts = REFINE_PARTS
        parent = np.repeat(np.arange(len(idx)), parts)
        frac = np.tile(np.arange(0, parts + 1) / parts, len(idx))
        rows = np.repeat(self.row[idx], parts + 1)
        t = np.repeat(self.t0[idx], parts + 1) + frac * np.repeat(self.t1[idx] - self.t0[idx], parts + 1)
        words = self.path._along(self.moves, self.ws, self.we, rows, t, self.arcs)
        P, N, R = self.path.forward(self.path.normalise(words), self.moves.tcp[rows])
        C = P + self.path.standoff_mm * N
        end = np.ones(len(t), dtype=bool)
        end[::parts + 1] = False  # the first of each group is the stretch's start, not a sample
        cur = np.nonzero(end)[0]
        prev = cur - 1
        lin, ang = self.path.margins(P[cur], N[cur], C[cur], R[cur], P[prev], N[prev], C[prev], R[prev],
                                     self.arcs[rows[cur]])
        sub = Refiner(self.path, self.moves, self.ws, self.we, self.arcs, rows[cur], t[prev], t[cur])
        return C[cur], R[cur], lin, ang, parent, sub


def _arc_angles(start: np.ndarray, end: np.ndarray, arc: np.ndarray):
    """Per arc: plane axes (a, b), normal axis, start angle, signed sweep (rad), start and end radius."""
    axis = arc[:, 3].astype(np.int64)
    a = np.choose(axis, [1, 2, 0])
    b = np.choose(axis, [2, 0, 1])
    n = np.arange(len(arc))
    c = arc[:, :3]
    sa, sb = start[n, a] - c[n, a], start[n, b] - c[n, b]
    ea, eb = end[n, a] - c[n, a], end[n, b] - c[n, b]
    a0, a1 = np.arctan2(sb, sa), np.arctan2(eb, ea)
    ccw = arc[:, 4] > 0
    sweep = np.where(ccw, np.mod(a1 - a0, 2 * np.pi), -np.mod(a0 - a1, 2 * np.pi))
    # start == end: a full circle (a controller turns once round)
    full = np.abs(sweep) < 1e-9
    sweep = np.where(full, np.where(ccw, 2 * np.pi, -2 * np.pi), sweep)
    return a, b, axis, a0, sweep, np.hypot(sa, sb), np.hypot(ea, eb)


def arc_extent(start: np.ndarray, end: np.ndarray, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed sweep (rad) and a length at least the path's (mm) of arcs (start, end (n, 3) mm)."""
    _, _, axis, _, sweep, r0, r1 = _arc_angles(start, end, arc)
    n = np.arange(len(arc))
    rise = np.abs(end[n, axis] - start[n, axis])
    return sweep, np.abs(sweep) * np.maximum(r0, r1) + np.abs(r1 - r0) + rise


def arc_points(start: np.ndarray, end: np.ndarray, arc: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points (m, 3) at parameter t (m,) of arcs (one row each of start, end, arc): the angle and
    the radius go linearly from start to end, the normal coordinate too (a helix)."""
    a, b, axis, a0, sweep, r0, r1 = _arc_angles(start, end, arc)
    n = np.arange(len(arc))
    angle = a0 + t * sweep
    radius = r0 + t * (r1 - r0)
    out = np.empty_like(start)
    out[n, a] = arc[:, :3][n, a] + radius * np.cos(angle)
    out[n, b] = arc[:, :3][n, b] + radius * np.sin(angle)
    out[n, axis] = start[n, axis] + t * (end[n, axis] - start[n, axis])
    return out
