"""Exact "is this ball touching that solid" tests for many small balls against one closed mesh.

The deposit check asks, for thousands of (pose, bead) pairs, whether a bead sphere meets the
clipped head: within its radius of the head's surface, or inside the head. One coal call per pair
costs ~10 µs of Python; here the pairs go through one compiled loop, with exact point-to-triangle
distances (Ericson, Real-Time Collision Detection 5.1.5) and the generalised winding number (van
Oosterom and Strackee): the answers of coal's sphere-mesh test plus a containment test.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ncfix import cache
from ncfix.collision.split import map_runs
from ncfix.collision.voxelize import EDT_SLACK_MM, distance_transform, voxelize
from ncfix.memory import ensure_fits, grid_cells

# The sign grid's cell edge (mm): a point farther than half its diagonal from the surface takes
# the side of its nearest cell centre; nearer ones need a winding number.
SIGN_PITCH_MM = 0.5
# Covers the voxelizer's ray jitter and float rounding (mm).
SIGN_SLACK_MM = 1e-4
# ``surface_distances`` skips a triangle whose box lies this much (mm) beyond the nearest one so far.
CULL_MM = 1e-6
# Cell lists hold at most this many cells: a large mesh gets larger cells (``_cell_lists``).
MAX_CELLS = 4_000_000
# The code a NearSurface comes from: editing any of these files makes every cached one a miss.
NEAR_SOURCES = ("ncfix.collision.near", "ncfix.collision.voxelize", "ncfix.collision.grid", "ncfix.geometry.tolerances")
_NEAR_ARRAYS = ("triangles", "cap_mm", "cell_mm", "lo", "dims", "start", "listed", "inside", "sign_lo", "sign_pitch",
                "depth")


def tri_closest(px, py, pz, t):  # pragma: no cover - compiled
    """The point of triangle t (3, 3) closest to (px, py, pz) (Ericson 5.1.5)."""
    ax, ay, az = t[0, 0], t[0, 1], t[0, 2]
    abx, aby, abz = t[1, 0] - ax, t[1, 1] - ay, t[1, 2] - az
    acx, acy, acz = t[2, 0] - ax, t[2, 1] - ay, t[2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - t[1, 0], py - t[1, 1], pz - t[1, 2]
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - t[2, 0], py - t[2, 1], pz - t[2, 2]
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = t[1, 0], t[1, 1], t[1, 2]
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = t[2, 0], t[2, 1], t[2, 2]
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3)
            qx, qy, qz = ax + v * abx, ay + v * aby, az + v * abz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6)
            qx, qy, qz = ax + w * acx, ay + w * acy, az + w * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx = t[1, 0] + w * (t[2, 0] - t[1, 0])
            qy = t[1, 1] + w * (t[2, 1] - t[1, 1])
            qz = t[1, 2] + w * (t[2, 2] - t[1, 2])
        else:
            denom = va + vb + vc
            if denom <= 0.0:  # degenerate: the nearest vertex
                best = np.inf
                qx, qy, qz = ax, ay, az
                for k in range(3):
                    dd = (px - t[k, 0]) ** 2 + (py - t[k, 1]) ** 2 + (pz - t[k, 2]) ** 2
                    if dd < best:
                        best, qx, qy, qz = dd, t[k, 0], t[k, 1], t[k, 2]
                return qx, qy, qz
            v = vb / denom
            w = vc / denom
            qx, qy, qz = ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w
    return qx, qy, qz


def _tri_d2(px, py, pz, t):  # pragma: no cover - compiled
    """Squared distance from (px, py, pz) to triangle t (3, 3)."""
    qx, qy, qz = tri_closest(px, py, pz, t)
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


def _winding(px, py, pz, tris):  # pragma: no cover - compiled
    """Generalised winding number of a point for a triangle soup (about 1 inside, 0 outside)."""
    total = 0.0
    for g in range(tris.shape[0]):
        ax, ay, az = tris[g, 0, 0] - px, tris[g, 0, 1] - py, tris[g, 0, 2] - pz
        bx, by, bz = tris[g, 1, 0] - px, tris[g, 1, 1] - py, tris[g, 1, 2] - pz
        cx, cy, cz = tris[g, 2, 0] - px, tris[g, 2, 1] - py, tris[g, 2, 2] - pz
        la = np.sqrt(ax * ax + ay * ay + az * az)
        lb = np.sqrt(bx * bx + by * by + bz * bz)
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
        den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la \
            + (cx * ax + cy * ay + cz * az) * lb
        total += np.arctan2(det, den)
    return total / (2.0 * np.pi)


def _count_kernel(tris, lo, cell, dims, reach, counts):  # pragma: no cover - compiled
    """Pass 1 of the cell lists: how many triangles each cell lists (``_cells_kernel``)."""
    _cells_kernel(tris, lo, cell, dims, reach, counts, counts, counts[:0], False)


def _cells_kernel(tris, lo, cell, dims, reach, counts, start, out, fill):  # pragma: no cover - compiled
    """Every (cell, triangle) pair with the triangle within ``reach`` of the cell centre: counted
    (fill False, into counts) or written (fill True, at start[cell] + counts[cell], into out)."""
    r2 = reach * reach
    for g in range(tris.shape[0]):
        i0 = np.empty(3, np.int64)
        i1 = np.empty(3, np.int64)
        for a in range(3):
            mn = min(tris[g, 0, a], tris[g, 1, a], tris[g, 2, a]) - reach
            mx = max(tris[g, 0, a], tris[g, 1, a], tris[g, 2, a]) + reach
            i0[a] = max(int(np.floor((mn - lo[a]) / cell)), 0)
            i1[a] = min(int(np.floor((mx - lo[a]) / cell)), dims[a] - 1)
        for x in range(i0[0], i1[0] + 1):
            cx = lo[0] + (x + 0.5) * cell
            for y in range(i0[1], i1[1] + 1):
                cy = lo[1] + (y + 0.5) * cell
                for z in range(i0[2], i1[2] + 1):
                    cz = lo[2] + (z + 0.5) * cell
                    if _tri_d2(cx, cy, cz, tris[g]) <= r2:
                        k = (x * dims[1] + y) * dims[2] + z
                        if fill:
                            out[start[k] + counts[k]] = g
                        counts[k] += 1


def _touch(px, py, pz, r, inside_check, tris, lo, cell, dims, cap, start, listed, slo, spitch,
           inside):  # pragma: no cover - compiled
    """Whether the ball (px, py, pz; r) touches the solid: its surface within r of the centre (one
    cell's list when r <= cap, else every triangle), or, with inside_check, the centre inside."""
    r2 = r * r
    if r <= cap:
        x = int(np.floor((px - lo[0]) / cell))
        y = int(np.floor((py - lo[1]) / cell))
        z = int(np.floor((pz - lo[2]) / cell))
        if not (0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]):
            return False  # outside the box: no triangle within cap, and not inside
        k = (x * dims[1] + y) * dims[2] + z
        for j in range(start[k], start[k + 1]):
            if _tri_d2(px, py, pz, tris[listed[j]]) <= r2:
                return True
    else:
        for j in range(tris.shape[0]):
            if _tri_d2(px, py, pz, tris[j]) <= r2:
                return True
    if not inside_check:
        return False
    # No surface within r: the centre is inside exactly when the solid holds it (d > r).
    return _side(px, py, pz, r, tris, slo, spitch, inside) < 0


