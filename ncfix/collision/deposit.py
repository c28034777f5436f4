"""The rolling deposit model: which blocks deposit, where their material lies, and the beads laid
so far.

The rule (``choose_rule``, decided on the first window: E words, else the deposit codes, else
every feed move), the bead's place and shape (``BeadShape``: below the tip along the tool axis),
plunges, lifts and ploughing moves laid at their lower end (``axial_moves``), and the strands of
looping tips (``strand_along``, ``strand_at_rest``) are described in docs/deposit.md.
``BeadStore`` keeps the beads twice: exact centres for the exact test, and ``BeadField``, a
rolling distance field for the fast one, whose memory is the beads' box, not the program's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from ncfix.collision.split import map_parts, thread_count
from ncfix.geometry.cells import group_cells
from ncfix.memory import ensure_fits

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

# Exact bead centres kept (the newest; BeadStore): 2**18 beads is about 65 m of deposited path at
# the 0.5 mm pitch (beads every 0.25 mm), 6 MB of centres and about as much of k-d trees.
EXACT_BEADS_MAX = 1 << 18
# The retired beads' field is this many times coarser than the pitch (it only has to clear poses
# away from them: near them a pose counts as colliding anyway).
OLD_FIELD_COARSENING = 2


# A depositing move whose direction lies within this angle (degrees) of the tool axis at both its
# ends is a plunge or a lift: its material is laid at its lower end only. Plunges and lifts are
# programmed along the axis (0°); a printing move is far from it (a layer's path runs across the
# axis). 10° leaves room for rounding of the words of short moves.
AXIAL_DEG = 10.0


@dataclass(frozen=True)
class BeadShape:
    """The deposited bead as stated (``--bead-width``/``--bead-height`` or ``--bead-radius``) and
    how the checker holds it.

    The stated bead, at each bead sample, is a round-edged disc across the tool axis N: ``width_mm``
    across, ``height_mm`` along N (the set of points within height/2 of a disc of radius
    (width − height)/2 about the centre, at right angles to N; for width = height a ball: the round
    bead of radius width/2). Cut across the path it is the usual bead section, a rectangle with
    round ends ("obround"), width × height. Its centre lies ``drop_mm`` below the path point P along
    N: with --standoff 0 (filament: the nozzle tip on the path) the bead's top is at the tip,
    drop = height/2; with a standoff (h > 0) P is where the process puts the bead, its centre, drop
    = 0.

    The checker holds it as one sphere of ``radius_mm`` = max(width, height)/2 about that centre,
    which contains it: a point of the disc is at most (width − height)/2 from the centre, plus
    height/2 (``tests/test_deposit_rule.py`` checks it against the exact section).
    """

    width_mm: float
    height_mm: float
    drop_mm: float = 0.0

    @property
    def radius_mm(self) -> float:
        return 0.5 * max(self.width_mm, self.height_mm)

    def strand(self, ratio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(radius (n,), drop (n,)): the sphere that holds a strand of ``ratio`` (n,) times the
        stated section, and its centre's drop below P (deposit.md, "Looping tips").

        The strand keeps the stated bead's thickness (the smaller of width and height) and
        narrows: its larger dimension is what carries the section at that thickness; once the
        section is below the thickness's round, it is a round strand of that section. It is
        never larger than the stated bead (ratio >= 1: the stated bead, exactly). With
        --standoff 0 its top stays at the tip (the drop is half its height), else it is centred
        on P as the stated bead is."""
        ratio = np.asarray(ratio, dtype=np.float64)
        radius = np.full(ratio.shape, self.radius_mm)
        drop = np.full(ratio.shape, self.drop_mm)
        thin = ratio < 1.0
        if not thin.any():
            return radius, drop
        w, h = self.width_mm, self.height_mm
        m, big = min(w, h), max(w, h)
        core = 0.25 * np.pi * m * m  # the round of the thickness
        area = ratio[thin] * (m * (big - m) + core)
        long = np.where(area >= core, m + (area - core) / max(m, 1e-300), np.sqrt(area / (0.25 * np.pi)))
        long = np.minimum(long, big)
        tall = np.where(area < core, long, h if w >= h else long)  # the strand's height along N
        radius[thin] = 0.5 * long
        if self.drop_mm:
            drop[thin] = np.minimum(self.drop_mm, self.drop_mm * tall / h)
        return radius, drop

    @classmethod
    def stated(cls, bead_radius_mm: float, width_mm: float | None, height_mm: float | None,
               standoff_mm: float) -> "BeadShape":
        """The bead of the options: width × height when stated, else round of the radius (0: off)."""
        if width_mm is None or height_mm is None:
            width_mm = height_mm = 2.0 * float(bead_radius_mm)
        drop = 0.5 * float(height_mm) if float(standoff_mm) == 0.0 else 0.0
        return cls(float(width_mm), float(height_mm), drop)


def axial_moves(start_mm: np.ndarray, end_mm: np.ndarray, n_start: np.ndarray, n_end: np.ndarray) -> np.ndarray:
    """(n,) bool: moves (start, end (n, 3) P, workpiece mm) that run along the tool axis (unit
    vectors n_start, n_end (n, 3)) within AXIAL_DEG at both ends: plunges and lifts."""
    d = np.asarray(end_mm, dtype=np.float64) - np.asarray(start_mm, dtype=np.float64)
    length = np.linalg.norm(d, axis=1)
    cos_min = np.cos(np.radians(AXIAL_DEG))
    with np.errstate(invalid="ignore", divide="ignore"):
        c0 = np.abs(np.einsum("ij,ij->i", d, n_start)) / length
        c1 = np.abs(np.einsum("ij,ij->i", d, n_end)) / length
    return (length > 0) & (c0 >= cos_min) & (c1 >= cos_min)


# Looping tips (deposit.md "Looping tips"): a depositing move's tip path is probed at LOOP_PROBE
# even steps of the move; a path LOOP_RATIO times its programmed length or longer is a loop, then
# measured at LOOP_STEPS_PER_MM steps per mm of the probe's length (LOOP_PROBE to
# LOOP_SAMPLES_MAX steps). A path less than 1% longer keeps the stated bead (within 1% of its
# section; the stated bead is the larger, so this errs toward "collides").
LOOP_PROBE = 8
LOOP_RATIO = 1.01
LOOP_STEPS_PER_MM = 20.0
LOOP_SAMPLES_MAX = 4096
# A looping move's beads lie at most min(bead spacing, the strand's radius) apart along its path,
# and at least this fraction of the bead spacing (a very thin strand is held as wider spheres,
# not as very many).
LOOP_SPACING_MIN = 0.25


def loop_samples(probe_mm: float) -> int:
    """Even steps to measure a looping tip path with (its probed length ``probe_mm``)."""
    return int(min(max(np.ceil(LOOP_STEPS_PER_MM * probe_mm), LOOP_PROBE), LOOP_SAMPLES_MAX))


