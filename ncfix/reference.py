"""Exact reference check of head poses against part meshes and deposited beads (tests, benchmarks).

Parts: ``ncfix.collision.exact``, the checker's own exact test (coal BVH mesh-vs-mesh, and each
connected body tested for lying wholly inside the other mesh, so the yes/no answer is exact);
beads: spheres, checked analytically against the head clipped at the tip allowance, apart from
the checker's bead kernels. Poses follow docs/contract.md: tip at C (workpiece mm), rotation R
with R @ (0, 0, 1) = N. ``label_program`` reads a whole program with its own deposit loop.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import coal
import numpy as np
import trimesh

from ncfix.collision.deposit import (LOOP_PROBE, LOOP_RATIO, LOOP_SPACING_MIN, BeadShape, axial_moves, held_radius,
                                     loop_samples, strand_along, strand_at_rest)
from ncfix.collision.exact import ExactParts, bvh, clip_head
from ncfix.collision.plough import ploughing_moves
from ncfix.geometry.distance import point_mesh_distance, winding_numbers
from ncfix.kinematics.poses import PoseMap
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile


class ExactReference(ExactParts):
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
    ) -> None:
        super().__init__(head, parts, open_parts=open_parts)
        self.tip_allowance_mm = float(tip_allowance_mm)
        self._bead_head = clip_head(head, self.tip_allowance_mm)
        self._bead_triangles = np.asarray(self._bead_head.triangles, dtype=np.float64)
        self._bead_bvh = bvh(self._bead_head)
        hull = self._bead_head.convex_hull
        self._hull_normals = np.asarray(hull.face_normals, dtype=np.float64)
        self._hull_offsets = np.einsum("ij,ij->i", self._hull_normals, np.asarray(hull.triangles)[:, 0])

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
            if coal.collide(self._bead_bvh, identity, sphere, coal.Transform3s(np.eye(3), point), self.collision_request, result):
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
    the rule of docs/contract.md (E words: E grows; else between the deposit codes; else every feed move); each
    pose is checked against
    the beads laid before it, including the move that ends at it, as spheres ``bead_spacing_mm``
    apart along the path through P, each ``bead_drop_mm`` below it along the tool axis; a move
    along the axis (``deposit.axial_moves``) or one that ploughs through its own extrudate
    (``plough.ploughing_moves``) lays one, at its lower end. A move whose tip runs a
    path LOOP_RATIO times its programmed length or longer (TCP off: the axes move linearly, P
    does not) lays a thinner strand along the tip's path (``deposit.strand_along``, the sphere
    radius ``deposit.held_radius``; bead_shape: the stated bead, default round of the radius).
    """
    profile = load_profile(machine)
    ref = ExactReference(head, parts, tip_allowance_mm=tip_allowance_mm)
    interpreter = Interpreter(profile, path, deposit_codes, compiled_reader=True)  # one chunk: see cost.program_vectors
    with open(path, "rb") as handle:
        chunk = interpreter.feed_chunk(handle.readlines(), 1)
    moving = np.flatnonzero(chunk.motion >= 0)
    poses = PoseMap(profile)
    tcp = poses.tcp(chunk, moving)
    words = chunk.words[moving]
    p, n, r = poses.forward(words, tcp)
    has_e = not np.isnan(chunk.e_delta).all()
    head_triangles = np.asarray(head.triangles, dtype=np.float64)
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
            ploughs = ploughing_moves(head_triangles, (previous + standoff_mm * n0)[None],
                                      (p[row] + standoff_mm * n1)[None], r[row - 1][None], r[row][None])[0]
            lower_end = axial_moves(previous[None], p[row][None], n0[None], n1[None])[0] or ploughs
            if lower_end:
                low = row if float((p[row] - previous) @ (n0 + n1)) < 0 else row - 1
                laid = (p[low] - bead_drop_mm * n[low])[None]
            else:
                laid = bead_centres(previous, p[row], bead_spacing_mm)
                t = np.linspace(0.0, 1.0, len(laid))[:, None]
                axis = n0 + t * (n1 - n0)
                laid = laid - bead_drop_mm * axis / np.linalg.norm(axis, axis=1, keepdims=True)
            rad = np.full(len(laid), bead_radius_mm)
            chord = float(np.linalg.norm(p[row] - previous))
            if not profile.is_vector and chunk.motion[i] == 1 and chord > 0 and not lower_end:
                probe = np.linalg.norm(np.diff(tip_path(row, LOOP_PROBE)[0], axis=0), axis=1).sum()
                if probe > LOOP_RATIO * chord:
                    pp, _, t = tip_path(row, loop_samples(probe))
                    got = strand_along(pp, t, chord, shape, bead_spacing_mm)
                    if got is not None:
                        tb, strand, drop = got
                        w = words[row - 1][None] + tb[:, None] * (words[row] - words[row - 1])[None]
                        pb, nb, _ = profile.kinematics.forward(w, tcp=bool(tcp[row]))
                        thin = pb - drop * nb
                        if held_radius(strand, thin, bead_radius_mm) < bead_radius_mm:
                            up = profile.kinematics.vertical(0.5 * (words[row - 1] + words[row]))
                            step = min(bead_spacing_mm, max(strand, LOOP_SPACING_MIN * bead_spacing_mm))
                            lowered, taut = strand_at_rest(thin, up[0], step)
                            rest = np.concatenate([lowered, taut])
                            held = max(held_radius(strand, lowered, bead_radius_mm),
                                       held_radius(strand, taut, bead_radius_mm))
                            laid, rad = rest, np.full(len(rest), held)
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
