"""EPA correction: CoACD cache, GJK/EPA extraction vectors, and tilting the head about its tip."""

from __future__ import annotations

import time
from pathlib import Path

import coal
import numpy as np
import pytest
import trimesh

from ncfix.correct.decompose import cache_key, decompose
from ncfix.correct.epa import (EpaModel, _angle_deg, _boxes_met, _clip_hull, _convex, _pieces_met, _tilt_axis,
                              _turned)
from ncfix.geometry.frames import angle_between_deg, axis_rotation, minimal_rotation, rotation_from_z
from ncfix.reference import ExactReference

REPO = Path(__file__).resolve().parents[1]
Z = np.array([0.0, 0.0, 1.0])


def cylinder_head(radius_mm=3.0, height_mm=30.0) -> trimesh.Trimesh:
    """A cylinder standing on its tip disc: tip at the origin, axis +Z."""
    head = trimesh.creation.cylinder(radius=radius_mm, height=height_mm, sections=32)
    head.apply_translation([0.0, 0.0, height_mm / 2])
    return head


def box(lo, hi) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=[lo, hi])


def l_shape() -> trimesh.Trimesh:
    """A non-convex part: two bars meeting at a corner (CoACD cuts it in two)."""
    return box([0, 0, 0], [10, 2, 4]).union(box([0, 0, 0], [2, 10, 4]))


def exact_is_free(ref: ExactReference, tip, beads=None, radius_mm=1.0):
    """The caller's checker for tilt(): exact against the parts and (optionally) the beads."""

    def is_free(normals):
        rotations = minimal_rotation(normals)
        out = []
        for r in rotations:
            hit = ref.collides(tip, r)
            if not hit and beads is not None:
                hit = ref.bead_collides(tip, r, beads, radius_mm)
            out.append(not hit)
        return np.array(out)

    return is_free


def cap_directions(max_tilt_deg, step_deg=0.5, azimuth_step_deg=2.0):
    tilt, azimuth = np.meshgrid(
        np.radians(np.arange(0.0, max_tilt_deg + 1e-9, step_deg)), np.radians(np.arange(0.0, 360.0, azimuth_step_deg))
    )
    t, a = tilt.ravel(), azimuth.ravel()
    return np.column_stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])


def smallest_free_tilt(is_free, max_tilt_deg, azimuth_step_deg=2.0):
    """Brute force over a cap of directions (0.5° tilt rings): the least tilt the checker accepts."""
    directions = cap_directions(max_tilt_deg, azimuth_step_deg=azimuth_step_deg)
    free = is_free(directions)
    return float(angle_between_deg(Z, directions[free]).min())


# ---- decomposition cache ------------------------------------------------------------------


def test_decomposition_is_computed_once_then_read_from_the_cache(tmp_path):
    part = l_shape()
    cold = decompose(part, cache_dir=tmp_path)
    assert not cold.cached and len(cold.pieces) == 2
    assert all(p.to_trimesh().is_convex and p.to_trimesh().is_watertight for p in cold.pieces)
    assert list(tmp_path.iterdir()) == [tmp_path / f"coacd-{cold.key}.npz"]
    warm = decompose(part, cache_dir=tmp_path)
    assert warm.cached and warm.key == cold.key and warm.seconds < cold.seconds
    for a, b in zip(cold.pieces, warm.pieces):
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


def test_decomposition_is_deterministic(tmp_path):
    first = decompose(l_shape(), cache_dir=tmp_path / "a")
    second = decompose(l_shape(), cache_dir=tmp_path / "b")
    assert not second.cached
    for a, b in zip(first.pieces, second.pieces):
        assert np.array_equal(a.vertices, b.vertices)


def test_cache_key_changes_with_threshold_and_mesh():
    part = l_shape()
    moved = part.copy()
    moved.apply_translation([0.0, 0.0, 1e-3])
    keys = {cache_key(part, 0.05), cache_key(part, 0.1), cache_key(moved, 0.05)}
    assert len(keys) == 3
    assert cache_key(part, 0.05) == cache_key(l_shape(), 0.05)


def test_corrupt_cache_file_is_recomputed_and_overwritten(tmp_path):
    part = box([0, 0, 0], [5, 5, 5])
    key = decompose(part, cache_dir=tmp_path).key
    path = tmp_path / f"coacd-{key}.npz"
    for garbage in (b"not a zip file", path.read_bytes()[:100]):
        path.write_bytes(garbage)
        again = decompose(part, cache_dir=tmp_path)
        assert not again.cached and len(again.pieces) == 1
        assert decompose(part, cache_dir=tmp_path).cached


