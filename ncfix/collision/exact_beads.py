"""The exact deposit test of undecided poses, as one compiled loop (``Checker._exact_kept``).

Per pose, the candidate beads near the sphere tree's failing nodes are gathered from a bucket grid
of chunks (runs of consecutive beads held as a segment widened by their distance from it, so that
the many beads below the tip allowance on a dense print are dropped a chunk at a time) and tested
exactly (point-triangle distances to the clipped head, ``near``), most suspect first,
stopping at the first touching bead. It makes the same decisions as a numpy formulation (k-d tree
pairs, a coal call per bead) without holding the ~10⁸ candidate pairs of a nozzle running among its
own beads. The loop's filters: ``first_bead_hits``; design: docs/deposit.md#the-exact-bead-test.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ncfix.collision.split import map_runs
from ncfix.collision.near import NearSurface, _signed_distance, _signed_distance_below, _touch, depth_bound

# Bucket grid of the beads: cell edge (mm), doubled until the grid has at most MAX_CELLS cells.
CELL_MM = 3.0
MAX_CELLS = 1 << 22
# A bead binned into a cell lies within this (mm) of the cell's box (floor((b - lo) / cell) is
# computed in floating point): the kernel's cell tests widen each box by it.
CELL_SLACK_MM = 1e-6
# Chunks: runs of at most CHUNK_BEADS consecutive beads (in laying order) whose ends are at most
# CHUNK_MM apart and whose beads lie within CHUNK_DEV_MM of the segment between the ends (a
# straight move's beads: on it). The kernel tests a chunk as that segment widened by its beads'
# largest distance from it (plus CHUNK_SLACK_MM, more than the rounding of any test on it), so a
# run of beads wholly below the allowance plane or far from a node is dropped at once.
CHUNK_BEADS = 8
CHUNK_MM = 2.0
CHUNK_DEV_MM = 0.05
CHUNK_SLACK_MM = 1e-6
# Consecutive poses share one gathering of chunks (``_run_lists``): runs of at most RUN_POSES, each
# tip within RUN_MM and each axis within RUN_TURN (the length of the difference of the unit
# axes) of the run's first. A chunk the gathering leaves out is below the allowance plane of every
# pose of the run by RUN_SLACK_MM, more than the rounding of the tests.
RUN_POSES = 16
RUN_MIN = 4  # a shorter run costs more to gather than it saves
RUN_MM = 2.0
RUN_TURN = 0.05
RUN_SLACK_MM = 1e-6


def _head_lb(x, y, z, dist, origin, pitch, box, margin):  # pragma: no cover - compiled
    """DistanceGrid.lower_bound_np for one head-frame point."""
    nx, ny, nz = dist.shape
    ix = min(max(int(np.rint((x - origin[0]) / pitch)), 0), nx - 1)
    iy = min(max(int(np.rint((y - origin[1]) / pitch)), 0), ny - 1)
    iz = min(max(int(np.rint((z - origin[2]) / pitch)), 0), nz - 1)
    cx, cy, cz = origin[0] + ix * pitch, origin[1] + iy * pitch, origin[2] + iz * pitch
    off = np.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2)
    gx = max(max(box[0, 0] - x, x - box[1, 0]), 0.0)
    gy = max(max(box[0, 1] - y, y - box[1, 1]), 0.0)
    gz = max(max(box[0, 2] - z, z - box[1, 2]), 0.0)
    outside = np.sqrt(gx * gx + gy * gy + gz * gz)
    return max(np.float64(dist[ix, iy, iz]) - off - margin, outside)


def _place(C, R, lin, ang, p, node_start, node_c, node_r, node_reach, bead_r, clearance, wc, wq):  # pragma: no cover - compiled
    """The failing nodes of pose p in the world: centres into wc, query radii (node radius + sweep
    margin + bead radius + clearance) into wq; returns their number."""
    c0, c1, c2 = C[p, 0], C[p, 1], C[p, 2]
    nodes = node_start[p + 1] - node_start[p]
    for i in range(nodes):
        j = node_start[p] + i
        wc[i, 0] = c0 + R[p, 0, 0] * node_c[j, 0] + R[p, 0, 1] * node_c[j, 1] + R[p, 0, 2] * node_c[j, 2]
        wc[i, 1] = c1 + R[p, 1, 0] * node_c[j, 0] + R[p, 1, 1] * node_c[j, 1] + R[p, 1, 2] * node_c[j, 2]
        wc[i, 2] = c2 + R[p, 2, 0] * node_c[j, 0] + R[p, 2, 1] * node_c[j, 1] + R[p, 2, 2] * node_c[j, 2]
        wq[i] = node_r[j] + lin[p] + ang[p] * node_reach[j] + bead_r + clearance
    return nodes


def _span(w, qc, lo, cell, dim):  # pragma: no cover - compiled
    """The bucket cells (first, last) along one axis that a ball about w of radius qc reaches."""
    return max(int(np.floor((w - qc - lo) / cell)), 0), min(int(np.floor((w + qc - lo) / cell)), dim - 1)


def _run_end(C, R, p0, n):  # pragma: no cover - compiled
    """The end (exclusive) of the run of poses from p0 that share a gathering: at most RUN_POSES,
    each tip within RUN_MM of p0's and each axis within RUN_TURN of p0's."""
    q = p0 + 1
    while q < n and q - p0 < RUN_POSES:
        dx, dy, dz = C[q, 0] - C[p0, 0], C[q, 1] - C[p0, 1], C[q, 2] - C[p0, 2]
        tx, ty, tz = R[q, 0, 2] - R[p0, 0, 2], R[q, 1, 2] - R[p0, 1, 2], R[q, 2, 2] - R[p0, 2, 2]
        if dx * dx + dy * dy + dz * dz > RUN_MM * RUN_MM or tx * tx + ty * ty + tz * tz > RUN_TURN * RUN_TURN:
            break
        q += 1
    return q


def _run_lists(C, R, lin, ang, seq, p0, p1, node_start, node_c, node_r, node_reach, chunk_seg, chunk_seq,
               chunk_start, creach, glo, gcell, gdims, bead_r, clearance, allowance, rho, wc, wq,
               pick):  # pragma: no cover - compiled
    """The gathering of the run of poses p0..p1-1: the box of bucket cells their failing nodes reach
    (the cells each pose's loop visits, in its own arithmetic), and the chunks of those cells that
    the loop may keep for some pose of the run, in cell order and in their order within a cell
    (into pick) -> (the box: its first cell and its size along y and z, each cell's first position
    in pick).
    A chunk is left out when every pose of the run would drop it at once: its beads are all laid
    after the run's last sample, or its widened segment lies below the allowance plane of every
    pose. The plane test of pose p: max(a_p·(s - c_p)) over the segment's ends s + dev + top_p <=
    allowance (a_p the axis, c_p the tip); with r the run's first pose, a_p·(s - c_p) <=
    a_r·(s - c_r) + |a_p - a_r|·|s - c_r| + |a_p·(c_r - c_p)|, so a chunk below the plane of r by
    the largest of those terms and the largest top (plus RUN_SLACK_MM, far above the rounding of
    either test) is below every pose's."""
    big = np.iinfo(np.int64).max
    b0, b1, b2, e0, e1, e2 = big, big, big, -1, -1, -1
    ar0, ar1, ar2 = R[p0, 0, 2], R[p0, 1, 2], R[p0, 2, 2]
    cr0, cr1, cr2 = C[p0, 0], C[p0, 1], C[p0, 2]
    turn, axial, top, last = 0.0, 0.0, 0.0, seq[p0]
    for p in range(p0, p1):
        nodes = _place(C, R, lin, ang, p, node_start, node_c, node_r, node_reach, bead_r, clearance, wc, wq)
        for i in range(nodes):
            qc = wq[i] + creach
            x0, x1 = _span(wc[i, 0], qc, glo[0], gcell, gdims[0])
            y0, y1 = _span(wc[i, 1], qc, glo[1], gcell, gdims[1])
            z0, z1 = _span(wc[i, 2], qc, glo[2], gcell, gdims[2])
            if x0 <= x1 and y0 <= y1 and z0 <= z1:
                b0, b1, b2 = min(b0, x0), min(b1, y0), min(b2, z0)
                e0, e1, e2 = max(e0, x1), max(e1, y1), max(e2, z1)
        tx, ty, tz = R[p, 0, 2] - ar0, R[p, 1, 2] - ar1, R[p, 2, 2] - ar2
        turn = max(turn, np.sqrt(tx * tx + ty * ty + tz * tz))
        axial = max(axial, abs(R[p, 0, 2] * (cr0 - C[p, 0]) + R[p, 1, 2] * (cr1 - C[p, 1]) + R[p, 2, 2] * (cr2 - C[p, 2])))
        top = max(top, bead_r + clearance + lin[p] + ang[p] * rho)
        last = max(last, seq[p])
    n0, n1, n2 = max(e0 - b0 + 1, 0), max(e1 - b1 + 1, 0), max(e2 - b2 + 1, 0)
    start = np.zeros(n0 * n1 * n2 + 1, np.int64)
    m = 0
    for x in range(n0):
        for y in range(n1):
            for z in range(n2):
                cidx = ((x + b0) * gdims[1] + y + b1) * gdims[2] + z + b2
                for h in range(chunk_start[cidx], chunk_start[cidx + 1]):
                    if chunk_seq[h] > last:
                        continue
                    sx, sy, sz = chunk_seg[h, 0] - cr0, chunk_seg[h, 1] - cr1, chunk_seg[h, 2] - cr2
                    ex, ey, ez = chunk_seg[h, 3] - cr0, chunk_seg[h, 4] - cr1, chunk_seg[h, 5] - cr2
                    za = ar0 * sx + ar1 * sy + ar2 * sz
                    zb = ar0 * ex + ar1 * ey + ar2 * ez
                    far = np.sqrt(max(sx * sx + sy * sy + sz * sz, ex * ex + ey * ey + ez * ez))
                    if max(za, zb) + chunk_seg[h, 6] + top + turn * far + axial + RUN_SLACK_MM <= allowance:
                        continue
                    pick[m] = h
                    m += 1
                start[(x * n1 + y) * n2 + z + 1] = m
    return (b0, b1, b2, n1, n2), start


def _kernel(C, R, lin, ang, seq, node_start, node_c, node_r, node_reach,
            beads, bseq, brad, chunk_seg, chunk_first, chunk_seq, chunk_start, creach, glo, gcell, gdims,
            hdist, horigin, hpitch, hbox, hmargin,
            tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo, spitch, inside, sdepth,
            bead_r, clearance, allowance, rho, deepest, shared):  # pragma: no cover - compiled
    """``first_bead_hits``'s loop. With ``shared`` the poses go in runs (``_run_end``), each with
    its own gathering of chunks (``_run_lists``), else one by one over every chunk of the cells."""
    n = C.shape[0]
    depth = np.full(n, np.inf)
    hit = np.zeros(n, np.bool_)
    candidates = np.zeros(n, np.int64)
    tested = 0
    cmark = np.full(chunk_first.shape[0], -1, np.int64)
    most = 1
    for p in range(n):
        most = max(most, node_start[p + 1] - node_start[p])
    wc = np.empty((most, 3))
    wq = np.empty(most)
    buf = np.empty((beads.shape[0], 3))
    buf_need = np.empty(beads.shape[0])
    buf_r = np.empty(beads.shape[0])
    buf_lb = np.empty(beads.shape[0])
    buf_sd = np.empty(beads.shape[0])
    half = 0.5 * gcell + CELL_SLACK_MM  # a cell's half edge, with the slack of its chunks' binning
    every = np.zeros(0, np.int64)  # not read: a run not gathered lists the chunks themselves
    pick = np.empty(chunk_seq.shape[0], np.int64)
    p0 = 0
    while p0 < n:
        p1 = _run_end(C, R, p0, n) if shared else p0 + 1
        gathered = p1 - p0 >= RUN_MIN  # a shorter run visits every chunk of the cells itself
        box, box_start, listed = (0, 0, 0, gdims[1], gdims[2]), chunk_start, every
        if gathered:
            box, box_start = _run_lists(C, R, lin, ang, seq, p0, p1, node_start, node_c, node_r,
                                                     node_reach, chunk_seg, chunk_seq, chunk_start, creach, glo,
                                                     gcell, gdims, bead_r, clearance, allowance, rho, wc, wq, pick)
            listed = pick
        for p in range(p0, p1):
            k = _gather(C, R, lin, ang, seq, p, node_start, node_c, node_r, node_reach, beads, bseq, brad,
                        chunk_seg, chunk_first, chunk_seq, creach, glo, gcell, gdims, box, box_start, listed, gathered,
                        hdist, horigin, hpitch, hbox, hmargin, bead_r, clearance, allowance, rho, half, cmark, wc,
                        wq, buf, buf_need, buf_r, buf_lb)
            candidates[p] = k
            if k == 0:
                continue
            tested += _test(p, k, buf, buf_need, buf_r, buf_lb, buf_sd, tris, nlo, ncell, ndims, ncap, nstart,
                            nlisted, slo, spitch, inside, sdepth, deepest, hit, depth)
        p0 = p1
    return hit, depth, candidates, tested


def _gather(C, R, lin, ang, seq, p, node_start, node_c, node_r, node_reach, beads, bseq, brad, chunk_seg,
            chunk_first, chunk_seq, creach, glo, gcell, gdims, box, box_start, listed, gathered,
            hdist, horigin, hpitch, hbox, hmargin, bead_r, clearance, allowance, rho, half, cmark, wc, wq,
            buf, buf_need, buf_r, buf_lb):  # pragma: no cover - compiled
    """The candidate beads of pose p into buf (head frame), buf_need, buf_r, buf_lb -> their
    number. The cells of the box (its first cell box[:3], its size along y and z box[3:]) list
    their chunks in listed[box_start[c]:box_start[c + 1]] (c numbered in the box) when
    ``gathered``, else the chunks box_start[c]..box_start[c + 1] - 1 themselves."""
    b0, b1, b2, n1, n2 = box
    k = 0
    c0, c1, c2 = C[p, 0], C[p, 1], C[p, 2]
    ax, ay, az = R[p, 0, 2], R[p, 1, 2], R[p, 2, 2]  # the head's axis
    # The most any bead of the pose can need above the allowance plane (its radius, the
    # clearance and the largest sweep margin): a chunk wholly below the plane by it holds no
    # bead the plane test below would keep; a cell, by that and its chunks' reach.
    top = bead_r + clearance + lin[p] + ang[p] * rho
    below = allowance - top - half * (abs(ax) + abs(ay) + abs(az)) - creach
    nodes = _place(C, R, lin, ang, p, node_start, node_c, node_r, node_reach, bead_r, clearance, wc, wq)
    for i in range(nodes):
        wx, wy, wz, q = wc[i, 0], wc[i, 1], wc[i, 2], wq[i]
        qc = q + creach  # a chunk's beads lie within creach of its cell's box
        qc2 = qc * qc
        x0, x1 = _span(wx, qc, glo[0], gcell, gdims[0])
        y0, y1 = _span(wy, qc, glo[1], gcell, gdims[1])
        z0, z1 = _span(wz, qc, glo[2], gcell, gdims[2])
        for x in range(x0, x1 + 1):
            mx = glo[0] + (x + 0.5) * gcell  # the cell's centre
            gx = max(abs(wx - mx) - half, 0.0)  # the ball's centre to the cell's box
            for y in range(y0, y1 + 1):
                my = glo[1] + (y + 0.5) * gcell
                gy = max(abs(wy - my) - half, 0.0)
                for z in range(z0, z1 + 1):
                    cidx = ((x - b0) * n1 + y - b1) * n2 + z - b2
                    first, end = box_start[cidx], box_start[cidx + 1]
                    if first == end:
                        continue
                    mz = glo[2] + (z + 0.5) * gcell
                    gz = max(abs(wz - mz) - half, 0.0)
                    if gx * gx + gy * gy + gz * gz > qc2:
                        continue  # the cell's chunks lie wholly outside the ball
                    if ax * (mx - c0) + ay * (my - c1) + az * (mz - c2) <= below:
                        continue  # wholly below the allowance plane
                    for e in range(first, end):
                        h = listed[e] if gathered else e
                        if cmark[h] == p:
                            continue  # done for this pose: rejected, or its beads gathered
                        if chunk_seq[h] > seq[p]:
                            cmark[h] = p  # every bead laid after the pose
                            continue
                        sx, sy, sz = chunk_seg[h, 0], chunk_seg[h, 1], chunk_seg[h, 2]
                        ux, uy, uz = chunk_seg[h, 3] - sx, chunk_seg[h, 4] - sy, chunk_seg[h, 5] - sz
                        dev = chunk_seg[h, 6]
                        # Its beads lie within dev of the segment: the axis height of a segment
                        # is largest at an end.
                        za = ax * (sx - c0) + ay * (sy - c1) + az * (sz - c2)
                        zb = za + ax * ux + ay * uy + az * uz
                        if max(za, zb) + dev + top <= allowance:
                            cmark[h] = p
                            continue
                        vx, vy, vz = wx - sx, wy - sy, wz - sz
                        uu = ux * ux + uy * uy + uz * uz
                        t = 0.0 if uu <= 0.0 else min(max((vx * ux + vy * uy + vz * uz) / uu, 0.0), 1.0)
                        vx, vy, vz = vx - t * ux, vy - t * uy, vz - t * uz
                        if vx * vx + vy * vy + vz * vz > (q + dev) * (q + dev):
                            continue  # not near this node (another may reach it)
                        cmark[h] = p  # its beads are gathered now, against every node of the pose
                        for b in range(chunk_first[h], chunk_first[h + 1]):
                            if bseq[b] > seq[p]:
                                continue
                            near_node = False
                            for u in range(nodes):
                                dx, dy, dz = beads[b, 0] - wc[u, 0], beads[b, 1] - wc[u, 1], beads[b, 2] - wc[u, 2]
                                if dx * dx + dy * dy + dz * dz <= wq[u] * wq[u]:
                                    near_node = True
                                    break
                            if not near_node:
                                continue
                            # R^T (b - C): the head frame
                            ex, ey, ez = beads[b, 0] - c0, beads[b, 1] - c1, beads[b, 2] - c2
                            lx = R[p, 0, 0] * ex + R[p, 1, 0] * ey + R[p, 2, 0] * ez
                            ly = R[p, 0, 1] * ex + R[p, 1, 1] * ey + R[p, 2, 1] * ez
                            lz = R[p, 0, 2] * ex + R[p, 1, 2] * ey + R[p, 2, 2] * ez
                            # A head point at distance d from the tip moves at most lin + ang·d
                            # between samples; a bead laid at this very sample gets no margin.
                            need = brad[b] + clearance  # its own radius (at most bead_r)
                            if bseq[b] != seq[p]:
                                swept = lin[p] + ang[p] * rho
                                near = lin[p] + ang[p] * (np.sqrt(lx * lx + ly * ly + lz * lz) + need + swept)
                                need += min(swept, near)
                            if lz + need <= allowance:
                                continue  # wholly below the allowance plane
                            lb = _head_lb(lx, ly, lz, hdist, horigin, hpitch, hbox, hmargin)
                            if lb > need:
                                continue
                            buf[k, 0], buf[k, 1], buf[k, 2] = lx, ly, lz
                            buf_need[k] = need
                            buf_r[k] = brad[b]
                            buf_lb[k] = lb
                            k += 1
    return k


def _test(p, k, buf, buf_need, buf_r, buf_lb, buf_sd, tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo,
          spitch, inside, sdepth, deepest, hit, depth):  # pragma: no cover - compiled
    """The exact test of pose p's k candidates (``_gather``), most suspect first, to the first
    touching one (hit[p]; with ``deepest``, depth[p] the deepest candidate's clearance) -> the
    candidates tested."""
    touched, tested = _first_touch(k, buf, buf_need, buf_lb, tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo,
                                   spitch, inside)
    if not touched:
        return tested
    hit[p] = True
    if deepest:  # the pose's clearance: the deepest of its candidates
        # A lower bound on each one's clearance (its signed distance minus its radius): lb outside
        # (lb > 0), minus the depth bound inside; smallest first, until the bound passes the best
        # found.
        for u in range(k):
            buf_sd[u] = (buf_lb[u] if buf_lb[u] > 0.0 else
                         -depth_bound(buf[u, 0], buf[u, 1], buf[u, 2], slo, spitch, sdepth)) - buf_r[u]
        by_sd = np.argsort(buf_sd[:k], kind="mergesort")
        best = np.inf
        for u in range(k):
            v = by_sd[u]
            if buf_sd[v] >= best:
                break
            if best + buf_r[v] < 0.0:  # only a point deeper than the best can change it
                sd = _signed_distance_below(buf[v, 0], buf[v, 1], buf[v, 2], buf_lb[v] > 0.0, best + buf_r[v], tris,
                                            nlo, ncell, ndims, ncap, nstart, nlisted, slo, spitch, inside)
            else:
                sd = _signed_distance(buf[v, 0], buf[v, 1], buf[v, 2], buf_lb[v] > 0.0, tris, nlo, ncell, ndims,
                                      ncap, nstart, nlisted, slo, spitch, inside)
            best = min(best, sd - buf_r[v])
        depth[p] = best
    return tested


def _first_touch(k, buf, buf_need, buf_lb, tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo, spitch,
                 inside):  # pragma: no cover - compiled
    """The k candidates (head-frame centres buf, each one's radius plus margin buf_need) tested
    exactly, the most suspect (smallest bound buf_lb, stably) first, to the first touching one ->
    (whether one touches, the candidates tested)."""
    order = np.argsort(buf_lb[:k], kind="mergesort")
    for t in range(k):
        i = order[t]
        if _touch(buf[i, 0], buf[i, 1], buf[i, 2], buf_need[i], buf_lb[i] <= 0.0, tris, nlo, ncell, ndims,
                  ncap, nstart, nlisted, slo, spitch, inside):
            return True, t + 1
    return False, k


_head_lb = njit(cache=True, nogil=True)(_head_lb)
_place = njit(cache=True, nogil=True, inline="always")(_place)
_span = njit(cache=True, nogil=True, inline="always")(_span)
_run_end = njit(cache=True, nogil=True)(_run_end)
_run_lists = njit(cache=True, nogil=True)(_run_lists)
_gather = njit(cache=True, nogil=True)(_gather)
_first_touch = njit(cache=True, nogil=True)(_first_touch)
_test = njit(cache=True, nogil=True)(_test)
_kernel = njit(cache=True, nogil=True)(_kernel)


def candidates_free(C, R, cells, head_grid, near: NearSurface, *, need: float, allowance: float,
                    clearance: float = 0.0):
    """Per pose (n) of one tip (``Checker.deposit_free``): free of the beads in ``cells`` ((beads,
    members, counts, starts, cell centres, cell radii[, each bead's radius]),
    ``Checker._tip_cells``); and the beads tested exactly. A cell the head grid's bound clears (or
    wholly below the allowance plane by more than ``need``, the largest bead's radius plus the
    clearance) clears its beads; a bead it cannot clear is tested exactly (a ball of its own radius
    plus ``clearance``, else ``need``, against the clipped head, the centre's side checked where
    the bound allows it inside), the most suspect first, and a pose stops at its first touching
    bead."""
    B, members, counts, starts, cc, cr = cells[:6]
    own = np.ascontiguousarray(cells[6], np.float64) + float(clearance) if len(cells) > 6 else \
        np.full(len(B), float(need))
    own = np.minimum(own, float(need))
    f64 = np.float64
    C, R = np.ascontiguousarray(C, f64).reshape(-1, 3), np.ascontiguousarray(R, f64).reshape(-1, 3, 3)
    hbox, horigin = np.ascontiguousarray(head_grid._box(), f64), np.asarray(head_grid.origin_mm, f64)

    def run(lo, hi):
        return _candidates_kernel(
            C[lo:hi], R[lo:hi], np.ascontiguousarray(cc, f64), np.ascontiguousarray(cr, f64),
            np.ascontiguousarray(counts, np.int64), np.ascontiguousarray(starts, np.int64),
            np.ascontiguousarray(members, np.int64), np.ascontiguousarray(B, f64), own, float(need),
            float(allowance),
            head_grid.dist_mm, horigin, float(head_grid.pitch_mm), hbox, float(head_grid.margin_mm),
            near.triangles, near.lo, near.cell_mm, near.dims, near.cap_mm, near.start, near.listed,
            near.sign_lo, near.sign_pitch, near.inside)

    parts = map_runs(run, len(C))
    if len(parts) == 1:
        return ~parts[0][0], int(parts[0][1])
    return ~np.concatenate([p[0] for p in parts]), int(sum(p[1] for p in parts))


def _candidates_kernel(C, R, cc, cr, counts, starts, members, beads, own, need, allowance,
                       hdist, horigin, hpitch, hbox, hmargin,
                       tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo, spitch, inside):  # pragma: no cover - compiled
    """(hit (n,), beads tested): ``candidates_free``'s loop (head-frame point of a world point q at
    pose p: R_pᵀ (q − C_p))."""
    n = C.shape[0]
    hit = np.zeros(n, np.bool_)
    tested = 0
    buf = np.empty((beads.shape[0], 3))
    buf_lb = np.empty(beads.shape[0])
    buf_need = np.empty(beads.shape[0])
    for p in range(n):
        k = 0
        for c in range(cc.shape[0]):
            ex, ey, ez = cc[c, 0] - C[p, 0], cc[c, 1] - C[p, 1], cc[c, 2] - C[p, 2]
            z = R[p, 0, 2] * ex + R[p, 1, 2] * ey + R[p, 2, 2] * ez
            if not z + cr[c] + need > allowance:  # wholly below the allowance plane: exempt
                continue
            x = R[p, 0, 0] * ex + R[p, 1, 0] * ey + R[p, 2, 0] * ez
            y = R[p, 0, 1] * ex + R[p, 1, 1] * ey + R[p, 2, 1] * ez
            if _head_lb(x, y, z, hdist, horigin, hpitch, hbox, hmargin) > need + cr[c]:
                continue
            for j in range(starts[c], starts[c] + counts[c]):
                b = members[j]
                nb = own[b]  # this bead's radius plus the clearance (at most need)
                ex, ey, ez = beads[b, 0] - C[p, 0], beads[b, 1] - C[p, 1], beads[b, 2] - C[p, 2]
                z = R[p, 0, 2] * ex + R[p, 1, 2] * ey + R[p, 2, 2] * ez
                if not z + nb > allowance:
                    continue
                x = R[p, 0, 0] * ex + R[p, 1, 0] * ey + R[p, 2, 0] * ez
                y = R[p, 0, 1] * ex + R[p, 1, 1] * ey + R[p, 2, 1] * ez
                lb = _head_lb(x, y, z, hdist, horigin, hpitch, hbox, hmargin)
                if lb > nb:
                    continue
                buf[k, 0], buf[k, 1], buf[k, 2] = x, y, z
                buf_lb[k] = lb
                buf_need[k] = nb
                k += 1
        if k == 0:
            continue
        hit[p], t = _first_touch(k, buf, buf_need, buf_lb, tris, nlo, ncell, ndims, ncap, nstart, nlisted, slo,
                                 spitch, inside)
        tested += t
    return hit, tested


class BeadBuckets:
    """Beads (the store's exact ones and the window's pending ones, with the sequence number from
    which each is seen: -1 = always, and the radius of the sphere each is held as) in chunks of
    consecutive beads (``_chunks``), the chunks in a bucket grid over the region a batch of
    queries covers."""

    def __init__(self, beads: np.ndarray, seq: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 radii: np.ndarray | float = 0.0):
        beads = np.ascontiguousarray(beads, dtype=np.float64).reshape(-1, 3)
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        # The beads inside [lo, hi] (into the beads given, ascending) are those inside the box cut
        # to the beads' own bounds, which gives the grid its origin.
        self.index, low, high = _inside(beads, lo, hi)
        if len(beads):
            lo, hi = np.maximum(lo, low), np.minimum(hi, high)
        cell = CELL_MM
        extent = np.maximum(hi - lo, 0.0) if len(self.index) else np.zeros(3)
        while np.prod(np.floor(extent / cell) + 1) > MAX_CELLS:
            cell *= 2.0
        self.lo, self.cell = lo, cell
        self.dims = (np.floor(extent / cell) + 1).astype(np.int64)
        # Rows are gathered with np.take: the same copy as fancy indexing, several times faster.
        self.beads = np.take(beads, self.index, axis=0)
        self.seq = np.ascontiguousarray(np.asarray(seq, dtype=np.int64)[self.index])
        radii = np.asarray(radii, dtype=np.float64)
        self.radii = np.ascontiguousarray(np.broadcast_to(radii, (len(beads),))[self.index] if radii.ndim else
                                          np.full(len(self.index), float(radii)))
        # The chunks, each listed under the cell of its segment's middle (a compiled counting sort:
        # np.argsort(flat, kind="stable") and np.bincount), and the beads in chunk order, with
        # their sequence numbers and radii.
        ends, seg, low_seq = _chunks(self.beads, self.seq)
        order, self.chunk_start = _sort_by_cell(0.5 * (seg[:, :3] + seg[:, 3:6]), lo, float(cell), self.dims)
        self.chunk_seg, self.chunk_seq = np.ascontiguousarray(seg[order]), np.ascontiguousarray(low_seq[order])
        counts = (ends[1:] - ends[:-1])[order]
        self.chunk_first = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        members = np.arange(len(self.beads)) + np.repeat(ends[order] - self.chunk_first[:-1], counts)
        self.chunk_beads = np.take(self.beads, members, axis=0)
        self.chunk_bseq = np.ascontiguousarray(self.seq[members])
        self.chunk_radii = np.ascontiguousarray(self.radii[members])
        # How far a chunk's beads lie from the middle of its segment, at most.
        self.chunk_reach = float((0.5 * np.linalg.norm(seg[:, 3:6] - seg[:, :3], axis=1) + seg[:, 6]).max()) \
            if len(seg) else 0.0


def _inside(beads, lo, hi):  # pragma: no cover - compiled
    """(indices (ascending) of the beads (n, 3) inside the box [lo, hi] (bounds included), the
    beads' smallest and largest coordinates (3,) each)."""
    out = np.empty(beads.shape[0], np.int64)
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    m = 0
    for i in range(beads.shape[0]):
        for a in range(3):
            low[a] = min(low[a], beads[i, a])
            high[a] = max(high[a], beads[i, a])
        if lo[0] <= beads[i, 0] <= hi[0] and lo[1] <= beads[i, 1] <= hi[1] and lo[2] <= beads[i, 2] <= hi[2]:
            out[m] = i
            m += 1
    return out[:m].copy(), low, high


def _chunks(beads, seq):  # pragma: no cover - compiled
    """Runs of consecutive beads (m, 3), greedily (``CHUNK_BEADS``, ``CHUNK_MM``, ``CHUNK_DEV_MM``):
    (each run's first bead and the end (runs + 1,); per run, its segment's ends and the largest
    distance of its beads from the segment plus ``CHUNK_SLACK_MM`` (runs, 7); the smallest
    sequence number of its beads (runs,))."""
    m = beads.shape[0]
    ends = np.empty(m + 1, np.int64)
    seg = np.empty((m, 7))
    low = np.empty(m, np.int64)
    c = 0
    i = 0
    while i < m:
        j = i  # the run's last bead so far
        dev = 0.0
        while j + 1 < m and j + 1 - i < CHUNK_BEADS:
            ux, uy, uz = beads[j + 1, 0] - beads[i, 0], beads[j + 1, 1] - beads[i, 1], beads[j + 1, 2] - beads[i, 2]
            uu = ux * ux + uy * uy + uz * uz
            if uu > CHUNK_MM * CHUNK_MM:
                break
            worst = 0.0
            for k in range(i + 1, j + 1):
                vx, vy, vz = beads[k, 0] - beads[i, 0], beads[k, 1] - beads[i, 1], beads[k, 2] - beads[i, 2]
                t = 0.0 if uu <= 0.0 else min(max((vx * ux + vy * uy + vz * uz) / uu, 0.0), 1.0)
                vx, vy, vz = vx - t * ux, vy - t * uy, vz - t * uz
                worst = max(worst, np.sqrt(vx * vx + vy * vy + vz * vz))
            if worst > CHUNK_DEV_MM:
                break
            j += 1
            dev = worst
        ends[c] = i
        for a in range(3):
            seg[c, a] = beads[i, a]
            seg[c, 3 + a] = beads[j, a]
        seg[c, 6] = dev + CHUNK_SLACK_MM
        low[c] = seq[i]
        for k in range(i + 1, j + 1):
            low[c] = min(low[c], seq[k])
        c += 1
        i = j + 1
    ends[c] = m
    return ends[:c + 1].copy(), seg[:c].copy(), low[:c].copy()


def _sort_by_cell(beads, lo, cell, dims):  # pragma: no cover - compiled
    """(the points (m, 3) ordered by cell, stably (m,); each cell's first position (cells + 1,)):
    cell (i, j, k) = floor((b - lo) / cell), clipped to dims, numbered (i·dims₁ + j)·dims₂ + k."""
    m = beads.shape[0]
    cells = dims[0] * dims[1] * dims[2]
    flat = np.empty(m, np.int64)
    start = np.zeros(cells + 1, np.int64)
    for j in range(m):
        ix = min(np.int64(np.floor((beads[j, 0] - lo[0]) / cell)), dims[0] - 1)
        iy = min(np.int64(np.floor((beads[j, 1] - lo[1]) / cell)), dims[1] - 1)
        iz = min(np.int64(np.floor((beads[j, 2] - lo[2]) / cell)), dims[2] - 1)
        flat[j] = (ix * dims[1] + iy) * dims[2] + iz
        start[flat[j] + 1] += 1
    for c in range(cells):
        start[c + 1] += start[c]
    fill = start[:cells].copy()
    order = np.empty(m, np.int64)
    for j in range(m):
        order[fill[flat[j]]] = j
        fill[flat[j]] += 1
    return order, start


_inside = njit(cache=True, nogil=True)(_inside)
_candidates_kernel = njit(cache=True, nogil=True)(_candidates_kernel)
_sort_by_cell = njit(cache=True, nogil=True)(_sort_by_cell)
_chunks = njit(cache=True, nogil=True)(_chunks)


def first_bead_hits(C, R, lin, ang, seq, node_pose, node_c, node_r, node_reach, buckets: BeadBuckets,
                    head_grid, near: NearSurface, *, bead_r: float, clearance: float, allowance: float,
                    rho: float, deepest: bool = True, shared: bool = True):
    """Per pose (n): hit (bool), with ``deepest`` its clearance: the smallest signed distance from a
    bead centre it sees to the clipped head minus that bead's radius (``buckets.radii``, at most
    ``bead_r``, which bounds the search) (+inf where free or not ``deepest``),
    the candidate beads it had after the filters, and the beads tested exactly.

    The sphere tree names each pose's failing nodes at ``CANDIDATE_LEVEL``; a bead can touch the
    clipped head only within ``node radius + lin + ang·reach + bead radius + clearance`` of one of
    them. The loop visits, per failing node, the cells of the bucket grid around its ball (skipping
    a cell whose chunks lie wholly outside the ball, or wholly below the tip-allowance plane by the
    largest margin a bead of the pose can need: none of their beads would pass the tests below),
    then the chunks there: a chunk whose beads the pose does not see yet, or whose widened segment
    lies wholly below that plane, is dropped for the pose; one out of the node's ball is left for
    the other nodes; the others' beads are taken once per pose, each within some node's ball (on a
    filament print's dense beads, almost every chunk near the tip is dropped whole). Of those it
    drops beads the pose does not see yet (laid at a later sample), beads wholly below the
    tip-allowance plane, and beads the head grid's lower bound clears; it then tests the rest
    exactly, smallest bound first, and stops at the pose's first touching bead (exact
    point-triangle distances, a winding number where the bound allows the centre to be inside).
    With ``shared`` (the default) runs of consecutive poses gather their chunks once
    (``_run_lists``), leaving out those every pose of the run would drop: each pose then keeps the
    same candidates in the same order as when it visits every chunk itself (``shared`` False).
    node_pose (m,) ascending: the pose of each failing node; node_c (m, 3) head-frame centres,
    node_r / node_reach (m,) radius and reach."""
    n = len(C)
    node_start = np.searchsorted(node_pose, np.arange(n + 1)).astype(np.int64)
    f64 = np.float64
    C, R = np.ascontiguousarray(C, f64), np.ascontiguousarray(R, f64)
    lin, ang, seq = np.ascontiguousarray(lin, f64), np.ascontiguousarray(ang, f64), np.ascontiguousarray(seq, np.int64)
    node_c, node_r = np.ascontiguousarray(node_c, f64), np.ascontiguousarray(node_r, f64)
    node_reach = np.ascontiguousarray(node_reach, f64)
    hbox, horigin = np.ascontiguousarray(head_grid._box(), f64), np.asarray(head_grid.origin_mm, f64)
    sdepth = near.depth  # built lazily: once, here, not in the threads

    def run(lo, hi):  # poses lo..hi-1: node_start[lo..hi] still index the whole node arrays
        return _kernel(
            C[lo:hi], R[lo:hi], lin[lo:hi], ang[lo:hi], seq[lo:hi], node_start[lo:hi + 1], node_c, node_r,
            node_reach, buckets.chunk_beads, buckets.chunk_bseq, buckets.chunk_radii, buckets.chunk_seg,
            buckets.chunk_first, buckets.chunk_seq, buckets.chunk_start, buckets.chunk_reach, buckets.lo,
            float(buckets.cell), buckets.dims, head_grid.dist_mm, horigin, float(head_grid.pitch_mm), hbox,
            float(head_grid.margin_mm), near.triangles, near.lo, near.cell_mm, near.dims, near.cap_mm, near.start,
            near.listed, near.sign_lo, near.sign_pitch, near.inside, sdepth,
            float(bead_r), float(clearance), float(allowance), float(rho), bool(deepest), bool(shared))

    parts = map_runs(run, n)
    if len(parts) == 1:
        hit, depth, candidates, tested = parts[0]
        return hit, depth, candidates, int(tested)
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]), int(sum(p[3] for p in parts)))
