"""Meshes read as arrays (``ncfix.geometry.meshdata``, the cached ``load_mesh``): the same arrays,
bodies, boxes and transforms as trimesh gives, so that a warm-cache run that never imports trimesh
derives the same results as one that does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from ncfix.collision.exact import inside
from ncfix.errors import GeometryError
from ncfix.geometry import mesh as mesh_module
from ncfix.geometry.mesh import load_head, load_mesh
from ncfix.geometry.meshdata import Mesh, as_mesh, component_labels, face_adjacency

REPO = Path(__file__).resolve().parents[1]
CORPUS = REPO.parent / "shared" / "corpus"
BUNDLED = sorted([*(REPO / "samples").glob("*.stl"), *(REPO / "tests" / "golden" / "meshes").glob("*.stl")])
CORPUS_MESHES = sorted(p for p in CORPUS.rglob("*") if p.suffix.lower() in (".stl", ".obj")) if CORPUS.is_dir() else []


def _meshes(corpus: bool) -> list:
    if corpus:
        if not CORPUS_MESHES:
            return [pytest.param(None, marks=pytest.mark.skip(reason=f"no corpus meshes in {CORPUS}"))]
        return [pytest.param(p, id=str(p.relative_to(CORPUS))) for p in CORPUS_MESHES]
    return [pytest.param(p, id=p.name) for p in BUNDLED]


def _trimesh_load(path: Path, role: str):
    """What ``load_mesh`` computed before it cached its result: trimesh's read and repairs."""
    return mesh_module._validate(mesh_module._read_triangles(path, mesh_module.MESH_FORMATS[path.suffix.lower()], role),
                                 str(path), role)


def _check_file(path: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "cache"))
    for role in ("part", "head"):
        try:
            want = _trimesh_load(path, role)
        except GeometryError as exc:
            for _ in range(2):  # a file trimesh cannot read, or a head that is not closed: same error, never cached
                with pytest.raises(GeometryError) as raised:
                    load_mesh(path, role)
                assert str(raised.value) == str(exc)
            continue
        cold = load_mesh(path, role)
        warm = load_mesh(path, role)
        for got in (cold, warm):
            assert got.arrays.vertices.dtype == np.float64 and got.arrays.faces.dtype == np.int64
            assert np.array_equal(got.arrays.vertices, np.asarray(want.mesh.vertices))
            assert np.array_equal(got.arrays.faces, np.asarray(want.mesh.faces))
            assert (got.closed, got.warnings, got.name, got.role) == (want.closed, want.warnings, want.name, want.role)
            tm = want.mesh
            assert np.array_equal(got.arrays.bounds, tm.bounds)
            assert np.array_equal(got.arrays.triangles, tm.triangles)
            labels = trimesh.graph.connected_component_labels(tm.face_adjacency, node_count=len(tm.faces))
            assert np.array_equal(component_labels(got.arrays.faces), labels)


@pytest.mark.parametrize("path", _meshes(False))
def test_a_bundled_mesh_reads_back_from_the_cache_as_trimesh_read_it(path, tmp_path, monkeypatch):
    _check_file(path, tmp_path, monkeypatch)


@pytest.mark.parametrize("path", _meshes(True))
def test_a_corpus_mesh_reads_back_from_the_cache_as_trimesh_read_it(path, tmp_path, monkeypatch):
    _check_file(path, tmp_path, monkeypatch)


def test_a_cached_mesh_is_read_without_trimesh(tmp_path, monkeypatch):
    """A hit does not read the file with trimesh; a changed file (its bytes are the key) is read again."""
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(10.0, 20.0, 30.0)).export(path)
    first = load_mesh(path, "part")

    def refuse(*args, **kwargs):
        raise AssertionError("read with trimesh although cached")

    monkeypatch.setattr(mesh_module, "_read_triangles", refuse)
    again = load_mesh(path, "part")
    assert np.array_equal(again.arrays.vertices, first.arrays.vertices)
    again.arrays.apply_transform(np.diag([2.0, 2.0, 2.0, 1.0]))  # a placement moves a copy, not the cache
    assert np.array_equal(load_mesh(path, "part").arrays.vertices, first.arrays.vertices)
    trimesh.creation.box(extents=(10.0, 20.0, 31.0)).export(path)
    with pytest.raises(AssertionError, match="although cached"):
        load_mesh(path, "part")