def strand_along(path_mm: np.ndarray, t: np.ndarray, programmed_mm: float, shape: "BeadShape",
                 spacing_mm: float):
    """Where a looping move's strand lies: (bead parameters tb (q,) in [0, 1], the strand's
    radius, its centre's drop), or None when it is no thinner than the stated bead.

    path_mm (k + 1, 3): the tip (P) at the move's parameters t (k + 1,) (0 .. 1), as the
    controller moves; programmed_mm: the programmed path's length. The move's material is spread
    over the tip's path: a strand of programmed / path length times the stated section
    (``BeadShape.strand``). Its beads are at even steps of length along the path, at most
    min(spacing, radius) apart (at least LOOP_SPACING_MIN · spacing). The path's length is that
    of the polyline through the points given, never longer than the path: the strand is never
    made thinner than the rule says."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path_mm, axis=0), axis=1))])
    length = float(cum[-1])
    if not length > 0.0 or programmed_mm >= length:
        return None
    (r,), (drop,) = shape.strand(np.array([programmed_mm / length]))
    if r >= shape.radius_mm:
        return None
    step = min(spacing_mm, max(r, LOOP_SPACING_MIN * spacing_mm))
    count = int(np.ceil(length / step - 1e-9)) + 1
    tb = np.interp(np.linspace(0.0, length, count), cum, t)
    tb[0], tb[-1] = 0.0, 1.0
    return tb, float(r), float(drop)


def strand_at_rest(beads_mm: np.ndarray, up: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a looping move's strand, drawn along the tip's path (beads (q, 3), its two ends
    first and last), comes to rest (deposit.md, "Looping tips"): (the path's beads lowered,
    (q, 3); the straight line between the ends, beads at most ``spacing_mm`` apart (c, 3)).

    A thin strand drawn through the air does not stay up there: it is anchored where it sticks,
    at the move's two ends, and between them it is pulled taut along the straight line between
    them or sags under its own weight, below the place it was drawn. Either way it lies no higher
    along the machine's vertical ``up`` (3,) (a unit vector in the part frame, at the middle of
    the move) than the higher of its ends: the path's beads above that level are lowered to it."""
    beads = np.asarray(beads_mm, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    top = float(max(beads[0] @ u, beads[-1] @ u))
    lowered = beads - np.maximum(beads @ u - top, 0.0)[:, None] * u
    span = float(np.linalg.norm(beads[-1] - beads[0]))
    count = int(np.ceil(span / spacing_mm - 1e-9)) + 1 if span > 0 else 1
    s = np.linspace(0.0, 1.0, count)[:, None]
    return lowered, beads[0] + s * (beads[-1] - beads[0])


def held_radius(strand_mm: float, beads_mm: np.ndarray, radius_mm: float) -> float:
    """The radius a looping move's beads (q, 3) (a chain along its strand of radius
    ``strand_mm``) are held as: spheres that cover the strand between consecutive beads,
    sqrt(r² + (gap/2)²) with the widest gap between them, never above the stated ``radius_mm``."""
    gap = float(np.linalg.norm(np.diff(beads_mm, axis=0), axis=1).max()) if len(beads_mm) > 1 else 0.0
    return min(float(radius_mm), float(np.sqrt(strand_mm * strand_mm + 0.25 * gap * gap)))


class DepositRule(Enum):
    EXTRUSION = "extrusion words (E grows)"
    CODES = "deposit codes (between ON and OFF)"
    EVERY_FEED = "every feed move"
    OFF = "off (--bead-radius 0)"


def rule_text(rule: DepositRule, extrusion_letter: str = "E") -> str:
    """The rule as the report states it: the extrusion rule names the profile's extrusion word."""
    return f"extrusion words ({extrusion_letter} grows)" if rule is DepositRule.EXTRUSION else rule.value


def choose_rule(e_delta: np.ndarray, deposit_codes_given: bool, bead_radius_mm: float) -> DepositRule:
    """The rule for the whole program (docs/contract.md), from the first window's extrusion column:
    if any extrusion word appears in the first chunk the checker sees, the E rule holds for the
    whole program; a program whose first E word comes later is read with the other rules."""
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


# The bead field (see BeadField). The fine grid certifies distances up to FINE_REACH_MM (uint8,
# FINE_REACH_MM / 255 per step): enough for the head's smallest balls with a sweep margin of a
# couple of millimetres; beyond it the coarse grid (4 mm cells) and the beads' box take over.
FINE_REACH_MM = 3.0
FINE_LEVELS = 255
COARSE_CELLS = 8  # fine cells per coarse cell edge
COARSE_REACH_MM = 32.0  # the coarse grid certifies distances up to this (the head's large spheres)
# Bead chains are stamped as chords through several beads when every bead lies within this of the
# chord (the stamped distance is lowered by the deviation, so it stays a lower bound).
CHORD_TOL_MM = 0.01
CHORD_MAX_POINTS = 256
CHORD_MAX_MM = 12.0  # longer chords waste their bounding box on slanted paths
# A stamp is cut into slabs for the threads when it walks at least this many columns of cells
# (``stamp_slabs``). Measured on the stamps of model_1 and bathtub_273 (recorded, re-run alone on the
# 2-core machine): one thread stamps about 0.06 µs a column (15,000 columns: about 1 ms), and a
# split saves up to half of it with a core free, while it costs about 0.4 ms more than one thread
# when the machine is oversubscribed (the pool's thread waiting for a core and the GIL; 10 µs
# when a core is free). From here on a split saves with a core free at least what it loses on a
# busy machine; smaller stamps stay in the calling thread.
STAMP_SPLIT_COLUMNS = 15_000
# Slabs a thread: the calling thread and the pool's take them in turn (``split.map_parts``), so a
# thread that loses its core holds up a quarter of its share, not all of it. Cut where the chords
# lie, more slabs cost no more cells (measured: the slabs stamped one after the other take the
# time of the whole).
STAMP_SLABS_PER_THREAD = 4
# Subtracted from every stamped distance: covers float rounding of the distance arithmetic.
FIELD_SLACK_MM = 1e-5
GROW_MM = 24.0  # grids grow by at least this on a side, so a growing print reallocates rarely


class BeadStore:
    """Bead sphere centres laid so far (workpiece mm): exact centres and the rolling field.

    ``add`` appends centres (consecutive centres at most ``link`` apart form a chain, stamped into
    the field as a chain of segments, which holds every sphere on it). The exact centres are kept
    in levels (runs of consecutive beads, at most LEVEL_BEADS_MAX each, merged like a binary
    counter), each with a k-d tree built on the first query that needs it.

    Bounded memory: at most EXACT_BEADS_MAX exact centres are kept, the newest. Older ones are
    *retired* into ``old``, a BeadField of their own at twice the pitch (its memory is their box,
    like the main field's): an exact test that the old field cannot clear counts as a hit (``Checker``), so
    the answer errs only toward "collides", and only near material laid more than
    EXACT_BEADS_MAX beads (about 65 m of path at the 0.5 mm pitch) earlier.
    """

    def __init__(self, radius_mm: float, exact_max: int | None = None):
        self.radius_mm = float(radius_mm)
        self.exact_max = int(exact_max if exact_max is not None else EXACT_BEADS_MAX)
        self.level_max = max(1, self.exact_max // 4)
        # [points (m, 3) float64 in laying order, cKDTree or None, {cell mm: BeadCells},
        #  their radii (m,) or None (all ``radius_mm``)], oldest first
        self._levels: list[list] = []
        self._open: list[np.ndarray] = []  # beads not in a level yet (newest)
        self._open_r: list[np.ndarray | None] = []  # their radii (None: all ``radius_mm``)
        self._open_n = 0
        self.count = 0  # every bead ever added
        self.retired = 0  # the oldest ``retired`` beads live only in ``old``
        self.old: BeadField | None = None
        self._field: BeadField | None = None
        self._unstamped: list[np.ndarray] = []

    # -- building ----------------------------------------------------------------------------
    def add(self, points_mm: np.ndarray, radii_mm: np.ndarray | None = None) -> None:
        """Beads (m, 3), each held as a sphere of its radius (m,) for the exact test (None: all
        ``radius_mm``; no radius above it: the field and every bound hold ``radius_mm``)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return
        if self._field is not None:
            self._field.add(pts)
        else:
            self._unstamped.append(pts)
        self._add_exact(pts, radii_mm)

    def _add_exact(self, pts: np.ndarray, radii_mm: np.ndarray | None = None) -> None:
        """Only the exact centres (the caller stamped the field already)."""
        self._open.append(pts)
        self._open_r.append(None if radii_mm is None else np.minimum(
            np.asarray(radii_mm, dtype=np.float64).reshape(-1), self.radius_mm))
        self._open_n += len(pts)
        self.count += len(pts)
        if self._open_n >= self.level_max:
            self._close()
        if self.count - self.retired > self.exact_max + self.level_max and self._field is not None:
            self._retire()

    def field(self, pitch_mm: float) -> "BeadField":
        """The rolling distance field of every bead added so far, at ``pitch_mm`` (made on first use)."""
        if self._field is None or self._field.pitch_mm != float(pitch_mm):
            if self.retired:
                raise RuntimeError("the bead field's pitch cannot change once beads are retired")
            self._field = BeadField(self.radius_mm, pitch_mm)
            self._unstamped = [level[0] for level in self._levels] + list(self._open)
        for pts in self._unstamped:
            self._field.add(pts)
        self._unstamped = []
        if self.count - self.retired > self.exact_max + self.level_max:
            self._retire()
        return self._field

    def _close(self) -> None:
        """The open beads become a level; levels merge while the newest is no bigger (and small)."""
        if not self._open:
            return
        pts = np.concatenate(self._open)
        radii = self._radii(self._open, self._open_r)
        self._open, self._open_r, self._open_n = [], [], 0
        while self._levels and len(self._levels[-1][0]) <= len(pts) and \
                len(self._levels[-1][0]) + len(pts) <= self.level_max:
            level = self._levels.pop()
            radii = self._radii([level[0], pts], [level[3], radii])
            pts = np.concatenate([level[0], pts])
        self._levels.append([pts, None, {}, radii])

    def _radii(self, parts: list[np.ndarray], radii: list[np.ndarray | None]) -> np.ndarray | None:
        """The radii of the beads of ``parts`` joined (None when every one is ``radius_mm``)."""
        if all(r is None for r in radii):
            return None
        return np.concatenate([np.full(len(p), self.radius_mm) if r is None else r for p, r in zip(parts, radii)])

    def exact(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Every exact bead (m, 3), oldest first, and its radius (m,) (None: all ``radius_mm``)."""
        self._close()
        pts = [level[0] for level in self._levels]
        radii = self._radii(pts, [level[3] for level in self._levels])
        return (np.concatenate(pts) if pts else np.zeros((0, 3))), radii

    def _retire(self) -> None:
        """Move the oldest levels into the old field until at most ``exact_max`` beads stay exact,
        and crop the main field to the beads left exact (it bounds the old ones through ``below``):
        its memory follows the newest material, not the whole print."""
        self._close()
        retired = False
        while self._levels and self.count - self.retired > self.exact_max:
            pts = self._levels.pop(0)[0]
            if self.old is None:  # twice as coarse: 1/8 of the memory and of the stamping
                self.old = BeadField(self.radius_mm, OLD_FIELD_COARSENING * self._field.pitch_mm)
                self._field.below = self.old
            self.old.add(pts)
            self.retired += len(pts)
            retired = True
        kept = [level[0] for level in self._levels] + list(self._open)
        if retired and kept:
            lo = np.min([p.min(axis=0) for p in kept], axis=0)
            hi = np.max([p.max(axis=0) for p in kept], axis=0)
            self._field.crop(lo, hi)

    def trees(self) -> list[tuple[cKDTree, np.ndarray]]:
        """(k-d tree, centres) of the exact levels, oldest first (trees built here when missing)."""
        from scipy.spatial import cKDTree

        self._close()
        for level in self._levels:
            if level[1] is None:
                level[1] = cKDTree(level[0], leafsize=16, balanced_tree=False, compact_nodes=False)
        return [(level[1], level[0]) for level in self._levels]

    def near(self, centre_mm: np.ndarray, radius_mm: float) -> list[np.ndarray]:
        """Per exact level, oldest first: its centres within ``radius_mm`` of the point, in laying
        order. Joined, they are in laying order whatever the levels are: the levels depend on when
        the store was queried (``_close``), and a caller that keeps the first of each cell (the
        epa strategy's beads) must not (ball queries return a tree's own order). A ball that holds
        a level's whole box (with a margin for rounding) gets all its centres without a query."""
        centre = np.asarray(centre_mm, dtype=np.float64).reshape(3)
        self.trees()  # built where missing
        out = []
        for level in self._levels:
            pts, tree = level[0], level[1]
            corner = np.maximum(np.abs(tree.mins - centre), np.abs(tree.maxes - centre))
            if float(corner @ corner) < radius_mm * radius_mm * (1.0 - 1e-9):
                out.append(pts)
            else:
                found = np.sort(np.asarray(tree.query_ball_point(centre, radius_mm), dtype=np.int64))
                out.append(pts[found])
        return out

    def cells(self, cell_mm: float) -> list["BeadCells"]:
        """The exact levels' beads grouped in cubes of ``cell_mm`` (``BeadCells``), oldest first
        (built here when missing, kept with their level)."""
        self._close()
        out = []
        for level in self._levels:
            if cell_mm not in level[2]:
                level[2][cell_mm] = BeadCells(level[0], cell_mm, level[3])
            out.append(level[2][cell_mm])
        return out

    @property
    def nbytes(self) -> int:
        fields = sum(f.nbytes for f in (self._field, self.old) if f is not None)
        exact = sum(p.nbytes * (2 if tree is not None else 1) + sum(c.nbytes for c in cells.values())
                    + (radii.nbytes if radii is not None else 0)
                    for p, tree, cells, radii in self._levels) + self._open_n * 24
        return int(exact + fields)

    # -- queries -----------------------------------------------------------------------------
    def nearest(self, centers_mm: np.ndarray, upper_mm: float = np.inf) -> np.ndarray:
        """Distance (m,) from each point (m, 3) to the nearest exact bead centre (inf when beyond ``upper_mm``)."""
        centers = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(centers), np.inf)
        for tree, _ in self.trees():
            d, _ = tree.query(centers, k=1, distance_upper_bound=upper_mm)
            np.minimum(out, d, out=out)
        return out


class BeadCells:
    """Beads grouped in cubes of ``cell_mm``: each cell's beads (consecutive in ``beads``, in the
    order given: laying order), its centre (their mean) and radius (the farthest of them from it),
    and a k-d tree of the centres (built on the first ``near``). ``radii``: each bead's own radius
    (``BeadStore.add``), in ``bead_radii`` in the beads' order (None: none given)."""

    def __init__(self, points_mm: np.ndarray, cell_mm: float, radii_mm: np.ndarray | None = None):
        points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        _, order, self.counts = group_cells(np.floor(points / cell_mm).astype(np.int64))
        self.beads = points[order]
        self.bead_radii = None if radii_mm is None else np.asarray(radii_mm, dtype=np.float64)[order]
        self.starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(np.int64)
        if len(points):
            self.centre = np.add.reduceat(self.beads, self.starts, axis=0) / self.counts[:, None]
            off = np.linalg.norm(self.beads - np.repeat(self.centre, self.counts, axis=0), axis=1)
            self.radius = np.maximum.reduceat(off, self.starts)
            self._lo, self._hi = self.centre.min(axis=0), self.centre.max(axis=0)
        else:
            self.centre, self.radius = np.zeros((0, 3)), np.zeros(0)
            self._lo = self._hi = np.zeros(3)
        self.widest = float(self.radius.max()) if len(self.radius) else 0.0
        self._tree: cKDTree | None = None

    def near(self, centre_mm: np.ndarray, radius_mm: float) -> np.ndarray:
        """Indices (ascending) of the cells that may hold a bead within ``radius_mm`` of the point."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.centre)
        idx = np.sort(np.asarray(self._tree.query_ball_point(centre_mm, radius_mm + self.widest), dtype=np.int64))
        far = np.linalg.norm(self.centre[idx] - centre_mm, axis=1) - self.radius[idx]
        return idx[far <= radius_mm]

    def gather(self, centre_mm: np.ndarray, radius_mm: float, radii: bool = False) -> tuple:
        """``take(near(centre_mm, radius_mm), radii)``. A ball that holds every cell centre (the
        farthest corner of their box closer than the radius) gets every cell without a query: the
        same cells, in the same order, as ``near`` would give."""
        corner = np.maximum(np.abs(self._lo - centre_mm), np.abs(self._hi - centre_mm))
        if float(np.sqrt(corner @ corner)) < radius_mm:
            return self.take(None, radii)
        return self.take(self.near(centre_mm, radius_mm), radii)

    def take(self, cells: np.ndarray | None = None, radii: bool = False) -> tuple:
        """(beads of these cells (m, 3), cell by cell, each in the order given; beads per cell (k,);
        centres (k, 3); radii (k,)), with ``radii`` also the beads' own radii (m,) or None; every
        cell when None (the arrays kept here: not to be written)."""
        if cells is None:
            out = (self.beads, self.counts, self.centre, self.radius)
            return out + (self.bead_radii,) if radii else out
        counts = self.counts[cells]
        offs = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        pick = np.repeat(self.starts[cells], counts) + offs
        out = (self.beads[pick], counts, self.centre[cells], self.radius[cells])
        if radii:
            out += (None if self.bead_radii is None else self.bead_radii[pick],)
        return out

    @property
    def nbytes(self) -> int:
        return int(self.beads.nbytes + self.counts.nbytes + self.starts.nbytes + self.centre.nbytes
                   + self.radius.nbytes + (self.centre.nbytes if self._tree is not None else 0)
                   + (self.bead_radii.nbytes if self.bead_radii is not None else 0))


class BeadField:
    """A rolling lower bound on the distance from any point to the bead material (spheres).

    Two dense grids over the box of the beads, grown as beads come in (memory: the box, not the
    program's length), plus the beads' bounding box:

    - *fine* (uint8, one cell per pitch³, lattice centres at integer multiples of the pitch):
      ``v(c) = max(0, dist(c, chain) - r)`` floored to FINE_REACH_MM/255 steps and clamped at
      FINE_REACH_MM, where the chain is the polyline through consecutive beads (every bead lies on
      it, so its distance is no larger than the beads'). Each new chord min-updates the cells within
      its reach (the *stamp*), so every cell holds min(FINE_REACH_MM, its value): a lower bound at
      the centre, and ``v(c) - |x - c|`` is one at any x (1-Lipschitz), c the nearest centre.
    - *coarse* (float32, 4 mm cells): for each cell K, the smallest gap between K and a cell
      holding a bead centre, minus r, clamped at COARSE_REACH_MM: a lower bound for every point
      of K. Updated only when a cell gets its first bead (a kernel of precomputed gaps).
    - the box of all bead centres: ``dist(x, box) - r`` anywhere in space.

    ``lower_bound`` returns the largest of the three. Stamping is numba-compiled on the CPU; the
    grids are mirrored to the torch device (zero-copy on the CPU), so CPU and CUDA test the same
    numbers. ``overlay`` stamps beads for the time of a ``with`` block only.
    """

    def __init__(self, radius_mm: float, pitch_mm: float):
        self.radius_mm = float(radius_mm)
        self.pitch_mm = float(pitch_mm)
        self.step_mm = FINE_REACH_MM / FINE_LEVELS
        self.link_mm = 0.5 * self.pitch_mm * (1.0 + 1e-9)  # bead spacing (bead_samples)
        self.coarse_mm = COARSE_CELLS * self.pitch_mm
        self.fine = np.full((1, 1, 1), FINE_LEVELS, dtype=np.uint8)
        self.fine_lo = np.zeros(3, dtype=np.int64)
        self.coarse = np.full((1, 1, 1), COARSE_REACH_MM, dtype=np.float32)
        self.occupied = np.zeros((1, 1, 1), dtype=bool)
        self.coarse_lo = np.zeros(3, dtype=np.int64)
        self.box = np.array([[np.inf] * 3, [-np.inf] * 3])
        self.count = 0
        self._last: np.ndarray | None = None  # last bead of the previous add (chains go on)
        self._tensors: dict = {}
        self._dirty: list[tuple[str, tuple[slice, ...]]] = []
        self._kernel = _coarse_kernel(self.coarse_mm, self.radius_mm)
        # The last overlay's points and its grids before its last chord (``_Overlay``), or None
        # once the grids changed for good (``_changed``).
        self._overlaid: tuple | None = None
        # Material this field no longer holds (``crop``: the store's retired beads), bounded by a
        # field of its own: ``lower_bound`` is the smaller of the two.
        self.below: BeadField | None = None

    @property
    def fine_reach_mm(self) -> float:
        return self.step_mm * FINE_LEVELS

    @property
    def nbytes(self) -> int:
        return int(self.fine.nbytes + self.coarse.nbytes + self.occupied.nbytes)

    # -- stamping ----------------------------------------------------------------------------
    def add(self, points_mm: np.ndarray) -> None:
        """Stamp bead centres (m, 3) (consecutive ones within a bead spacing form a chain)."""
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return
        chain = pts
        if self._last is not None and np.linalg.norm(pts[0] - self._last) <= self.link_mm:
            chain = np.concatenate([self._last[None], pts])
        self._last = pts[-1].copy()
        self._grow(pts)
        self.box = np.array([np.minimum(self.box[0], pts.min(axis=0)), np.maximum(self.box[1], pts.max(axis=0))])
        self.count += len(pts)
        a, b, dev, _ = self._chords(chain)
        self._changed()
        kern = _stamp_kernels()
        kern.stamp_chords(self.fine, self.fine_lo, self.pitch_mm, a, b, dev, self.radius_mm, self.step_mm,
                          FINE_LEVELS, FIELD_SLACK_MM)
        cells = self._coarse_index(pts)  # repeats are skipped by the kernel (already occupied)
        kern.stamp_coarse(self.coarse, self.occupied, self.coarse_lo, cells, self._kernel[0], self._kernel[1])
        if self._tensors and any(k != "cpu" for k in self._tensors):
            self._mark_dirty(a, b, dev, cells)

    def _chords(self, chain: np.ndarray):
        """(a, b, deviation, start): the chords of the chain (``_chords_py``)."""
        link = np.linalg.norm(np.diff(chain, axis=0), axis=1) <= self.link_mm
        return _stamp_kernels().chords(chain, link, CHORD_TOL_MM, CHORD_MAX_POINTS, CHORD_MAX_MM)

    def _changed(self) -> None:
        """The grids' content or placement changed for good (``overlay``'s stamps no longer apply)."""
        self._overlaid = None

    def _fine_reach(self) -> float:
        return self.fine_reach_mm + self.radius_mm + CHORD_TOL_MM + self.pitch_mm

    def _coarse_index(self, pts: np.ndarray) -> np.ndarray:
        return np.floor((pts / self.pitch_mm + 0.5) / COARSE_CELLS).astype(np.int64)

    def _grow(self, pts: np.ndarray) -> None:
        """Reallocate the grids (content kept) when beads come outside the region they cover."""
        h = self.pitch_mm
        reach = self._fine_reach()
        need_lo = np.floor((pts.min(axis=0) - reach) / h).astype(np.int64) - 1
        need_hi = np.ceil((pts.max(axis=0) + reach) / h).astype(np.int64) + 2
        self.fine, self.fine_lo, grown_f = _regrid(self.fine, self.fine_lo, need_lo, need_hi,
                                                   int(np.ceil(GROW_MM / h)), FINE_LEVELS, h)
        pad = int(np.ceil(COARSE_REACH_MM / self.coarse_mm)) + 2
        k = self._coarse_index(np.array([pts.min(axis=0), pts.max(axis=0)]))
        grow_c = int(np.ceil(GROW_MM / self.coarse_mm))
        self.coarse, lo_c, grown_c = _regrid(self.coarse, self.coarse_lo, k[0] - pad, k[1] + pad + 1, grow_c,
                                             COARSE_REACH_MM)
        self.occupied, _, _ = _regrid(self.occupied, self.coarse_lo, k[0] - pad, k[1] + pad + 1, grow_c, False)
        self.coarse_lo = lo_c
        if grown_f or grown_c:
            self._tensors = {}
            self._dirty = []
            self._changed()

    def crop(self, lo_mm: np.ndarray, hi_mm: np.ndarray) -> None:
        """Keep the grids only where they can matter for beads inside the box [lo_mm, hi_mm] (the
        beads the field still has to bound; ``below`` bounds the rest): cells farther from the box
        than the reach of a stamp hold the far value anyway for those beads. Cells kept may still
        hold stamps of beads outside (lower values: still a lower bound); the box becomes the
        given one. Not inside an ``overlay``."""
        lo_mm, hi_mm = np.asarray(lo_mm, dtype=np.float64), np.asarray(hi_mm, dtype=np.float64)
        h = self.pitch_mm
        reach = self._fine_reach()
        need_lo = np.floor((lo_mm - reach) / h).astype(np.int64) - 1
        need_hi = np.ceil((hi_mm + reach) / h).astype(np.int64) + 2
        self.fine, self.fine_lo = _cropped(self.fine, self.fine_lo, need_lo, need_hi)
        pad = int(np.ceil(COARSE_REACH_MM / self.coarse_mm)) + 2
        k = self._coarse_index(np.array([lo_mm, hi_mm]))
        coarse_lo = self.coarse_lo
        self.coarse, self.coarse_lo = _cropped(self.coarse, coarse_lo, k[0] - pad, k[1] + pad + 1)
        self.occupied, _ = _cropped(self.occupied, coarse_lo, k[0] - pad, k[1] + pad + 1)
        self.box = np.array([np.maximum(self.box[0], lo_mm), np.minimum(self.box[1], hi_mm)])
        self._tensors = {}
        self._dirty = []
        self._changed()

    def _mark_dirty(self, a, b, dev, cells) -> None:
        h = self.pitch_mm
        reach = self._fine_reach()
        lo = np.maximum(np.floor((np.minimum(a, b).min(axis=0) - reach) / h).astype(np.int64) - self.fine_lo, 0)
        hi = np.minimum(np.ceil((np.maximum(a, b).max(axis=0) + reach) / h).astype(np.int64) - self.fine_lo + 1,
                        self.fine.shape)
        self._dirty.append(("fine", tuple(slice(int(x), int(y)) for x, y in zip(lo, hi))))
        pad = int(np.ceil(COARSE_REACH_MM / self.coarse_mm)) + 2
        lo = np.maximum(cells.min(axis=0) - pad - self.coarse_lo, 0)
        hi = np.minimum(cells.max(axis=0) + pad + 1 - self.coarse_lo, self.coarse.shape)
        self._dirty.append(("coarse", tuple(slice(int(x), int(y)) for x, y in zip(lo, hi))))

    class _Overlay:
        """Stamps points into the field for a ``with`` block, then puts the grids back.

        Overlays of a growing chain (the pending beads of the runs of one detection, each the
        beads of the one before and more) stamp only what is new: the grids as the last overlay
        left them before its last chord are kept, and an overlay whose points begin with the last
        one's, on grids that did not change since (``_changed``), starts from them and stamps the
        chords from that last chord's start on. The chords of a chain are found greedily from its
        start, so those before the last one are the same for any chain that begins with it, and
        a stamp is a least value per cell (the order of the chords does not matter): the grids
        come out as stamping every point would make them."""

        def __init__(self, field: "BeadField", points: np.ndarray):
            self.field, self.points = field, np.asarray(points, dtype=np.float64).reshape(-1, 3)

        def __enter__(self):
            f, pts = self.field, self.points
            self.saved = None
            if len(pts) == 0:
                return f
            f._grow(pts)
            cells = f._coarse_index(pts)
            h = f.pitch_mm
            reach = f._fine_reach()
            lo = np.maximum(np.floor((pts.min(axis=0) - reach) / h).astype(np.int64) - f.fine_lo, 0)
            hi = np.minimum(np.ceil((pts.max(axis=0) + reach) / h).astype(np.int64) - f.fine_lo + 1, f.fine.shape)
            fs = tuple(slice(int(x), int(y)) for x, y in zip(lo, hi))
            pad = int(np.ceil(COARSE_REACH_MM / f.coarse_mm)) + 2
            lo = np.maximum(cells.min(axis=0) - pad - f.coarse_lo, 0)
            hi = np.minimum(cells.max(axis=0) + pad + 1 - f.coarse_lo, f.coarse.shape)
            cs = tuple(slice(int(x), int(y)) for x, y in zip(lo, hi))
            self.saved = (fs, f.fine[fs].copy(), cs, f.coarse[cs].copy(), f.occupied[cs].copy(), f.box.copy(),
                          f.count, f._last)
            f.box = np.array([np.minimum(f.box[0], pts.min(axis=0)), np.maximum(f.box[1], pts.max(axis=0))])
            f.count += len(pts)
            start, new_cells = 0, cells
            last = f._overlaid
            if last is not None and len(last[0]) <= len(pts) and np.array_equal(last[0], pts[:len(last[0])]):
                before, start, last_fs, fine, last_cs, coarse, occupied = last
                f.fine[last_fs], f.coarse[last_cs], f.occupied[last_cs] = fine, coarse, occupied
                new_cells = cells[len(before):]
            a, b, dev, first = f._chords(pts[start:])
            kern = _stamp_kernels()
            kern.stamp_chords(f.fine, f.fine_lo, h, a[:-1], b[:-1], dev[:-1], f.radius_mm, f.step_mm, FINE_LEVELS,
                              FIELD_SLACK_MM)
            fine = f.fine[fs].copy()
            kern.stamp_chords(f.fine, f.fine_lo, h, a[-1:], b[-1:], dev[-1:], f.radius_mm, f.step_mm, FINE_LEVELS,
                              FIELD_SLACK_MM)
            kern.stamp_coarse(f.coarse, f.occupied, f.coarse_lo, new_cells, f._kernel[0], f._kernel[1])
            f._overlaid = (pts.copy(), start + int(first[-1]), fs, fine, cs, f.coarse[cs].copy(),
                           f.occupied[cs].copy())
            if f._tensors and any(k != "cpu" for k in f._tensors):
                f._dirty += [("fine", fs), ("coarse", cs)]
            return f

        def __exit__(self, *exc):
            if self.saved is None:
                return False
            f = self.field
            fs, fine, cs, coarse, occ, box, count, last = self.saved
            f.fine[fs], f.coarse[cs], f.occupied[cs] = fine, coarse, occ
            f.box, f.count, f._last = box, count, last
            if f._tensors and any(k != "cpu" for k in f._tensors):
                f._dirty += [("fine", fs), ("coarse", cs)]
            return False

    def overlay(self, points_mm: np.ndarray) -> "BeadField._Overlay":
        """``with field.overlay(points):`` the points are stamped inside the block, undone after it
        (chains only within ``points``; the coarse occupancy and the box come back too)."""
        return BeadField._Overlay(self, points_mm)

    # -- queries -----------------------------------------------------------------------------
    def tensors(self, device):
        """The grids on ``device`` (CPU: views of the numpy arrays; else copies kept in sync)."""
        import torch

        key = str(device)
        t = self._tensors.get(key)
        if t is None:
            if key == "cpu":
                fine, coarse = torch.from_numpy(self.fine), torch.from_numpy(self.coarse)
            else:
                fine, coarse = torch.as_tensor(self.fine, device=device), torch.as_tensor(self.coarse, device=device)
            t = self._tensors[key] = {"fine": fine, "coarse": coarse}
            for name, grid, lo in (("fine", self.fine, self.fine_lo), ("coarse", self.coarse, self.coarse_lo)):
                t[name + "_lo"] = torch.as_tensor(lo, dtype=torch.int64, device=device)
                t[name + "_hi"] = torch.as_tensor(lo + np.array(grid.shape) - 1, dtype=torch.int64, device=device)
        elif key != "cpu" and self._dirty:
            for name, sl in self._dirty:
                src = self.fine if name == "fine" else self.coarse
                t[name][sl] = torch.as_tensor(np.ascontiguousarray(src[sl]), device=device)
            self._dirty = []
        if t.get("box_of") is not self.box:  # the box changes with every add / overlay (a new array)
            t["box"] = torch.as_tensor(self.box, dtype=torch.float64, device=device)
            t["box_of"] = self.box
        return t

    def lower_bound(self, points):
        """Lower bound (mm) on the distance from points (m, 3) float64 tensor to the bead material -> (m,)."""
        import torch

        if self.count == 0:
            return torch.full((len(points),), float("inf"), dtype=torch.float64, device=points.device)
        t = self.tensors(points.device)
        h = self.pitch_mm
        idx = torch.round(points / h)
        diff = points - idx * h
        off = torch.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2])
        fine = _gather(t["fine"], t["fine_lo"], t["fine_hi"], idx.to(torch.int64), float(FINE_LEVELS))
        lb = fine * self.step_mm - off
        k = torch.floor((points / h + 0.5) / COARSE_CELLS).to(torch.int64)
        lb = torch.maximum(lb, _gather(t["coarse"], t["coarse_lo"], t["coarse_hi"], k, COARSE_REACH_MM))
        box = t["box"]
        gap = torch.clamp(torch.maximum(box[0] - points, points - box[1]), min=0.0)
        outside = torch.sqrt(gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] + gap[:, 2] * gap[:, 2]) - self.radius_mm
        lb = torch.maximum(lb, outside)
        if self.below is not None and self.below.count:
            lb = torch.minimum(lb, self.below.lower_bound(points))
        return lb

    def lower_bound_np(self, points: np.ndarray) -> np.ndarray:
        """The same bound for numpy points (m, 3) -> (m,) float64, in numpy: the same operations
        in the same order as ``lower_bound`` (tests, small queries; no torch)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.count == 0:
            return np.full(len(points), np.inf)
        h = self.pitch_mm
        idx = np.round(points / h)
        diff = points - idx * h
        off = np.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2])
        fine = _gather_np(self.fine, self.fine_lo, idx.astype(np.int64), float(FINE_LEVELS))
        lb = fine * self.step_mm - off
        k = np.floor((points / h + 0.5) / COARSE_CELLS).astype(np.int64)
        lb = np.maximum(lb, _gather_np(self.coarse, self.coarse_lo, k, COARSE_REACH_MM))
        box = self.box
        gap = np.maximum(np.maximum(box[0] - points, points - box[1]), 0.0)
        outside = np.sqrt(gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] + gap[:, 2] * gap[:, 2]) - self.radius_mm
        lb = np.maximum(lb, outside)
        if self.below is not None and self.below.count:
            lb = np.minimum(lb, self.below.lower_bound_np(points))
        return lb


