"""Exact tests of head poses against part meshes: the checker's last word on a pose and the
clearances its report gives. ``ncfix.reference`` (the tests' oracle) adds the bead tests on top.

A pose collides when a head triangle meets a part triangle (coal BVH mesh-vs-mesh), or when a body
lies wholly inside the other mesh: mesh-mesh collision tests triangles only, so each connected body
of the part and of the head is tested on its own, one vertex of it by its generalised winding
number with respect to the whole other mesh (a body in a hollow part's cavity is outside it). An
open part (``open_parts``) has no inside: only its bodies inside the head count. Separated poses get
the exact mesh-to-mesh distance; colliding ones a lower bound on the penetration (only its sign is
exact). Poses: tip at C (workpiece mm), rotation R (3, 3); a head-frame point x is at C + R @ x.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import coal
import manifold3d
import numpy as np
from numba import njit

from ncfix import cache
from ncfix.collision.near import _winding
from ncfix.geometry.meshdata import Mesh, as_mesh, component_labels, mesh_arrays

if TYPE_CHECKING:
    import trimesh

# Boxes that rule out a body widened by this (mm): a vertex moved by a pose is off by ~1e-13 mm.
_BOX_SLACK_MM = 1e-9


def bvh(mesh: Mesh | trimesh.Trimesh) -> coal.BVHModelOBBRSS:
    """coal's bounding-volume hierarchy of a mesh's triangles."""
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(mesh.faces), len(mesh.vertices))
    model.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    model.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    return model


def body_probes(mesh: Mesh | trimesh.Trimesh) -> np.ndarray:
    """(k, 3): one vertex of each connected body of a mesh (faces sharing an edge)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    labels = component_labels(faces)
    first = np.unique(labels, return_index=True)[1]
    return np.asarray(mesh.vertices, dtype=np.float64)[faces[first, 0]]


