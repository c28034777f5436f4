"""The seed's EPA correction: tilt the head about its tip along the GJK/EPA extraction vector.

The parts are cut into convex pieces (``decompose``), the head is its convex hull; coal's GJK/EPA
gives each overlapping piece's penetration, their weighted sum the extraction vector E, and the
tool vector is turned about the tip toward E until the caller's conservative checker accepts it.
The hull model only steers: every orientation returned passed that checker, so the answer is as
safe as it is. Design and its approximations: docs/correction.md (``--strategy epa``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

from typing import TYPE_CHECKING

import coal
import numpy as np
from numba import njit

from ncfix import cache
from ncfix.collision.near import tri_closest
from ncfix.correct.decompose import Decomposition, decompose
from ncfix.geometry.frames import angle_between_deg, axis_rotation
from ncfix.geometry.meshdata import Mesh, as_mesh, as_trimesh, mesh_arrays

if TYPE_CHECKING:
    import trimesh

RotationOf = Callable[[np.ndarray], np.ndarray]
IsFree = Callable[[np.ndarray], np.ndarray]
# A tilt walk driven by its caller (``EpaModel.tilt_steps``): yields batches, is sent their answers.
TiltWalk = Generator[np.ndarray, np.ndarray, "TiltResult"]

VARIANTS = ("fixed", "lami")
# Orientations handed to ``is_free`` per call: the walk's next steps, or one fallback ring.
_BATCH = 8
# Fallback ring: azimuths tried at each tilt when the hull model gives no usable direction.
_RING_AZIMUTHS = 8
# The "lami" path may bend back toward N0; it stops after this many times max_tilt / step.
_LAMI_STEP_FACTOR = 4
# Directions shorter than this (mm) are "none": no penetration, or E parallel to N.
_TINY = 1e-12


@dataclass
class Extraction:
    """The extraction vector of one pose.

    vector : (3,) float64, workpiece frame, mm: moves the head out (zero when nothing penetrates)
    depth_mm : the largest single penetration depth found (0 when none)
    bodies : names of the penetrated parts (as given to EpaModel), then "deposit" for beads
    """

    vector: np.ndarray
    depth_mm: float
    bodies: list[str] = field(default_factory=list)


@dataclass
class TiltResult:
    """The outcome of one tilt search.

    normal : (3,) float64 unit tool vector accepted by ``is_free``, or None when none was found
        within max_tilt
    tilt_deg : angle from N0 to ``normal``; when normal is None, the largest tilt tried
    iterations : orientations tried, up to and including the answer
    bodies : bodies the hull model found penetrated at N0
    """

    normal: np.ndarray | None
    tilt_deg: float
    iterations: int
    bodies: list[str]


class EpaModel:
    """Convex-hull model of a head and parts for GJK/EPA extraction vectors and tilts.

    head_mesh : closed mesh (``Mesh`` or trimesh) in the head frame (tip at the origin, axis +Z);
        its hulls are cached (``_head_hulls``)
    parts : (name, closed mesh in workpiece mm) pairs, decomposed with CoACD (cached)
    threshold, cache_dir : passed to ``decompose``
    bead_radius_mm : radius of the bead spheres given to ``extraction_vector``/``tilt``
    tip_allowance_mm : the head below this height (head frame) is not tested against beads
    """

    def __init__(
        self,
        head_mesh: trimesh.Trimesh | Mesh,
        parts: list[tuple[str, trimesh.Trimesh | Mesh]],
        *,
        threshold: float = 0.05,
        cache_dir: str | Path | None = None,
        bead_radius_mm: float = 1.0,
        tip_allowance_mm: float = 1.0,
    ):
        hulls = _head_hulls(as_mesh(head_mesh), float(tip_allowance_mm), cache_dir)
        hull = Mesh(hulls["hull_vertices"], hulls["hull_faces"])
        self._head_points = hull.vertices
        # No head point is farther from the tip: callers gather the beads within this (plus a radius).
        self.head_reach_mm = float(np.linalg.norm(self._head_points, axis=1).max())
        self._head_normals = np.ascontiguousarray(hulls["hull_normals"], dtype=np.float64)
        self._head_offsets = np.einsum("ij,ij->i", self._head_normals, hull.triangles[:, 0])
        self._head_centre = self._head_points.mean(axis=0)  # the broad phase's view point
        self._head = _convex(hull)
        bead_hull = Mesh(hulls["bead_vertices"], hulls["bead_faces"])
        self._bead_head = _convex(bead_hull)
        self._bead_lo, self._bead_hi = np.asarray(bead_hull.bounds, dtype=np.float64)
        self._bead_normals = np.asarray(hulls["bead_normals"], dtype=np.float64)
        self._bead_offsets = np.einsum("ij,ij->i", self._bead_normals, bead_hull.triangles[:, 0])
        self._bead_triangles = np.ascontiguousarray(bead_hull.triangles, dtype=np.float64)
        self.bead_radius_mm = float(bead_radius_mm)
        self._sphere = coal.Sphere(self.bead_radius_mm) if self.bead_radius_mm > 0 else None

        self._pieces: list[coal.Convex] = []
        self._piece_names: list[str] = []
        bounds, vertices = [], []
        self.decompose_seconds = 0.0
        self.cached = True
        self.decompositions: list[tuple[str, Decomposition]] = []  # per part, as ``decompose`` gave it
        for name, mesh in parts:
            result = decompose(as_mesh(mesh), threshold=threshold, cache_dir=cache_dir, name=name)
            self.decompositions.append((name, result))
            self.decompose_seconds += result.seconds
            self.cached &= result.cached
            for piece in result.pieces:
                self._pieces.append(_convex(piece))
                self._piece_names.append(name)
                bounds.append(piece.bounds)
                vertices.append(np.asarray(piece.vertices, dtype=np.float64))
        self.pieces_count = len(self._pieces)
        box = np.asarray(bounds, dtype=np.float64).reshape(-1, 2, 3)
        self._piece_vertices = np.ascontiguousarray(np.vstack(vertices) if vertices else np.zeros((0, 3)))
        self._piece_vstart = np.concatenate([[0], np.cumsum([len(v) for v in vertices])]).astype(np.int64)
        self._piece_lo, self._piece_hi = box[:, 0], box[:, 1]
        self._request = coal.CollisionRequest()
        self._request.enable_contact = True
        self._request.num_max_contacts = 1
        self._identity = coal.Transform3s()

    # ---- extraction vector ----------------------------------------------------------------

    def extraction_vector(self, C: np.ndarray, R: np.ndarray, beads_mm: np.ndarray | None = None) -> Extraction:
        """E at the pose tip ``C`` (3,) workpiece mm, rotation ``R`` (3, 3); beads (m, 3) centres or None.

        Only the pieces whose bounding box meets the head's world bounding box are tested ("GJK
        with bounding box"), less those whose vertices all lie beyond the plane of the hull face
        facing them most (a separating plane: they cannot meet the hull, so no answer changes; on
        bathtub_5000 two fifths as many GJK calls). For each, coal's GJK says whether the hulls
        overlap and its EPA gives the penetration depth d_i and the direction V_i (length d_i)
        that moves the head out. Beads above the tip allowance are spheres, tested the same way
        against the head's hull clipped at the tip allowance plane. E = Σ w_i V_i with
        w_i = |V_i| / Σ|V_k|."""
        c = np.ascontiguousarray(C, dtype=np.float64).reshape(3)
        r = np.ascontiguousarray(R, dtype=np.float64).reshape(3, 3)
        vectors, bodies = [], []
        met = _pieces_met(self._head_points, c, r, self._piece_lo, self._piece_hi, self._head_normals,
                          self._head_offsets, self._head_centre, self._piece_vertices, self._piece_vstart)
        if len(met):  # a walk's poses mostly meet a few pieces, or none: the pose only for those
            pose = coal.Transform3s(r, c)
            for i in met.tolist():
                v = self._penetration(self._head, pose, self._pieces[i], self._identity)
                if v is not None:
                    vectors.append(v)
                    if self._piece_names[i] not in bodies:
                        bodies.append(self._piece_names[i])
        if beads_mm is not None and self._sphere is not None:
            near = self._beads_near(c, r, beads_mm)
            if len(near):  # no bead near: no exit (``bead_exits`` of none is none)
                exits = self.bead_exits(c, r, near)
                exits = exits[np.linalg.norm(exits, axis=1) > _TINY]
                if len(exits):
                    vectors.append(exits)
                    bodies.append("deposit")
        return _combine(vectors, bodies)

    def bead_exits(self, c: np.ndarray, r: np.ndarray, beads: np.ndarray) -> np.ndarray:
        """(k, 3) workpiece-frame exit vectors of the clipped head hull at (c, r) from each bead
        sphere (k, 3) centres (zero where apart): the sphere-polytope case of GJK/EPA, solved
        exactly. A centre inside the hull leaves through its nearest face plane (depth: the
        distance to that plane plus the radius); one outside is pushed from the hull's closest
        point on its visible faces (depth: the radius minus that distance). coal's GJK/EPA
        (``_penetration``) gives the same vectors to its tolerance, a call per bead."""
        if len(beads) == 0:
            return np.zeros((0, 3))
        local = (np.asarray(beads, dtype=np.float64) - c) @ r
        return _sphere_exits(np.ascontiguousarray(local), self._bead_normals, self._bead_offsets,
                             self._bead_triangles, self.bead_radius_mm) @ r.T

    def _penetration(self, head, pose, other, other_pose) -> np.ndarray | None:
        """The head's exit vector from one convex body (length = EPA depth), or None when apart.

        coal's contact normal points from o1 (the head) to o2 and its penetration_depth is the
        signed distance (negative when overlapping), so depth * normal moves o1 out of o2.
        """
        result = coal.CollisionResult()
        if not coal.collide(head, pose, other, other_pose, self._request, result):
            return None
        contact = result.getContact(0)
        v = contact.penetration_depth * np.asarray(contact.normal, dtype=np.float64)
        return v if math.sqrt(v.dot(v)) > _TINY else None  # ``np.linalg.norm`` of a vector, its call aside

    def _beads_near(self, c: np.ndarray, r: np.ndarray, beads_mm: np.ndarray) -> np.ndarray:
        """Bead centres (k, 3) whose sphere may reach the clipped hull: within every face plane
        by less than the radius (this includes "above the tip allowance plane minus the radius")."""
        beads = np.ascontiguousarray(beads_mm, dtype=np.float64).reshape(-1, 3)
        keep = _within_hull(beads, np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(r, dtype=np.float64),
                            self._bead_lo, self._bead_hi, self._bead_normals, self._bead_offsets, self.bead_radius_mm)
        return beads[keep]

    # ---- tilt -----------------------------------------------------------------------------

    def tilt(
        self,
        C: np.ndarray,
        N0: np.ndarray,
        rotation_of: RotationOf,
        is_free: IsFree,
        *,
        max_tilt_deg: float,
        step_deg: float = 0.5,
        variant: str = "fixed",
        beads_mm: np.ndarray | None = None,
    ) -> TiltResult:
        """Rotate the tool vector about the tip ``C`` until ``is_free`` accepts it.

        C : (3,) tip, workpiece mm (stays fixed); N0 : (3,) programmed tool vector
        rotation_of : (n, 3) unit vectors -> (n, 3, 3) rotations (the machine decides the spin)
        is_free : (n, 3) unit vectors -> (n,) bool, the caller's conservative check at tip C
        variant : "fixed" (E once) or "lami" (E recomputed and combined at each step)
        N is turned toward the part of E perpendicular to N (that moves the head along E), in
        small steps. "lami" takes the resultant of the previous and the new direction (Lami's
        theorem), each weighted by its depth, so the path bends around an obstacle.
        Orientations are tried in order of the walk, ``_BATCH`` per ``is_free`` call. When the
        hull model finds no penetration at N0, or E is parallel to N0 (no tilt direction), a
        fallback tries ``_RING_AZIMUTHS`` azimuths at each tilt step and keeps the first free one
        at the smallest tilt. ``tilt_steps`` is the same walk, driven by its caller.
        """
        walk = self.tilt_steps(C, N0, rotation_of, max_tilt_deg=max_tilt_deg, step_deg=step_deg,
                               variant=variant, beads_mm=beads_mm)
        return run_tilts([walk], lambda asked: [is_free(normals) for _, normals in asked])[0]

    def tilt_steps(
        self,
        C: np.ndarray,
        N0: np.ndarray,
        rotation_of: RotationOf,
        *,
        max_tilt_deg: float,
        step_deg: float = 0.5,
        variant: str = "fixed",
        beads_mm: np.ndarray | None = None,
    ) -> TiltWalk:
        """``tilt``'s walk as a generator: it yields each batch of orientations to test ((k, 3):
        N0 alone first, then up to ``_BATCH`` of the walk), is sent their answers ((k,) bool)
        and returns the TiltResult. Walks of many tips can so be tested together (``run_tilts``);
        each asks and gets exactly what ``tilt`` would."""
        if variant not in VARIANTS:
            raise ValueError(f"unknown tilt variant {variant!r}; known: {', '.join(VARIANTS)}")
        c = np.asarray(C, dtype=np.float64).reshape(3)
        n0 = np.asarray(N0, dtype=np.float64).reshape(3)
        n0 = n0 / np.linalg.norm(n0)
        if bool(np.asarray((yield n0[None]), dtype=bool).reshape(-1)[0]):
            return TiltResult(n0, 0.0, 0, [])
        start = self.extraction_vector(c, _rotation(rotation_of, n0), beads_mm)
        axis = _tilt_axis(n0, start.vector)
        angles = _tilt_angles(max_tilt_deg, step_deg)
        if axis is None:
            walk = _ring(n0, _rotation(rotation_of, n0), angles)
        elif variant == "fixed":
            walk = iter(axis_rotation(axis, np.radians(angles)) @ n0)
        else:
            walk = self._lami_walk(c, n0, axis, start, rotation_of, max_tilt_deg, step_deg, beads_mm)
        tried = 0
        widest = 0.0
        while batch := list(islice(walk, _BATCH)):
            normals = np.asarray(batch, dtype=np.float64)
            hit = np.flatnonzero(np.asarray((yield normals), dtype=bool).reshape(-1))
            if hit.size:
                normal = normals[hit[0]]
                return TiltResult(normal, float(angle_between_deg(n0, normal)), tried + int(hit[0]) + 1, start.bodies)
            tried += len(normals)
            widest = max(widest, float(angle_between_deg(n0, normals).max()))
        return TiltResult(None, widest, tried, start.bodies)

    def _lami_walk(
        self,
        c: np.ndarray,
        n0: np.ndarray,
        axis: np.ndarray,
        start: Extraction,
        rotation_of: RotationOf,
        max_tilt_deg: float,
        step_deg: float,
        beads_mm: np.ndarray | None,
    ) -> Iterator[np.ndarray]:
        """Tool vectors along the bending path, until it leaves the max_tilt cone.

        The direction is the resultant of the previous direction, weighted by the previous depth,
        and the new E (its length is its depth). A pose the hull model finds clear keeps the
        current direction. The path depends on the hull model only, so it can be generated ahead
        of the ``is_free`` batches.
        """
        # Scalar arithmetic: a step is a few dozen flops, numpy's per-call overhead would be most
        # of the walk's time (the hull model's tests aside).
        step = math.radians(step_deg)
        cos_step, sin_step = math.cos(step), math.sin(step)
        limit = max_tilt_deg + 1e-9
        first = tuple(float(v) for v in n0)
        direction = tuple(float(v) for v in start.vector / np.linalg.norm(start.vector))
        weight = float(np.linalg.norm(start.vector))
        axis = tuple(float(v) for v in axis)
        n = first
        for _ in range(_LAMI_STEP_FACTOR * max(1, int(np.ceil(max_tilt_deg / step_deg)))):
            n = _turned(axis, cos_step, sin_step, n)
            if _angle_deg(first, n) > limit:
                return
            normal = np.array(n)
            yield normal
            e = self.extraction_vector(c, _rotation(rotation_of, normal), beads_mm).vector
            ex, ey, ez = float(e[0]), float(e[1]), float(e[2])
            depth = math.sqrt(ex * ex + ey * ey + ez * ez)
            if depth > _TINY:
                rx, ry, rz = weight * direction[0] + ex, weight * direction[1] + ey, weight * direction[2] + ez
                size = math.sqrt(rx * rx + ry * ry + rz * rz)
                direction = (rx / size, ry / size, rz / size)
                weight = depth
            turned = _cross_unit(n, direction)
            axis = axis if turned is None else turned


# ---- helpers ------------------------------------------------------------------------------


def _convex(mesh: Mesh) -> coal.ConvexBase:
    """A coal convex shape from a convex mesh (its points and triangles), for any mesh.

    coal keeps each vertex's neighbours (its GJK support search climbs along them) in lists of
    at most ``_COAL_MAX_NEIGHBOURS``, and refuses a shape with a vertex of more. The triangles
    of a hull can have such a vertex where the hull does not: qhull fans a flat cap of n
    points from one of them (a revolved head of 128 segments cut at the tip allowance: a cap of
    256 points). Then the same points are given to coal's own hull, whose neighbours are the
    polytope's true edges: the same shape. Where even a true vertex has more edges (the apex of
    a cone of 256 or more segments), the shape is ``_outer_polytope``: a polytope holding the
    hull, off by hundredths of a millimetre, only ever larger (so the hull model errs toward
    "collides")."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if _max_valence(faces, len(vertices)) <= _COAL_MAX_NEIGHBOURS:
        points = coal.StdVec_Vec3s()
        points.extend(list(vertices))
        triangles = coal.StdVec_Triangle()
        triangles.extend([coal.Triangle(int(a), int(b), int(c)) for a, b, c in faces])
        return coal.Convex(points, triangles)
    shape = _coal_hull(vertices)
    if shape is None:
        shape = _coal_hull(_outer_polytope(vertices))
    if shape is None:  # pragma: no cover - _outer_polytope bounds the valence well below the limit
        raise ValueError(f"cannot build a convex shape of {len(vertices)} points for the hull model")
    return shape


