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

from collections.abc import Collection, Mapping
from dataclasses import dataclass

import coal
import manifold3d
import numpy as np
import trimesh

from ncfix.geometry.distance import winding_numbers

# Boxes that rule out a body widened by this (mm): a vertex moved by a pose is off by ~1e-13 mm.
_BOX_SLACK_MM = 1e-9


def bvh(mesh: trimesh.Trimesh) -> coal.BVHModelOBBRSS:
    """coal's bounding-volume hierarchy of a mesh's triangles."""
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(mesh.faces), len(mesh.vertices))
    model.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    model.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    return model


def body_probes(mesh: trimesh.Trimesh) -> np.ndarray:
    """(k, 3): one vertex of each connected body of a mesh (faces sharing an edge)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(faces))
    first = np.unique(labels, return_index=True)[1]
    return np.asarray(mesh.vertices, dtype=np.float64)[faces[first, 0]]


def in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The points (n, 3) inside the box [lo, hi] widened by _BOX_SLACK_MM."""
    keep = ((points >= lo - _BOX_SLACK_MM) & (points <= hi + _BOX_SLACK_MM)).all(axis=1)
    return points[keep]


@dataclass
class ExactPart:
    name: str
    mesh: trimesh.Trimesh
    bvh: coal.BVHModelOBBRSS
    closed: bool  # bounds a volume (an open part is a surface: nothing is inside it)
    probes: np.ndarray  # (k, 3) one vertex of each connected body


class ExactParts:
    """Exact clearance of a head pose to part meshes.

    head : closed trimesh in the head frame (tip at the origin, axis +Z)
    parts : name -> trimesh in workpiece mm
    open_parts : names of parts that do not bound a volume (surfaces only)
    """

    def __init__(self, head: trimesh.Trimesh, parts: Mapping[str, trimesh.Trimesh], *,
                 open_parts: Collection[str] = ()) -> None:
        self.head = head
        self.head_bvh = bvh(head)
        self._head_triangles = np.asarray(head.triangles, dtype=np.float64)
        self._head_vertices = np.asarray(head.vertices, dtype=np.float64)
        self._head_probes = body_probes(head)
        self._head_lo, self._head_hi = np.array(head.bounds, dtype=np.float64)
        self.parts = [
            ExactPart(name, mesh, bvh(mesh), name not in open_parts, body_probes(mesh))
            for name, mesh in parts.items()
        ]
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
        if len(local) and (winding_numbers(local, self._head_triangles) > 0.5).any():
            return True
        if not part.closed:
            return False
        lo, hi = np.array(part.mesh.bounds, dtype=np.float64)
        world = in_box(c + self._head_probes @ r.T, lo, hi)
        return bool(len(world) and (winding_numbers(world, np.asarray(part.mesh.triangles)) > 0.5).any())

    def _depth(self, part: ExactPart, c: np.ndarray, r: np.ndarray) -> float:
        """Deepest head vertex inside the part / part vertex inside the head (mm, >= 0)."""
        depth = 0.0
        head_world = c + self._head_vertices @ r.T
        inside = part.mesh.contains(head_world) if part.closed else np.zeros(len(head_world), dtype=bool)
        if inside.any():
            depth = max(depth, self._distance_to(part.bvh, head_world[inside]).max())
        lo, hi = head_world.min(axis=0), head_world.max(axis=0)
        pv = np.asarray(part.mesh.vertices)
        near = pv[((pv >= lo) & (pv <= hi)).all(axis=1)]
        if len(near):
            local = (near - c) @ r
            inside = self.head.contains(local)
            if inside.any():
                depth = max(depth, self._distance_to(self.head_bvh, local[inside]).max())
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


def clip_head(head: trimesh.Trimesh, height_mm: float) -> trimesh.Trimesh:
    """The head above z = height_mm (head frame), capped so it stays a closed solid (manifold3d)."""
    if height_mm <= float(head.bounds[0, 2]):
        return head
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
