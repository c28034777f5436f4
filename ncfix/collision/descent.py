"""The sphere-tree descent of the checker as compiled loops, for the CPU; torch stays the path for CUDA.

In torch the descent (``Checker._undecided``, ``Checker._failing_nodes``) costs a dozen small tensor
operations per level, most of a short program's fix spent in their overhead. Here it runs pose by
pose in one numba loop (runs of poses on the machine's cores: ``split``), with the same lower bounds
evaluated point by point in the same arithmetic order and the same rules (a node is clear when
``lb(C + R c) > r + lin + ang·reach + extra``; a pose is undecided when a leaf fails or more than
``cap`` nodes fail on one level), so both paths make the same decisions.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ncfix.collision.deposit import COARSE_CELLS, COARSE_REACH_MM, FINE_LEVELS, BeadField
from ncfix.collision.grid import DistanceGrid
from ncfix.collision.split import map_runs

MODE_CLEAR = 0  # an empty field: every node is clear
MODE_GRID = 1
MODE_FIELD = 2
MODE_FIELD_BELOW = 3  # a field whose retired beads are bounded by a second field (the smaller bound)

# Scalars travel as tuples (values: the compiler keeps them in registers; arrays of them would be
# reloaded at every node, as the stores of the descent may alias them).
_NO_GRID = (np.zeros((1, 1, 1), dtype=np.float32), (0.0,) * 11)
_NO_FIELD = (np.zeros((1, 1, 1), dtype=np.uint8), np.zeros((1, 1, 1), dtype=np.float32), (0,) * 6, (0.0,) * 11)


def _field_arrays(f: BeadField):
    lo = tuple(int(v) for v in np.concatenate([f.fine_lo, f.coarse_lo]))
    box = tuple(float(v) for v in np.asarray(f.box, dtype=np.float64).reshape(-1))
    return f.fine, f.coarse, lo, (f.pitch_mm, f.step_mm, f.radius_mm, float(FINE_LEVELS), COARSE_REACH_MM) + box


def bound_spec(lower_bound):
    """(mode, grid, field, below) for the kernels, from a ``lower_bound`` bound method (of a
    ``DistanceGrid`` or a ``BeadField``). Read at call time: a field's grids change with every add,
    overlay and growth."""
    body = getattr(lower_bound, "__self__", None)
    if isinstance(body, DistanceGrid):
        dist = np.ascontiguousarray(body.dist_mm, dtype=np.float32)
        scalars = (body.pitch_mm, body.margin_mm) + tuple(float(v) for v in body.origin_mm) + \
            tuple(float(v) for v in body._box().reshape(-1))
        return MODE_GRID, (dist, scalars), _NO_FIELD, _NO_FIELD
    if isinstance(body, BeadField):
        if body.count == 0:
            return MODE_CLEAR, _NO_GRID, _NO_FIELD, _NO_FIELD
        if body.below is not None and body.below.count:
            if body.below.below is not None and body.below.below.count:
                raise ValueError("a bead field bounded below by more than one field")
            return MODE_FIELD_BELOW, _NO_GRID, _field_arrays(body), _field_arrays(body.below)
        return MODE_FIELD, _NO_GRID, _field_arrays(body), _NO_FIELD
    raise TypeError(f"no compiled bound for {lower_bound!r}")


def _gather(grid, a, b, c, default):
    """grid[a, b, c] as float64 (indices relative to the grid), ``default`` outside it."""
    if a < 0 or b < 0 or c < 0 or a >= grid.shape[0] or b >= grid.shape[1] or c >= grid.shape[2]:
        return default
    return np.float64(grid[a, b, c])


def _box_gap(x, y, z, x0, y0, z0, x1, y1, z1):
    gx = max(max(x0 - x, x - x1), 0.0)
    gy = max(max(y0 - y, y - y1), 0.0)
    gz = max(max(z0 - z, z - z1), 0.0)
    return np.sqrt(gx * gx + gy * gy + gz * gz)


def _field_lb(x, y, z, f):
    """``BeadField.lower_bound`` at one point (the same operations in the same order)."""
    fine, coarse, lo, s = f
    h, step, radius, levels, coarse_reach = s[0], s[1], s[2], s[3], s[4]
    rx, ry, rz = x / h, y / h, z / h
    ix, iy, iz = np.rint(rx), np.rint(ry), np.rint(rz)
    dx, dy, dz = x - ix * h, y - iy * h, z - iz * h
    off = np.sqrt(dx * dx + dy * dy + dz * dz)
    lb = _gather(fine, np.int64(ix) - lo[0], np.int64(iy) - lo[1], np.int64(iz) - lo[2], levels) * step - off
    kx = np.int64(np.floor((rx + 0.5) / COARSE_CELLS)) - lo[3]
    ky = np.int64(np.floor((ry + 0.5) / COARSE_CELLS)) - lo[4]
    kz = np.int64(np.floor((rz + 0.5) / COARSE_CELLS)) - lo[5]
    lb = max(lb, _gather(coarse, kx, ky, kz, coarse_reach))
    return max(lb, _box_gap(x, y, z, s[5], s[6], s[7], s[8], s[9], s[10]) - radius)


def _grid_lb(x, y, z, g):
    """``DistanceGrid.lower_bound`` at one point."""
    dist, s = g
    pitch, margin, ox, oy, oz = s[0], s[1], s[2], s[3], s[4]
    n0, n1, n2 = dist.shape
    i = min(max(np.int64(np.rint((x - ox) / pitch)), 0), n0 - 1)
    j = min(max(np.int64(np.rint((y - oy) / pitch)), 0), n1 - 1)
    k = min(max(np.int64(np.rint((z - oz) / pitch)), 0), n2 - 1)
    dx = x - (ox + i * pitch)
    dy = y - (oy + j * pitch)
    dz = z - (oz + k * pitch)
    return max(np.float64(dist[i, j, k]) - np.sqrt(dx * dx + dy * dy + dz * dz) - margin,
               _box_gap(x, y, z, s[5], s[6], s[7], s[8], s[9], s[10]))


def _lb(x, y, z, mode, g, f, b):
    if mode == MODE_GRID:
        return _grid_lb(x, y, z, g)
    if mode == MODE_FIELD:
        return _field_lb(x, y, z, f)
    if mode == MODE_FIELD_BELOW:
        return min(_field_lb(x, y, z, f), _field_lb(x, y, z, b))
    return np.inf


def _lb_points(P, mode, g, f, b, out):
    for i in range(P.shape[0]):
        out[i] = _lb(P[i, 0], P[i, 1], P[i, 2], mode, g, f, b)


def _node_fails(C, R, p, nd, lin, ang, extra, center, radius, reach, mode, g, f, b):
    cx, cy, cz = center[nd, 0], center[nd, 1], center[nd, 2]
    x = C[p, 0] + (R[p, 0, 0] * cx + R[p, 0, 1] * cy + R[p, 0, 2] * cz)
    y = C[p, 1] + (R[p, 1, 0] * cx + R[p, 1, 1] * cy + R[p, 1, 2] * cz)
    z = C[p, 2] + (R[p, 2, 0] * cx + R[p, 2, 1] * cy + R[p, 2, 2] * cz)
    need = radius[nd] + lin[p] + ang[p] * reach[nd] + extra
    return _lb(x, y, z, mode, g, f, b) <= need


def _undecided_loop(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels, mode, g, f,
                    b, out):
    """Depth first, stopping at the first failing leaf: a pose is undecided when a failing node
    whose ancestors (from the entry level) all fail is a leaf, or is one more than ``cap`` on its
    level. Which nodes fail does not depend on the order they are visited in, so this is the
    decision of a level-by-level descent, reached after fewer nodes when a leaf fails."""
    n = C.shape[0]
    width = children.shape[1]
    stack = np.empty(last - first + levels * (cap + 1) * width, dtype=np.int64)
    depth = np.empty(stack.shape[0], dtype=np.int64)
    count = np.zeros(levels + 1, dtype=np.int64)
    for p in range(n):
        m = 0
        for q in range(last - 1, first - 1, -1):
            stack[m] = q
            depth[m] = 0
            m += 1
        count[:] = 0
        undecided = False
        while m > 0:
            m -= 1
            nd, lev = stack[m], depth[m]
            if not _node_fails(C, R, p, nd, lin, ang, extra, center, radius, reach, mode, g, f, b):
                continue
            if children[nd, 0] < 0 or count[lev] == cap:  # a failing ball, or too many failing nodes
                undecided = True
                break
            count[lev] += 1
            for s in range(width - 1, -1, -1):
                ch = children[nd, s]
                if ch >= 0:
                    stack[m] = ch
                    depth[m] = lev + 1
                    m += 1
        out[p] = undecided


def _failing_loop(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                  mode, g, f, b, pad, box):
    """Per pose, the nodes at ``level`` whose sphere fails (from the root) -> (pose, node), in
    pose order and tree order within a pose. ``box`` (2, 3) grows to hold each such node's ball
    widened by ``pad``: centre C + R c, radius r + lin + ang·reach + pad + extra."""
    n = C.shape[0]
    front = np.empty(size, dtype=np.int64)
    nxt = np.empty(size, dtype=np.int64)
    pose_out = np.empty(max(1024, 64 * n), dtype=np.int64)
    node_out = np.empty(pose_out.shape[0], dtype=np.int64)
    total = 0
    for p in range(n):
        front[0] = 0
        m = 1
        for lev in range(level + 1):
            nf = 0
            for q in range(m):
                nd = front[q]
                if _node_fails(C, R, p, nd, lin, ang, extra, center, radius, reach, mode, g, f, b):
                    if lev < level:
                        for s in range(child_count[nd]):
                            nxt[nf] = child_start[nd] + s
                            nf += 1
                        continue
                    if total == pose_out.shape[0]:
                        grown = np.empty(2 * total, dtype=np.int64)
                        grown[:total] = pose_out
                        pose_out = grown
                        grown = np.empty(2 * total, dtype=np.int64)
                        grown[:total] = node_out
                        node_out = grown
                    pose_out[total] = p
                    node_out[total] = nd
                    total += 1
                    cx, cy, cz = center[nd, 0], center[nd, 1], center[nd, 2]
                    ball = radius[nd] + lin[p] + ang[p] * reach[nd] + pad + extra
                    for a in range(3):
                        w = C[p, a] + (R[p, a, 0] * cx + R[p, a, 1] * cy + R[p, a, 2] * cz)
                        box[0, a] = min(box[0, a], w - ball)
                        box[1, a] = max(box[1, a], w + ball)
            front, nxt = nxt, front
            m = nf
            if m == 0:
                break
    return pose_out[:total].copy(), node_out[:total].copy()


# The kernels below run their loop with ``mode`` a constant, one copy per kind of bound: with the
# bound chosen at every node, the descent took twice as long (the compiler keeps no kind's values
# at hand). The same arithmetic either way.
def _undecided_kernel(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels, mode, g, f,
                      b, out):
    if mode == MODE_FIELD:
        _undecided_loop(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels, MODE_FIELD,
                        g, f, b, out)
    elif mode == MODE_GRID:
        _undecided_loop(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels, MODE_GRID,
                        g, f, b, out)
    elif mode == MODE_FIELD_BELOW:
        _undecided_loop(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels,
                        MODE_FIELD_BELOW, g, f, b, out)
    else:
        _undecided_loop(C, R, lin, ang, extra, center, radius, reach, children, first, last, cap, levels, MODE_CLEAR,
                        g, f, b, out)


def _failing_kernel(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                    mode, g, f, b, pad, box):
    if mode == MODE_FIELD:
        return _failing_loop(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                             MODE_FIELD, g, f, b, pad, box)
    if mode == MODE_GRID:
        return _failing_loop(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                             MODE_GRID, g, f, b, pad, box)
    if mode == MODE_FIELD_BELOW:
        return _failing_loop(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                             MODE_FIELD_BELOW, g, f, b, pad, box)
    return _failing_loop(C, R, lin, ang, extra, center, radius, reach, child_start, child_count, level, size,
                         MODE_CLEAR, g, f, b, pad, box)


_gather = njit(cache=True, nogil=True, inline="always")(_gather)
_box_gap = njit(cache=True, nogil=True, inline="always")(_box_gap)
_field_lb = njit(cache=True, nogil=True, inline="always")(_field_lb)
_grid_lb = njit(cache=True, nogil=True, inline="always")(_grid_lb)
_lb = njit(cache=True, nogil=True, inline="always")(_lb)
_lb_points = njit(cache=True, nogil=True)(_lb_points)
_node_fails = njit(cache=True, nogil=True, inline="always")(_node_fails)
_undecided_loop = njit(cache=True, nogil=True, inline="always")(_undecided_loop)
_failing_loop = njit(cache=True, nogil=True, inline="always")(_failing_loop)
_undecided_kernel = njit(cache=True, nogil=True)(_undecided_kernel)
_failing_kernel = njit(cache=True, nogil=True)(_failing_kernel)


class HostTree:
    """A SphereTree's arrays for the kernels (children padded with -1, as ``TreeTensors``)."""

    def __init__(self, center: np.ndarray, radius: np.ndarray, reach: np.ndarray, child_start: np.ndarray,
                 child_count: np.ndarray, children: np.ndarray, level_start: np.ndarray) -> None:
        self.center = np.ascontiguousarray(center, dtype=np.float64)
        self.radius = np.ascontiguousarray(radius, dtype=np.float64)
        self.reach = np.ascontiguousarray(reach, dtype=np.float64)
        self.child_start = np.ascontiguousarray(child_start, dtype=np.int64)
        self.child_count = np.ascontiguousarray(child_count, dtype=np.int64)
        self.children = np.ascontiguousarray(children, dtype=np.int64)
        self.level_start = np.asarray(level_start, dtype=np.int64)
        self.widest = int(np.diff(self.level_start).max())


