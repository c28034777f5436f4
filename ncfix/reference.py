"""Exact reference check of head poses against part meshes and deposited beads (tests, benchmarks).

Parts: coal BVH mesh-vs-mesh. A pose collides when a head triangle meets a part triangle, or when
a body lies wholly inside the other mesh: mesh-mesh collision tests triangles only, so each
connected body of the part (a mesh may hold several: fixtures, parts exported together) and of
the head is tested on its own, one vertex of it by its generalised winding number with respect
to the whole other mesh (a body in a hollow part's cavity is outside it). With no triangles
meeting, a body lies wholly inside or wholly outside, so the yes/no answer is exact. An open part
(``open_parts``) has no inside: only its bodies inside the head count. Separated poses get the
exact mesh-to-mesh distance. For colliding poses the negative number is the deepest penetration
found: the deepest head vertex inside a part and the deepest part vertex inside the head. It is
a lower bound on the true penetration depth (which is not well defined for non-convex bodies);
only its sign is exact.

Beads: spheres, checked analytically against the head above the tip allowance (the head clipped
by the plane z = tip_allowance_mm in the head frame with manifold3d, so it stays a closed solid).

Poses follow the CONTRACT: tip at C (workpiece mm), rotation R (3, 3) with R @ (0, 0, 1) = N;
a head-frame point x is at C + R @ x in the workpiece.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass

import coal
import numpy as np
import trimesh

from ncfix.geometry.distance import point_mesh_distance, winding_numbers

# Boxes that rule out a body widened by this (mm): a vertex moved by a pose is off by ~1e-13 mm.
_BOX_SLACK_MM = 1e-9


def _bvh(mesh: trimesh.Trimesh) -> coal.BVHModelOBBRSS:
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(mesh.faces), len(mesh.vertices))
    model.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    model.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    return model


def _body_probes(mesh: trimesh.Trimesh) -> np.ndarray:
    """(k, 3): one vertex of each connected body of a mesh (faces sharing an edge)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(faces))
    first = np.unique(labels, return_index=True)[1]
    return np.asarray(mesh.vertices, dtype=np.float64)[faces[first, 0]]


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The points (n, 3) inside the box [lo, hi] widened by _BOX_SLACK_MM."""
    keep = ((points >= lo - _BOX_SLACK_MM) & (points <= hi + _BOX_SLACK_MM)).all(axis=1)
    return points[keep]


@dataclass
class _Part:
    name: str
    mesh: trimesh.Trimesh
    bvh: coal.BVHModelOBBRSS
    closed: bool  # bounds a volume (an open part is a surface: nothing is inside it)
    probes: np.ndarray  # (k, 3) one vertex of each connected body


class ExactReference:
    """Exact clearance of a head pose to part meshes and to bead spheres.

    head : closed trimesh in the head frame (tip at the origin, axis +Z)
    parts : name -> trimesh in workpiece mm
    tip_allowance_mm : the head below this height is not checked against beads
    open_parts : names of parts that do not bound a volume (surfaces only)
    """

    def __init__(
        self,
        head: trimesh.Trimesh,
        parts: Mapping[str, trimesh.Trimesh],
        *,
        tip_allowance_mm: float = 1.0,
        open_parts: Collection[str] = (),
    ):
        self.head = head
        self._head_bvh = _bvh(head)
        self._head_triangles = np.asarray(head.triangles, dtype=np.float64)
        self._head_vertices = np.asarray(head.vertices, dtype=np.float64)
        self._head_probes = _body_probes(head)
        self._head_lo, self._head_hi = np.array(head.bounds, dtype=np.float64)
        self.parts = [
            _Part(name, mesh, _bvh(mesh), name not in open_parts, _body_probes(mesh))
            for name, mesh in parts.items()
        ]
        self.tip_allowance_mm = float(tip_allowance_mm)
        self._bead_head = _clip_head(head, self.tip_allowance_mm)
        self._bead_triangles = np.asarray(self._bead_head.triangles, dtype=np.float64)
        self._bead_bvh = _bvh(self._bead_head)
        hull = self._bead_head.convex_hull
        self._hull_normals = np.asarray(hull.face_normals, dtype=np.float64)
        self._hull_offsets = np.einsum("ij,ij->i", self._hull_normals, np.asarray(hull.triangles)[:, 0])
        self._dreq = coal.DistanceRequest()
        self._creq = coal.CollisionRequest()

    # ---- parts ---------------------------------------------------------------------------

    def part_clearances(self, tip_mm: np.ndarray, rotation: np.ndarray) -> dict[str, float]:
        """Signed clearance (mm; negative = overlap) of one pose to each part."""
        c = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        head_tf = coal.Transform3s(r, c)
        identity = coal.Transform3s()
        out: dict[str, float] = {}
        for part in self.parts:
            cres = coal.CollisionResult()
            hit = coal.collide(self._head_bvh, head_tf, part.bvh, identity, self._creq, cres) > 0
            if not hit:
                hit = self._contained(part, c, r)
            if hit:
                out[part.name] = -self._depth(part, c, r)
            else:
                dres = coal.DistanceResult()
                out[part.name] = float(
                    coal.distance(self._head_bvh, head_tf, part.bvh, identity, self._dreq, dres)
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
            if coal.collide(self._head_bvh, head_tf, part.bvh, identity, self._creq, cres) > 0:
                return True
            if self._contained(part, c, r):
                return True
        return False

    def _contained(self, part: _Part, c: np.ndarray, r: np.ndarray) -> bool:
        """With no triangle pair meeting: whether a body of the part lies inside the head, or a
        body of the head inside the part (one vertex of each body, by its winding number with
        respect to the whole other mesh; a vertex outside the other's box is outside it)."""
        local = _in_box((part.probes - c) @ r, self._head_lo, self._head_hi)
        if len(local) and (winding_numbers(local, self._head_triangles) > 0.5).any():
            return True
        if not part.closed:
            return False
        lo, hi = np.array(part.mesh.bounds, dtype=np.float64)
        world = _in_box(c + self._head_probes @ r.T, lo, hi)
        return bool(len(world) and (winding_numbers(world, np.asarray(part.mesh.triangles)) > 0.5).any())

    def _depth(self, part: _Part, c: np.ndarray, r: np.ndarray) -> float:
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
                depth = max(depth, self._distance_to(self._head_bvh, local[inside]).max())
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

    # ---- beads ---------------------------------------------------------------------------

    def bead_clearance(
        self,
        tip_mm: np.ndarray,
        rotation: np.ndarray,
        centers_mm: np.ndarray,
        radius_mm: float,
    ) -> float:
        """Signed clearance (mm; negative = overlap) between the head above the tip allowance and
        bead spheres.

        centers_mm : (m, 3) float64, bead sphere centres, workpiece mm
        returns : min over beads of (signed distance from centre to the clipped head) - radius;
        +inf when there are no beads. Exact: beads are visited nearest first until no remaining
        bead can be closer than the best found.
        """
        centers = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        if len(centers) == 0:
            return float("inf")
        c = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        local = (centers - c) @ r
        # The signed distance to the clipped head's box bounds the signed distance to the head
        # from below (the head lies in its box: outside it is nearer, inside it is shallower).
        box_lo, box_hi = self._bead_head.bounds
        gap = np.maximum(box_lo - local, local - box_hi)
        outside = np.linalg.norm(np.maximum(gap, 0.0), axis=1)
        lower = np.where(gap.max(axis=1) > 0.0, outside, gap.max(axis=1)) - radius_mm
        order = np.argsort(lower)
        best = np.inf
        step = 64
        for start in range(0, len(order), step):
            block = order[start : start + step]
            if lower[block[0]] >= best:
                break
            signed = self.signed_distance_to_clipped_head(local[block])
            best = min(best, float((signed - radius_mm).min()))
        return best

    def bead_collides(self, tip_mm: np.ndarray, rotation: np.ndarray, centers_mm: np.ndarray,
                      radius_mm) -> bool:
        """Whether any bead sphere overlaps the head above the tip allowance (exact, early exit).
        ``radius_mm``: one radius for every bead, or each bead's (m,).

        A bead farther than its radius outside one face plane of the clipped head's convex hull
        cannot touch the head; the others are tested exactly: coal sphere-vs-mesh for contact
        with the surface, then a containment test for a bead wholly inside the head.
        """
        centers = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
        if len(centers) == 0:
            return False
        c = np.asarray(tip_mm, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        local = (centers - c) @ r
        outside = (local @ self._hull_normals.T - self._hull_offsets).max(axis=1)
        radii = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), (len(centers),))
        close = outside < radii
        near, near_r = local[close], radii[close]
        if len(near) == 0:
            return False
        identity = coal.Transform3s()
        spheres: dict = {}
        for point, rad in zip(near, near_r):
            sphere = spheres.get(float(rad))
            if sphere is None:
                sphere = spheres[float(rad)] = coal.Sphere(float(rad))
            result = coal.CollisionResult()
            if coal.collide(self._bead_bvh, identity, sphere, coal.Transform3s(np.eye(3), point), self._creq, result):
                return True
        inside = winding_numbers(near[outside[close] < -near_r], self._bead_triangles) > 0.5
        return bool(inside.any())

    def signed_distance_to_clipped_head(self, points_head_mm: np.ndarray) -> np.ndarray:
        """Signed distance (positive outside) from head-frame points (n, 3) to the bead-checked head."""
        pts = np.asarray(points_head_mm, dtype=np.float64).reshape(-1, 3)
        unsigned = point_mesh_distance(pts, self._bead_triangles)
        inside = winding_numbers(pts, self._bead_triangles) > 0.5
        return np.where(inside, -unsigned, unsigned)

    def bead_clearances(
        self, tips_mm: np.ndarray, rotations: np.ndarray, centers_mm: np.ndarray, radius_mm: float
    ) -> np.ndarray:
        """Batched ``bead_clearance`` for poses (n, 3)/(n, 3, 3) against one bead set -> (n,)."""
        tips = np.asarray(tips_mm, dtype=np.float64).reshape(-1, 3)
        rots = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        return np.array([self.bead_clearance(t, q, centers_mm, radius_mm) for t, q in zip(tips, rots)])


