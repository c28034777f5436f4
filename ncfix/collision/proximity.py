"""Whether the head comes within a distance of a part, exactly, in one compiled call.

The checker's exact part test for the poses its sphere tree could not clear: the same answer as
coal's mesh-mesh test with a security margin (up to ``SLACK_MM``, toward "collides"), from the
structures the checker already has (a ball tree of the split head triangles, the part's grid and
cell lists), without holding the GIL. How and why it is exact: docs/collision.md, "The exact part
test".
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from ncfix import cache
from ncfix.collision import descent, near
from ncfix.collision.grid import DistanceGrid
from ncfix.collision.head import build_sphere_tree, leaf_order
from ncfix.collision.near import _cell_lists, _tri_d2

if TYPE_CHECKING:
    import trimesh

# The head's triangles are split until no edge is longer than this (mm): small triangles have
# tight balls (the tree clears them) and boxes of a few cells.
HEAD_EDGE_MM = 6.0
# The ball tree's leaf cell (mm): octree levels of 2, 4, 8 ... mm over the triangles' balls.
TREE_LEAF_MM = 2.0
# Part triangles within this (mm) of any point of a cell are listed there: distances up to it are
# answered here, larger ones by the caller (coal).
CAP_MM = 2.0
# The cells' edge (mm); a large part's grow (``near.MAX_CELLS``).
CELL_MM = 2.0
# Added to every distance compared (mm): rounding may only turn a near miss into a hit.
SLACK_MM = 1e-9
# Pairs (head leaf, part triangle) found within the distance lately, tried first by the next
# test: poses tested one after another often touch the part at the same place.
RECENT_PAIRS = 16


def _seg_seg_d2(p0, p1, p2, q0, q1, q2, r0, r1, r2, s0, s1, s2):  # pragma: no cover - compiled
    """Squared distance between segments pq and rs (Ericson, Real-Time Collision Detection 5.1.9)."""
    d10, d11, d12 = q0 - p0, q1 - p1, q2 - p2
    d20, d21, d22 = s0 - r0, s1 - r1, s2 - r2
    e0, e1, e2 = p0 - r0, p1 - r1, p2 - r2
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * e0 + d21 * e1 + d22 * e2
    eps = 1e-18
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d10 * e0 + d11 * e1 + d12 * e2
        if e <= eps:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d10 * d20 + d11 * d21 + d12 * d22
            denom = a * e - b * b
            s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    x0 = p0 + d10 * s - (r0 + d20 * t)
    x1 = p1 + d11 * s - (r1 + d21 * t)
    x2 = p2 + d12 * s - (r2 + d22 * t)
    return x0 * x0 + x1 * x1 + x2 * x2


def _edge_crosses(p0, p1, p2, q0, q1, q2, t, thr2):  # pragma: no cover - compiled
    """Whether segment pq crosses the plane of triangle t (3, 3) at a point within sqrt(thr2) of t
    (a segment in the plane is left to the edge and vertex tests)."""
    ux, uy, uz = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    vx, vy, vz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    sp = nx * (p0 - t[0, 0]) + ny * (p1 - t[0, 1]) + nz * (p2 - t[0, 2])
    sq = nx * (q0 - t[0, 0]) + ny * (q1 - t[0, 1]) + nz * (q2 - t[0, 2])
    if (sp > 0.0 and sq > 0.0) or (sp < 0.0 and sq < 0.0) or sp == sq:
        return False
    k = sp / (sp - sq)
    return _tri_d2(p0 + k * (q0 - p0), p1 + k * (q1 - p1), p2 + k * (q2 - p2), t) <= thr2


def _plane_apart(a, b, reach):  # pragma: no cover - compiled
    """Whether triangle b (3, 3) lies wholly more than ``reach`` to one side of a's plane (then
    no point of it is within reach of a)."""
    ux, uy, uz = a[1, 0] - a[0, 0], a[1, 1] - a[0, 1], a[1, 2] - a[0, 2]
    vx, vy, vz = a[2, 0] - a[0, 0], a[2, 1] - a[0, 1], a[2, 2] - a[0, 2]
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    size = np.sqrt(nx * nx + ny * ny + nz * nz)
    if size == 0.0:
        return False
    lo = np.inf
    hi = -np.inf
    for i in range(3):
        s = (nx * (b[i, 0] - a[0, 0]) + ny * (b[i, 1] - a[0, 1]) + nz * (b[i, 2] - a[0, 2])) / size
        lo = min(lo, s)
        hi = max(hi, s)
    return lo > reach or hi < -reach


def _tris_within(a, b, thr2):  # pragma: no cover - compiled
    """Whether triangles a and b (3, 3) come within sqrt(thr2) of each other (module doc)."""
    reach = np.sqrt(thr2)
    if _plane_apart(a, b, reach) or _plane_apart(b, a, reach):
        return False
    for i in range(3):
        if _tri_d2(a[i, 0], a[i, 1], a[i, 2], b) <= thr2 or _tri_d2(b[i, 0], b[i, 1], b[i, 2], a) <= thr2:
            return True
    for i in range(3):
        i1 = (i + 1) % 3
        for j in range(3):
            j1 = (j + 1) % 3
            if _seg_seg_d2(a[i, 0], a[i, 1], a[i, 2], a[i1, 0], a[i1, 1], a[i1, 2],
                           b[j, 0], b[j, 1], b[j, 2], b[j1, 0], b[j1, 1], b[j1, 2]) <= thr2:
                return True
    for i in range(3):
        i1 = (i + 1) % 3
        if _edge_crosses(a[i, 0], a[i, 1], a[i, 2], a[i1, 0], a[i1, 1], a[i1, 2], b, thr2):
            return True
        if _edge_crosses(b[i, 0], b[i, 1], b[i, 2], b[i1, 0], b[i1, 1], b[i1, 2], a, thr2):
            return True
    return False


def _place(c, r, head, j, w):  # pragma: no cover - compiled
    """Head triangle j at tip c, rotation r, into w (3, 3)."""
    for v in range(3):
        x, y, z = head[j, v, 0], head[j, v, 1], head[j, v, 2]
        for a in range(3):
            w[v, a] = c[a] + r[a, 0] * x + r[a, 1] * y + r[a, 2] * z


def _pair_reached(c, r, reach, j, t, leaf0, parent, center, radius, g, part, part_lo, part_hi, lo, cell, dims, start,
                  listed):  # pragma: no cover - compiled
    """Whether the descent of ``_within_kernel`` at tip c, rotation r puts head leaf j and part
    triangle t to the pair test: the grid clears neither the leaf's ball nor any ball above it,
    the cell of the leaf's centre lists t, and neither t's box nor its distance from the centre
    rejects it (the descent's tests, in its arithmetic)."""
    nd, wx, wy, wz = leaf0 + j, 0.0, 0.0, 0.0
    while nd >= 0:
        x, y, z = center[nd, 0], center[nd, 1], center[nd, 2]
        px = c[0] + r[0, 0] * x + r[0, 1] * y + r[0, 2] * z
        py = c[1] + r[1, 0] * x + r[1, 1] * y + r[1, 2] * z
        pz = c[2] + r[2, 0] * x + r[2, 1] * y + r[2, 2] * z
        if descent._grid_lb(px, py, pz, g) > radius[nd] + reach:
            return False
        if nd == leaf0 + j:
            wx, wy, wz = px, py, pz
        nd = parent[nd]
    q0 = int(np.floor((wx - lo[0]) / cell))
    q1 = int(np.floor((wy - lo[1]) / cell))
    q2 = int(np.floor((wz - lo[2]) / cell))
    if not (0 <= q0 < dims[0] and 0 <= q1 < dims[1] and 0 <= q2 < dims[2]):
        return False
    q = (q0 * dims[1] + q1) * dims[2] + q2
    listed_here = False
    for e in range(start[q], start[q + 1]):
        listed_here |= listed[e] == t
    grow = radius[leaf0 + j] + reach
    return listed_here and not (
        part_lo[t, 0] > wx + grow or part_lo[t, 1] > wy + grow or part_lo[t, 2] > wz + grow
        or part_hi[t, 0] < wx - grow or part_hi[t, 1] < wy - grow or part_hi[t, 2] < wz - grow
        or _tri_d2(wx, wy, wz, part[t]) > grow * grow)


def _within_kernel(c, r, d, head, center, radius, child_start, child_count, parent, leaf0, stack_size, g, part,
                   part_lo, part_hi, lo, cell, dims, start, listed, recent):  # pragma: no cover - compiled
    """Whether the head's triangles ``head`` (n, 3, 3, head frame; the leaves of the ball tree
    center / radius / child_start / child_count / parent, leaf i at node leaf0 + i) at tip c
    (3,), rotation r (3, 3) come within d of the part's triangles ``part`` (m, 3, 3) (module
    doc): 0 when not, 1 when the descent found a pair, 2 when a recent pair is within d; g: the
    part grid's compiled bound (``descent._grid_lb``'s arrays).

    ``recent`` (k, 2): pairs (leaf, part triangle) found within d lately, most recent first,
    -1 where none; each is tried first: the pair test, then, for a pair within d, every test the
    descent would put it to (the balls of the leaf and of every node above it not cleared by the
    grid, the triangle listed in the leaf's cell and within its reach), so a pair found so is one
    the descent reaches: the answer is the descent's. A pair found within d goes to the front of
    ``recent`` (one test at a time: the caller's pairs are its state)."""
    reach = d + SLACK_MM
    thr2 = reach * reach
    w = np.empty((3, 3))
    for m in range(recent.shape[0]):
        j, t = recent[m, 0], recent[m, 1]
        if j < 0:
            break
        _place(c, r, head, j, w)
        if _tris_within(w, part[t], thr2) and _pair_reached(c, r, reach, j, t, leaf0, parent, center, radius, g, part,
                                                            part_lo, part_hi, lo, cell, dims, start, listed):
            _to_front(recent, j, t)
            return 2
    stack = np.empty(stack_size, np.int64)
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        nd = stack[top]
        x, y, z = center[nd, 0], center[nd, 1], center[nd, 2]
        wx = c[0] + r[0, 0] * x + r[0, 1] * y + r[0, 2] * z
        wy = c[1] + r[1, 0] * x + r[1, 1] * y + r[1, 2] * z
        wz = c[2] + r[2, 0] * x + r[2, 1] * y + r[2, 2] * z
        if descent._grid_lb(wx, wy, wz, g) > radius[nd] + reach:
            continue  # no point of the node's ball comes within d
        if child_count[nd] > 0:
            for s in range(child_count[nd] - 1, -1, -1):
                stack[top] = child_start[nd] + s
                top += 1
            continue
        j = nd - leaf0
        # The part triangles within d of the leaf's ball are listed in the cell of its centre.
        q0 = int(np.floor((wx - lo[0]) / cell))
        q1 = int(np.floor((wy - lo[1]) / cell))
        q2 = int(np.floor((wz - lo[2]) / cell))
        if not (0 <= q0 < dims[0] and 0 <= q1 < dims[1] and 0 <= q2 < dims[2]):
            continue  # beyond the cells' box: no part triangle within their reach
        q = (q0 * dims[1] + q1) * dims[2] + q2
        if start[q] == start[q + 1]:
            continue
        grow = radius[nd] + reach  # a part triangle within d of the leaf's triangle is this near its centre
        placed = False
        for e in range(start[q], start[q + 1]):
            t = listed[e]
            if (part_lo[t, 0] > wx + grow or part_lo[t, 1] > wy + grow or part_lo[t, 2] > wz + grow
                    or part_hi[t, 0] < wx - grow or part_hi[t, 1] < wy - grow or part_hi[t, 2] < wz - grow):
                continue
            if _tri_d2(wx, wy, wz, part[t]) > grow * grow:
                continue
            if not placed:
                _place(c, r, head, j, w)
                placed = True
            if _tris_within(w, part[t], thr2):
                _to_front(recent, j, t)
                return 1
    return 0


def _to_front(recent, j, t):  # pragma: no cover - compiled
    """The pair (j, t) to the front of ``recent`` (k, 2), out of its old place or off the end."""
    m = recent.shape[0] - 1
    for k in range(recent.shape[0]):
        if recent[k, 0] == j and recent[k, 1] == t:
            m = k
            break
    for k in range(m, 0, -1):
        recent[k, 0], recent[k, 1] = recent[k - 1, 0], recent[k - 1, 1]
    if recent.shape[0]:
        recent[0, 0], recent[0, 1] = j, t


_seg_seg_d2 = njit(cache=True, nogil=True)(_seg_seg_d2)
_edge_crosses = njit(cache=True, nogil=True)(_edge_crosses)
_plane_apart = njit(cache=True, nogil=True)(_plane_apart)
_tris_within = njit(cache=True, nogil=True)(_tris_within)
_place = njit(cache=True, nogil=True)(_place)
_pair_reached = njit(cache=True, nogil=True)(_pair_reached)
_to_front = njit(cache=True, nogil=True)(_to_front)
_within_kernel = njit(cache=True, nogil=True)(_within_kernel)


def _balls(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 3) and radii (n,) of balls holding each triangle (n, 3, 3): the centre of its
    box, the farthest vertex's distance (widened by the slack)."""
    centre = 0.5 * (tris.min(axis=1) + tris.max(axis=1))
    radius = np.linalg.norm(tris - centre[:, None, :], axis=2).max(axis=1) + SLACK_MM
    return centre, radius


# The arrays a HeadProximity is made of (the on-disk cache keeps them).
_ARRAYS = ("head", "center", "radius", "child_start", "child_count", "leaf0", "levels", "cap_mm", "cell_mm", "lo",
           "dims", "start", "listed")
# The code the arrays come from: editing any of these files makes every cached one a miss.
PROXIMITY_SOURCES = ("ncfix.collision.proximity", "ncfix.collision.head", "ncfix.collision.near",
                     "ncfix.geometry.tolerances")


def build_arrays(head: trimesh.Trimesh, part_triangles: np.ndarray, cap_mm: float = CAP_MM,
                 cell_mm: float = CELL_MM) -> dict[str, np.ndarray]:
    """The arrays of a HeadProximity: the head's triangles split to edges of at most
    ``HEAD_EDGE_MM`` (the same surface) in the order of their ball tree's leaves, the tree and its
    number of levels, and cell lists of the part's triangles (given again to HeadProximity):
    cells of ``CELL_MM`` (larger for a large part: ``near._cell_lists``), each listing every part
    triangle within cap + the widest leaf radius of any of its points (a leaf looks up the cell of
    its ball's centre)."""
    import trimesh

    vertices, faces = trimesh.remesh.subdivide_to_size(np.asarray(head.vertices, dtype=np.float64),
                                                       np.asarray(head.faces, dtype=np.int64), HEAD_EDGE_MM)
    tris = np.asarray(vertices, dtype=np.float64)[faces]
    centre, radius = _balls(tris)
    order = leaf_order(centre, TREE_LEAF_MM)
    tree = build_sphere_tree(centre[order], radius[order], TREE_LEAF_MM)
    leaf0 = int(tree.level_start[-2])
    if not np.array_equal(tree.center_mm[leaf0:], centre[order]):  # pragma: no cover - leaf_order's promise
        raise AssertionError("HeadProximity: the tree's leaves are not the triangles in order")
    part = np.ascontiguousarray(part_triangles, dtype=np.float64).reshape(-1, 3, 3)
    lo, dims, start, listed, cell_mm = _cell_lists(part, float(cap_mm) + float(radius.max()), float(cell_mm))
    return {"head": tris[order], "center": tree.center_mm, "radius": tree.radius_mm,
            "child_start": tree.child_start, "child_count": tree.child_count, "leaf0": np.int64(leaf0),
            "levels": np.int64(len(tree.level_start) - 1), "cap_mm": np.float64(cap_mm),
            "cell_mm": np.float64(cell_mm), "lo": lo, "dims": dims, "start": start, "listed": listed.astype(np.int32)}


class HeadProximity:
    """The head's triangles against one part's, for ``within`` (module doc).

    arrays : ``build_arrays``'s for these part triangles (head frame for the head)
    part_triangles : (m, 3, 3) float64, workpiece frame
    grid : the part's DistanceGrid (clears the tree's balls)
    """

    def __init__(self, arrays: dict[str, np.ndarray], part_triangles: np.ndarray, grid: DistanceGrid):
        self.head = np.ascontiguousarray(arrays["head"], dtype=np.float64)
        self.center = np.ascontiguousarray(arrays["center"], dtype=np.float64)
        self.radius = np.ascontiguousarray(arrays["radius"], dtype=np.float64)
        self.child_start = np.ascontiguousarray(arrays["child_start"], dtype=np.int64)
        self.child_count = np.ascontiguousarray(arrays["child_count"], dtype=np.int64)
        self.leaf0 = int(arrays["leaf0"])
        self.parent = np.full(len(self.radius), -1, dtype=np.int64)  # the root's is -1
        for node in np.flatnonzero(self.child_count):
            self.parent[self.child_start[node]:self.child_start[node] + self.child_count[node]] = node
        self.recent = np.full((RECENT_PAIRS, 2), -1, dtype=np.int64)  # ``_within_kernel``'s
        # Depth first: at most (children - 1) nodes wait on the stack per level, plus the node.
        self.stack_size = int(self.child_count.max() + 1) * int(arrays["levels"]) + 1
        self.part = np.ascontiguousarray(part_triangles, dtype=np.float64).reshape(-1, 3, 3)
        self.part_lo = np.ascontiguousarray(self.part.min(axis=1))
        self.part_hi = np.ascontiguousarray(self.part.max(axis=1))
        self.cap_mm, self.cell_mm = float(arrays["cap_mm"]), float(arrays["cell_mm"])
        self.lo = np.ascontiguousarray(arrays["lo"], dtype=np.float64)
        self.dims = np.ascontiguousarray(arrays["dims"], dtype=np.int64)
        self.start = np.ascontiguousarray(arrays["start"], dtype=np.int64)
        self.listed = np.ascontiguousarray(arrays["listed"], dtype=np.int32)
        _, self.bound, _, _ = descent.bound_spec(grid.lower_bound)

    def within(self, c: np.ndarray, r: np.ndarray, d: float) -> bool:
        """Whether the head at tip c (3,), rotation r (3, 3) comes within d (mm, 0 <= d <= cap) of
        the part's surface (to SLACK_MM, toward yes)."""
        return self.test(c, r, d, self.recent) > 0

    def test(self, c: np.ndarray, r: np.ndarray, d: float, recent: np.ndarray) -> int:
        """``within`` with the recent pairs ``recent`` ((k, 2) int64, updated): 0 (not within), 1
        (a pair found by the descent) or 2 (a recent pair) (``_within_kernel``)."""
        if not 0.0 <= d <= self.cap_mm:
            raise ValueError(f"HeadProximity.within: d = {d} mm is outside [0, {self.cap_mm}]")
        return int(_within_kernel(np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(r, dtype=np.float64),
                                  float(d), self.head, self.center, self.radius, self.child_start, self.child_count,
                                  self.parent, self.leaf0, self.stack_size, self.bound, self.part, self.part_lo,
                                  self.part_hi, self.lo, self.cell_mm, self.dims, self.start, self.listed, recent))


def cached_head_proximity(head: trimesh.Trimesh, part: trimesh.Trimesh, grid: DistanceGrid,
                          cache_dir: str | None = None, name: str = "a part") -> HeadProximity:
    """A HeadProximity of the head against the part, its arrays read from the on-disk cache
    (``ncfix.cache``) when they were built before from the same meshes, sizes, code and libraries
    (``name``: the part's file, for the notice of a build)."""
    key = cache.make_key(
        "proximity",
        np.asarray(head.vertices, dtype=np.float64), np.asarray(head.faces, dtype=np.int64),
        np.asarray(part.triangles, dtype=np.float64), CAP_MM, CELL_MM, near.MAX_CELLS, HEAD_EDGE_MM, TREE_LEAF_MM,
        cache.fingerprint(*PROXIMITY_SOURCES), {package: cache.version(package) for package in ("numpy", "trimesh")},
    )

    def from_arrays(a: dict[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        n = len(a["radius"])
        if a["center"].shape != (n, 3) or a["head"].shape[1:] != (3, 3) or a["dims"].shape != (3,) \
                or len(a["start"]) != int(np.prod(a["dims"])) + 1 or a["start"][-1] != len(a["listed"]) \
                or int(a["leaf0"]) + len(a["head"]) != n or int(a["levels"]) < 1:
            return None
        return a

    arrays, _ = cache.cached("proximity", key, _ARRAYS, lambda: build_arrays(head, part.triangles),
                             lambda a: a, from_arrays, cache_dir,
                             what=f"the head's proximity lists for {name} (first run for this head and mesh)")
    return HeadProximity(arrays, part.triangles, grid)
