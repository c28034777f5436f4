"""Whether one body lies wholly inside the other at a head pose: the exact part test's second half.

Where no head triangle meets a part triangle, every connected body of either mesh lies wholly
inside or wholly outside the other solid, so one vertex per body decides, by its generalised
winding number with respect to the other mesh (all of its bodies: a body in a hollow cavity is
outside). See docs/collision.md#undecided-poses-and-the-exact-tests; ``ncfix.reference``'s
``ExactReference`` answers the same question plainly, for the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ncfix.collision.near import _winding
from ncfix.geometry.meshdata import component_labels

# Box tests widened by this (mm): a vertex placed by the pose's rotation is off by ~1e-13 mm.
SLACK_MM = 1e-9


@dataclass
class MeshBodies:
    """The connected bodies of a mesh, in its own frame.

    triangles : (m, 3, 3) float64, the mesh's triangles grouped by body
    start : (k + 1,) int64, body b's triangles are triangles[start[b]:start[b + 1]]
    probe : (k, 3) float64, one vertex of each body
    lo, hi : (k, 3) float64, each body's box
    vertices : (v, 3) float64, each body's vertices grouped by body, the extreme ones along the
        axes first (the head's box test meets a vertex outside after a few)
    vstart : (k + 1,) int64, body b's vertices are vertices[vstart[b]:vstart[b + 1]]
    """

    triangles: np.ndarray
    start: np.ndarray
    probe: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    vertices: np.ndarray
    vstart: np.ndarray

    @property
    def count(self) -> int:
        return len(self.probe)


def mesh_bodies(mesh) -> MeshBodies:
    """Split a mesh into its connected bodies (faces sharing an edge); vectorised, as a badly
    exported part may hold many thousands of them."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    labels = component_labels(faces)
    order = np.argsort(labels, kind="stable")
    faces, labels = faces[order], labels[order]
    count = int(labels.max()) + 1 if len(labels) else 0
    start = np.searchsorted(labels, np.arange(count + 1)).astype(np.int64)
    tris = np.ascontiguousarray(verts[faces])
    if count == 0:
        empty = np.zeros((0, 3))
        return MeshBodies(tris, start, empty, empty, empty, empty, np.zeros(1, dtype=np.int64))
    lo = np.minimum.reduceat(tris.min(axis=1), start[:-1])
    hi = np.maximum.reduceat(tris.max(axis=1), start[:-1])
    probe = tris[start[:-1], 0]
    # Each body's vertices (a vertex where bodies touch belongs to each), extreme ones first.
    pairs = np.unique(np.column_stack([np.repeat(labels, 3), faces.reshape(-1)]), axis=0)
    body, v = pairs[:, 0], verts[pairs[:, 1]]
    extreme = ((v == lo[body]) | (v == hi[body])).any(axis=1)
    pairs = pairs[np.lexsort((~extreme, body))]
    vstart = np.searchsorted(pairs[:, 0], np.arange(count + 1)).astype(np.int64)
    return MeshBodies(tris, start, probe, lo, hi, np.ascontiguousarray(verts[pairs[:, 1]]), vstart)


class Nested:
    """The containment test of one head against one part.

    The two overlap (no triangles meeting) exactly when a body of the part lies inside the head or
    a body of the head inside the part. A part mesh may hold several bodies (fixtures, clamps,
    parts exported together, a separate small feature): each is tested on its own, as the head's
    bodies are; an open part has no inside: only its bodies inside the head count. The bodies are
    split once (``MeshBodies``); a pose costs one compiled call that skips, by boxes, every body
    that cannot be inside (a part body whose box leaves the head's bounding ball, a head body with
    a vertex outside the part's box) and computes a winding number only for the rest.

    head, part : their ``MeshBodies`` (head frame; workpiece mm)
    closed : whether the part bounds a volume (else the head cannot be inside it)
    """

    def __init__(self, head: MeshBodies, part: MeshBodies, closed: bool):
        self.head, self.part, self.closed = head, part, bool(closed)
        v = head.vertices
        self._centre = v.mean(axis=0) if len(v) else np.zeros(3)
        self._radius = float(np.linalg.norm(v - self._centre, axis=1).max()) if len(v) else 0.0
        self._head_lo = v.min(axis=0) if len(v) else np.zeros(3)
        self._head_hi = v.max(axis=0) if len(v) else np.zeros(3)
        self._part_lo = part.lo.min(axis=0) if part.count else np.zeros(3)
        self._part_hi = part.hi.max(axis=0) if part.count else np.zeros(3)

    def __call__(self, c: np.ndarray, r: np.ndarray) -> bool:
        """Whether, with the head's tip at c (3,) and its rotation r (3, 3), a body of the part lies
        inside the head or a body of the head inside the part (exact when no triangles meet)."""
        h, p = self.head, self.part
        return bool(_nested_kernel(
            np.asarray(c, dtype=np.float64), np.asarray(r, dtype=np.float64), self._centre, self._radius,
            self._head_lo, self._head_hi, h.triangles, h.vertices, h.vstart, h.probe,
            p.triangles, p.start, p.probe, p.lo, p.hi, self._part_lo, self._part_hi, self.closed))


def _nested_kernel(c, r, centre, radius, head_lo, head_hi, head_tris, head_verts, head_vstart, head_probe,
                   tris, start, probe, lo, hi, part_lo, part_hi, closed):  # pragma: no cover - compiled
    """``Nested.__call__``'s loops: a head-frame point x is at c + r x in the workpiece."""
    s = SLACK_MM
    # A part body inside the head lies in the head's bounding ball (centre, radius), so in its box.
    wx = c[0] + r[0, 0] * centre[0] + r[0, 1] * centre[1] + r[0, 2] * centre[2]
    wy = c[1] + r[1, 0] * centre[0] + r[1, 1] * centre[1] + r[1, 2] * centre[2]
    wz = c[2] + r[2, 0] * centre[0] + r[2, 1] * centre[1] + r[2, 2] * centre[2]
    reach = radius + s
    for b in range(probe.shape[0]):
        if lo[b, 0] < wx - reach or lo[b, 1] < wy - reach or lo[b, 2] < wz - reach \
                or hi[b, 0] > wx + reach or hi[b, 1] > wy + reach or hi[b, 2] > wz + reach:
            continue
        ex, ey, ez = probe[b, 0] - c[0], probe[b, 1] - c[1], probe[b, 2] - c[2]
        qx = r[0, 0] * ex + r[1, 0] * ey + r[2, 0] * ez
        qy = r[0, 1] * ex + r[1, 1] * ey + r[2, 1] * ez
        qz = r[0, 2] * ex + r[1, 2] * ey + r[2, 2] * ez
        if qx < head_lo[0] - s or qy < head_lo[1] - s or qz < head_lo[2] - s \
                or qx > head_hi[0] + s or qy > head_hi[1] + s or qz > head_hi[2] + s:
            continue
        if _winding(qx, qy, qz, head_tris) > 0.5:
            return True
    if not closed:
        return False
    # A head body inside the part lies in the part's box; its probe's winding number counts the
    # part's bodies whose box holds it (a closed body adds nothing at a point outside its box).
    for g in range(head_probe.shape[0]):
        inside_box = True
        for v in range(head_vstart[g], head_vstart[g + 1]):
            x, y, z = head_verts[v, 0], head_verts[v, 1], head_verts[v, 2]
            px = c[0] + r[0, 0] * x + r[0, 1] * y + r[0, 2] * z
            py = c[1] + r[1, 0] * x + r[1, 1] * y + r[1, 2] * z
            pz = c[2] + r[2, 0] * x + r[2, 1] * y + r[2, 2] * z
            if px < part_lo[0] - s or py < part_lo[1] - s or pz < part_lo[2] - s \
                    or px > part_hi[0] + s or py > part_hi[1] + s or pz > part_hi[2] + s:
                inside_box = False
                break
        if not inside_box:
            continue
        x, y, z = head_probe[g, 0], head_probe[g, 1], head_probe[g, 2]
        px = c[0] + r[0, 0] * x + r[0, 1] * y + r[0, 2] * z
        py = c[1] + r[1, 0] * x + r[1, 1] * y + r[1, 2] * z
        pz = c[2] + r[2, 0] * x + r[2, 1] * y + r[2, 2] * z
        total = 0.0
        for b in range(probe.shape[0]):
            if px < lo[b, 0] - s or py < lo[b, 1] - s or pz < lo[b, 2] - s \
                    or px > hi[b, 0] + s or py > hi[b, 1] + s or pz > hi[b, 2] + s:
                continue
            total += _winding(px, py, pz, tris[start[b]:start[b + 1]])
        if total > 0.5:
            return True
    return False


_nested_kernel = njit(cache=True, nogil=True)(_nested_kernel)