def _f64(a, shape):
    return np.ascontiguousarray(a, dtype=np.float64).reshape(shape)


def undecided(tree: HostTree, lower_bound, C, R, lin, ang, extra: float, entry: int, cap: int) -> np.ndarray:
    """(n,) bool: as ``Checker._undecided``, entering the tree at level ``entry``."""
    n = len(C)
    out = np.zeros(n, dtype=bool)
    mode, g, f, b = bound_spec(lower_bound)
    if n == 0 or mode == MODE_CLEAR:
        return out
    entry = min(entry, len(tree.level_start) - 2)
    first, last = int(tree.level_start[entry]), int(tree.level_start[entry + 1])
    C, R, lin, ang = _f64(C, (n, 3)), _f64(R, (n, 3, 3)), _f64(lin, n), _f64(ang, n)

    def run(lo, hi):
        _undecided_kernel(C[lo:hi], R[lo:hi], lin[lo:hi], ang[lo:hi], float(extra), tree.center, tree.radius,
                          tree.reach, tree.children, first, last, int(cap), len(tree.level_start) - 1 - entry, mode,
                          g, f, b, out[lo:hi])

    map_runs(run, n)
    return out


def empty_box() -> np.ndarray:
    """(2, 3) the box of nothing: +inf below, -inf above (any point widens it to itself)."""
    return np.array([[np.inf] * 3, [-np.inf] * 3])