def _sign_cell(px, py, pz, slo, spitch, shape):  # pragma: no cover - compiled
    """The sign-grid cell whose centre is nearest the point and the distance to it; ix = -1 when
    the point lies outside the grid."""
    ix = int(np.rint((px - slo[0]) / spitch))
    iy = int(np.rint((py - slo[1]) / spitch))
    iz = int(np.rint((pz - slo[2]) / spitch))
    if not (0 <= ix < shape[0] and 0 <= iy < shape[1] and 0 <= iz < shape[2]):
        return -1, 0, 0, 0.0
    off = np.sqrt((px - slo[0] - ix * spitch) ** 2 + (py - slo[1] - iy * spitch) ** 2 + (pz - slo[2] - iz * spitch) ** 2)
    return ix, iy, iz, off


def _sign_certain(px, py, pz, d, slo, spitch, inside):  # pragma: no cover - compiled
    """The side of a point whose distance to the surface is d, from the nearest sign-grid centre
    c: 1 outside, -1 inside, 0 unknown. The ball of radius d about the point holds no surface, so
    when |p - c| < d (less the voxelizer's ray jitter) p is on c's side."""
    ix, iy, iz, off = _sign_cell(px, py, pz, slo, spitch, inside.shape)
    if ix < 0:
        return 1  # the sign grid covers the solid's box: outside it is outside
    if off + SIGN_SLACK_MM >= d:
        return 0
    return -1 if inside[ix, iy, iz] else 1


