"""The compiled exact ball-touch and signed-distance tests against brute force (ncfix.collision.near)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ncfix.geometry.distance import point_mesh_distance, winding_numbers
from ncfix.collision.near import NearSurface, _signed_distance


@pytest.fixture(scope="module")
def solid():
    """A closed, non-convex solid: a box with a cylinder bored through it, plus a sphere on top."""
    box = trimesh.creation.box((40.0, 30.0, 20.0))
    bore = trimesh.creation.cylinder(radius=6.0, height=50.0, sections=24)
    cap = trimesh.creation.icosphere(subdivisions=2, radius=9.0)
    cap.apply_translation((8.0, 0.0, 14.0))
    mesh = box.difference(bore).union(cap)
    assert mesh.is_volume
    return np.asarray(mesh.triangles, dtype=np.float64)


def _points(triangles, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = triangles.reshape(-1, 3).min(axis=0), triangles.reshape(-1, 3).max(axis=0)
    pts = rng.uniform(lo - 4.0, hi + 4.0, size=(n, 3))
    # and points close to the surface, on both sides
    tri = triangles[rng.integers(0, len(triangles), n // 2)]
    w = rng.dirichlet(np.ones(3), n // 2)
    on = np.einsum("nk,nkj->nj", w, tri)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    near = on + normal * rng.uniform(-0.6, 0.6, (n // 2, 1))
    return np.concatenate([pts, near])


@pytest.fixture(scope="module")
def brute(solid):
    """4,500 points about the solid (a third of them within 0.6 mm of its surface), their distance to
    it, whether they lie inside and their signed distance, by brute force (computed once: it is
    most of this module's time)."""
    pts = _points(solid, 3000, seed=8)
    d = point_mesh_distance(pts, solid)
    inside = winding_numbers(pts, solid) > 0.5
    return pts, d, inside, np.where(inside, -d, d)


@pytest.mark.parametrize("cap_mm, cell_mm", [(2.5, 2.0), (1.0, 0.7)])
def test_touch_matches_brute_force(solid, brute, cap_mm, cell_mm):
    pts, d, inside, _ = brute
    rng = np.random.default_rng(4)
    radii = rng.uniform(0.05, 3.5, len(pts))  # some above the cap: every triangle is read there
    near = NearSurface(solid, cap_mm, cell_mm)
    for check_inside in (True, False):
        first, tested = near.first_touch(pts, radii, np.full(len(pts), check_inside), np.arange(len(pts)), len(pts))
        truth = (d <= radii) | (inside & check_inside)
        assert tested == len(pts)
        assert ((first >= 0) == truth).all()
        assert truth.sum() > 0.1 * len(pts) and (~truth).sum() > 0.1 * len(pts)


def test_touch_stops_each_group_at_its_first_touching_ball(solid, brute):
    pts, d, inside, _ = brute
    radii = np.full(len(pts), 1.0)
    group, groups = np.arange(len(pts)) // 15, len(pts) // 15  # groups of 15
    touch = (d <= radii) | inside
    first, _ = NearSurface(solid, 2.0).first_touch(pts, radii, np.ones(len(pts), bool), group, groups)
    for g in range(groups):
        members = np.nonzero(group == g)[0]
        hits = members[touch[members]]
        assert first[g] == (hits[0] if len(hits) else -1)


def test_signed_distance_matches_brute_force(solid, brute):
    pts, _, _, sd = brute
    near = NearSurface(solid, 2.0)
    got = np.array([_signed_distance(p[0], p[1], p[2], False, near.triangles, near.lo, near.cell_mm, near.dims,
                                     near.cap_mm, near.start, near.listed, near.sign_lo, near.sign_pitch,
                                     near.inside) for p in pts])
    assert np.allclose(got, sd, atol=1e-9)
    assert (sd < -1.0).sum() > 100 and (np.abs(sd) < 0.3).sum() > 100  # deep inside and at the surface


def test_depth_bound_holds_and_is_tight(solid, brute):
    """Minus ``depth_bound`` never exceeds the signed distance (brute force), inside and out, and
    lies within one and a half sign-cell diagonals of it inside (the nearest outside centre is at
    most a diagonal past the surface, the point half one from its centre): what lets the
    deepest-bead search stop early."""
    from ncfix.collision.near import depth_bound

    pts, _, _, sd = brute
    near = NearSurface(solid, 2.0)
    bound = -np.array([depth_bound(p[0], p[1], p[2], near.sign_lo, near.sign_pitch, near.depth) for p in pts])
    assert (bound <= sd).all()
    inside = sd < 0
    assert inside.sum() > 1000 and (sd < -3.0).sum() > 100
    assert (sd[inside] - bound[inside] <= 1.5 * np.sqrt(3.0) * near.sign_pitch + 1e-3).all()


def test_signed_distance_below_a_threshold(solid, brute):
    """``_signed_distance_below`` gives the exact signed distance where it is below the threshold
    and the threshold itself elsewhere (outside points, and inside ones no deeper than it)."""
    from ncfix.collision.near import _signed_distance_below

    pts, _, _, sd = brute
    below = np.random.default_rng(10).uniform(-5.0, -0.05, len(pts))
    near = NearSurface(solid, 2.0)
    args = (near.triangles, near.lo, near.cell_mm, near.dims, near.cap_mm, near.start, near.listed, near.sign_lo,
            near.sign_pitch, near.inside)
    got = np.array([_signed_distance_below(p[0], p[1], p[2], False, t, *args) for p, t in zip(pts, below)])
    deeper = sd < below
    assert deeper.sum() > 100 and ((sd < 0) & ~deeper).sum() > 100
    assert np.allclose(got[deeper], sd[deeper], atol=1e-9)
    assert (got[~deeper] == below[~deeper]).all()


def test_a_large_mesh_gets_larger_cells_and_the_same_distances():
    """A 3 m block would need 10^9 cells of 2 mm (8 GB of offsets): the cells grow until its box
    holds at most MAX_CELLS, and the distances stay the exact ones (here, to a box: closed form)."""
    from ncfix.collision import near

    block = trimesh.creation.box(bounds=[[-1500.0, -1500.0, -3000.0], [1500.0, 1500.0, 0.0]])
    tris = np.asarray(block.triangles, dtype=np.float64)
    *_, cell = near._cell_lists(tris, 12.0, 2.0)
    assert cell > 2.0
    rng = np.random.default_rng(4)
    points = rng.uniform([-1600.0, -1600.0, -3100.0], [1600.0, 1600.0, 100.0], (400, 3))
    points[:100, 2] = rng.uniform(-5.0, 5.0, 100)  # near the top face
    got = near.surface_distances(tris, points, 12.0)
    lo, hi = np.array([-1500.0, -1500.0, -3000.0]), np.array([1500.0, 1500.0, 0.0])
    outside = np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)
    inside = np.minimum(points - lo, hi - points).min(axis=1)
    want = np.where((points > lo).all(axis=1) & (points < hi).all(axis=1), inside, outside)
    assert np.allclose(got, want, atol=1e-9, rtol=0)