def _transforms() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    out = [np.eye(4), np.diag([-1.0, 1.0, 1.0, 1.0]), np.diag([1.0, 1.0, 1.0 + 5e-9, 1.0])]
    shift = np.eye(4)
    shift[:3, 3] = (10.0, -20.0, 0.5)
    out.append(shift)
    for _ in range(4):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = q, rng.normal(0, 50, 3)  # half of them mirror (det -1)
        out.append(m)
    return out


@pytest.mark.parametrize("k", range(len(_transforms())))
def test_apply_transform_is_trimeshs_to_the_bit(k):
    """Placements and the head's orientation move a ``Mesh`` as trimesh moved it: the same
    vertices bit for bit, faces reversed by a mirroring transform."""
    matrix = _transforms()[k]
    tm = load_head(REPO / "samples" / "deposition_head.stl").mesh.copy()
    mine = as_mesh(tm).copy()
    tm.apply_transform(matrix)
    mine.apply_transform(matrix)
    assert np.array_equal(mine.vertices, np.asarray(tm.vertices))
    assert np.array_equal(mine.faces, np.asarray(tm.faces))
    assert np.array_equal(mine.bounds, tm.bounds)


def test_bodies_and_adjacency_are_trimeshs_on_a_mesh_of_many_bodies():
    """Shuffled faces of several boxes, one of them with an edge shared by four faces (two boxes
    touching along it: an edge of more than two faces joins none), and a lone vertex."""
    rng = np.random.default_rng(4)
    boxes = []
    for i in range(5):
        b = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        b.apply_translation((3.0 * i, 0.0, 0.0))
        boxes.append(b)
    edge = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    edge.apply_translation((1.0, 1.0, 0.0))  # shares the edge x = 0.5, y = 0.5 with the first box
    joined = trimesh.util.concatenate([*boxes, edge])
    joined.merge_vertices()
    faces = np.asarray(joined.faces)[rng.permutation(len(joined.faces))]
    vertices = np.vstack([np.asarray(joined.vertices), [[99.0, 99.0, 99.0]]])
    tm = trimesh.Trimesh(vertices, faces, process=False)
    want = trimesh.graph.connected_component_labels(tm.face_adjacency, node_count=len(faces))
    assert want.max() + 1 == 6
    assert np.array_equal(component_labels(faces), want)
    pairs = np.sort(face_adjacency(faces), axis=1)
    assert np.array_equal(pairs[np.lexsort(pairs.T[::-1])], np.unique(np.sort(tm.face_adjacency, axis=1), axis=0))
    assert np.array_equal(Mesh(vertices, faces).bounds, tm.bounds)  # the lone vertex is not in the box


@pytest.mark.parametrize("name", ["deposition_head.stl", "recreated_mold.stl"])
def test_inside_is_trimeshs_contains_away_from_the_surface(name):
    """The depth's inside test (winding numbers) gives trimesh's ``contains`` for every point
    farther than a micrometre from the surface (on the surface, either answer adds no depth)."""
    tm = load_mesh(REPO / "samples" / name, "part").mesh
    rng = np.random.default_rng(5)
    lo, hi = tm.bounds
    points = np.vstack([rng.uniform(lo - 2.0, hi + 2.0, (3000, 3)),
                        tm.vertices[rng.integers(0, len(tm.vertices), 1000)] + rng.normal(0, 0.3, (1000, 3))])
    away = np.abs(trimesh.proximity.signed_distance(tm, points)) > 1e-6
    got = inside(points, np.asarray(tm.triangles), tm.bounds)
    assert got.any() and (~got).any()
    assert np.array_equal(got[away], tm.contains(points)[away])
    assert not inside(points, np.asarray(tm.triangles), tm.bounds, lambda p: np.zeros(len(p), dtype=bool)).any()
