"""Moves whose nozzle ploughs through its own extrudate: their material ends at their lower end.

When the tip's earlier positions along a move lie inside the head (a plunge along the nozzle's
axis, or a few degrees off it under a wide cone), nothing extruded can stay where it left the tip:
it is pushed ahead and ends under the nozzle. That is a property of the head's shape, decided
exactly and erring toward "not inside" (the material is then laid along the move, the conservative
reading). See docs/deposit.md#which-moves-deposit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ncfix.collision.near import _winding

# Crossings closer to the tip than this (mm) are the tip's own surface (it sits on the head mesh).
TIP_EPS_MM = 1e-6
# Barycentric slack: a crossing this close to a triangle's edge is "unsure" (not inside).
EDGE_EPS = 1e-9


@njit(cache=True, nogil=True)
def _segments_inside(tris, u, length, out):  # pragma: no cover - compiled
    """out[i]: the segment s·u[i], s in (TIP_EPS_MM, length[i]], lies inside the solid of tris."""
    for i in range(u.shape[0]):
        ux, uy, uz = u[i, 0], u[i, 1], u[i, 2]
        inside = True
        for k in range(tris.shape[0]):
            v0x, v0y, v0z = tris[k, 0, 0], tris[k, 0, 1], tris[k, 0, 2]
            e1x, e1y, e1z = tris[k, 1, 0] - v0x, tris[k, 1, 1] - v0y, tris[k, 1, 2] - v0z
            e2x, e2y, e2z = tris[k, 2, 0] - v0x, tris[k, 2, 1] - v0y, tris[k, 2, 2] - v0z
            px, py, pz = uy * e2z - uz * e2y, uz * e2x - ux * e2z, ux * e2y - uy * e2x
            det = e1x * px + e1y * py + e1z * pz
            if det == 0.0:
                continue  # the segment runs parallel to the triangle's plane: no crossing
            inv = 1.0 / det
            sx, sy, sz = -v0x, -v0y, -v0z
            a = (sx * px + sy * py + sz * pz) * inv
            if a < -EDGE_EPS or a > 1.0 + EDGE_EPS:
                continue
            qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
            b = (ux * qx + uy * qy + uz * qz) * inv
            if b < -EDGE_EPS or a + b > 1.0 + EDGE_EPS:
                continue
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
            if t <= TIP_EPS_MM or t > length[i] + TIP_EPS_MM:
                continue
            inside = False  # the segment meets the surface (or passes within rounding of an edge)
            break
        if inside:
            end = length[i]
            inside = _winding(end * ux, end * uy, end * uz, tris) > 0.5
        out[i] = inside


def ploughing_moves(triangles: np.ndarray, start_mm: np.ndarray, end_mm: np.ndarray,
                    r_start: np.ndarray, r_end: np.ndarray) -> np.ndarray:
    """(n,) bool: moves (start, end (n, 3) tip positions, workpiece mm; head rotations r_start,
    r_end (n, 3, 3)) that plough through their own extrudate.

    In the head frame (tip at the origin) a move of displacement d leaves its material at the
    points -s·d, s in (0, 1], relative to the tip at the move's end; the move ploughs when that
    whole segment lies inside the head mesh, at the head's orientations at both ends of the move.
    Exact, erring toward "not inside": no head triangle may cross the segment beyond the tip itself
    (``TIP_EPS_MM``), its far end must have winding number about 1, and a crossing that passes
    within rounding of a triangle's edge (``EDGE_EPS``) makes the answer "not inside".

    triangles : (m, 3, 3) float64, the head mesh in its frame (tip at the origin, axis +Z).
    Only moves that run into the head (toward the tip's side, ``d · N < 0`` at both ends) are
    tested; the others are False.
    """
    d = np.asarray(end_mm, dtype=np.float64) - np.asarray(start_mm, dtype=np.float64)
    length = np.linalg.norm(d, axis=1)
    out = np.zeros(len(d), dtype=bool)
    n0, n1 = r_start[:, :, 2], r_end[:, :, 2]
    with np.errstate(invalid="ignore"):
        into = (length > 0) & (np.einsum("ij,ij->i", d, n0) < 0) & (np.einsum("ij,ij->i", d, n1) < 0)
    rows = np.flatnonzero(into)
    if len(rows) == 0:
        return out
    tris = np.ascontiguousarray(triangles, dtype=np.float64)
    back = -d[rows] / length[rows, None]  # from the tip at the end back to where the move began
    ok = np.ones(len(rows), dtype=bool)
    for r in (r_start, r_end):
        u = np.einsum("nji,nj->ni", r[rows], back)  # into the head frame: Rᵀ·u
        # Only the segments still inside at the other orientation are tested (most are not: the
        # test runs over every triangle for them, twice).
        live = np.flatnonzero(ok)
        if len(live) == 0:
            break
        inside = np.empty(len(live), dtype=bool)
        _segments_inside(tris, np.ascontiguousarray(u[live]), np.ascontiguousarray(length[rows][live]), inside)
        ok[live] = inside
    out[rows] = ok
    return out
