"""How deep the head goes into a part along a move: the report's penetration estimate.

How far a pose collides is not well defined for bodies that are not convex, so ncfix reports the
largest distance from a point of the head's surface inside the part to the part's surface, over the
poses of the move: a head through a 10 mm wall reports about 5 mm wherever its ends are, not the
clearance of one pose near the exit. An estimate to within a few millimetres, for the report only:
no decision depends on it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from ncfix import cache
from ncfix.collision.grid import DistanceGrid
from ncfix.collision.voxelize import distance_transform

if TYPE_CHECKING:
    import trimesh

# Poses of a move whose depth is measured: this many, evenly spread, and its last. Depth changes no
# faster than the head moves, so a pass is measured to within half the head's travel between them.
MOVE_POSES = 8
# The code the cached depth field comes from (with the grid's key, which covers the grid's code).
DEPTH_SOURCES = ("ncfix.collision.depth", "ncfix.collision.voxelize")


class DepthProbe:
    """Penetration depth estimates of head poses into parts.

    Each part's distance grid marks the cells that may hold part material; the distance transform
    of those cells to the nearest unmarked one (an unmarked cell centre lies outside the part)
    gives, at a point's nearest cell centre, its depth to within about a cell diagonal. The field
    is made the first time a part collision is reported (one EDT of the grid, ``inside_mm``), and
    kept in the on-disk cache beside a cached grid (it comes from the grid alone). The
    head is sampled at about one point per spacing² of its surface, a move at ``MOVE_POSES`` poses.

    head : trimesh in the head frame; grids : one DistanceGrid per part (the checker's)
    spacing_mm : how far apart the head's surface points are at most (``surface_points``)
    """

    def __init__(self, head: trimesh.Trimesh, grids: list[DistanceGrid], spacing_mm: float):
        self.points = surface_points(np.asarray(head.triangles, dtype=np.float64), float(spacing_mm))
        self.grids = grids
        self._inside: list[np.ndarray | None] = [None] * len(grids)

    def inside_mm(self, k: int) -> np.ndarray:
        """(nx, ny, nz) float32: at each marked cell of part k's grid, the distance to the nearest
        unmarked cell centre (0 on unmarked cells)."""
        if self._inside[k] is None:
            self._inside[k] = inside_field(self.grids[k])
        return self._inside[k]

    def depth_mm(self, k: int, C: np.ndarray, R: np.ndarray) -> float:
        """The deepest head point inside part k over poses (tips C (m, 3), rotations R (m, 3, 3)):
        the field at its nearest cell less half a cell diagonal, 0 when no point is inside."""
        grid = self.grids[k]
        field = self.inside_mm(k)
        C = np.ascontiguousarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.ascontiguousarray(R, dtype=np.float64).reshape(-1, 3, 3)
        best = _deepest(self.points, C, R, field, np.asarray(grid.origin_mm, dtype=np.float64), float(grid.pitch_mm))
        return max(0.0, best - 0.5 * np.sqrt(3.0) * grid.pitch_mm) if best > 0 else 0.0


def inside_field(grid: DistanceGrid) -> np.ndarray:
    """``DepthProbe.inside_mm`` of one grid: read from the on-disk cache when the grid came from
    it (keyed by the grid's own key, this code and the EDT's version), else computed."""

    def build() -> np.ndarray:
        return distance_transform(grid.dist_mm == 0, grid.pitch_mm)

    if not grid.cache_key:
        return build()
    key = cache.make_key("depth", grid.cache_key, cache.fingerprint(*DEPTH_SOURCES),
                         {package: cache.version(package) for package in ("numpy", "edt")})

    def from_arrays(a: dict[str, np.ndarray]) -> np.ndarray | None:
        field = a["inside_mm"]
        return field if field.dtype == np.float32 and field.shape == grid.dist_mm.shape else None

    field, _ = cache.cached("depth", key, ("inside_mm",), build, lambda f: {"inside_mm": f}, from_arrays,
                            grid.cache_dir)
    return field


def _deepest(points, C, R, field, origin, pitch):  # pragma: no cover - compiled
    """The largest ``field`` value at the nearest cell of the points (p, 3) placed at each pose
    (C (n, 3), R (n, 3, 3): world = C + R @ p); points outside the grid count 0."""
    nx, ny, nz = field.shape
    best = 0.0
    for i in range(C.shape[0]):
        for j in range(points.shape[0]):
            px, py, pz = points[j, 0], points[j, 1], points[j, 2]
            a = int(np.floor((C[i, 0] + R[i, 0, 0] * px + R[i, 0, 1] * py + R[i, 0, 2] * pz - origin[0]) / pitch + 0.5))
            b = int(np.floor((C[i, 1] + R[i, 1, 0] * px + R[i, 1, 1] * py + R[i, 1, 2] * pz - origin[1]) / pitch + 0.5))
            c = int(np.floor((C[i, 2] + R[i, 2, 0] * px + R[i, 2, 1] * py + R[i, 2, 2] * pz - origin[2]) / pitch + 0.5))
            if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz:
                value = field[a, b, c]
                if value > best:
                    best = value
    return best


_deepest = njit(cache=True, nogil=True)(_deepest)


def move_poses(C: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``MOVE_POSES`` of a move's sample poses (C (m, 3), R (m, 3, 3)), evenly spread, and its last."""
    keep = np.unique(np.append(np.linspace(0, len(C) - 1, MOVE_POSES).round().astype(np.int64), len(C) - 1))
    return C[keep], R[keep]


def surface_points(triangles: np.ndarray, spacing_mm: float) -> np.ndarray:
    """(p, 3) points on triangles (t, 3, 3), about one per spacing² of area: each triangle's
    vertices and its area / spacing² points of the R2 low-discrepancy sequence folded into it
    (deterministic)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    count = np.ceil(area / spacing_mm ** 2).astype(np.int64)
    tri = np.repeat(np.arange(len(triangles)), count)
    k = np.arange(len(tri)) - np.repeat(np.cumsum(count) - count, count) + 1
    g = 1.32471795724474602596  # the plastic number: R2's generator
    u, v = np.modf(k / g)[0], np.modf(k / g ** 2)[0]
    fold = u + v > 1.0
    u[fold], v[fold] = 1.0 - u[fold], 1.0 - v[fold]
    inner = a[tri] + u[:, None] * (b - a)[tri] + v[:, None] * (c - a)[tri]
    return np.ascontiguousarray(np.unique(np.concatenate([triangles.reshape(-1, 3), inner]), axis=0))