def test_default_cache_folder_comes_from_ncfix_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "env"))
    result = decompose(box([0, 0, 0], [5, 5, 5]))
    assert (tmp_path / "env" / f"coacd-{result.key}.npz").is_file()


# ---- coal's sign convention and the extraction vector ----------------------------------------


def test_coal_normal_points_from_o1_to_o2_and_depth_is_negative():
    # Sphere (o1) centred at x = 6 overlaps the box (o2, x <= 5) by 1 mm.
    request = coal.CollisionRequest()
    request.enable_contact = True
    result = coal.CollisionResult()
    hits = coal.collide(
        coal.Sphere(2.0), coal.Transform3s(np.eye(3), np.array([6.0, 0.0, 0.0])),
        coal.Box(10.0, 10.0, 10.0), coal.Transform3s(), request, result,
    )
    contact = result.getContact(0)
    assert hits == 1
    assert np.allclose(contact.normal, [-1.0, 0.0, 0.0])
    assert contact.penetration_depth == pytest.approx(-1.0)
    # so depth * normal = (+1, 0, 0) moves o1 out of o2
    assert np.allclose(contact.penetration_depth * contact.normal, [1.0, 0.0, 0.0])


def test_extraction_vector_points_out_of_the_box(tmp_path):
    # Head x in [-3, 3]; the box starts at x = 2: 1 mm deep, the way out is -x.
    model = EpaModel(cylinder_head(), [("wall", box([2, -20, 10], [20, 20, 40]))], cache_dir=tmp_path)
    out = model.extraction_vector(np.zeros(3), np.eye(3))
    assert out.bodies == ["wall"]
    assert np.allclose(out.vector, [-1.0, 0.0, 0.0], atol=1e-4)
    assert out.depth_mm == pytest.approx(1.0, abs=1e-4)
    # tilted 30° toward -x, the same head is clear of the wall
    tilted = rotation_from_z(np.array([-np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))]))
    clear = model.extraction_vector(np.zeros(3), tilted)
    assert clear.bodies == [] and clear.depth_mm == 0.0 and not clear.vector.any()


def test_extraction_vector_weights_pieces_by_their_depths(tmp_path):
    # Box head x, y in [-2, 2]: part a 1 mm deep from +x, part b 1.5 mm deep from -y.
    head = box([-2, -2, 0], [2, 2, 20])
    parts = [("a", box([1, -10, 5], [10, 10, 15])), ("b", box([-10, -10, 5], [10, -0.5, 15]))]
    model = EpaModel(head, parts, cache_dir=tmp_path)
    assert model.pieces_count == 2 and not model.cached
    out = model.extraction_vector(np.zeros(3), np.eye(3))
    # E = (1·(-1, 0, 0) + 1.5·(0, 1.5, 0)) / 2.5
    # (CoACD's hulls carry float32 rounding: 1e-7 relative on coordinates of 10 mm)
    assert np.allclose(out.vector, [-0.4, 0.9, 0.0], atol=2e-3)
    assert out.depth_mm == pytest.approx(1.5, abs=2e-3)
    assert out.bodies == ["a", "b"]
    again = EpaModel(head, parts, cache_dir=tmp_path)
    assert again.cached and again.decompose_seconds < model.decompose_seconds


def test_far_pieces_are_skipped_by_their_bounding_boxes(tmp_path):
    model = EpaModel(cylinder_head(), [("far", box([50, 50, 0], [60, 60, 10]))], cache_dir=tmp_path)
    out = model.extraction_vector(np.zeros(3), np.eye(3))
    assert out.bodies == [] and not out.vector.any()


def test_beads_above_the_tip_allowance_push_the_head_away(tmp_path):
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path, bead_radius_mm=1.0, tip_allowance_mm=1.0)
    column = np.column_stack([np.full(10, 3.5), np.zeros(10), np.linspace(2.0, 20.0, 10)])
    out = model.extraction_vector(np.zeros(3), np.eye(3), column)
    assert out.bodies == ["deposit"]
    assert np.allclose(out.vector, [-0.5, 0.0, 0.0], atol=1e-4)
    # a bead just under the tip is below the allowance plane: not an obstacle
    under = model.extraction_vector(np.zeros(3), np.eye(3), np.array([[0.0, 0.0, -0.5]]))
    assert under.bodies == [] and not under.vector.any()
    assert model.extraction_vector(np.zeros(3), np.eye(3), np.zeros((0, 3))).bodies == []