def test_far_points_read_wider_lists_and_get_the_same_distances(monkeypatch):
    """Points beyond the cap are looked up in lists of a doubling cap before every triangle is read:
    the distances are the very same floats as reading every triangle, near and far, and a point
    past the last list (or outside every list) still gets its exact distance."""
    from ncfix.collision import near

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    tris = np.asarray(mesh.triangles, dtype=np.float64)
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.uniform(-25.0, 25.0, (300, 3)), rng.uniform(-400.0, 400.0, (300, 3))])
    tiered = near.surface_distances(tris, points, 3.0)
    monkeypatch.setattr(near, "FAR_TIERS", 0)  # every point beyond the cap reads every triangle
    every = near.surface_distances(tris, points, 3.0)
    assert np.array_equal(tiered, every)
    assert np.allclose(tiered, np.abs(np.linalg.norm(points, axis=1) - 20.0), atol=0.5)  # a sphere, nearly
    assert (tiered > 3.0 * near.FAR_FACTOR ** 6).any() and (tiered < 3.0).any()


def test_surface_distances_are_the_floats_of_reading_every_triangle(solid):
    """The box culling and the previous point's nearest triangle only skip triangles: each distance
    is the very float of the least ``_tri_d2`` over every triangle, and it does not depend on the
    points before it (a point alone, or the points in another order, get the same floats)."""
    from ncfix.collision import near

    tris = solid
    rng = np.random.default_rng(11)
    # Lattice runs (as a grid's band gives them), scattered points, far ones and points on edges.
    lattice = np.stack(np.meshgrid(*[np.arange(-24.0, 24.0, 1.5)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    corners = tris.reshape(-1, 3)[rng.integers(0, len(tris) * 3, 200)]
    points = np.concatenate([lattice, _points(tris, 600, 12), rng.uniform(-300.0, 300.0, (100, 3)), corners])
    every = np.array([np.sqrt(min(near._tri_d2(p[0], p[1], p[2], t) for t in tris)) for p in points])
    got = near.surface_distances(tris, points, 3.0)
    assert np.array_equal(got, every)
    order = rng.permutation(len(points))
    assert np.array_equal(near.surface_distances(tris, points[order], 3.0), every[order])
    alone = np.array([near.surface_distances(tris, p[None], 3.0)[0] for p in points[::37]])
    assert np.array_equal(alone, every[::37])