def in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The points (n, 3) inside the box [lo, hi] widened by _BOX_SLACK_MM."""
    keep = ((points >= lo - _BOX_SLACK_MM) & (points <= hi + _BOX_SLACK_MM)).all(axis=1)
    return points[keep]


def _windings(points, triangles):  # pragma: no cover - compiled
    """Generalised winding number of each point (n, 3) with respect to the triangles (m, 3, 3)."""
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        out[i] = _winding(points[i, 0], points[i, 1], points[i, 2], triangles)
    return out


_windings = njit(cache=True, nogil=True)(_windings)


def inside(points: np.ndarray, triangles: np.ndarray, bounds: np.ndarray,
           maybe: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(n,) bool: which points (n, 3) lie inside the closed mesh of these triangles (m, 3, 3):
    winding number above one half. A point on or outside the mesh's box (2, 3) is outside, as is
    one ``maybe`` (points -> (n,) bool) rules out: only a point that can be inside is tested."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = np.asarray(bounds, dtype=np.float64)
    test = ((points > lo) & (points < hi)).all(axis=1)
    if maybe is not None and test.any():
        test[test] = maybe(points[test])
    out = np.zeros(len(points), dtype=bool)
    if test.any():
        out[test] = _windings(np.ascontiguousarray(points[test]), np.ascontiguousarray(triangles)) > 0.5
    return out


@dataclass
class ExactPart:
    name: str
    mesh: Mesh
    bvh: coal.BVHModelOBBRSS
    closed: bool  # bounds a volume (an open part is a surface: nothing is inside it)
    probes: np.ndarray  # (k, 3) one vertex of each connected body
    triangles: np.ndarray  # (m, 3, 3) float64
    bounds: np.ndarray  # (2, 3) float64
    # points (n, 3) -> (n,) bool, False where a point is certainly outside (a distance bound), or None
    maybe_inside: Callable[[np.ndarray], np.ndarray] | None = None


class ExactParts:
    """Exact clearance of a head pose to part meshes.

    head : closed mesh in the head frame (tip at the origin, axis +Z; a ``Mesh`` or a trimesh)
    parts : name -> mesh in workpiece mm
    open_parts : names of parts that do not bound a volume (surfaces only)
    maybe_inside : name -> points (n, 3) -> (n,) bool, False for points certainly outside that
        part (its distance grid's bound above zero); only a speed-up of the depth's inside test
    """

    def __init__(self, head: Mesh | trimesh.Trimesh, parts: Mapping[str, Mesh | trimesh.Trimesh], *, open_parts: Collection[str] = (),
                 maybe_inside: Mapping[str, Callable[[np.ndarray], np.ndarray]] | None = None) -> None:
        head = as_mesh(head)
        self.head = head
        self.head_bvh = bvh(head)
        self._head_triangles = np.asarray(head.triangles, dtype=np.float64)
        self._head_vertices = np.asarray(head.vertices, dtype=np.float64)
        self._head_probes = body_probes(head)
        self._head_bounds = np.array(head.bounds, dtype=np.float64)
        self._head_lo, self._head_hi = self._head_bounds
        maybe_inside = maybe_inside or {}
        self.parts = []
        for name, mesh in parts.items():
            mesh = as_mesh(mesh)
            self.parts.append(ExactPart(name, mesh, bvh(mesh), name not in open_parts, body_probes(mesh),
                                        np.asarray(mesh.triangles, dtype=np.float64),
                                        np.array(mesh.bounds, dtype=np.float64), maybe_inside.get(name)))
        self._dreq = coal.DistanceRequest()
        self.collision_request = coal.CollisionRequest()

    def part_clearances(self, tip_mm: np.ndarray, rotation: np.ndarray) -> dict[str, float]:
        """Signed clearance (mm; negative = overlap) of one pose to each part."""
        c = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        head_tf = coal.Transform3s(r, c)
        identity = coal.Transform3s()
        out: dict[str, float] = {}
        for part in self.parts:
            cres = coal.CollisionResult()
            hit = coal.collide(self.head_bvh, head_tf, part.bvh, identity, self.collision_request, cres) > 0
            if not hit:
                hit = self._contained(part, c, r)
            if hit:
                out[part.name] = -self._depth(part, c, r)
            else:
                dres = coal.DistanceResult()
                out[part.name] = float(
                    coal.distance(self.head_bvh, head_tf, part.bvh, identity, self._dreq, dres)
                )
        return out

    def clearance(self, tip_mm: np.ndarray, rotation: np.ndarray, *, margin_mm: float = 0.0) -> tuple[float, list[str]]:
        """(min signed clearance over parts in mm, names of parts closer than ``margin_mm``)."""
        per_part = self.part_clearances(tip_mm, rotation)
        if not per_part:
            return float("inf"), []
        hit = [name for name, d in per_part.items() if d < margin_mm]
        return min(per_part.values()), hit

    def clearances(
        self, tips_mm: np.ndarray, rotations: np.ndarray, *, margin_mm: float = 0.0
    ) -> tuple[np.ndarray, list[list[str]]]:
        """Batched ``clearance``: tips (n, 3), rotations (n, 3, 3) -> (n,) float64 mm, n name lists."""
        tips = np.asarray(tips_mm, dtype=np.float64).reshape(-1, 3)
        rots = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        values = np.empty(len(tips))
        names: list[list[str]] = []
        for i in range(len(tips)):
            values[i], hit = self.clearance(tips[i], rots[i], margin_mm=margin_mm)
            names.append(hit)
        return values, names

    def collides(self, tip_mm: np.ndarray, rotation: np.ndarray) -> bool:
        """Exact yes/no: does the head at this pose overlap (or touch) any part?"""
        c = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        head_tf = coal.Transform3s(r, c)
        identity = coal.Transform3s()
        for part in self.parts:
            cres = coal.CollisionResult()
            if coal.collide(self.head_bvh, head_tf, part.bvh, identity, self.collision_request, cres) > 0:
                return True
            if self._contained(part, c, r):
                return True
        return False

    def _contained(self, part: ExactPart, c: np.ndarray, r: np.ndarray) -> bool:
        """With no triangle pair meeting: whether a body of the part lies inside the head, or a
        body of the head inside the part (one vertex of each body, by its winding number with
        respect to the whole other mesh; a vertex outside the other's box is outside it)."""
        local = in_box((part.probes - c) @ r, self._head_lo, self._head_hi)
        if len(local) and (_windings(np.ascontiguousarray(local), self._head_triangles) > 0.5).any():
            return True
        if not part.closed:
            return False
        lo, hi = part.bounds
        world = in_box(c + self._head_probes @ r.T, lo, hi)
        return bool(len(world) and (_windings(np.ascontiguousarray(world), part.triangles) > 0.5).any())

    def _depth(self, part: ExactPart, c: np.ndarray, r: np.ndarray) -> float:
        """Deepest head vertex inside the part / part vertex inside the head (mm, >= 0)."""
        depth = 0.0
        head_world = c + self._head_vertices @ r.T
        if part.closed:
            within = inside(head_world, part.triangles, part.bounds, part.maybe_inside)
        else:
            within = np.zeros(len(head_world), dtype=bool)
        if within.any():
            depth = max(depth, self._distance_to(part.bvh, head_world[within]).max())
        lo, hi = head_world.min(axis=0), head_world.max(axis=0)
        pv = np.asarray(part.mesh.vertices)
        near = pv[((pv >= lo) & (pv <= hi)).all(axis=1)]
        if len(near):
            local = (near - c) @ r
            within = inside(local, self._head_triangles, self._head_bounds)
            if within.any():
                depth = max(depth, self._distance_to(self.head_bvh, local[within]).max())
        return float(depth)

    def _distance_to(self, model: coal.BVHModelOBBRSS, points: np.ndarray) -> np.ndarray:
        probe = coal.Sphere(1e-9)
        identity = coal.Transform3s()
        out = np.empty(len(points))
        for i, p in enumerate(points):
            dres = coal.DistanceResult()
            out[i] = coal.distance(
                probe, coal.Transform3s(np.eye(3), p), model, identity, self._dreq, dres
            )
        return np.abs(out)


def clip_head(head: Mesh | trimesh.Trimesh, height_mm: float) -> trimesh.Trimesh:
    """The head above z = height_mm (head frame), capped so it stays a closed solid (manifold3d)."""
    import trimesh

    if height_mm <= float(head.bounds[0, 2]):
        return head if isinstance(head, trimesh.Trimesh) else head.to_trimesh()
    solid = manifold3d.Manifold(
        manifold3d.Mesh64(
            vert_properties=np.asarray(head.vertices, dtype=np.float64),
            tri_verts=np.asarray(head.faces, dtype=np.uint64),
        )
    )
    if solid.status() != manifold3d.Error.NoError:
        raise ValueError(f"the head mesh is not a closed manifold solid ({solid.status()})")
    kept = solid.trim_by_plane((0.0, 0.0, 1.0), float(height_mm)).to_mesh64()
    faces = np.asarray(kept.tri_verts, dtype=np.int64)
    if len(faces) == 0:
        raise ValueError(f"the tip allowance {height_mm} mm removes the whole head")
    return trimesh.Trimesh(np.asarray(kept.vert_properties[:, :3], dtype=np.float64), faces)


# The code the clipped head comes from.
CLIP_SOURCES = ("ncfix.collision.exact", "ncfix.geometry.meshdata")


def cached_clip_head(head, height_mm: float, cache_dir: str | None = None) -> Mesh:
    """``clip_head``'s mesh as arrays, read from the on-disk cache when this head was clipped at
    this height before (trimesh's processing of the capped mesh is then not imported)."""
    head = as_mesh(head)
    key = cache.make_key("clip", head.vertices, head.faces, float(height_mm), cache.fingerprint(*CLIP_SOURCES),
                         {package: cache.version(package) for package in ("numpy", "trimesh", "manifold3d")})

    def from_arrays(a: dict[str, np.ndarray]) -> Mesh | None:
        v, f = a["vertices"], a["faces"]
        return Mesh(v, f) if mesh_arrays(v, f) else None

    clipped, _ = cache.cached("clip", key, ("vertices", "faces"), lambda: as_mesh(clip_head(head, height_mm)),
                              lambda m: {"vertices": m.vertices, "faces": m.faces}, from_arrays, cache_dir)
    return clipped