# ---- tilt -----------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["fixed", "lami"])
def test_tilt_away_from_a_wall_is_free_and_nearly_minimal(tmp_path, variant):
    head, wall = cylinder_head(), box([2, -20, 10], [20, 20, 40])
    model = EpaModel(head, [("wall", wall)], cache_dir=tmp_path)
    is_free = exact_is_free(ExactReference(head, {"wall": wall}), np.zeros(3))
    result = model.tilt(np.zeros(3), Z, minimal_rotation, is_free, max_tilt_deg=30.0, variant=variant)
    assert result.normal is not None and result.bodies == ["wall"]
    assert is_free(result.normal[None])[0]
    assert result.normal[0] < 0 and abs(result.normal[1]) < 1e-9  # straight away from the wall
    best = smallest_free_tilt(is_free, 30.0)
    assert best - 1e-9 <= result.tilt_deg <= best + 0.5 + 1e-9
    assert result.iterations == round(result.tilt_deg / 0.5)


def test_tilt_out_of_a_corner_bends_with_lami(tmp_path):
    # Wall x is 1 mm deep, wall y 0.5 mm: the first E points mostly along -x, but the cheapest
    # way out is diagonal. "fixed" keeps the first azimuth; "lami" turns toward the diagonal.
    head = cylinder_head()
    walls = {"x": box([2, -20, 10], [20, 20, 40]), "y": box([-20, 2.5, 12], [20, 20, 40])}
    model = EpaModel(head, list(walls.items()), cache_dir=tmp_path)
    is_free = exact_is_free(ExactReference(head, walls), np.zeros(3))
    best = smallest_free_tilt(is_free, 30.0)
    tilts = {}
    for variant in ("fixed", "lami"):
        result = model.tilt(np.zeros(3), Z, minimal_rotation, is_free, max_tilt_deg=30.0, variant=variant)
        assert result.normal is not None and result.bodies == ["x", "y"]
        assert is_free(result.normal[None])[0]
        assert result.normal[0] < 0 and result.normal[1] < 0
        tilts[variant] = result.tilt_deg
    assert tilts["lami"] <= best + 0.5 < tilts["fixed"] <= best + 5.0


@pytest.mark.parametrize("variant", ["fixed", "lami"])
def test_no_normal_when_max_tilt_is_too_small(tmp_path, variant):
    head, wall = cylinder_head(), box([2, -20, 10], [20, 20, 40])
    model = EpaModel(head, [("wall", wall)], cache_dir=tmp_path)
    calls = []

    def is_free(normals):
        calls.append(len(normals))
        return exact_is_free(ExactReference(head, {"wall": wall}), np.zeros(3))(normals)

    result = model.tilt(np.zeros(3), Z, minimal_rotation, is_free, max_tilt_deg=3.0, variant=variant)
    assert result.normal is None and result.bodies == ["wall"]
    assert result.tilt_deg == pytest.approx(3.0) and result.iterations == 6
    assert calls == [1, 6]  # N0 alone, then the six steps in one batch


def test_tilt_leaves_a_free_pose_alone(tmp_path):
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path)
    result = model.tilt(np.zeros(3), Z, minimal_rotation, lambda n: np.ones(len(n), bool), max_tilt_deg=30.0)
    assert np.array_equal(result.normal, Z) and result.tilt_deg == 0.0 and result.iterations == 0


def test_tilt_away_from_beads(tmp_path):
    head = cylinder_head()
    # a wall of beads beside the head, 0.5 mm into it, from 8 mm above the tip upward
    beads = np.array([[3.5, y, z] for y in np.linspace(-6, 6, 13) for z in np.linspace(8, 28, 11)])
    model = EpaModel(head, [], cache_dir=tmp_path, bead_radius_mm=1.0, tip_allowance_mm=1.0)
    ref = ExactReference(head, {}, tip_allowance_mm=1.0)
    is_free = exact_is_free(ref, np.zeros(3), beads, 1.0)
    best = smallest_free_tilt(is_free, 10.0, azimuth_step_deg=5.0)
    for variant in ("fixed", "lami"):
        result = model.tilt(
            np.zeros(3), Z, minimal_rotation, is_free, max_tilt_deg=30.0, variant=variant, beads_mm=beads
        )
        assert result.normal is not None and result.bodies == ["deposit"]
        assert not ref.bead_collides(np.zeros(3), rotation_from_z(result.normal), beads, 1.0)
        assert result.normal[0] < 0 and best - 1e-9 <= result.tilt_deg <= best + 0.5 + 1e-9