def _signed_distance_below(px, py, pz, outside, below, tris, lo, cell, dims, cap, start, listed, slo, spitch,
                           inside):  # pragma: no cover - compiled
    """``_signed_distance`` where it is below ``below`` (< 0), else ``below`` itself: a triangle
    within -below of the point ends the search (the point is then no deeper than that)."""
    if outside:
        return below
    best = _nearest_d2(px, py, pz, below * below, tris, lo, cell, dims, cap, start, listed)
    if best < 0.0:
        return below
    d = np.sqrt(best)
    side = _side(px, py, pz, d, tris, slo, spitch, inside)
    return d * side if side < 0 else below


def depth_bound(px, py, pz, slo, spitch, depth):  # pragma: no cover - compiled
    """An upper bound on how deep below the surface the point lies (0 where it is certainly
    outside): that of its nearest sign-grid centre c plus |p - c| (distance is 1-Lipschitz). So
    the signed distance at p is at least minus this."""
    ix, iy, iz, off = _sign_cell(px, py, pz, slo, spitch, depth.shape)
    if ix < 0:
        return 0.0  # the sign grid covers the solid's box: outside it is outside
    return np.float64(depth[ix, iy, iz]) + off


def _nearest_d2(px, py, pz, stop2, tris, lo, cell, dims, cap, start, listed):  # pragma: no cover - compiled
    """The squared distance from a point to the surface: the cell's list when the surface is
    within ``cap`` (exact then), else every triangle; -1 as soon as a triangle lies within
    squared distance ``stop2`` (never when stop2 < 0)."""
    best = np.inf
    x = int(np.floor((px - lo[0]) / cell))
    y = int(np.floor((py - lo[1]) / cell))
    z = int(np.floor((pz - lo[2]) / cell))
    if 0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]:
        k = (x * dims[1] + y) * dims[2] + z
        for j in range(start[k], start[k + 1]):
            d2 = _tri_d2(px, py, pz, tris[listed[j]])
            if d2 <= stop2:
                return -1.0
            best = min(best, d2)
    if best > cap * cap:  # the list holds every triangle within cap: beyond it, read them all
        for j in range(tris.shape[0]):
            d2 = _tri_d2(px, py, pz, tris[j])
            if d2 <= stop2:
                return -1.0
            best = min(best, d2)
    return best


def _box_d2(px, py, pz, box):  # pragma: no cover - compiled
    """Squared distance from (px, py, pz) to the box (2, 3) (0 inside it): never above the squared
    distance to anything in the box."""
    dx = max(box[0, 0] - px, 0.0, px - box[1, 0])
    dy = max(box[0, 1] - py, 0.0, py - box[1, 1])
    dz = max(box[0, 2] - pz, 0.0, pz - box[1, 2])
    return dx * dx + dy * dy + dz * dz


