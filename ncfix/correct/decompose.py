"""CoACD convex decomposition of a part mesh, cached on disk (one .npz per mesh and parameters).

CoACD (Wei et al., SIGGRAPH 2022) cuts a non-convex mesh into pieces whose convex hulls stay within
``threshold`` (a concavity measure, relative to the mesh size). Their union covers the part only
approximately (beyond it in shallow concave regions; slivers may be missed where CoACD's manifold
preprocessing reshapes the surface), so it guides the EPA correction's direction and never judges
a collision. It takes seconds (8 s for the 724-face sample mold at 0.05): the hulls are cached.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import time
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np

from ncfix import cache
from ncfix.geometry.meshdata import Mesh

if TYPE_CHECKING:
    import trimesh

# CoACD's own seed; fixed so that a decomposition is reproducible bit for bit.
_SEED = 0
_ARRAYS = ("vertices", "faces", "vertex_offsets", "face_offsets")


@dataclass
class Decomposition:
    """Convex pieces of one part.

    pieces : convex hulls, workpiece mm, the part's frame (``Mesh``: trimesh is imported only to
        decompose, not to read the pieces from the cache)
    seconds : wall time spent here (decomposing, or ~0 when read from the cache)
    cached : True when the pieces came from the cache
    key : hex sha256 naming the cache file
    """

    pieces: list[Mesh]
    seconds: float
    cached: bool
    key: str


def cache_key(mesh: trimesh.Trimesh | Mesh, threshold: float) -> str:
    """sha256 of the vertex (float64) and face (int64) arrays, the parameters and CoACD's version.
    The seed is fixed, so the same key always means the same hulls (``coacd-KEY.npz``, ``ncfix.cache``;
    a file that cannot be read is recomputed and overwritten)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    params = {"threshold": float(threshold), "seed": _SEED, "coacd": importlib.metadata.version("coacd")}
    digest.update(json.dumps(params, sort_keys=True).encode())
    return digest.hexdigest()


def decompose(
    mesh: trimesh.Trimesh | Mesh, *, threshold: float = 0.05, cache_dir: str | Path | None = None,
    name: str = "a part",
) -> Decomposition:
    """Convex pieces of ``mesh`` (closed, workpiece mm), from the cache when present.

    threshold : CoACD's concavity threshold (smaller: more, tighter pieces)
    cache_dir : folder of the .npz files; None means ``ncfix.cache.cache_dir()``. A folder that
        cannot be written is not an error: the pieces are returned uncached.
    name : the part, for the notice of a decomposition (``cache.cached``)
    """
    start = time.perf_counter()
    key = cache_key(mesh, threshold)
    pieces, hit = cache.cached("coacd", key, _ARRAYS, lambda: _run_coacd(mesh, threshold), _to_arrays, _from_arrays,
                               cache_dir, what=f"the CoACD decomposition of {name.split(':', 1)[-1]} (first run for this mesh)")
    return Decomposition(pieces=pieces, seconds=time.perf_counter() - start, cached=hit, key=key)


def _run_coacd(mesh: trimesh.Trimesh | Mesh, threshold: float) -> list[Mesh]:
    import coacd
    import trimesh

    coacd.set_log_level("error")
    parts = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)),
        threshold=float(threshold),
        seed=_SEED,
    )
    # CoACD returns hulls already; re-hulling gives consistently wound, closed convex triangle sets.
    hulls = [trimesh.Trimesh(vertices, faces, process=False).convex_hull for vertices, faces in parts]
    return [Mesh(hull.vertices, hull.faces) for hull in hulls]


def _to_arrays(pieces: list[Mesh]) -> dict[str, np.ndarray]:
    """All vertices and faces stacked, with offsets."""
    return {
        "vertices": np.concatenate([p.vertices for p in pieces]).astype(np.float64),
        "faces": np.concatenate([p.faces for p in pieces]).astype(np.int64),
        "vertex_offsets": np.cumsum([0] + [len(p.vertices) for p in pieces]).astype(np.int64),
        "face_offsets": np.cumsum([0] + [len(p.faces) for p in pieces]).astype(np.int64),
    }


def _from_arrays(arrays: dict[str, np.ndarray]) -> list[Mesh] | None:
    """The pieces, or None when the arrays do not make valid pieces (then they are recomputed)."""
    vertices = np.asarray(arrays["vertices"], dtype=np.float64)
    faces = np.asarray(arrays["faces"], dtype=np.int64)
    vo = np.asarray(arrays["vertex_offsets"], dtype=np.int64)
    fo = np.asarray(arrays["face_offsets"], dtype=np.int64)
    if len(vo) < 2 or len(vo) != len(fo) or vo[-1] != len(vertices) or fo[-1] != len(faces):
        return None
    pieces = []
    for i in range(len(vo) - 1):
        v, f = vertices[vo[i] : vo[i + 1]], faces[fo[i] : fo[i + 1]]
        if len(v) < 4 or len(f) < 4 or f.min() < 0 or f.max() >= len(v) or not np.isfinite(v).all():
            return None
        pieces.append(Mesh(v, f))
    return pieces