def _clip_head(head: trimesh.Trimesh, height_mm: float) -> trimesh.Trimesh:
    """The head above z = height_mm (head frame), capped so it stays a closed solid (manifold3d)."""
    if height_mm <= float(head.bounds[0, 2]):
        return head
    import manifold3d

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


def bead_centres(start_mm: np.ndarray, end_mm: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Sphere centres (m, 3) along one deposited move, ``spacing_mm`` apart at most, both ends kept."""
    start = np.asarray(start_mm, dtype=np.float64)
    end = np.asarray(end_mm, dtype=np.float64)
    steps = max(1, int(np.ceil(np.linalg.norm(end - start) / spacing_mm)))
    t = np.linspace(0.0, 1.0, steps + 1)[:, None]
    return start + (end - start) * t


def label_program(
    path: str,
    machine: str,
    head: trimesh.Trimesh,
    parts: Mapping[str, trimesh.Trimesh],
    *,
    standoff_mm: float = 6.0,
    bead_radius_mm: float = 1.0,
    tip_allowance_mm: float = 1.0,
    bead_spacing_mm: float = 0.25,
    deposit_codes: tuple[str, str] | None = None,
    bead_drop_mm: float = 0.0,
    bead_shape=None,
) -> list[tuple[int, list[str]]]:
    """The exact answer for a program: (line, bodies) of every motion block whose pose collides.

    Poses at the programmed orientation (tip C = P + h·N, rotation from the profile). Deposit by
    the CONTRACT rule (E words: E grows; else between the deposit codes; else every feed move); each
    pose is checked against
    the beads laid before it, including the move that ends at it, as spheres ``bead_spacing_mm``
    apart along the path through P, each ``bead_drop_mm`` below it along the tool axis; a move
    along the axis (``deposit.axial_moves``) lays one, at its lower end. A move whose tip runs a
    path LOOP_RATIO times its programmed length or longer (TCP off: the axes move linearly, P
    does not) lays a thinner strand along the tip's path (``deposit.strand_along``, the sphere
    radius ``deposit.held_radius``; bead_shape: the stated bead, default round of the radius).
    """
    from ncfix.collision.deposit import (LOOP_PROBE, LOOP_RATIO, BeadShape, axial_moves, held_radius, loop_samples,
                                         strand_along)
    from ncfix.nc.modal import Interpreter
    from ncfix.profiles import load_profile

    profile = load_profile(machine)
    ref = ExactReference(head, parts, tip_allowance_mm=tip_allowance_mm)
    interpreter = Interpreter(profile, path, deposit_codes)
    with open(path, "rb") as handle:
        chunk = interpreter.feed_chunk(handle.readlines(), 1)
    moving = np.flatnonzero(chunk.motion >= 0)
    if profile.tcp == "program":
        tcp = chunk.tcp[moving]
    else:
        tcp = np.full(len(moving), profile.tcp != "never")
    words = chunk.words[moving]
    p = np.empty((len(moving), 3))
    n = np.empty((len(moving), 3))
    r = np.empty((len(moving), 3, 3))
    for flag in (True, False):
        sel = tcp == flag
        if sel.any():
            p[sel], n[sel], r[sel] = profile.kinematics.forward(words[sel], tcp=bool(flag))
    has_e = not np.isnan(chunk.e_delta).all()
    shape = bead_shape if bead_shape is not None else BeadShape(2.0 * bead_radius_mm, 2.0 * bead_radius_mm,
                                                                 bead_drop_mm)

    def tip_path(row: int, samples: int):
        """P and N at even steps of the move into ``row``, the words moving linearly."""
        t = np.arange(samples + 1) / samples
        w = words[row - 1][None] + t[:, None] * (words[row] - words[row - 1])[None]
        pp, nn, _ = profile.kinematics.forward(w, tcp=bool(tcp[row]))
        return pp, nn, t

    beads = np.zeros((0, 3))
    radii = np.zeros(0)
    out = []
    previous = None
    for row, i in enumerate(moving):
        feed = chunk.motion[i] >= 1
        if has_e:
            deposits = feed and chunk.e_delta[i] > 0
        elif deposit_codes:
            deposits = feed and chunk.deposit_on[i] == 1
        else:
            deposits = feed
        if deposits and previous is not None and bead_radius_mm > 0:
            n0, n1 = n[row - 1], n[row]
            if axial_moves(previous[None], p[row][None], n0[None], n1[None])[0]:
                low = row if float((p[row] - previous) @ (n0 + n1)) < 0 else row - 1
                laid = (p[low] - bead_drop_mm * n[low])[None]
            else:
                laid = bead_centres(previous, p[row], bead_spacing_mm)
                t = np.linspace(0.0, 1.0, len(laid))[:, None]
                axis = n0 + t * (n1 - n0)
                laid = laid - bead_drop_mm * axis / np.linalg.norm(axis, axis=1, keepdims=True)
            rad = np.full(len(laid), bead_radius_mm)
            chord = float(np.linalg.norm(p[row] - previous))
            if not profile.is_vector and chunk.motion[i] == 1 and chord > 0 and \
                    not axial_moves(previous[None], p[row][None], n0[None], n1[None])[0]:
                probe = np.linalg.norm(np.diff(tip_path(row, LOOP_PROBE)[0], axis=0), axis=1).sum()
                if probe > LOOP_RATIO * chord:
                    pp, _, t = tip_path(row, loop_samples(probe))
                    got = strand_along(pp, t, chord, shape, bead_spacing_mm)
                    if got is not None:
                        tb, strand, drop = got
                        w = words[row - 1][None] + tb[:, None] * (words[row] - words[row - 1])[None]
                        pb, nb, _ = profile.kinematics.forward(w, tcp=bool(tcp[row]))
                        thin = pb - drop * nb
                        held = held_radius(strand, thin, bead_radius_mm)
                        if held < bead_radius_mm:
                            laid, rad = thin, np.full(len(thin), held)
            beads = np.vstack([beads, laid])
            radii = np.concatenate([radii, rad])
        previous = p[row]
        tip = p[row] + standoff_mm * n[row]
        bodies = [f"part:{name}" for name, value in ref.part_clearances(tip, r[row]).items() if value < 0]
        if len(beads) and bead_radius_mm > 0 and ref.bead_collides(tip, r[row], beads, radii):
            bodies.append("deposit")
        if bodies:
            out.append((chunk.first_lineno + int(i), bodies))
    return out