# coal stores a vertex's neighbour count in one byte (``Convex::fillNeighbors``, "Too many neighbors").
_COAL_MAX_NEIGHBOURS = 255
# ``_outer_polytope``: face normals are grouped by the nearest of this many directions (a Fibonacci
# lattice, about 4.5° apart): a vertex meets at most a few dozen groups' planes.
_OUTER_DIRECTIONS = 2000


def _max_valence(faces: np.ndarray, vertices: int) -> int:
    """The most edges any vertex of the triangles (f, 3) has."""
    if len(faces) == 0:
        return 0
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    edges = np.unique(edges, axis=0)
    return int(np.bincount(edges.ravel(), minlength=vertices).max())


def _coal_hull(points: np.ndarray) -> coal.ConvexBase | None:
    """coal's hull of the points (qhull, facets not triangulated: neighbours along the true
    edges), or None when a vertex still has too many of them."""
    vec = coal.StdVec_Vec3s()
    vec.extend(list(np.asarray(points, dtype=np.float64)))
    try:
        return coal.ConvexBase.convexHull(vec, False, "")
    except RuntimeError as error:
        if "Too many neighbors" in str(error):
            return None
        raise


def _outer_polytope(points: np.ndarray) -> np.ndarray:
    """(m, 3) vertices of a polytope that holds the hull of the points (n, 3) and has no vertex
    of many edges: the hull's face normals are grouped by the nearest of ``_OUTER_DIRECTIONS``
    lattice directions, each group becomes one plane along its area-weighted mean normal at the
    points' support in that direction (so it holds every point), with the six axis planes; the
    polytope is their intersection. The planes around a vertex of many faces (a fine cone's apex)
    become a few dozen."""
    import trimesh
    from scipy.spatial import HalfspaceIntersection

    points = np.asarray(points, dtype=np.float64)
    hull = trimesh.convex.convex_hull(points)
    normals, areas = np.asarray(hull.face_normals), np.asarray(hull.area_faces)
    i = np.arange(_OUTER_DIRECTIONS) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / _OUTER_DIRECTIONS), np.pi * (1.0 + 5.0 ** 0.5) * i
    lattice = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    group = np.argmax(normals @ lattice.T, axis=1)
    sums = np.zeros((_OUTER_DIRECTIONS, 3))
    np.add.at(sums, group, areas[:, None] * normals)
    sums = sums[np.linalg.norm(sums, axis=1) > 0]
    directions = np.vstack([sums / np.linalg.norm(sums, axis=1)[:, None], np.eye(3), -np.eye(3)])
    offsets = (points @ directions.T).max(axis=0)
    centre = np.asarray(hull.centroid, dtype=np.float64)
    # Each plane pushed out by a rounding's width, so that the intersection holds the points.
    slack = 1e-9 * max(1.0, float(np.abs(points).max()))
    planes = np.column_stack([directions, -(offsets + slack)])
    return np.asarray(HalfspaceIntersection(planes, centre).intersections, dtype=np.float64)