def test_ring_fallback_when_the_hull_model_sees_nothing(tmp_path):
    # No parts: E is zero, yet the checker only accepts tilts of 3° or more toward +y.
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path)

    def is_free(normals):
        tilt = angle_between_deg(Z, normals)
        return (tilt >= 3.0 - 1e-9) & (normals[:, 1] > 0.9 * np.linalg.norm(normals[:, :2], axis=1))

    result = model.tilt(np.zeros(3), Z, minimal_rotation, is_free, max_tilt_deg=30.0)
    assert result.normal is not None and result.tilt_deg == pytest.approx(3.0)
    assert np.allclose(result.normal, [0.0, np.sin(np.radians(3)), np.cos(np.radians(3))])
    assert result.bodies == []


def test_unknown_variant_names_the_known_ones(tmp_path):
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path)
    with pytest.raises(ValueError, match="unknown tilt variant 'best'; known: fixed, lami"):
        model.tilt(np.zeros(3), Z, minimal_rotation, lambda n: np.zeros(len(n), bool), max_tilt_deg=5, variant="best")


# ---- the real sample meshes -----------------------------------------------------------------


@pytest.mark.heavy
def test_real_mold_and_head(tmp_path):
    from ncfix.geometry.mesh import load_head, load_mesh

    head = load_head(REPO / "samples" / "deposition_head.stl").mesh
    mold = load_mesh(REPO / "samples" / "recreated_mold.stl", "part").mesh
    model = EpaModel(head, [("part:mold", mold)], cache_dir=tmp_path)
    assert not model.cached and model.pieces_count > 10
    warm = EpaModel(head, [("part:mold", mold)], cache_dir=tmp_path)
    assert warm.cached and warm.pieces_count == model.pieces_count and warm.decompose_seconds < 1.0

    # On the floor near the +x end wall, vertical: the head hits the wall and must lean back (-x).
    tip = np.array([54.1, -6.7, 26.0])
    ref = ExactReference(head, {"part:mold": mold})
    assert ref.collides(tip, np.eye(3))
    start = time.perf_counter()
    out = model.extraction_vector(tip, np.eye(3))
    assert time.perf_counter() - start < 0.05
    assert out.bodies == ["part:mold"] and out.vector[0] < 0
    is_free = exact_is_free(ref, tip)
    for variant in ("fixed", "lami"):
        result = model.tilt(tip, Z, minimal_rotation, is_free, max_tilt_deg=30.0, variant=variant)
        assert result.normal is not None and is_free(result.normal[None])[0]
        assert result.tilt_deg <= 8.0  # the smallest free tilt here is about 5°


def test_beads_near_keeps_the_beads_within_a_radius_of_the_clipped_hull(tmp_path):
    """The compiled filter keeps exactly the bead centres inside the clipped hull's box grown by
    the radius and less than the radius outside each of its face planes (the numpy formulation)."""
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path, bead_radius_mm=1.0, tip_allowance_mm=1.0)
    rng = np.random.default_rng(8)
    beads = rng.uniform(-15, 40, (5000, 3))
    c = np.array([1.0, -2.0, 3.0])
    r = rotation_from_z(np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]))
    local = (beads - c) @ r
    boxed = ((local > model._bead_lo - 1.0) & (local < model._bead_hi + 1.0)).all(axis=1)
    inside = (local @ model._bead_normals.T - model._bead_offsets < 1.0).all(axis=1)
    got = model._beads_near(c, r, beads)
    assert 50 < len(got) < 4000
    assert np.array_equal(got, beads[boxed & inside])
    # In the order the strategy gives them (one per cell, neighbours together), where the face
    # that cleared the bead before is tried first.
    order = np.lexsort(np.floor(beads / 2.0).T[::-1])
    assert np.array_equal(model._beads_near(c, r, beads[order]), beads[order][(boxed & inside)[order]])


