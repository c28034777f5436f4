"""A triangle mesh as two arrays, with the little of trimesh a check reads from it.

A warm-cache check reads every grid, tree and cell list from the cache and needs of its meshes
only their vertices, faces, triangles and boxes; importing trimesh (with the scipy and networkx
modules it pulls in) would be about a second of its start-up. ``Mesh`` gives those in numpy, with
trimesh's own arithmetic where a value is computed (``apply_transform``, ``bounds``), so that what
is derived from it is the same to the bit; ``to_trimesh`` gives a ``trimesh.Trimesh`` of the same
arrays where a computation needs trimesh (building a grid or a model on a cache miss, CoACD).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh

_IDENTITY4 = np.eye(4)


class Mesh:
    """A triangle mesh.

    vertices : (n, 3) float64, in the mesh's frame (mm)
    faces : (m, 3) int64, indices into vertices, counter-clockwise seen from outside
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self._trimesh = None

    @property
    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float64: each face's corners."""
        return self.vertices[self.faces]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: the box of the vertices the faces use (trimesh's ``bounds``)."""
        used = np.zeros(len(self.vertices), dtype=bool)
        used[self.faces] = True
        inside = self.vertices[used]
        return np.array([inside.min(axis=0), inside.max(axis=0)])

    def copy(self) -> Mesh:
        return Mesh(self.vertices.copy(), self.faces.copy())

    def apply_transform(self, matrix: np.ndarray) -> Mesh:
        """Move the mesh by a (4, 4) homogeneous transform in place, as trimesh's
        ``Trimesh.apply_transform`` does (the same products; a mirroring transform reverses each
        face's order so that its winding stays outward)."""
        matrix = np.asanyarray(matrix, order="C", dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError("the transform must be a (4, 4) matrix")
        if float(np.ptp(matrix - _IDENTITY4)) < 1e-8:
            return self
        if len(self.vertices) and np.abs(matrix - _IDENTITY4).max() >= 1e-8:
            stack = np.column_stack((self.vertices, np.ones(len(self.vertices))))
            self.vertices = np.ascontiguousarray(np.dot(matrix, stack.T).T[:, :3])
        rotates = float(np.ptp(matrix[:3, :3] - _IDENTITY4[:3, :3])) >= 1e-6
        if rotates and np.linalg.det(matrix[:3, :3]) < 0.0:
            self.faces = np.ascontiguousarray(np.fliplr(self.faces))
        self._trimesh = None
        return self

    def to_trimesh(self) -> trimesh.Trimesh:
        """A ``trimesh.Trimesh`` of these arrays (not processed), made on first use."""
        if self._trimesh is None:
            import trimesh

            self._trimesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        return self._trimesh


def mesh_arrays(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether arrays read back from the cache make a ``Mesh`` as it is stored: vertices (n, 3)
    float64 and faces (m, 3) int64 (``ncfix.cache.cached``'s ``from_arrays`` checks)."""
    return vertices.dtype == np.float64 and faces.dtype == np.int64 and vertices.ndim == 2 and faces.ndim == 2 \
        and vertices.shape[1] == 3 and faces.shape[1] == 3


def as_mesh(mesh) -> Mesh:
    """A ``Mesh`` of anything with ``vertices`` and ``faces`` (a trimesh, a Mesh: itself)."""
    if isinstance(mesh, Mesh):
        return mesh
    return Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))


def as_trimesh(mesh) -> trimesh.Trimesh:
    """A ``trimesh.Trimesh`` of a ``Mesh`` (``to_trimesh``); a trimesh is itself."""
    return mesh.to_trimesh() if isinstance(mesh, Mesh) else mesh


def face_adjacency(faces: np.ndarray) -> np.ndarray:
    """(k, 2) int64: the pairs of faces that share an edge no other face has (trimesh's
    ``face_adjacency``: an edge of three or more faces joins none of them)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(faces), dtype=np.int64), 3)
    if len(edges) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    shared = counts[inverse] == 2
    order = np.argsort(inverse[shared], kind="stable")
    return owner[shared][order].reshape(-1, 2)


def component_labels(faces: np.ndarray) -> np.ndarray:
    """(m,) int64: the connected body of each face (faces joined by ``face_adjacency``), numbered
    in the order of each body's first face, as ``trimesh.graph.connected_component_labels`` (scipy's
    ``connected_components``) numbers them."""
    count = len(faces)
    pairs = face_adjacency(faces)
    label = np.arange(count, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    while True:
        low = np.minimum(label[a], label[b])
        before = label.copy()
        np.minimum.at(label, a, low)
        np.minimum.at(label, b, low)
        label = label[label]  # each face's root: the smallest face of its body, once converged
        while True:
            jumped = label[label]
            if np.array_equal(jumped, label):
                break
            label = jumped
        if np.array_equal(label, before):
            break
    return np.unique(label, return_inverse=True)[1].reshape(-1).astype(np.int64)