# The code the head's hulls come from (part of their cache key).
_HULL_SOURCES = ("ncfix.correct.epa", "ncfix.geometry.meshdata")
_HULL_ARRAYS = ("hull_vertices", "hull_faces", "hull_normals", "bead_vertices", "bead_faces", "bead_normals")


def _head_hulls(head: Mesh, tip_allowance_mm: float, cache_dir: str | Path | None) -> dict[str, np.ndarray]:
    """The head's convex hull and that hull cut at the tip allowance (``_clip_hull``): vertices,
    faces and face normals as trimesh computes them, read from the cache when this head was
    hulled at this allowance before (a warm fix then does not import trimesh and scipy's qhull)."""
    key = cache.make_key("hull", head.vertices, head.faces, tip_allowance_mm, cache.fingerprint(*_HULL_SOURCES),
                         {package: cache.version(package) for package in ("numpy", "scipy", "trimesh")})

    def build() -> dict[str, np.ndarray]:
        hull = as_trimesh(head).convex_hull
        bead = _clip_hull(hull, tip_allowance_mm)
        return {"hull_vertices": hull.vertices, "hull_faces": hull.faces, "hull_normals": hull.face_normals,
                "bead_vertices": bead.vertices, "bead_faces": bead.faces, "bead_normals": bead.face_normals}

    def from_arrays(a: dict[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        for hull in ("hull", "bead"):
            normals = a[f"{hull}_normals"]
            if not mesh_arrays(a[f"{hull}_vertices"], a[f"{hull}_faces"]) or normals.dtype != np.float64 \
                    or normals.shape != a[f"{hull}_faces"].shape:
                return None
        return a

    def to_arrays(a: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {name: np.asarray(a[name]) for name in _HULL_ARRAYS}

    hulls, _ = cache.cached("hull", key, _HULL_ARRAYS, build, to_arrays, from_arrays, cache_dir)
    return hulls


def _clip_hull(hull: trimesh.Trimesh, height_mm: float) -> trimesh.Trimesh:
    """The convex hull cut by the plane z = height_mm, keeping the part above (still convex)."""
    import trimesh
    v = np.asarray(hull.vertices, dtype=np.float64)
    edges = np.asarray(hull.edges_unique)
    z0, z1 = v[edges[:, 0], 2] - height_mm, v[edges[:, 1], 2] - height_mm
    cut = z0 * z1 < 0
    t = (z0[cut] / (z0[cut] - z1[cut]))[:, None]
    crossings = v[edges[cut, 0]] + t * (v[edges[cut, 1]] - v[edges[cut, 0]])
    points = np.vstack([v[v[:, 2] >= height_mm], crossings])
    if len(points) < 4 or np.ptp(points[:, 2]) <= 0:
        raise ValueError(f"the tip allowance {height_mm} mm removes the whole head")
    return trimesh.convex.convex_hull(points)


def _combine(vectors: list[np.ndarray], bodies: list[str]) -> Extraction:
    """E = Σ w_i V_i with w_i = |V_i| / Σ|V_k| (seed, "EPA Algorithm"); ``vectors``: (3,) vectors
    and (k, 3) blocks of them."""
    if not vectors:
        return Extraction(np.zeros(3), 0.0, bodies)
    v = np.vstack(vectors)
    lengths = np.linalg.norm(v, axis=1)
    e = (lengths[:, None] * v).sum(axis=0) / lengths.sum()
    return Extraction(e, float(lengths.max()), bodies)


def _rotation(rotation_of: RotationOf, n: np.ndarray) -> np.ndarray:
    return np.asarray(rotation_of(n[None]), dtype=np.float64).reshape(3, 3)


def _tilt_axis(n: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
    """Unit axis turning n toward the part of ``direction`` perpendicular to it (None if parallel).

    Rotating n by a small angle about n × d moves n toward d's perpendicular part, and with it
    every head point above the tip: the head moves along d.
    """
    axis = _cross_unit(tuple(float(v) for v in n), tuple(float(v) for v in direction))
    return None if axis is None else np.array(axis)


def _cross_unit(n: tuple, d: tuple) -> tuple | None:
    """``_tilt_axis`` on (x, y, z) tuples."""
    x, y, z = n[1] * d[2] - n[2] * d[1], n[2] * d[0] - n[0] * d[2], n[0] * d[1] - n[1] * d[0]
    norm = math.sqrt(x * x + y * y + z * z)
    if norm > _TINY * max(1.0, math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])):
        return x / norm, y / norm, z / norm
    return None


def _turned(u: tuple, cos_a: float, sin_a: float, n: tuple) -> tuple:
    """n (x, y, z) rotated about the unit axis u by the angle of (cos_a, sin_a), right-handed
    (``axis_rotation``'s matrix, applied)."""
    ux, uy, uz = u
    x, y, z = n
    o = 1.0 - cos_a
    return ((cos_a + o * (ux * ux)) * x + (-sin_a * uz + o * (ux * uy)) * y + (sin_a * uy + o * (ux * uz)) * z,
            (sin_a * uz + o * (uy * ux)) * x + (cos_a + o * (uy * uy)) * y + (-sin_a * ux + o * (uy * uz)) * z,
            (-sin_a * uy + o * (uz * ux)) * x + (sin_a * ux + o * (uz * uy)) * y + (cos_a + o * (uz * uz)) * z)


def _angle_deg(a: tuple, b: tuple) -> float:
    """``angle_between_deg`` of two (x, y, z) unit vectors."""
    x, y, z = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
    return math.degrees(math.atan2(math.sqrt(x * x + y * y + z * z), a[0] * b[0] + a[1] * b[1] + a[2] * b[2]))


def _tilt_angles(max_tilt_deg: float, step_deg: float) -> np.ndarray:
    """step, 2·step, … up to max_tilt, with max_tilt itself last when it is not a multiple."""
    if step_deg <= 0:
        raise ValueError(f"step_deg must be > 0, not {step_deg}")
    angles = step_deg * np.arange(1, int(np.floor(max_tilt_deg / step_deg + 1e-9)) + 1)
    if max_tilt_deg > 0 and (len(angles) == 0 or angles[-1] < max_tilt_deg - 1e-9):
        angles = np.append(angles, max_tilt_deg)
    return angles


def _ring(n0: np.ndarray, r0: np.ndarray, angles_deg: np.ndarray) -> Iterator[np.ndarray]:
    """Fallback: ``_RING_AZIMUTHS`` directions at each tilt, azimuths from the head's own x axis."""
    azimuth = 2 * np.pi * np.arange(_RING_AZIMUTHS) / _RING_AZIMUTHS
    around = np.cos(azimuth)[:, None] * r0[:, 0] + np.sin(azimuth)[:, None] * r0[:, 1]
    for tilt in np.radians(angles_deg):
        yield from np.cos(tilt) * n0 + np.sin(tilt) * around


def run_tilts(walks: list[TiltWalk], test: Callable[[list[tuple[int, np.ndarray]]], list[np.ndarray]]) -> list[TiltResult]:
    """Drive tilt walks (``EpaModel.tilt_steps``) in step: each round, ``test`` gets (walk index,
    batch) of every unfinished walk, in the walks' order, and answers each batch ((k,) bool);
    returns each walk's TiltResult."""
    results: list[TiltResult | None] = [None] * len(walks)
    asks: dict[int, np.ndarray] = {}

    def advance(i: int, answer: np.ndarray | None) -> None:
        try:
            asks[i] = next(walks[i]) if answer is None else walks[i].send(answer)
        except StopIteration as done:
            results[i] = done.value

    for i in range(len(walks)):
        advance(i, None)
    while asks:
        asked = list(asks.items())
        asks.clear()
        for (i, _), answer in zip(asked, test(asked)):
            advance(i, answer)
    return results


def _within_hull(beads, c, r, lo, hi, normals, offsets, rad):  # pragma: no cover - compiled
    """(m,) bool: bead centres whose head-frame point R^T (b - c) lies in the hull's box grown by
    rad and less than rad outside every face plane (a bead stops at the first plane it clears)."""
    out = np.zeros(beads.shape[0], np.bool_)
    last = 0
    for i in range(beads.shape[0]):
        ex, ey, ez = beads[i, 0] - c[0], beads[i, 1] - c[1], beads[i, 2] - c[2]
        x = r[0, 0] * ex + r[1, 0] * ey + r[2, 0] * ez
        y = r[0, 1] * ex + r[1, 1] * ey + r[2, 1] * ez
        z = r[0, 2] * ex + r[1, 2] * ey + r[2, 2] * ez
        if not (lo[0] - rad < x < hi[0] + rad and lo[1] - rad < y < hi[1] + rad and lo[2] - rad < z < hi[2] + rad):
            continue
        # The face that cleared the bead before is tried first: neighbouring beads (the caller's
        # are in cells) are mostly cleared by the same face. The answer does not depend on it.
        if normals[last, 0] * x + normals[last, 1] * y + normals[last, 2] * z - offsets[last] >= rad:
            continue
        inside = True
        for f in range(normals.shape[0]):
            if normals[f, 0] * x + normals[f, 1] * y + normals[f, 2] * z - offsets[f] >= rad:
                inside = False
                last = f
                break
        out[i] = inside
    return out


def _boxes_met(points, c, r, lo, hi):  # pragma: no cover - compiled
    """Indices of the boxes (lo, hi: (k, 3)) that meet the bounding box of the points (m, 3)
    placed at tip c, rotation r (world = c + r @ p)."""
    wlo = np.full(3, np.inf)
    whi = np.full(3, -np.inf)
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for a in range(3):
            w = c[a] + r[a, 0] * px + r[a, 1] * py + r[a, 2] * pz
            wlo[a] = min(wlo[a], w)
            whi[a] = max(whi[a], w)
    out = np.empty(lo.shape[0], np.int64)
    k = 0
    for j in range(lo.shape[0]):
        if (lo[j, 0] <= whi[0] and lo[j, 1] <= whi[1] and lo[j, 2] <= whi[2]
                and hi[j, 0] >= wlo[0] and hi[j, 1] >= wlo[1] and hi[j, 2] >= wlo[2]):
            out[k] = j
            k += 1
    return out[:k]


def _pieces_met(points, c, r, lo, hi, normals, offsets, centre, vertices, vstart):  # pragma: no cover - compiled
    """``_boxes_met``'s boxes less the pieces (vertices[vstart[j]:vstart[j + 1]], world frame)
    that lie wholly beyond a face plane of the hull the points span (normals, offsets: its face
    planes in the head frame, outward): such a plane separates them. The face tried for a piece
    is the one facing its centre most (from the hull's ``centre``, head frame); a piece it does
    not separate is kept (the GJK test decides)."""
    met = _boxes_met(points, c, r, lo, hi)
    out = np.empty(met.shape[0], np.int64)
    k = 0
    hx, hy, hz = centre[0], centre[1], centre[2]
    for m in range(met.shape[0]):
        j = met[m]
        # The piece's box centre in the head frame, seen from the hull's centre.
        wx = 0.5 * (lo[j, 0] + hi[j, 0]) - c[0]
        wy = 0.5 * (lo[j, 1] + hi[j, 1]) - c[1]
        wz = 0.5 * (lo[j, 2] + hi[j, 2]) - c[2]
        dx = r[0, 0] * wx + r[1, 0] * wy + r[2, 0] * wz - hx
        dy = r[0, 1] * wx + r[1, 1] * wy + r[2, 1] * wz - hy
        dz = r[0, 2] * wx + r[1, 2] * wy + r[2, 2] * wz - hz
        best = -np.inf
        face = 0
        for f in range(normals.shape[0]):
            t = normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz
            if t > best:
                best, face = t, f
        nx, ny, nz = normals[face, 0], normals[face, 1], normals[face, 2]
        # The face's normal in the world frame: every vertex beyond the plane means apart.
        ux = r[0, 0] * nx + r[0, 1] * ny + r[0, 2] * nz
        uy = r[1, 0] * nx + r[1, 1] * ny + r[1, 2] * nz
        uz = r[2, 0] * nx + r[2, 1] * ny + r[2, 2] * nz
        apart = True
        for v in range(vstart[j], vstart[j + 1]):
            if ux * (vertices[v, 0] - c[0]) + uy * (vertices[v, 1] - c[1]) + uz * (vertices[v, 2] - c[2]) \
                    <= offsets[face]:
                apart = False
                break
        if not apart:
            out[k] = j
            k += 1
    return out[:k]


def _sphere_exits(points, normals, offsets, triangles, rad):  # pragma: no cover - compiled
    """(m, 3) head-frame exit vectors of a convex hull (face planes normals · x = offsets, outward;
    its triangles) from spheres of radius rad at points (m, 3): zero where a sphere clears it."""
    m = points.shape[0]
    out = np.zeros((m, 3))
    for i in range(m):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        worst = -np.inf  # the largest signed plane distance, and its face
        face = -1
        for f in range(normals.shape[0]):
            d = normals[f, 0] * x + normals[f, 1] * y + normals[f, 2] * z - offsets[f]
            if d > worst:
                worst, face = d, f
        if worst >= rad:
            continue  # a separating plane
        if worst <= 0.0:  # inside: out through the nearest face plane
            depth = rad - worst
            out[i, 0], out[i, 1], out[i, 2] = -depth * normals[face, 0], -depth * normals[face, 1], -depth * normals[face, 2]
            continue
        best = np.inf
        qx = qy = qz = 0.0
        for f in range(normals.shape[0]):  # the closest point lies on a face the centre sees
            if normals[f, 0] * x + normals[f, 1] * y + normals[f, 2] * z - offsets[f] <= 0.0:
                continue
            cx, cy, cz = tri_closest(x, y, z, triangles[f])
            d2 = (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2
            if d2 < best:
                best, qx, qy, qz = d2, cx, cy, cz
        dist = np.sqrt(best)
        if dist >= rad or dist <= 0.0:
            continue
        s = (rad - dist) / dist
        out[i, 0], out[i, 1], out[i, 2] = s * (qx - x), s * (qy - y), s * (qz - z)
    return out


_within_hull = njit(cache=True, nogil=True)(_within_hull)
_boxes_met = njit(cache=True, nogil=True)(_boxes_met)
_pieces_met = njit(cache=True, nogil=True)(_pieces_met)
_sphere_exits = njit(cache=True, nogil=True)(_sphere_exits)