def test_pieces_met_are_those_whose_boxes_meet_the_placed_hull_box(tmp_path):
    """The compiled broad phase picks exactly the pieces whose boxes meet the box of the head's
    hull placed at the pose (numpy formulation), down to boxes 1e-9 mm apart or overlapping."""
    model = EpaModel(cylinder_head(), [], cache_dir=tmp_path)
    rng = np.random.default_rng(5)
    points = model._head_points
    for _ in range(50):
        c = rng.uniform(-20, 20, 3)
        r = rotation_from_z(rng.normal(size=3) * [0.3, 0.3, 0.0] + Z)
        world = c + points @ r.T
        lo, hi = world.min(axis=0), world.max(axis=0)
        piece_lo = rng.uniform(-40, 40, (200, 3))
        piece_hi = piece_lo + rng.uniform(0, 20, (200, 3))
        piece_hi[:5] = lo + 1e-9  # overlapping at a corner
        piece_lo[5:10] = hi + 1e-9  # just apart
        want = np.flatnonzero(((piece_lo <= hi) & (piece_hi >= lo)).all(axis=1))
        assert 5 <= len(want) < 200 and not np.isin(np.arange(5, 10), want).any()
        assert np.array_equal(_boxes_met(points, c, r, piece_lo, piece_hi), want)


def test_pieces_dropped_by_a_hull_face_cannot_meet_the_hull():
    """The broad phase keeps every piece that meets the head's hull (coal's GJK, the test the
    strategy runs next), drops only pieces some hull face plane separates, and among the pieces
    whose boxes meet the placed hull's box drops many: the extraction vectors do not change, the
    GJK calls do."""
    head = trimesh.load(REPO / "samples" / "deposition_head.stl")
    model = EpaModel(head, [])
    hull = model._head
    rng = np.random.default_rng(8)
    pieces = [trimesh.convex.convex_hull(rng.normal(size=(int(rng.integers(4, 40)), 3)) * rng.uniform(2, 25, 3)
                                         + rng.uniform(-90, 90, 3)) for _ in range(150)]
    lo = np.array([p.bounds[0] for p in pieces])
    hi = np.array([p.bounds[1] for p in pieces])
    vertices = np.ascontiguousarray(np.vstack([p.vertices for p in pieces]), dtype=np.float64)
    vstart = np.concatenate([[0], np.cumsum([len(p.vertices) for p in pieces])]).astype(np.int64)
    shapes = [_convex(p) for p in pieces]
    boxed = dropped = 0
    for _ in range(60):
        c = rng.uniform(-30, 30, 3)
        r = rotation_from_z(rng.normal(size=3) * [0.4, 0.4, 0.0] + Z)
        met = set(_boxes_met(model._head_points, c, r, lo, hi).tolist())
        kept = set(_pieces_met(model._head_points, c, r, lo, hi, model._head_normals, model._head_offsets,
                               model._head_centre, vertices, vstart).tolist())
        assert kept <= met
        for j in met:
            touching = coal.collide(hull, coal.Transform3s(r, c), shapes[j], coal.Transform3s(),
                                    coal.CollisionRequest(), coal.CollisionResult()) > 0
            assert j in kept or not touching, (j, c, r)
        boxed += len(met)
        dropped += len(met - kept)
    assert boxed > 500 and dropped > 0.2 * boxed


def test_walk_arithmetic_matches_the_matrix_formulation():
    """The lami walk's scalar steps are ``axis_rotation``, ``angle_between_deg`` and the
    normalised cross product, to rounding."""
    rng = np.random.default_rng(6)
    for _ in range(200):
        u, n, d = (v / np.linalg.norm(v) for v in rng.normal(size=(3, 3)))
        angle = rng.uniform(-0.2, 0.2)
        turned = _turned(tuple(u), np.cos(angle), np.sin(angle), tuple(n))
        assert np.abs(np.array(turned) - axis_rotation(u, np.array([angle]))[0] @ n).max() < 1e-15
        assert _angle_deg(tuple(n), turned) == pytest.approx(angle_between_deg(n, np.array(turned)), abs=1e-12)
        cross = np.cross(n, 3.0 * d)
        assert np.abs(_tilt_axis(n, 3.0 * d) - cross / np.linalg.norm(cross)).max() < 1e-15
    assert _tilt_axis(Z, -2.0 * Z) is None