def failing_nodes(tree: HostTree, lower_bound, C, R, lin, ang, extra: float, level: int, pad: float = 0.0):
    """(pose, node, box): as ``Checker._failing_nodes`` (int64 arrays, pose order, then tree order),
    and the box (2, 3) that holds every such node's ball widened by ``pad`` (``_failing_kernel``;
    +inf / -inf when there is none)."""
    n = len(C)
    mode, g, f, b = bound_spec(lower_bound)
    empty = np.zeros(0, dtype=np.int64)
    box = empty_box()
    if n == 0 or mode == MODE_CLEAR:
        return empty, empty, box
    level = min(level, len(tree.level_start) - 2)
    C, R, lin, ang = _f64(C, (n, 3)), _f64(R, (n, 3, 3)), _f64(lin, n), _f64(ang, n)

    def run(lo, hi):
        part = box.copy()
        pose, node = _failing_kernel(C[lo:hi], R[lo:hi], lin[lo:hi], ang[lo:hi], float(extra), tree.center,
                                     tree.radius, tree.reach, tree.child_start, tree.child_count, int(level),
                                     tree.widest, mode, g, f, b, float(pad), part)
        return pose + lo, node, part

    parts = map_runs(run, n)
    if len(parts) == 1:
        return parts[0]
    boxes = np.array([r for _, _, r in parts])
    return (np.concatenate([p for p, _, _ in parts]), np.concatenate([q for _, q, _ in parts]),
            np.array([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)]))


def lower_bounds(lower_bound, points) -> np.ndarray:
    """(m,) the compiled bound at points (m, 3): the numbers ``lower_bound`` gives in torch."""
    P = _f64(points, (-1, 3))
    out = np.full(len(P), np.inf)
    mode, g, f, b = bound_spec(lower_bound)
    if mode != MODE_CLEAR:
        _lb_points(P, mode, g, f, b, out)
    return out