def _cull_limit(best):  # pragma: no cover - compiled
    """The squared box distance past which a triangle is certainly farther than ``best`` (a squared
    distance): ``CULL_MM`` beyond it, far more than the rounding of either distance."""
    return (np.sqrt(best) + CULL_MM) ** 2


def _min_d2(px, py, pz, tris, boxes, a, b, listed, best, arg):  # pragma: no cover - compiled
    """The least of ``best`` (the squared distance to triangle ``arg``) and the squared distances to
    the triangles listed[a:b] (every triangle in a..b when listed is empty) -> (least, its
    triangle). A triangle whose box lies beyond ``_cull_limit`` of the least so far is skipped: its
    own distance is larger, so the least is the same float as reading them all."""
    lim = _cull_limit(best)
    for j in range(a, b):
        g = listed[j] if len(listed) else j
        if _box_d2(px, py, pz, boxes[g]) > lim:
            continue
        d2 = _tri_d2(px, py, pz, tris[g])
        if d2 < best:
            best, arg = d2, g
            lim = _cull_limit(best)
    return best, arg


def _near_distances_kernel(points, out, tris, boxes, lo, cell, dims, cap, start, listed,
                           last):  # pragma: no cover - compiled
    """out[i] = the exact distance from points[i] to the surface when it is within ``cap`` (the
    cell's list holds the nearest triangle then), else -1 (not known here), or with ``last`` the
    exact distance always (every triangle read past the cap).

    The nearest triangle of the point before starts each search (``hint``): it only lets
    ``_min_d2`` skip more. When it is not in the cell's list it lies beyond the cap (the list holds
    every triangle within the cap, with 1e-9 mm to spare), so the least within the cap is the
    list's own either way, and each point's distance does not depend on the points before it."""
    cap2 = cap * cap
    none = listed[:0]
    hint = -1
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best, arg = np.inf, -1
        x = int(np.floor((px - lo[0]) / cell))
        y = int(np.floor((py - lo[1]) / cell))
        z = int(np.floor((pz - lo[2]) / cell))
        if 0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]:
            if hint >= 0:
                best, arg = _tri_d2(px, py, pz, tris[hint]), hint
            k = (x * dims[1] + y) * dims[2] + z
            best, arg = _min_d2(px, py, pz, tris, boxes, start[k], start[k + 1], listed, best, arg)
        if best > cap2 and last:
            best, arg = _min_d2(px, py, pz, tris, boxes, 0, tris.shape[0], none, best, arg)
        if best <= cap2 or last:
            out[i] = np.sqrt(best)
            hint = arg
        else:
            out[i] = -1.0


def _side(px, py, pz, d, tris, slo, spitch, inside):  # pragma: no cover - compiled
    """-1 inside, 1 outside, for a point at distance d from the surface: the sign grid where it
    is certain, else the winding number."""
    side = _sign_certain(px, py, pz, d, slo, spitch, inside)
    if side == 0:
        side = -1 if _winding(px, py, pz, tris) > 0.5 else 1
    return side


def _signed_distance(px, py, pz, outside, tris, lo, cell, dims, cap, start, listed, slo, spitch,
                     inside):  # pragma: no cover - compiled
    """Signed distance (positive outside) from a point to the closed solid (``_nearest_d2``, then
    ``_side``); ``outside``: the caller knows it is outside."""
    d = np.sqrt(_nearest_d2(px, py, pz, -1.0, tris, lo, cell, dims, cap, start, listed))
    if outside:
        return d
    return d * _side(px, py, pz, d, tris, slo, spitch, inside)