def test_bead_exit_vectors_match_coal_epa():
    """The compiled sphere-hull exits agree with coal's GJK/EPA, bead by bead: the same beads
    touch, the same vectors to EPA's tolerance (inside the hull, near a face, an edge, apart)."""
    head = trimesh.creation.cylinder(radius=4.0, height=30.0, sections=24)
    head.apply_translation([0.0, 0.0, 15.0])
    model = EpaModel(head, [], bead_radius_mm=1.2, tip_allowance_mm=1.0)
    rng = np.random.default_rng(3)
    c = np.array([10.0, -5.0, 3.0])
    r = rotation_from_z(np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0]))
    local = rng.uniform(model._bead_lo - 3.0, model._bead_hi + 3.0, (3000, 3))
    beads = c + local @ r.T
    near = model._beads_near(c, r, beads)
    mine = model.bead_exits(c, r, near)
    pose = coal.Transform3s(r, c)
    theirs = np.array([v if (v := model._penetration(model._bead_head, pose, model._sphere,
                                                       coal.Transform3s(np.eye(3), b))) is not None else np.zeros(3)
                       for b in near])
    touch = np.linalg.norm(theirs, axis=1) > 0
    assert 100 < touch.sum() < len(near)
    assert ((np.linalg.norm(mine, axis=1) > 0) == touch).all()
    assert np.abs(mine - theirs).max() < 1e-4


def _hull_signed_distance(hull: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact signed distance (negative inside) from points (n, 3) to a convex hull: inside, the
    nearest face plane; outside, the distance to its triangles (coal's BVH of the triangles, not
    its convex shapes)."""
    from ncfix.collision.exact import bvh as _bvh

    planes = points @ hull.face_normals.T - np.einsum("ij,ij->i", hull.face_normals, hull.triangles[:, 0])
    out = planes.max(axis=1)
    bvh, probe = _bvh(hull), coal.Sphere(1e-9)
    for i in np.flatnonzero(out > 0):
        out[i] = coal.distance(probe, coal.Transform3s(np.eye(3), points[i]), bvh, coal.Transform3s(),
                               coal.DistanceRequest(), coal.DistanceResult()) + 1e-9
    return out


@pytest.mark.parametrize("segments, pointed", [(128, False), (512, False), (1024, False), (512, True), (1024, True)])
def test_hull_model_of_a_finely_revolved_head_is_exact_or_larger(segments, pointed):
    """coal refuses a convex shape with a vertex of more than 255 neighbours: the triangles of a
    revolved head's hull fan its discs (the head of 128 segments cut at the tip allowance: 256
    points in one cap) and a pointed cone's apex has one edge per segment. The hull model
    builds for all of them: where the hull's true edges allow, the same shape (every sphere
    touches it exactly when it touches the hull, at the same EPA depth); at a fine apex, a
    shape that holds the hull and is at most 0.05 mm larger."""
    from heads import revolved_head

    head = revolved_head(segments, "fan", pointed=pointed)
    model = EpaModel(head, [], bead_radius_mm=1.0, tip_allowance_mm=1.0)
    rng = np.random.default_rng(segments)
    request = coal.CollisionRequest()
    request.enable_contact = True
    for shape, mesh in ((model._head, head.convex_hull), (model._bead_head, _clip_hull(head.convex_hull, 1.0))):
        outer = pointed and shape is model._head  # only the apex has too many true edges
        centres = rng.uniform(mesh.bounds[0] - 2.0, mesh.bounds[1] + 2.0, (400, 3))
        centres[:100, 2] = rng.uniform(-1.5, 2.0, 100)  # around the tip, the apex and the cut
        radius = 1.0
        signed = _hull_signed_distance(mesh, centres)
        sure = np.abs(signed - radius) > (0.05 if outer else 1e-6)
        touching = np.zeros(len(centres), dtype=bool)
        depth = np.zeros(len(centres))
        for i, c in enumerate(centres):
            result = coal.CollisionResult()
            touching[i] = coal.collide(shape, coal.Transform3s(), coal.Sphere(radius),
                                       coal.Transform3s(np.eye(3), c), request, result) > 0
            if touching[i]:
                depth[i] = -result.getContact(0).penetration_depth
        assert 50 < touching.sum() < 350
        assert (touching[signed < radius]).all()  # never smaller than the hull
        assert np.array_equal(touching[sure], (signed < radius)[sure])
        if not outer:
            inside = touching & sure
            assert np.abs(depth[inside] - (radius - signed[inside])).max() < 1e-3
