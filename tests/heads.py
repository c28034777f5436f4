"""Head meshes as CAD exports make them, for the tests: revolved heads of any ring resolution,
with or without fan-triangulated caps, and a torch with a side wire feeder. Each is a single
closed shell in the head frame (tip at the origin, axis +Z), written to and read back from
binary STL (float32 vertices, as a user's file is)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh

# (radius, height) mm of a nozzle cone and a body cylinder, from the tip up.
NOZZLE_PROFILE = ((0.5, 0.0), (8.0, 15.0), (20.0, 15.0), (20.0, 80.0))


def revolved_head(segments: int, caps: str = "fan", profile=NOZZLE_PROFILE, pointed: bool = False) -> trimesh.Trimesh:
    """A profile (radius, height) revolved about +Z in ``segments`` steps per ring.

    caps: "fan" closes the tip and top discs with a fan from a centre vertex (a vertex of
    ``segments`` edges, as many CAD exporters write a disc); "strip" closes them with a zig-zag
    of triangles between the ring's vertices (no vertex of more than a few edges).
    pointed: the nozzle comes to a point at the tip (the first ring collapses to one vertex: a
    vertex of ``segments`` edges on the hull itself).
    """
    rings = list(profile)
    a = 2.0 * np.pi * np.arange(segments) / segments
    ring_xy = np.column_stack([np.cos(a), np.sin(a)])
    vertices: list[np.ndarray] = []
    faces: list[tuple[int, int, int]] = []
    start = []
    for k, (r, z) in enumerate(rings):
        start.append(sum(len(v) for v in vertices))
        if k == 0 and pointed:
            vertices.append(np.array([[0.0, 0.0, z]]))
        else:
            vertices.append(np.column_stack([r * ring_xy, np.full(segments, z)]))
    for k in range(len(rings) - 1):
        lo, hi = start[k], start[k + 1]
        for i in range(segments):
            j = (i + 1) % segments
            if k == 0 and pointed:
                faces.append((lo, hi + j, hi + i))
            else:
                faces += [(lo + i, hi + j, hi + i), (lo + i, lo + j, hi + j)]
    n = sum(len(v) for v in vertices)
    top = start[-1]
    if caps == "fan":
        vertices.append(np.array([[0.0, 0.0, rings[0][1]], [0.0, 0.0, rings[-1][1]]]))
        for i in range(segments):
            j = (i + 1) % segments
            if not pointed:
                faces.append((n, j, i))
            faces.append((n + 1, top + i, top + j))
    elif caps == "strip":
        order = _zigzag(segments)
        for a0, b0, c0 in order:
            if not pointed:
                faces.append((c0, b0, a0))
            faces.append((top + a0, top + b0, top + c0))
    else:
        raise ValueError(f"caps must be 'fan' or 'strip', not {caps!r}")
    mesh = trimesh.Trimesh(np.vstack(vertices), np.array(faces), process=True)
    mesh.fix_normals()
    return as_stl(mesh)


def _zigzag(segments: int) -> list[tuple[int, int, int]]:
    """Triangles (counter-clockwise seen from +Z) covering a convex ring of ``segments``
    vertices as a strip running across it: each vertex has at most four of them."""
    left, right = 1, segments - 1
    out = []
    prev = 0
    take_left = True
    while left <= right:
        if take_left:
            out.append((prev, left, right) if left != right else (prev, left, (left + 1) % segments))
            prev = left
            left += 1
        else:
            out.append((prev, left, right))
            prev = right
            right -= 1
        take_left = not take_left
    return [t for t in out if len(set(t)) == 3]


def torch_with_feeder() -> trimesh.Trimesh:
    """A welding torch as a box-and-cylinder head: a nozzle cylinder (r 6 mm, 0-30 mm), a
    body box (50 x 50 mm, 30-110 mm) and a wire feeder box on its +X side (60 x 30 x 40 mm,
    reaching x = 85 mm): not round, one closed shell (a boolean union)."""
    import manifold3d

    def solid(mesh: trimesh.Trimesh):
        return manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.asarray(mesh.vertices, dtype=np.float64),
                                                     tri_verts=np.asarray(mesh.faces, dtype=np.uint64)))

    nozzle = trimesh.creation.cylinder(radius=6.0, height=31.0, sections=48)
    nozzle.apply_translation((0.0, 0.0, 15.5))
    body = trimesh.creation.box(bounds=[(-25.0, -25.0, 30.0), (25.0, 25.0, 110.0)])
    feeder = trimesh.creation.box(bounds=[(20.0, -15.0, 55.0), (85.0, 15.0, 95.0)])
    union = (solid(nozzle) + solid(body) + solid(feeder)).to_mesh64()
    mesh = trimesh.Trimesh(np.asarray(union.vert_properties[:, :3], dtype=np.float64),
                           np.asarray(union.tri_verts, dtype=np.int64))
    return as_stl(mesh)


def as_stl(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh as a binary STL file reads back (float32 vertices, merged)."""
    return trimesh.load(io.BytesIO(mesh.export(file_type="stl")), file_type="stl")


def write_stl(mesh: trimesh.Trimesh, path: Path) -> Path:
    mesh.export(path, file_type="stl")
    return path