def _gather(grid, lo, hi, idx, default: float):
    """grid[idx - lo] as float64, ``default`` where idx (m, 3) int64 (global) is outside [lo, hi]."""
    import torch

    rel = idx - lo
    clamped = torch.clamp(rel, min=torch.zeros_like(lo), max=hi - lo)
    inside = (clamped == rel).all(dim=1)
    shape = grid.shape
    flat = (clamped[:, 0] * shape[1] + clamped[:, 1]) * shape[2] + clamped[:, 2]
    values = grid.reshape(-1)[flat].to(torch.float64)
    return torch.where(inside, values, default)


def _gather_np(grid: np.ndarray, lo: np.ndarray, idx: np.ndarray, default: float) -> np.ndarray:
    """``_gather`` in numpy: grid[idx - lo] as float64, ``default`` where idx (m, 3) int64 is outside."""
    rel = idx - lo
    inside = ((rel >= 0) & (rel < np.array(grid.shape))).all(axis=1)
    out = np.full(len(idx), float(default))
    r = rel[inside]
    out[inside] = grid[r[:, 0], r[:, 1], r[:, 2]].astype(np.float64)
    return out


def _regrid(grid: np.ndarray, lo: np.ndarray, need_lo: np.ndarray, need_hi: np.ndarray, grow: int, fill,
            pitch_mm: float | None = None):
    """A grid covering global indices [need_lo, need_hi) and the old one; content kept.
    returns (grid, lo, grown). Refused (``ensure_fits``) when the new grid cannot fit in memory
    (``pitch_mm``: the --pitch the grid follows, for the message)."""
    hi = lo + np.array(grid.shape)
    empty = grid.size <= 1 and not np.any(grid != fill)
    if not empty and (need_lo >= lo).all() and (need_hi <= hi).all():
        return grid, lo, False
    if empty:
        new_lo, new_hi = need_lo - grow, need_hi + grow
    else:
        new_lo = np.where(need_lo < lo, np.minimum(need_lo, lo) - grow, lo)
        new_hi = np.where(need_hi > hi, np.maximum(need_hi, hi) + grow, hi)
    cells = float(np.prod((new_hi - new_lo).astype(np.float64)))
    ensure_fits("the deposit model's grid", cells, 2 * grid.itemsize, pitch_mm=pitch_mm)  # the old and the new
    out = np.full(tuple(int(x) for x in new_hi - new_lo), fill, dtype=grid.dtype)
    if not empty:
        o = lo - new_lo
        out[o[0]:o[0] + grid.shape[0], o[1]:o[1] + grid.shape[1], o[2]:o[2] + grid.shape[2]] = grid
    return out, new_lo, True