def _first_touch_kernel(points, radii, inside_check, group, n_groups, tris, lo, cell, dims, cap,
                        start, listed, slo, spitch, inside):  # pragma: no cover - compiled
    """Per group, the index of its first point (in the given order) whose ball touches the solid
    (-1: none), and the number of points tested (a group stops at its first touch)."""
    first = np.full(n_groups, -1, np.int64)
    tested = 0
    for i in range(points.shape[0]):
        g = group[i]
        if first[g] >= 0:
            continue
        tested += 1
        if _touch(points[i, 0], points[i, 1], points[i, 2], radii[i], inside_check[i], tris, lo, cell, dims, cap,
                  start, listed, slo, spitch, inside):
            first[g] = i
    return first, tested


_jit = njit(cache=True, nogil=True)
# Compiled in dependency order: a compiled loop calls the compiled helpers by their module names.
tri_closest = _jit(tri_closest)
_tri_d2 = _jit(_tri_d2)
_winding = _jit(_winding)
_cells_kernel = _jit(_cells_kernel)
_sign_cell = _jit(_sign_cell)
_sign_certain = _jit(_sign_certain)
_side = _jit(_side)
_touch = _jit(_touch)
_nearest_d2 = _jit(_nearest_d2)
_box_d2 = _jit(_box_d2)
_cull_limit = _jit(_cull_limit)
_min_d2 = _jit(_min_d2)
_near_distances_kernel = _jit(_near_distances_kernel)
_signed_distance = _jit(_signed_distance)
depth_bound = _jit(depth_bound)
_signed_distance_below = _jit(_signed_distance_below)
_count_kernel = _jit(_count_kernel)
_first_touch_kernel = _jit(_first_touch_kernel)


def _cell_lists(tris: np.ndarray, cap_mm: float, cell_mm: float, region: np.ndarray | None = None):
    """Cells of ``cell_mm`` over the triangles' box padded by ``cap_mm`` + a cell, each listing every
    triangle within ``cap_mm`` of any of its points -> (lo, dims, start, listed, cell_mm) (module
    doc). Where the box would need more than MAX_CELLS cells (a large mesh) the cell grows until it
    does not: the lists hold the same triangles for any cell size (longer ones for larger cells).
    ``region`` (2, 3): only the cells over this box (padded by a cell) are made, for queries there
    (a large mesh queried near a path); a point outside the cells reads every triangle."""
    flat = tris.reshape(-1, 3)
    if region is None:
        lo, hi = flat.min(axis=0) - cap_mm, flat.max(axis=0) + cap_mm
    else:
        lo, hi = np.asarray(region[0], dtype=np.float64), np.asarray(region[1], dtype=np.float64)
    while np.prod(np.ceil((hi - lo + 2.0 * cell_mm) / cell_mm)) > MAX_CELLS:
        cell_mm *= 1.25
    lo, hi = lo - cell_mm, hi + cell_mm
    dims = np.maximum(np.ceil((hi - lo) / cell_mm).astype(np.int64), 1)
    reach = cap_mm + 0.5 * np.sqrt(3.0) * cell_mm + 1e-9
    counts = np.zeros(int(np.prod(dims)), dtype=np.int64)
    _count_kernel(tris, lo, cell_mm, dims, reach, counts)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    listed = np.empty(int(start[-1]), dtype=np.int64)
    counts[:] = 0
    _cells_kernel(tris, lo, cell_mm, dims, reach, counts, start, listed, True)
    return lo, dims, start, listed, float(cell_mm)


# ``surface_distances``: a point farther than the cap from the surface is looked up again in
# lists of this many times the cap (cells as much larger), up to FAR_TIERS times, before it reads
# every triangle (a grid cropped from a large mesh has many such points beside its cut faces).
FAR_FACTOR = 2.0
FAR_TIERS = 6


