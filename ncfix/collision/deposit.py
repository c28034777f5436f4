"""The rolling deposit model: which blocks deposit, and the beads laid so far (a chain of spheres).

Which blocks deposit (CONTRACT.md): a feed move (G1/G2/G3, never G0) deposits when the program has
extrusion words and E grows (the modal reader gives ``e_delta`` > 0 for absolute and relative E);
otherwise, with ``--deposit-codes``, between ON and OFF; otherwise every feed move deposits.
"The program has extrusion words" is decided while streaming, on the first window (the first
chunk the checker sees): if any extrusion word appears there, the E rule holds for the whole
program; a program whose first E word comes later is read with the other rules.

Beads are spheres of the bead radius centred on the deposited path through P, sampled at most
half a pitch apart (each depositing move from its start to its end point, both included).
They are kept in a log-structured set of k-d trees (sizes doubling, merged as they fill), so
adding is amortised O(log n) per bead and a query visits O(log n) trees. Memory grows with the
beads laid (12 bytes each), which is the deposited volume, not the program's length of travel.
"""

from __future__ import annotations

from enum import Enum

import numpy as np
from scipy.spatial import cKDTree


class DepositRule(Enum):
    EXTRUSION = "extrusion words (E grows)"
    CODES = "deposit codes (between ON and OFF)"
    EVERY_FEED = "every feed move"
    OFF = "off (--bead-radius 0)"


def choose_rule(e_delta: np.ndarray, deposit_codes_given: bool, bead_radius_mm: float) -> DepositRule:
    """The rule for the whole program, from the first window's extrusion column (see module doc)."""
    if bead_radius_mm <= 0:
        return DepositRule.OFF
    if np.isfinite(e_delta).any():
        return DepositRule.EXTRUSION
    if deposit_codes_given:
        return DepositRule.CODES
    return DepositRule.EVERY_FEED


def depositing(rule: DepositRule, motion: np.ndarray, e_delta: np.ndarray, deposit_on: np.ndarray) -> np.ndarray:
    """(n,) bool: which lines deposit under ``rule`` (motion, e_delta, deposit_on: chunk columns)."""
    feed = motion >= 1
    if rule is DepositRule.OFF:
        return np.zeros(len(motion), dtype=bool)
    if rule is DepositRule.EXTRUSION:
        with np.errstate(invalid="ignore"):
            return feed & (e_delta > 0)
    if rule is DepositRule.CODES:
        return feed & (deposit_on == 1)
    return feed


class BeadStore:
    """Bead sphere centres laid so far (workpiece mm), searchable by distance.

    ``add`` appends centres; ``pending`` holds the current window's centres with their sequence
    numbers (the pose index from which on they exist) until ``commit`` moves them into the trees.
    """

    def __init__(self, radius_mm: float, leaf_size: int = 4096):
        self.radius_mm = float(radius_mm)
        self._levels: list[tuple[cKDTree, np.ndarray]] = []  # (tree, points float64), sizes ~doubling
        self._buffer: list[np.ndarray] = []
        self._buffer_n = 0
        self._leaf = leaf_size
        self.count = 0

    # -- building ----------------------------------------------------------------------------
    def add(self, points_mm: np.ndarray) -> None:
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return
        self._buffer.append(pts)
        self._buffer_n += len(pts)
        self.count += len(pts)
        if self._buffer_n >= self._leaf:
            self._flush_buffer()

    def _flush_buffer(self) -> None:
        if not self._buffer:
            return
        pts = np.concatenate(self._buffer)
        self._buffer, self._buffer_n = [], 0
        # Merge while the newest level is no bigger than the new one (binary-counter merging).
        while self._levels and len(self._levels[-1][1]) <= len(pts):
            pts = np.concatenate([self._levels.pop()[1], pts])
        self._levels.append((cKDTree(pts, leafsize=16, balanced_tree=False, compact_nodes=False), pts))

    def trees(self) -> list[tuple[cKDTree, np.ndarray]]:
        self._flush_buffer()
        return self._levels

    @property
    def nbytes(self) -> int:
        return int(sum(p.nbytes * 2 for _, p in self._levels) + self._buffer_n * 24)

    # -- queries -----------------------------------------------------------------------------
    def nearest(self, centers_mm: np.ndarray, upper_mm: float = np.inf) -> np.ndarray:
        """Distance (m,) from each point (m, 3) to the nearest bead centre (inf when beyond ``upper_mm``)."""
        centers = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(centers), np.inf)
        for tree, _ in self.trees():
            d, _ = tree.query(centers, k=1, distance_upper_bound=upper_mm)
            np.minimum(out, d, out=out)
        return out

    def within(self, centers_mm: np.ndarray, radii_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bead centres within ``radii_mm`` (m,) of each point (m, 3).

        returns (query index (k,) int64, bead id (k,) int64, bead centres (k, 3) float64), one row
        per hit; ids are unique across the store (for removing duplicates).
        """
        centers = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        radii = np.broadcast_to(np.asarray(radii_mm, dtype=np.float64), (len(centers),))
        qs, ids, ps = [], [], []
        base = 0
        for tree, pts in self.trees():
            q, idx = query_pairs(tree, centers, radii)
            if len(q):
                qs.append(q)
                ids.append(idx + base)
                ps.append(pts[idx])
            base += len(pts)
        if not qs:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        return np.concatenate(qs), np.concatenate(ids), np.concatenate(ps)


def query_pairs(tree: cKDTree, centers: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (query index, point index) pairs within ``radii`` (m,) of ``centers`` (m, 3)."""
    if len(centers) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lists = tree.query_ball_point(centers, radii, return_sorted=False)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    flat = np.fromiter((j for x in lists for j in x), dtype=np.int64, count=total)
    return np.repeat(np.arange(len(centers)), counts), flat


def bead_samples(start_mm: np.ndarray, end_mm: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Counts per move (n,) and the move parameters t in [0, 1] of bead centres on straight moves.

    start_mm, end_mm : (n, 3) float64. Each move gets ceil(length / spacing) + 1 centres,
    t = 0 .. 1 inclusive. returns (counts (n,) int64, t (sum counts,) float64).
    """
    length = np.linalg.norm(np.asarray(end_mm) - np.asarray(start_mm), axis=1)
    m = np.maximum(np.ceil(length / spacing_mm - 1e-9).astype(np.int64), 1)
    counts = m + 1
    offsets = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(int(counts.sum())) - offsets
    return counts, k / np.repeat(m, counts)