def _cropped(grid: np.ndarray, lo: np.ndarray, need_lo: np.ndarray, need_hi: np.ndarray):
    """The part of ``grid`` (global indices from ``lo``) within [need_lo, need_hi), as a copy
    (the rest is freed) -> (grid, lo); the grid as it is when it lies inside already. The region
    must overlap the grid (it holds the beads it is cropped to)."""
    a = np.clip(need_lo - lo, 0, grid.shape)
    b = np.clip(need_hi - lo, a, grid.shape)
    if (a == 0).all() and (b == np.array(grid.shape)).all():
        return grid, lo
    return grid[a[0]:b[0], a[1]:b[1], a[2]:b[2]].copy(), lo + a


def _coarse_kernel(cell_mm: float, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (p, 3) int64 and values (p,) float32: the gap between two coarse cells that far
    apart, minus the bead radius (floored at 0, lowered by the slack), where below the reach."""
    n = int(np.ceil((COARSE_REACH_MM + radius_mm) / cell_mm)) + 1
    r = np.arange(-n, n + 1)
    off = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    gap = np.maximum(np.abs(off) - 1, 0) * cell_mm
    val = np.sqrt((gap * gap).sum(axis=1)) - radius_mm - FIELD_SLACK_MM
    keep = val < COARSE_REACH_MM
    return off[keep].astype(np.int64), np.maximum(val[keep], 0.0).astype(np.float32)


def _chords_py(pts, link, tol, max_points, max_len):  # pragma: no cover - compiled
    """Chords through runs of linked points: (a (k, 3), b (k, 3), deviation (k,), index of each
    chord's first point (k,)). Every point and every segment between linked points lies within
    the deviation of its chord; an unlinked point is a chord of length 0."""
    n = pts.shape[0]
    a = np.empty((n, 3))
    b = np.empty((n, 3))
    dev = np.zeros(n)
    first = np.zeros(n, dtype=np.int64)
    c = 0
    s = 0
    while s < n:
        e = s
        best = 0.0
        while e + 1 < n and link[e] and e + 1 - s <= max_points:
            q = e + 1
            d0 = pts[q, 0] - pts[s, 0]
            d1 = pts[q, 1] - pts[s, 1]
            d2 = pts[q, 2] - pts[s, 2]
            length2 = d0 * d0 + d1 * d1 + d2 * d2
            if length2 > max_len * max_len:
                break
            worst = 0.0
            for m in range(s + 1, q):
                p0 = pts[m, 0] - pts[s, 0]
                p1 = pts[m, 1] - pts[s, 1]
                p2 = pts[m, 2] - pts[s, 2]
                t = 0.0
                if length2 > 0.0:
                    t = (p0 * d0 + p1 * d1 + p2 * d2) / length2
                    t = min(max(t, 0.0), 1.0)
                e0 = p0 - t * d0
                e1 = p1 - t * d1
                e2 = p2 - t * d2
                worst = max(worst, np.sqrt(e0 * e0 + e1 * e1 + e2 * e2))
                if worst > tol:
                    break
            if worst > tol:
                break
            e = q
            best = worst
        a[c] = pts[s]
        b[c] = pts[e]
        dev[c] = best
        first[c] = s
        c += 1
        if e == s or not link[e - 1] or e + 1 >= n or not link[e]:
            s = e + 1
        else:
            s = e
    return a[:c], b[:c], dev[:c], first[:c]


def _stamp_chords_py(grid, lo, h, a, b, dev, radius, step, levels, slack, x0, x1):  # pragma: no cover - compiled
    """Min-update the fine grid with each chord's distance (see BeadField), in the slab of cells
    x0 <= i < x1 (grid indices along x) only: stamps of disjoint slabs write disjoint cells."""
    nx, ny, nz = grid.shape
    full = step * levels
    inv_step = 1.0 / step  # u may come out one step high at an exact multiple: covered by the slack
    for s in range(a.shape[0]):
        cut = radius + dev[s] + slack
        reach = full + cut
        reach2 = reach * reach
        a0, a1, a2 = a[s, 0], a[s, 1], a[s, 2]
        d0 = b[s, 0] - a0
        d1 = b[s, 1] - a1
        d2 = b[s, 2] - a2
        length2 = d0 * d0 + d1 * d1 + d2 * d2
        inv = 1.0 / length2 if length2 > 0.0 else 0.0
        i0 = max(int(np.floor((min(a0, b[s, 0]) - reach) / h)) - lo[0], 0, x0)
        i1 = min(int(np.ceil((max(a0, b[s, 0]) + reach) / h)) - lo[0], nx - 1, x1 - 1)
        if i0 > i1:
            continue
        j0 = max(int(np.floor((min(a1, b[s, 1]) - reach) / h)) - lo[1], 0)
        j1 = min(int(np.ceil((max(a1, b[s, 1]) + reach) / h)) - lo[1], ny - 1)
        k0 = max(int(np.floor((min(a2, b[s, 2]) - reach) / h)) - lo[2], 0)
        k1 = min(int(np.ceil((max(a2, b[s, 2]) + reach) / h)) - lo[2], nz - 1)
        flat2 = d0 * d0 + d1 * d1
        inv_flat = 1.0 / flat2 if flat2 > 0.0 else 0.0
        for i in range(i0, i1 + 1):
            p0 = (i + lo[0]) * h - a0
            for j in range(j0, j1 + 1):
                p1 = (j + lo[1]) * h - a1
                base = p0 * d0 + p1 * d1
                # Along this column of cells the squared distance to the chord is convex in z, least
                # at the height of the chord's point nearest the column (in plan): the cells within
                # reach are one run about it. They are found from there up and down, each side
                # stopping at its first cell out of reach (the cells tested are those of the box).
                tc = min(max(base * inv_flat, 0.0), 1.0)
                kc = min(max(int(np.floor((a2 + tc * d2) / h)) - lo[2], k0), k1)
                k, dk = kc, 1
                while True:
                    if k > k1 or k < k0:  # this side's end of the box
                        if dk < 0:
                            break
                        k, dk = kc - 1, -1
                        continue
                    p2 = (k + lo[2]) * h - a2
                    t = (base + p2 * d2) * inv
                    t = min(max(t, 0.0), 1.0)
                    e0 = p0 - t * d0
                    e1 = p1 - t * d1
                    e2 = p2 - t * d2
                    dd = e0 * e0 + e1 * e1 + e2 * e2
                    if dd < reach2:
                        d = np.sqrt(dd) - cut
                        u = 0
                        if d > 0.0:
                            u = int(d * inv_step)
                        if u < grid[i, j, k]:
                            grid[i, j, k] = u
                    elif dk < 0:
                        break
                    elif k > kc:  # the upper side is done: the lower one from kc - 1
                        k, dk = kc - 1, -1
                        continue
                    k += dk


def _stamp_coarse_py(grid, occupied, lo, cells, offsets, values):  # pragma: no cover - compiled
    """Mark cells (m, 3) (global indices) occupied; min-update the kernel around each new one."""
    nx, ny, nz = grid.shape
    for c in range(cells.shape[0]):
        i = cells[c, 0] - lo[0]
        j = cells[c, 1] - lo[1]
        k = cells[c, 2] - lo[2]
        if occupied[i, j, k]:
            continue
        occupied[i, j, k] = True
        for p in range(offsets.shape[0]):
            x = i + offsets[p, 0]
            y = j + offsets[p, 1]
            z = k + offsets[p, 2]
            if 0 <= x < nx and 0 <= y < ny and 0 <= z < nz and values[p] < grid[x, y, z]:
                grid[x, y, z] = values[p]


def stamp_slabs(shape: tuple, lo: np.ndarray, h: float, a: np.ndarray, b: np.ndarray, dev: np.ndarray,
                reach_mm: float, count: int, least: float | None = None) -> list[tuple[int, int]]:
    """[x0, x1) slabs of the rows of a fine grid (``shape``, global index ``lo`` of its first cell,
    pitch ``h``) to stamp the chords a, b (k, 3) (deviations dev (k,)) in, at most ``count``: in
    order, covering range(shape[0]) without overlap, each with about the same share of the work.
    One slab when the work is below ``least`` (default STAMP_SPLIT_COLUMNS).

    The work is counted in columns of cells (one x, one y) a chord's stamp walks: its box's rows
    times its columns per row, each column a run of about the same number of cells (the reach's
    diameter), so the slabs are cut where the chords lie, not evenly."""
    nx = int(shape[0])
    if count <= 1 or len(a) == 0 or nx < 2:
        return [(0, nx)]
    reach = reach_mm + dev
    i0 = np.clip(np.floor((np.minimum(a[:, 0], b[:, 0]) - reach) / h).astype(np.int64) - lo[0], 0, nx)
    i1 = np.clip(np.ceil((np.maximum(a[:, 0], b[:, 0]) + reach) / h).astype(np.int64) - lo[0], -1, nx - 1)
    j0 = np.clip(np.floor((np.minimum(a[:, 1], b[:, 1]) - reach) / h).astype(np.int64) - lo[1], 0, shape[1])
    j1 = np.clip(np.ceil((np.maximum(a[:, 1], b[:, 1]) + reach) / h).astype(np.int64) - lo[1], -1, shape[1] - 1)
    cols = np.maximum(j1 - j0 + 1, 0) * (i1 >= i0)
    if float(cols @ np.maximum(i1 - i0 + 1, 0)) < (STAMP_SPLIT_COLUMNS if least is None else least):
        return [(0, nx)]
    # Columns per row: each chord adds its columns to the rows i0 .. i1 (a difference array).
    per_row = np.cumsum(np.bincount(i0, cols, minlength=nx + 1) - np.bincount(i1 + 1, cols, minlength=nx + 1))[:nx]
    cum = np.cumsum(per_row)
    share = cum[-1] * np.arange(1, count) / count
    row = np.minimum(np.searchsorted(cum, share), nx - 1)  # the row where each share is reached
    before = np.where(row > 0, cum[row - 1], 0.0)
    cuts = np.where(share - before <= cum[row] - share, row, row + 1)  # that row's nearer edge
    edges = np.unique(np.concatenate([[0], np.clip(cuts, 1, nx - 1), [nx]]))
    return [(int(x0), int(x1)) for x0, x1 in zip(edges[:-1], edges[1:])]


class _Kernels:
    def __init__(self):
        self.chords = njit(cache=True)(_chords_py)
        self.stamp_slab = njit(cache=True, nogil=True)(_stamp_chords_py)
        self.stamp_coarse = njit(cache=True)(_stamp_coarse_py)

    def stamp_chords(self, grid, lo, h, a, b, dev, radius, step, levels, slack, threads: int | None = None):
        """Min-update the fine grid with each chord's distance (``_stamp_chords_py``): when the
        stamp is large, in slabs of the grid's rows cut where the chords lie (``stamp_slabs``),
        which the process's threads take in turn (``split.map_parts``). A cell keeps the least value any chord gives it, whatever the order, and
        the slabs share no cell: the grid comes out the same for any cut and any number of threads
        (``tests/test_deposit_stamp.py``). ``threads``: default ``$NCFIX_THREADS`` or the cores."""
        threads = thread_count() if threads is None else int(threads)
        slabs = stamp_slabs(grid.shape, lo, h, a, b, dev, step * levels + radius + slack,
                            STAMP_SLABS_PER_THREAD * threads)
        map_parts(lambda x0, x1: self.stamp_slab(grid, lo, h, a, b, dev, radius, step, levels, slack, x0, x1),
                  slabs, threads)


_KERNELS: list = []


def _stamp_kernels() -> _Kernels:
    """The stamping loops, numba-compiled on first use (cached on disk)."""
    if not _KERNELS:
        _KERNELS.append(_Kernels())
    return _KERNELS[0]


def bead_samples(start_mm: np.ndarray, end_mm: np.ndarray, spacing_mm: float,
                 length_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Counts per move (n,) and the move parameters t in [0, 1] of bead centres.

    start_mm, end_mm : (n, 3) float64; length_mm : (n,) path length (default: the straight
    distance; an arc's is longer). Each move gets ceil(length / spacing) + 1 centres,
    t = 0 .. 1 inclusive. returns (counts (n,) int64, t (sum counts,) float64).
    """
    length = np.linalg.norm(np.asarray(end_mm) - np.asarray(start_mm), axis=1) if length_mm is None else length_mm
    m = np.maximum(np.ceil(length / spacing_mm - 1e-9).astype(np.int64), 1)
    counts = m + 1
    offsets = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(int(counts.sum())) - offsets
    return counts, k / np.repeat(m, counts)
