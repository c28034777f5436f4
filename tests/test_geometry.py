"""Mesh loading and validation, voxelization, the head model, and the exact reference check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from ncfix.collision.head import RiskZones, build_head_model
from ncfix.collision.voxelize import surface_cells, voxelize
from ncfix.errors import GeometryError
from ncfix.geometry.distance import point_mesh_distance, winding_numbers
from ncfix.geometry.frames import angle_between_deg, rotation_from_z
from ncfix.geometry.mesh import (
    LoadedMesh,
    check_part_overlaps,
    find_tip,
    load_head,
    load_mesh,
    orient_head,
)
from ncfix.reference import ExactReference

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
CORPUS = Path(__file__).resolve().parents[2] / "shared" / "corpus"


def write_ascii_stl(path: Path, triangles: np.ndarray) -> Path:
    lines = ["solid test"]
    for tri in np.asarray(triangles, dtype=np.float64):
        lines.append("facet normal 0 0 0\n outer loop")
        lines += [f"  vertex {x:.17g} {y:.17g} {z:.17g}" for x, y, z in tri]
        lines.append(" endloop\nendfacet")
    lines.append("endsolid test")
    path.write_text("\n".join(lines) + "\n")
    return path


def box_triangles(lo=(0.0, 0.0, 0.0), hi=(10.0, 10.0, 10.0)) -> np.ndarray:
    box = trimesh.creation.box(bounds=[lo, hi])
    return np.array(box.triangles)


@pytest.fixture(scope="module")
def sample_head() -> trimesh.Trimesh:
    return load_head(SAMPLES / "deposition_head.stl").mesh


@pytest.fixture(scope="module")
def sample_mold() -> trimesh.Trimesh:
    return load_mesh(SAMPLES / "recreated_mold.stl", "part").mesh


# ---- loading: errors ---------------------------------------------------------------------


def _missing(tmp: Path) -> Path:
    return tmp / "nope.stl"


def _empty(tmp: Path) -> Path:
    p = tmp / "empty.stl"
    p.write_bytes(b"")
    return p


def _step(tmp: Path) -> Path:
    p = tmp / "head.step"
    p.write_text("ISO-10303-21;\n")
    return p


def _garbage(tmp: Path) -> Path:
    p = tmp / "garbage.stl"
    p.write_text("this is not a mesh\n")
    return p


def _nan(tmp: Path) -> Path:
    tri = box_triangles()
    tri[0, 0, 0] = np.nan
    return write_ascii_stl(tmp / "nan.stl", tri)


def _open_head(tmp: Path) -> Path:
    # Two adjacent faces (4 triangles) missing: a 6-edge hole that fill_holes does not close.
    box = trimesh.creation.box(bounds=[[0, 0, 0], [10, 10, 10]])
    normals = box.face_normals
    keep = ~((normals[:, 0] > 0.5) | (normals[:, 2] > 0.5))
    return write_ascii_stl(tmp / "open.stl", box.triangles[keep])


LOAD_ERRORS = [
    (_missing, "head", "{p}: the head mesh file does not exist (check the --head path)"),
    (_missing, "part", "{p}: the part mesh file does not exist (check the --part path)"),
    (_empty, "head", "{p}: the head mesh file is empty (export the mesh again as STL or OBJ)"),
    (_step, "part", "{p}: cannot read '.step' files as a mesh (export the part as one of .obj, .stl)"),
    (_garbage, "head", "{p}: no triangles found: the file is not a STL mesh (export the head again as STL or OBJ)"),
    (_nan, "part", "{p}: 1 vertices have NaN or infinite coordinates (repair the mesh in CAD and export it again)"),
    (
        _open_head,
        "head",
        "{p}: the head mesh is not closed (6 open edges remain after filling holes) "
        "(export the head as one closed (watertight) solid)",
    ),
]


@pytest.mark.parametrize(("make", "role", "message"), LOAD_ERRORS)
def test_load_mesh_rejects_bad_files_with_a_message_saying_what_to_do(tmp_path, make, role, message):
    path = make(tmp_path)
    with pytest.raises(GeometryError) as info:
        load_mesh(path, role)
    assert str(info.value) == message.format(p=path)
    assert info.value.exit_code == 2


# ---- loading: repairs and warnings -------------------------------------------------------


def _degenerate(tmp: Path) -> Path:
    tri = box_triangles()
    sliver = np.array([[[1.0, 1.0, 10.0], [2.0, 2.0, 10.0], [3.0, 3.0, 10.0]]])
    return write_ascii_stl(tmp / "degenerate.stl", np.concatenate([tri, sliver, sliver]))


def _inverted(tmp: Path) -> Path:
    return write_ascii_stl(tmp / "inverted.stl", box_triangles()[:, ::-1, :])


def _quad_hole(tmp: Path) -> Path:
    box = trimesh.creation.box(bounds=[[0, 0, 0], [10, 10, 10]])
    keep = ~(box.face_normals[:, 2] > 0.5)
    return write_ascii_stl(tmp / "lid.stl", box.triangles[keep])


def _two_shells(tmp: Path) -> Path:
    tri = np.concatenate([box_triangles(), box_triangles((20, 0, 0), (30, 10, 10))])
    return write_ascii_stl(tmp / "two.stl", tri)


LOAD_WARNINGS = [
    (_degenerate, "part", True, ["{p}: dropped 2 degenerate (zero-area) triangles"]),
    (_inverted, "head", True, ["{p}: the triangles faced inward (negative volume) and were flipped"]),
    (_quad_hole, "head", True, ["{p}: the mesh had 4 open edges; the holes were filled"]),
    (
        _open_head,
        "part",
        False,
        ["{p}: the part mesh is not closed (6 open edges); it is used as a surface, "
         "so a head entirely inside it is not detected"],
    ),
    (_two_shells, "head", True, ["{p}: the head has 2 separate shells; they are treated as one solid"]),
]


@pytest.mark.parametrize(("make", "role", "closed", "warnings"), LOAD_WARNINGS)
def test_load_mesh_repairs_what_it_can_and_warns(tmp_path, make, role, closed, warnings):
    path = make(tmp_path)
    loaded = load_mesh(path, role)
    assert loaded.warnings == [w.format(p=path) for w in warnings]
    assert loaded.closed is closed
    if closed:
        assert loaded.mesh.is_watertight and loaded.mesh.volume > 0


@pytest.mark.parametrize("name", ["deposition_head.stl", "recreated_mold.stl"])
def test_samples_are_single_closed_shells(name):
    loaded = load_mesh(SAMPLES / name, "part")
    assert loaded.warnings == []
    assert loaded.closed and loaded.mesh.body_count == 1


def test_obj_and_binary_stl_load_the_same_geometry(tmp_path):
    box = trimesh.creation.box(bounds=[[0, 0, 0], [10, 20, 30]])
    box.export(tmp_path / "b.stl")
    box.export(tmp_path / "b.obj")
    for name in ("b.stl", "b.obj"):
        loaded = load_mesh(tmp_path / name, "part")
        assert loaded.warnings == []
        assert loaded.mesh.volume == pytest.approx(6000.0)


# ---- head orientation --------------------------------------------------------------------


def _box_head(tmp_path) -> LoadedMesh:
    # A 10 mm cube sitting on z = 0, "tip" at the centre of its bottom face.
    return load_mesh(write_ascii_stl(tmp_path / "h.stl", box_triangles((-5, -5, 0), (5, 5, 10))), "head")


ORIENT_ERRORS = [
    ((0, 0, 0), (0, 0, 0), "{p}: the head axis (0, 0, 0) has no direction "
     "(give --head-axis as a nonzero vector X,Y,Z from the tip toward the head)"),
    ((0, 0, 5), (0, 0, 1), "{p}: the head reaches 5 mm below the tip (0, 0, 5) along the axis (0, 0, 1) "
     "(check --head-tip and --head-axis; the lowest point along this axis is (0, 0, 0))"),
    ((0, 0, 0), (1, 0, 0), "{p}: the head reaches 5 mm below the tip (0, 0, 0) along the axis (1, 0, 0) "
     "(check --head-tip and --head-axis; the lowest point along this axis is (-5, 0, 5))"),
]


@pytest.mark.parametrize(("tip", "axis", "message"), ORIENT_ERRORS)
def test_orient_head_rejects_a_tip_that_is_not_the_lowest_point(tmp_path, tip, axis, message):
    loaded = _box_head(tmp_path)
    with pytest.raises(GeometryError) as info:
        orient_head(loaded, tip, axis)
    assert str(info.value) == message.format(p=loaded.name)


ORIENT_WARNINGS = [
    ((0, 0, 0), (0, 0, 1), []),
    ((0, 0, 0.4), (0, 0, 1), []),  # within the 0.5 mm tolerance
    ((0, 0, -2), (0, 0, 1), ["{p}: the head starts 2 mm above the tip (0, 0, -2) along the axis; "
                             "ncfix assumes the nozzle is at the tip"]),
    ((20, 0, 0), (0, 0, 1), ["{p}: the tip (20, 0, 0) is 15 mm away from the head mesh; check --head-tip"]),
]


@pytest.mark.parametrize(("tip", "axis", "warnings"), ORIENT_WARNINGS)
def test_orient_head_warns_when_the_tip_is_off_the_mesh(tmp_path, tip, axis, warnings):
    loaded = _box_head(tmp_path)
    oriented = orient_head(loaded, tip, axis)
    assert oriented.warnings == [w.format(p=loaded.name) for w in warnings]


CORPUS_HEADS = [
    ("s3_deformfdm/nozzle_converted.stl", (0.0, 1.0, 0.0), (0.0, 0.0, 0.0), 23.0),
    ("multiaxis_3dp_motionplanning/extruderHead_converted.stl", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), 30.0),
    ("e3d_v6/e3d_v6.stl", (0.0, 1.0, 0.0), (-4.4, -89.0, 12.5), 62.3),
]


@pytest.mark.parametrize(("name", "axis", "tip", "length_mm"), CORPUS_HEADS)
def test_corpus_heads_load_with_their_tip_at_the_origin_and_axis_up(name, axis, tip, length_mm):
    path = CORPUS / name
    if not path.is_file():
        pytest.skip(f"corpus file {path} is not available")
    raw = load_mesh(path, "head")
    assert np.allclose(find_tip(raw.mesh, np.array(axis)), tip, atol=0.05)
    head = orient_head(raw, tip, axis)
    assert head.warnings == []
    assert head.mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-6)
    assert head.mesh.bounds[1, 2] == pytest.approx(length_mm, abs=0.05)
    lowest = head.mesh.vertices[np.argmin(head.mesh.vertices[:, 2])]
    assert np.linalg.norm(lowest[:2]) < 0.5


# ---- parts against the program -----------------------------------------------------------


def test_part_far_from_the_toolpath_is_an_error(sample_mold):
    part = LoadedMesh(sample_mold, "mold.stl", "part", True)
    lo, hi = np.array([1000.0, 0, 0]), np.array([1100.0, 50, 50])
    with pytest.raises(GeometryError) as info:
        check_part_overlaps(part, lo, hi)
    assert str(info.value) == (
        "mold.stl: the part is 900 mm away from the toolpath (part box (-100, -50, 0)..(100, 50, 60), "
        "toolpath box (1000, 0, 0)..(1100, 50, 50)) (export the part in the program's workpiece frame and units)"
    )


PART_OVERLAP_CASES = [
    ((-50.0, -20.0, 20.0), (50.0, 20.0, 60.0), []),
    ((150.0, 0.0, 0.0), (170.0, 10.0, 10.0), ["mold.stl: the part does not overlap the toolpath's "
                                              "bounding box (it is 50 mm away); check its frame and units"]),
    ((-3.0, -2.0, 0.0), (3.0, 2.0, 2.0), ["mold.stl: the part's size does not match the toolpath's "
                                          "(the part is about 25.4 times larger than the toolpath: inches vs mm?)"]),
]


@pytest.mark.parametrize(("lo", "hi", "warnings"), PART_OVERLAP_CASES)
def test_part_overlap_warnings(sample_mold, lo, hi, warnings):
    part = LoadedMesh(sample_mold, "mold.stl", "part", True)
    assert check_part_overlaps(part, np.array(lo), np.array(hi)) == warnings


# ---- voxelizer ---------------------------------------------------------------------------


def test_voxelizer_is_exact_on_an_axis_aligned_box_with_vertices_on_cell_centres():
    box = trimesh.creation.box(bounds=[[0.25, 0.25, 0.25], [10.25, 5.25, 3.25]])
    grid = voxelize(box.vertices, box.faces, 0.5, origin_mm=np.zeros(3), shape=(24, 14, 10))
    assert grid.occupancy.sum() == 20 * 10 * 6


@pytest.mark.parametrize("pitch_mm", [0.5, 0.7])
def test_voxelizer_matches_winding_numbers_at_cell_centres(sample_head, pitch_mm):
    grid = voxelize(sample_head.vertices, sample_head.faces, pitch_mm)
    rng = np.random.default_rng(3)
    index = np.stack([rng.integers(0, n, 4000) for n in grid.shape], axis=1)
    inside = winding_numbers(grid.centers(index), np.asarray(sample_head.triangles)) > 0.5
    assert np.array_equal(grid.occupancy[tuple(index.T)], inside)
    assert grid.occupancy.sum() * pitch_mm**3 == pytest.approx(sample_head.volume, rel=5e-3)


def test_voxelizer_fills_overlapping_shells_as_a_union():
    a = trimesh.creation.box(bounds=[[0, 0, 0], [4, 4, 4]])
    b = trimesh.creation.box(bounds=[[2, 2, 2], [6, 6, 6]])
    both = trimesh.util.concatenate([a, b])
    grid = voxelize(both.vertices, both.faces, 0.5)
    centres = grid.filled_centers()
    in_a = (centres >= 0).all(axis=1) & (centres <= 4).all(axis=1)
    in_b = (centres >= 2).all(axis=1) & (centres <= 6).all(axis=1)
    assert (in_a | in_b).all()
    assert len(centres) == 2 * 8**3 - 4**3


def test_voxelizer_counts_parts_below_a_clipped_grid(sample_mold):
    full = voxelize(sample_mold.vertices, sample_mold.faces, 1.0)
    origin = full.origin_mm + np.array([0.0, 0.0, 30.0])
    clipped = voxelize(sample_mold.vertices, sample_mold.faces, 1.0, origin_mm=origin, shape=(full.shape[0], full.shape[1], 20))
    assert np.array_equal(clipped.occupancy, full.occupancy[:, :, 30:50])


def test_surface_cells_mark_every_cell_near_the_surface(sample_head):
    pitch = 0.8
    grid = voxelize(sample_head.vertices, sample_head.faces, pitch)
    radius = 0.5 * np.sqrt(3) * pitch
    band = surface_cells(sample_head.vertices, sample_head.faces, grid.origin_mm, grid.shape, pitch, radius)
    rng = np.random.default_rng(5)
    marked = np.argwhere(band)
    index = np.clip(marked[rng.integers(0, len(marked), 3000)] + rng.integers(-2, 3, (3000, 3)), 0, np.array(grid.shape) - 1)
    near = point_mesh_distance(grid.centers(index), np.asarray(sample_head.triangles)) <= radius
    assert band[tuple(index.T)][near].all()


@pytest.mark.parametrize("pitch", [0.5, 0.8])
def test_compiled_surface_cells_mark_the_same_cells_as_the_numpy_passes(sample_head, sample_mold, pitch):
    for mesh in (sample_head, sample_mold):
        grid = voxelize(mesh.vertices, mesh.faces, pitch)
        args = (mesh.vertices, mesh.faces, grid.origin_mm, grid.shape, pitch, 0.5 * np.sqrt(3) * pitch + 1e-6)
        assert np.array_equal(surface_cells(*args), surface_cells(*args, compiled=False))


@pytest.mark.parametrize("pitch", [0.5, 0.8])
def test_the_compiled_voxelizer_fills_the_same_cells_as_the_numpy_passes(sample_head, sample_mold, pitch):
    for mesh in (sample_head, sample_mold):
        whole = voxelize(mesh.vertices, mesh.faces, pitch)
        assert whole.occupancy.any()
        assert np.array_equal(whole.occupancy, voxelize(mesh.vertices, mesh.faces, pitch, compiled=False).occupancy)
        # a grid that cuts the mesh (crossings below and beside it), off the whole grid's lattice
        origin = whole.origin_mm + 0.37 * pitch + np.array([5.0, -3.0, 4.0])
        shape = tuple(int(n) for n in np.array(whole.shape) * 2 // 3)
        cut = voxelize(mesh.vertices, mesh.faces, pitch, origin_mm=origin, shape=shape)
        assert cut.occupancy.any()
        assert np.array_equal(cut.occupancy, voxelize(mesh.vertices, mesh.faces, pitch, origin_mm=origin, shape=shape,
                                                      compiled=False).occupancy)


# ---- head model --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sample_model(sample_head):
    return build_head_model(sample_head, 1.0)


def test_head_model_counts_and_risk_zone_proportions(sample_model):
    counts = sample_model.counts()
    assert counts["lower"] + counts["middle"] + counts["upper"] + counts["interior"] == counts["total"]
    assert counts["total"] == len(sample_model.radii_mm) == len(sample_model.zone)
    lower, middle, upper = sample_model.zone_fractions()
    assert lower + middle + upper == pytest.approx(1.0)
    # Densest at the bottom, as in the seed (58 / 35 / 7 %).
    assert lower > middle > upper > 0
    assert 0.5 < lower < 0.8 and upper < 0.15
    assert counts == {"lower": 10552, "middle": 3320, "upper": 620, "interior": 6084, "total": 20576, "spheres": 43}
    assert sample_model.summary() == (
        "head model at 1 mm: 20576 balls (14492 samples: lower 10552 (73%), middle 3320 (23%), "
        "upper 620 (4%); 6084 interior), 43 bounding spheres"
    )


def test_head_model_ball_sizes_follow_the_zones(sample_model):
    samples = ~sample_model.interior
    pitch = sample_model.pitch_mm
    for zone, level in enumerate(RiskZones().levels):
        radii = sample_model.radii_mm[samples & (sample_model.zone == zone)]
        assert np.allclose(radii, 0.5 * np.sqrt(3) * 2**level * pitch, atol=1e-5)


@pytest.mark.parametrize("pitch_mm", [0.5, pytest.param(1.0, marks=pytest.mark.heavy)])
def test_head_model_covers_every_point_of_the_head(sample_head, pitch_mm):
    model = build_head_model(sample_head, pitch_mm)
    rng = np.random.default_rng(11)
    lo, hi = sample_head.bounds
    box_points = rng.uniform(lo - 1.0, hi + 1.0, (3000, 3))
    surface, _ = trimesh.sample.sample_surface(sample_head, 3000, seed=12)
    near_surface = surface + rng.normal(0.0, 0.3, surface.shape)
    points = np.concatenate([box_points, near_surface, surface])
    inside = winding_numbers(points, np.asarray(sample_head.triangles)) > 0.5
    inside[-len(surface):] = True  # points on the surface belong to the head
    assert inside.sum() > 3000
    assert model.covers(points[inside]).all()


def test_head_model_bounding_spheres_contain_their_balls(sample_model):
    m = sample_model
    reach = np.linalg.norm(m.centers_mm - m.group_centers_mm[m.group], axis=1) + m.radii_mm
    assert (reach <= m.group_radii_mm[m.group] + 1e-9).all()


def test_free_by_head_model_is_free_by_the_exact_check(sample_head, sample_model):
    # A box part with an exact signed distance: balls all clear => the mesh check must say free.
    box = trimesh.creation.box(bounds=[[-20.0, -20.0, -10.0], [20.0, 20.0, 0.0]])
    ref = ExactReference(sample_head, {"box": box})
    rng = np.random.default_rng(7)
    model_free = 0
    for _ in range(150):
        n = rng.normal(size=3)
        n[2] = abs(n[2]) + 0.5
        n /= np.linalg.norm(n)
        tip = np.array([rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(0.2, 6.0)])
        rot = rotation_from_z(n)
        centres = tip + sample_model.centers_mm @ rot.T
        q = np.abs(centres - np.array([0.0, 0.0, -5.0])) - np.array([20.0, 20.0, 5.0])
        sdf = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
        if (sdf > sample_model.radii_mm).all():
            model_free += 1
            assert not ref.collides(tip, rot)
    assert model_free > 20


# ---- exact reference ---------------------------------------------------------------------


def test_reference_clearance_above_a_box_is_the_tip_height(sample_head):
    box = trimesh.creation.box(bounds=[[-50.0, -50.0, -10.0], [50.0, 50.0, 0.0]])
    ref = ExactReference(sample_head, {"table": box})
    for height in (0.5, 3.0, 6.0):
        value, hit = ref.clearance(np.array([0.0, 0.0, height]), np.eye(3))
        assert value == pytest.approx(height, abs=1e-6)
        assert hit == []
    value, hit = ref.clearance(np.array([0.0, 0.0, -2.0]), np.eye(3))
    assert value < 0 and hit == ["table"]


def test_reference_agrees_with_trimesh_distance_to_a_sphere(sample_head):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    ref = ExactReference(sample_head, {"ball": sphere})
    rng = np.random.default_rng(2)
    for _ in range(10):
        n = rng.normal(size=3)
        n[2] = abs(n[2]) + 0.3
        rot = rotation_from_z(n / np.linalg.norm(n))
        tip = rng.normal(size=3) * 3.0 + np.array([0.0, 0.0, 12.0])
        value, _ = ref.clearance(tip, rot)
        head_world = trimesh.Trimesh(tip + sample_head.vertices @ rot.T, sample_head.faces)
        # Both meshes are convex near the contact: the closest pair involves a head vertex or a
        # sphere vertex, so the minimum of the two one-sided distances is the mesh distance.
        d1 = -trimesh.proximity.signed_distance(sphere, head_world.vertices).max()
        d2 = -trimesh.proximity.signed_distance(head_world, sphere.vertices).max()
        if value >= 0:
            assert value == pytest.approx(min(d1, d2), abs=1e-3)
        else:
            assert min(d1, d2) < 0


def test_reference_sees_a_part_wholly_inside_the_head(sample_head):
    small = trimesh.creation.box(bounds=[[-2.0, -2.0, 60.0], [2.0, 2.0, 64.0]])
    ref = ExactReference(sample_head, {"inner": small})
    assert ref.collides(np.zeros(3), np.eye(3))
    value, hit = ref.clearance(np.zeros(3), np.eye(3))
    assert value < 0 and hit == ["inner"]


def test_reference_sees_a_body_inside_the_head_among_several_bodies_in_one_part(sample_head):
    """Mesh-mesh collision tests triangles only: the small block inside the head touches none,
    and a second body far away must not hide it, whichever comes first in the file."""
    small = trimesh.creation.box(bounds=[[-2.0, -2.0, 60.0], [2.0, 2.0, 64.0]])
    far = trimesh.creation.box(bounds=[[200.0, 0.0, 0.0], [201.0, 1.0, 1.0]])
    for bodies in ([small, far], [far, small]):
        ref = ExactReference(sample_head, {"two": trimesh.util.concatenate(bodies)})
        assert ref.collides(np.zeros(3), np.eye(3))
        assert ref.clearance(np.zeros(3), np.eye(3))[0] < 0
        assert not ref.collides(np.array([0.0, 0.0, 100.0]), np.eye(3))


def test_reference_sees_the_head_inside_a_hollow_parts_wall_not_in_its_cavity(sample_head):
    """A hollow box: two shells (the cavity's faces inward). The head inside the wall collides,
    the head inside the cavity is free although it lies inside the outer shell."""
    outer = trimesh.creation.box([1000.0] * 3)
    cavity = trimesh.creation.box([400.0] * 3)
    cavity.invert()
    ref = ExactReference(sample_head, {"hollow": trimesh.util.concatenate([outer, cavity])})
    assert not ref.collides(np.array([0.0, 0.0, -60.0]), np.eye(3))
    assert ref.collides(np.array([350.0, 0.0, -60.0]), np.eye(3))
    # An open part is a surface: nothing lies inside it.
    shell = ExactReference(sample_head, {"shell": outer}, open_parts={"shell"})
    assert not shell.collides(np.zeros(3), np.eye(3))


def test_compiled_containment_answers_as_the_reference(sample_head):
    """``nested.Nested`` (box tests, then one compiled winding number per body that passes them)
    gives the reference's answer wherever no triangles meet (the only poses it is asked about),
    among poses where bodies of a multi-body part lie inside the head, the head inside a large
    block or a hollow box's wall, a body of a two-body head inside a part; for closed and open
    parts."""
    import coal

    from ncfix.collision.nested import Nested, mesh_bodies

    rng = np.random.default_rng(11)
    smalls = []
    for k in range(12):
        body = trimesh.creation.box([rng.uniform(0.5, 6.0)] * 3) if k % 2 else \
            trimesh.creation.icosphere(1, rng.uniform(0.3, 3.0))
        body.apply_translation(rng.uniform(-20.0, 20.0, 3) + [0.0, 0.0, 40.0])
        smalls.append(body)
    outer, cavity = trimesh.creation.box([600.0] * 3), trimesh.creation.box([300.0] * 3)
    cavity.invert()
    parts = {"smalls": trimesh.util.concatenate(smalls),
             "large": trimesh.creation.box(bounds=[[-100.0, -100.0, -20.0], [100.0, 100.0, 160.0]]),
             "hollow": trimesh.util.concatenate([outer, cavity])}
    satellite = trimesh.creation.box(bounds=[[-40.0, -1.0, 9.0], [-38.0, 1.0, 11.0]])
    for head in (sample_head, trimesh.util.concatenate([sample_head, satellite])):
        for open_parts in ((), ("smalls", "large")):
            ref = ExactReference(head, parts, open_parts=open_parts)
            tests = [Nested(mesh_bodies(head), mesh_bodies(mesh), name not in open_parts)
                     for name, mesh in parts.items()]
            answers = []
            for k in range(300):
                n = rng.normal(size=3) + [0.0, 0.0, 1.0]
                r = rotation_from_z(n / np.linalg.norm(n))
                if k % 3 == 0:  # a small body about 30-60 mm up the head's axis
                    centre = smalls[rng.integers(len(smalls))].centroid
                    c = centre - r @ np.array([0.0, 0.0, rng.uniform(30.0, 60.0)]) + rng.normal(size=3)
                elif k % 3 == 1:  # in and about the large block
                    c = rng.normal(size=3) * [40.0, 40.0, 30.0] + [0.0, 0.0, 10.0]
                else:  # the hollow box's wall or cavity
                    c = rng.uniform(-350.0, 350.0, 3)
                for part, test in zip(ref.parts, tests):
                    meet = coal.collide(ref.head_bvh, coal.Transform3s(r, c), part.bvh, coal.Transform3s(),
                                        coal.CollisionRequest(), coal.CollisionResult()) > 0
                    if not meet:  # (where triangles meet, either answer stands)
                        answers.append(test(c, r))
                        assert answers[-1] == ref._contained(part, c, r)
            assert 40 < sum(answers) < len(answers) - 40


def test_bead_clearance_agrees_with_trimesh_signed_distance(sample_head):
    ref = ExactReference(sample_head, {}, tip_allowance_mm=1.0)
    rng = np.random.default_rng(4)
    centres = rng.uniform([-40, -40, -5], [60, 40, 40], (300, 3))
    rot = rotation_from_z(np.array([0.3, -0.2, 1.0]))
    tip = np.array([1.0, 2.0, 3.0])
    radius = 1.0
    local = (centres - tip) @ rot
    expected = -trimesh.proximity.signed_distance(ref._bead_head, local) - radius
    assert ref.bead_clearance(tip, rot, centres, radius) == pytest.approx(expected.min(), abs=1e-6)
    for i in range(0, 300, 37):
        assert ref.bead_clearance(tip, rot, centres[i : i + 1], radius) == pytest.approx(expected[i], abs=1e-6)


TIP_ALLOWANCE_CASES = [
    # bead centre below the tip by 0.5 mm, radius 1: overlaps the nozzle's first millimetre only.
    (0.0, -1.0 + 0.5),
    (1.0, None),  # the bottom 1 mm is not checked: clear
]


@pytest.mark.parametrize(("allowance_mm", "expected"), TIP_ALLOWANCE_CASES)
def test_tip_allowance_hides_the_nozzle_end_from_beads(sample_head, allowance_mm, expected):
    ref = ExactReference(sample_head, {}, tip_allowance_mm=allowance_mm)
    value = ref.bead_clearance(np.zeros(3), np.eye(3), np.array([[0.0, 0.0, -0.5]]), 1.0)
    if expected is None:
        assert value > 0
    else:
        assert value == pytest.approx(expected, abs=1e-9)


def test_rotation_from_z_maps_the_axis_onto_the_tool_vector():
    vectors = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.4, 0.8], [1e-9, 0, -1]], dtype=float)
    rots = rotation_from_z(vectors)
    unit = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    assert np.allclose(rots @ np.array([0.0, 0.0, 1.0]), unit, atol=1e-9)
    assert np.allclose(np.linalg.det(rots), 1.0)
    assert np.allclose(rots @ rots.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_rotation_between_is_the_minimal_rotation_in_every_case():
    """The compiled Rodrigues loop against the matrix formula I + K + K²/(1 + c) in numpy, for
    general pairs, both broadcast shapes and a single pair; opposite directions a half turn."""
    from ncfix.geometry.frames import minimal_rotation, rotation_between

    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(2000, 3)) * 5, rng.normal(size=(2000, 3))
    b[:3] = [[1, 0, 0], [0, 0, 1], [-1, 2, 3]]
    a[:3] = [[-2, 0, 0], [0, 0, -1], [1, -2, -3]]  # opposite: x (the helper becomes y), z, general
    ah, bh = (v / np.linalg.norm(v, axis=1, keepdims=True) for v in (a, b))
    v, c = np.cross(ah, bh), (ah * bh).sum(axis=1)
    k = np.zeros((len(a), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2], k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = -v[:, 2], v[:, 1], -v[:, 0], v[:, 2], \
        -v[:, 1], v[:, 0]
    want = np.eye(3) + k + (k @ k) / np.where(c < -1 + 1e-12, np.inf, 1 + c)[:, None, None]
    got = rotation_between(a, b)
    assert np.allclose(got[3:], want[3:], rtol=0, atol=1e-12)
    for i in range(3):  # a half turn: R â = b̂, R = Rᵀ, det 1
        assert np.allclose(got[i] @ ah[i], bh[i], atol=1e-12) and np.allclose(got[i], got[i].T, atol=1e-15)
        assert np.isclose(np.linalg.det(got[i]), 1.0)
    assert np.array_equal(rotation_between(a[5], b[5]), got[5])
    assert np.array_equal(rotation_between(a[5], b[:4]), rotation_between(np.tile(a[5], (4, 1)), b[:4]))
    assert np.array_equal(minimal_rotation(b), rotation_between(np.array([0.0, 0.0, 1.0]), b))


@pytest.mark.parametrize("n", [1, 7, 5000])
def test_flat_cell_keys_group_as_numpy_unique_rows(n):
    from ncfix.geometry.cells import first_of_each_cell, group_cells

    rows = np.random.default_rng(n).integers(-40, 40, (n, 3))
    cell_of, members, counts = group_cells(rows)
    _, want_of, want_counts = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    assert (cell_of == want_of.reshape(-1)).all() and (counts == want_counts).all()
    assert (members == np.argsort(want_of.reshape(-1), kind="stable")).all()
    assert (first_of_each_cell(rows) == np.sort(np.unique(rows, axis=0, return_index=True)[1])).all()


@pytest.mark.parametrize("span", [1, 6, 1000, 1 << 40])
def test_first_of_each_cell_is_numpy_unique_first_index(span):
    """The hashed first-of-each-cell gives np.unique's first indices, ascending: many repeats
    (a few cells), few, and keys too wide for one int64 (the rows themselves)."""
    from ncfix.geometry.cells import first_of_each_cell

    rng = np.random.default_rng(span % 97)
    for n in (0, 1, 2, 20000):
        rows = rng.integers(-span, span, (n, 3))
        want = np.sort(np.unique(rows, axis=0, return_index=True)[1]) if n else np.zeros(0, dtype=np.int64)
        got = first_of_each_cell(rows)
        assert got.dtype == np.int64 and np.array_equal(got, want)


@pytest.mark.parametrize("shape_a, shape_b", [((3,), (3,)), ((40, 3), (40, 3)), ((1, 3), (40, 3)), ((3,), (40, 3)),
                                              ((5, 8, 3), (5, 8, 3))])
def test_angle_between_is_the_numpy_formula_bit_for_bit(shape_a, shape_b):
    """``angle_between_deg`` writes the cross and dot products out; the answers are those of
    np.cross / np.linalg.norm / np.sum exactly (outputs stay byte-identical), down to 0 and 180°."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    if b.ndim == 2:
        b[:2] = [a.reshape(-1, 3)[0], -a.reshape(-1, 3)[0]]  # parallel and opposite
    numpy_way = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))
    got = angle_between_deg(a, b)
    assert got.shape == numpy_way.shape and np.array_equal(got, numpy_way)
    assert np.array_equal(angle_between_deg(a.tolist(), b.tolist()), numpy_way)  # lists as well