def surface_distances(triangles: np.ndarray, points: np.ndarray, cap_mm: float, cell_mm: float = 2.0) -> np.ndarray:
    """The exact distance (mm, float64) from each point (n, 3) to the nearest of the triangles
    (m, 3, 3). A point within ``cap_mm`` of them reads one cell's list; a farther one the lists of
    a larger cap (``FAR_FACTOR``), and past the last one every triangle: the same minimum over the
    same triangle distances either way, so ``cap_mm`` only sets the cost. The lists cover only the
    points' box. A triangle whose box is farther than the nearest one found is not measured
    (``_min_d2``: the same minimum). Runs of points go to the machine's cores."""
    tris = np.ascontiguousarray(triangles, dtype=np.float64)
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(pts), dtype=np.float64)
    if not len(pts):
        return out
    if not len(tris):
        out[:] = np.inf
        return out
    boxes = np.ascontiguousarray(np.stack([tris.min(axis=1), tris.max(axis=1)], axis=1))
    todo = None  # every point
    cap, cell = float(cap_mm), float(cell_mm)
    for tier in range(FAR_TIERS + 1):
        sub = pts if todo is None else np.ascontiguousarray(pts[todo])
        got = np.empty(len(sub), dtype=np.float64)
        # Column by column: ten times faster than min(axis=0) on a million rows.
        box = np.array([[sub[:, a].min() for a in range(3)], [sub[:, a].max() for a in range(3)]])
        lo, dims, start, listed, used_cell = _cell_lists(tris, cap, cell, box)
        last = tier == FAR_TIERS

        def run(a: int, b: int) -> None:
            _near_distances_kernel(sub[a:b], got[a:b], tris, boxes, lo, used_cell, dims, cap, start, listed, last)

        map_runs(run, len(sub))
        known = got >= 0.0
        if todo is None:
            out[known] = got[known]
            todo = np.flatnonzero(~known)
        else:
            out[todo[known]] = got[known]
            todo = todo[~known]
        if not len(todo):
            break
        cap, cell = cap * FAR_FACTOR, cell * FAR_FACTOR
    return out


