"""The set S of candidate orientations: one fixed grid of directions on the sphere, cut per block.

Every block takes the grid's directions within Θ (--max-tilt) of its programmed vector, plus the
programmed vector itself (candidate 0). Because the grid is shared, consecutive blocks share their
candidates: a path can hold an orientation exactly (step 0) or move to a neighbour (a step of about
the resolution), which a pattern turned onto each block's own vector would not allow.
The grid is a Fibonacci lattice: near-uniform, deterministic, any size.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

# Two dot products of unit vectors closer than this may order differently in another float
# evaluation (each carries at most a few units in the last place, about 1e-15): ``nearest``
# leaves such a choice to the dense product. Neighbours on the grid differ by about 1e-4.
NEAREST_MARGIN = 1e-12


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` near-uniform unit vectors (count, 3) on the sphere (golden-angle spiral)."""
    i = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def chord(angle_deg: float | np.ndarray) -> float | np.ndarray:
    """Straight-line distance between unit vectors ``angle_deg`` apart."""
    return 2.0 * np.sin(np.radians(angle_deg) / 2.0)


class SphereGrid:
    """Directions about ``resolution_deg`` apart (the mean spacing of the lattice)."""

    def __init__(self, resolution_deg: float):
        self.resolution_deg = float(resolution_deg)
        count = int(math.ceil(4.0 * math.pi / math.radians(resolution_deg) ** 2))
        self.points = fibonacci_sphere(count)

    @functools.cached_property
    def tree(self):
        """A k-d tree of the points, built on first use (the EPA strategy holds a graph fallback that
        may never search; importing scipy.spatial takes 0.1 s)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.points)

    def cap(self, centre: np.ndarray, radius_deg: float) -> np.ndarray:
        """Grid indices (sorted) within ``radius_deg`` of the unit vector ``centre``."""
        idx = self.tree.query_ball_point(np.asarray(centre, dtype=np.float64), float(chord(radius_deg)) + 1e-12)
        return np.sort(np.asarray(idx, dtype=np.int64))


def level_candidates(grid: SphereGrid, programmed: np.ndarray, max_tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Per level, the programmed vector (candidate 0) and the grid's directions within Θ of it.

    programmed : (L, 3) unit vectors. Returns candidates (L, K, 3) and valid (L, K) bool; rows
    are padded with the programmed vector (not valid) up to the largest K.
    """
    caps = [grid.cap(p, max_tilt_deg) for p in programmed]
    k = 1 + max((len(c) for c in caps), default=0)
    cands = np.repeat(programmed[:, None, :], k, axis=1).copy()
    valid = np.zeros((len(programmed), k), dtype=bool)
    valid[:, 0] = True
    for level, cap in enumerate(caps):
        cands[level, 1:1 + len(cap)] = grid.points[cap]
        valid[level, 1:1 + len(cap)] = True
    return cands, valid


def nearest(points: np.ndarray, among: np.ndarray) -> np.ndarray:
    """For each of ``points`` (n, 3), the index of the vector of ``among`` (m, 3), m ≥ 1, with the
    largest dot product: ``np.argmax(points @ among.T, axis=1)`` exactly (ties to the lowest
    index). A compiled loop finds it without the (n, m) product; only where a runner-up comes
    within NEAREST_MARGIN of the best (where another evaluation of the products could order
    them otherwise) is the dense product itself taken."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    among = np.ascontiguousarray(among, dtype=np.float64)
    best, clear = _nearest(points, among, NEAREST_MARGIN)
    if clear:
        return best
    return np.argmax(points @ among.T, axis=1)


@njit(cache=True, nogil=True)
def _nearest(points, among, margin):  # pragma: no cover - compiled
    """(index of the largest dot product per point, whether every best leads its runner-up by
    more than ``margin``)."""
    n, m = points.shape[0], among.shape[0]
    out = np.zeros(n, dtype=np.int64)
    clear = True
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        best, second, arg = -np.inf, -np.inf, 0
        for j in range(m):
            d = x * among[j, 0] + y * among[j, 1] + z * among[j, 2]
            if d > best:
                best, second, arg = d, best, j
            elif d > second:
                second = d
        out[i] = arg
        if not best - second > margin:
            clear = False
    return out, clear
