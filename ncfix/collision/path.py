"""Checking runs of consecutive motion blocks: end poses, sweeps between them, and their beads.

Between two motion points the words are interpolated as the controller does (linear in axis
angles, great circle for tool vectors via normalised linear interpolation of unit vectors) and
the pose is sampled so that no point of the head moves more than the pitch between samples
(|ΔC| + ρ·θ, ρ = the head's largest distance from its tip). Sample k is checked with an extra
margin d_k = |ΔC| + ρ·θ to sample k−1: every pose in between lies within d_k of sample k, so
the sampled checks cover the continuous sweep. The margin is split in its parts (lin = |ΔC|,
ang = θ): a head point at distance d from the tip is checked with lin + ang·d (the checker's
sphere tree knows each node's distance). Runs of samples are certified together first (coarse to
fine, ``Checker._grouped_undecided``). The sweep belongs to the block that ends it.

Beads of depositing moves are laid from the move's start to its end point, at most half a pitch
apart; a bead exists from the first sample at or after its place on the move (sequence numbers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncfix.collision.checker import Checker, rotation_angle
from ncfix.collision.deposit import BeadStore, bead_samples
from ncfix.kinematics.tool_vector import ToolVector


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

    def __len__(self) -> int:
        return len(self.w_end)


@dataclass
class MoveHits:
    """Per move: parts hit (n, n_parts), deposit hit (n,), the deposit clearance the exact test
    found (n,) (+inf where not tested), the sample that decides the reported clearance (n,)
    (the end pose when it collides, else the last colliding sample; -1 when free), and the
    samples' tip C and rotation R (for the report's exact clearances)."""

    part_hit: np.ndarray
    deposit_hit: np.ndarray
    deposit_clearance: np.ndarray
    sample: np.ndarray
    C: np.ndarray
    R: np.ndarray
    samples: int

    @property
    def any(self) -> np.ndarray:
        return self.part_hit.any(axis=1) | self.deposit_hit


class PathChecker:
    """Forward kinematics of words and the swept check of runs of moves against parts and beads."""

    def __init__(self, checker: Checker, profile, standoff_mm: float, pitch_mm: float):
        self.checker = checker
        self.kin = profile.kinematics
        self.is_vector = profile.is_vector
        self.standoff_mm = float(standoff_mm)
        self.pitch_mm = float(pitch_mm)

    def normalise(self, words: np.ndarray) -> np.ndarray:
        if self.is_vector:
            v = words[:, 3:6]
            norm = np.linalg.norm(v, axis=1, keepdims=True)
            words = words.copy()
            words[:, 3:6] = np.divide(v, norm, out=np.full_like(v, np.nan), where=norm > 0)
        return words

    def forward(self, words: np.ndarray, tcp: np.ndarray):
        """Programmed point P (n, 3), tool vector N (n, 3) and rotation R (n, 3, 3) of words."""
        n = len(words)
        P, N, R = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
        for flag in (False, True):
            sel = tcp == flag
            if sel.any():
                P[sel], N[sel], R[sel] = self.kin.forward(words[sel], tcp=bool(flag))
        return P, N, R

    def check(self, moves: Moves, store: BeadStore, seq0: int, *, commit: bool = True) -> tuple[MoveHits, int]:
        """Check every move (end pose and sweep) against the parts and the beads laid before it.

        store : the beads of every earlier move; seq0 : the sequence number of the first sample.
        With ``commit`` the moves' beads go into the store; without, the store is left as it was
        (the beads are then checked as pending, with their sequence numbers).
        Returns the hits and the sequence number after the last sample.
        """
        ck = self.checker
        h = self.standoff_mm
        ws, we, tcp, known = moves.w_start, moves.w_end, moves.tcp, moves.known_start
        ws = np.where(known[:, None], ws, we)
        Pe, Ne, Re = self.forward(we, tcp)
        Ps, Ns, Rs = self.forward(ws, tcp)
        Ce, Cs = Pe + h * Ne, Ps + h * Ns
        d_est = np.linalg.norm(Ce - Cs, axis=1) + ck.rho_mm * rotation_angle(Rs, Re)
        m = np.where(known, np.maximum(np.ceil(d_est / self.pitch_mm - 1e-9), 1), 1).astype(np.int64)
        total = int(m.sum())
        first = np.cumsum(m) - m  # index of each move's first sample
        row_of = np.repeat(np.arange(len(m)), m)
        k = np.arange(total) - first[row_of] + 1
        t = k / m[row_of]
        words = ws[row_of] + t[:, None] * (we[row_of] - ws[row_of])
        P, N, R = self.forward(self.normalise(words), tcp[row_of])
        C = P + h * N
        # Margin: how far any head point may be between this sample and the previous one.
        prev_C = np.where((k == 1)[:, None], Cs[row_of], np.roll(C, 1, axis=0))
        prev_R = np.where((k == 1)[:, None, None], Rs[row_of], np.roll(R, 1, axis=0))
        step = np.linalg.norm(C - prev_C, axis=1)
        turn = rotation_angle(prev_R, R)
        first_only = (k == 1) & ~known[row_of]
        step[first_only], turn[first_only] = 0.0, 0.0
        seq = seq0 + np.arange(total)
        # Distances between consecutive samples of the array (whatever the moves), for groups.
        chain_lin = np.zeros(total)
        chain_ang = np.zeros(total)
        if total > 1:
            chain_lin[1:] = np.linalg.norm(C[1:] - C[:-1], axis=1)
            chain_ang[1:] = rotation_angle(R[:-1], R[1:])
        cum_lin, cum_ang = np.cumsum(chain_lin), np.cumsum(chain_ang)

        pend, pend_seq = self._beads(moves, ws, Ps, Pe, m, first, seq0)
        part_hit = ck.sweep_parts(C, R, step, turn, cum_lin, cum_ang, move_of=row_of)
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
                                                  stamped=stamped, move_of=row_of)
            if stamped:
                store._add_exact(pend)
        elif commit:
            store.add(pend)
        ck.stats.poses += total

        n = len(moves)
        any_hit = part_hit.any(axis=1) | dep_hit
        sample = np.full(n, -1, dtype=np.int64)
        hit_idx = np.nonzero(any_hit)[0]
        sample[row_of[hit_idx]] = hit_idx  # the last colliding sample of each move (ascending)
        part_rows = np.logical_or.reduceat(part_hit, first, axis=0) if total else part_hit[:0]
        dep_rows = np.logical_or.reduceat(dep_hit, first)
        dep_clear_rows = np.minimum.reduceat(dep_clear, first)
        hits = MoveHits(part_rows, dep_rows, dep_clear_rows, sample, C, R, total)
        return hits, seq0 + total

    def bead_points(self, moves: Moves) -> np.ndarray:
        """The beads the moves lay (m, 3), as ``check`` lays them (for committing without a check)."""
        ws = np.where(moves.known_start[:, None], moves.w_start, moves.w_end)
        Ps, _, _ = self.forward(ws, moves.tcp)
        Pe, _, _ = self.forward(moves.w_end, moves.tcp)
        ones = np.ones(len(moves), dtype=np.int64)
        return self._beads(moves, ws, Ps, Pe, ones, np.zeros(len(moves), dtype=np.int64), 0)[0]

    def _beads(self, moves: Moves, ws, Ps, Pe, m, first, seq0):
        """Beads of the depositing moves, from start to end point, <= pitch/2 apart, with the
        sequence number of the first sample that sees each."""
        depo = moves.deposit
        if not depo.any() or self.checker.bead_radius_mm <= 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        di = np.nonzero(depo)[0]
        counts, tb = bead_samples(Ps[di], Pe[di], 0.5 * self.pitch_mm)
        brow = np.repeat(di, counts)
        bw = ws[brow] + tb[:, None] * (moves.w_end[brow] - ws[brow])
        if isinstance(self.kin, ToolVector):  # P is the XYZ words: no rotations to compute
            pend = bw[:, :3].copy()
        else:
            pend, _, _ = self.forward(self.normalise(bw), moves.tcp[brow])
        kb = np.maximum(np.ceil(tb * m[brow] - 1e-9), 1).astype(np.int64)
        return pend, seq0 + first[brow] + kb - 1