class NearSurface:
    """Cell lists of a closed mesh's triangles for exact ball-touch tests.

    Cell k lists every triangle within ``cap + half a cell diagonal`` of its centre, so every
    triangle within ``cap`` of any point of the cell is listed there (the triangle inequality). A
    ball of radius r <= cap at q needs only the list of q's cell; a larger one reads every triangle.

    triangles : (m, 3, 3) float64, the closed solid's surface
    cap_mm : balls up to this radius read one cell's list (larger ones read every triangle)
    cell_mm : the cells' edge (grown for a large mesh: ``_cell_lists``; ``self.cell_mm`` is the one used)
    """

    def __init__(self, triangles: np.ndarray, cap_mm: float, cell_mm: float = 2.0):
        # A copy of its own, writable like the cached one's (trimesh's arrays are read-only, and
        # numba compiles other kernels for read-only arrays: 5 s more on the first cached run).
        self.triangles = np.array(triangles, dtype=np.float64, order="C")
        self.cap_mm = float(cap_mm)
        self.lo, self.dims, self.start, self.listed, self.cell_mm = _cell_lists(self.triangles, self.cap_mm,
                                                                                float(cell_mm))
        # The sign grid: cell-centre occupancy (the column-parity voxelizer) at SIGN_PITCH_MM.
        vertices, faces = np.unique(self.triangles.reshape(-1, 3), axis=0, return_inverse=True)
        bounds = np.array([vertices.min(axis=0), vertices.max(axis=0)])
        ensure_fits(f"the exact test's sign grid of the head (at {SIGN_PITCH_MM:g} mm)",
                    grid_cells(bounds, SIGN_PITCH_MM, 2), 24, extent_mm=float(np.ptp(bounds, axis=0).max()))
        grid = voxelize(vertices, faces.reshape(-1, 3), SIGN_PITCH_MM, pad_cells=2)
        self.inside = np.ascontiguousarray(grid.occupancy)
        self.sign_lo, self.sign_pitch = np.asarray(grid.origin_mm, dtype=np.float64), float(SIGN_PITCH_MM)
        self._depth: np.ndarray | None = None

    @property
    def depth(self) -> np.ndarray:
        """(sign grid shape) float32 mm: an upper bound on the depth below the surface of every
        sign-grid centre (``depth_bound``; made on first use): the distance to the nearest centre
        outside, plus the slack. A centre outside is at most the slack deep (the voxelizer's ray
        jitter); one inside at most that far deep, as the segment to the outside centre crosses
        the surface."""
        if self._depth is None:
            d = distance_transform(self.inside, self.sign_pitch) if self.inside.any() else \
                np.zeros(self.inside.shape, dtype=np.float32)
            self._depth = np.ascontiguousarray(d + np.float32(SIGN_SLACK_MM + EDT_SLACK_MM), dtype=np.float32)
        return self._depth

    def first_touch(self, points: np.ndarray, radii: np.ndarray, inside_check: np.ndarray, group: np.ndarray,
                    n_groups: int) -> tuple[np.ndarray, int]:
        """For points (n, 3) in order, balls radii (n,), grouped by group (n,) in [0, n_groups):
        the index of each group's first ball that touches the solid (its surface within the
        radius, or, where inside_check, the centre inside), -1 where none; and the balls tested."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        group = np.asarray(group)
        if not (len(radii) == len(inside_check) == len(group) == len(points)) or \
                (len(group) and not (0 <= group.min() and group.max() < n_groups)):
            raise ValueError("first_touch: points, radii, inside_check and group must match, groups in [0, n_groups)")
        if len(points) == 0:
            return np.full(int(n_groups), -1, dtype=np.int64), 0
        first, tested = _first_touch_kernel(
            points, np.ascontiguousarray(radii, dtype=np.float64), np.ascontiguousarray(inside_check, dtype=np.bool_),
            np.ascontiguousarray(group, dtype=np.int64), int(n_groups), self.triangles, self.lo, self.cell_mm,
            self.dims, self.cap_mm, self.start, self.listed, self.sign_lo, self.sign_pitch, self.inside)
        return first, int(tested)


def cached_near_surface(triangles: np.ndarray, cap_mm: float, cell_mm: float = 2.0,
                        cache_dir: str | None = None, name: str = "the head") -> NearSurface:
    """``NearSurface(triangles, cap_mm, cell_mm)`` with its depth bound made, read from the on-disk
    cache (``ncfix.cache``) when it was built before from the same triangles, sizes and code."""
    tris = np.ascontiguousarray(triangles, dtype=np.float64)
    key = cache.make_key("near", tris, float(cap_mm), float(cell_mm), cache.fingerprint(*NEAR_SOURCES),
                         {package: cache.version(package) for package in ("numpy", "edt", "scipy")})

    def build() -> NearSurface:
        near = NearSurface(tris, cap_mm, cell_mm)
        near.depth  # noqa: B018 - made now, so that it is kept with the rest
        return near

    def from_arrays(a: dict[str, np.ndarray]) -> NearSurface | None:
        dims, start = a["dims"], a["start"]
        if dims.shape != (3,) or len(start) != int(np.prod(dims)) + 1 or start[-1] != len(a["listed"]) \
                or a["depth"].shape != a["inside"].shape or a["triangles"].shape != tris.shape:
            return None
        near = NearSurface.__new__(NearSurface)
        near.triangles, near.cap_mm, near.cell_mm = a["triangles"], float(a["cap_mm"]), float(a["cell_mm"])
        near.lo, near.dims, near.start, near.listed = a["lo"], dims, start, a["listed"]
        near.inside, near.sign_lo, near.sign_pitch = a["inside"], a["sign_lo"], float(a["sign_pitch"])
        near._depth = a["depth"]
        return near

    near, _ = cache.cached("near", key, _NEAR_ARRAYS, build, lambda near: cache.fields(near, _NEAR_ARRAYS),
                           from_arrays, cache_dir, what=f"the cell lists of {name} (first run for this mesh)")
    return near
