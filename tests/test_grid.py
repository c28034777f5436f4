"""The part grids near the body: cells known to lie outside store their exact distance (grid.py's
tighten_near_body), so the bound stays a lower bound everywhere and is at most 2h off in the band."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from ncfix.collision import grid as grid_module
from ncfix.collision.grid import EXACT_BAND_MM, Reach, build_distance_grid
from ncfix.geometry.distance import point_mesh_distance
from ncfix.geometry.mesh import load_mesh
from ncfix.collision.near import surface_distances

MOLD = Path(__file__).resolve().parents[1] / "samples" / "recreated_mold.stl"
PITCH = 0.5


@pytest.fixture(scope="module")
def mold() -> trimesh.Trimesh:
    return load_mesh(MOLD, "part").mesh


@pytest.fixture(scope="module")
def mold_grid(mold):
    """The mold's grid, as ncfix builds it (built once: two tests read it)."""
    return build_distance_grid(mold, PITCH)


@pytest.fixture(scope="module")
def mold_points(mold):
    """Points near the mold's surface (most within 1.5 mm, some within 4) and their exact distance."""
    points = np.concatenate([_near_surface_points(mold, 4000, 1.5, 5), _near_surface_points(mold, 2000, 4.0, 6)])
    return points, _true_distance(mold, points, True)


def _sheet() -> trimesh.Trimesh:
    """An open, wavy surface (no inside): its surface is the body."""
    x, y = np.meshgrid(np.linspace(-30, 30, 13), np.linspace(-20, 20, 9), indexing="ij")
    z = 3.0 * np.sin(x / 7.0) * np.cos(y / 9.0)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    faces = []
    for i in range(12):
        for j in range(8):
            a, b, c, d = i * 9 + j, (i + 1) * 9 + j, (i + 1) * 9 + j + 1, i * 9 + j + 1
            faces += [(a, b, c), (a, c, d)]
    return trimesh.Trimesh(vertices, np.array(faces), process=False)


def _near_surface_points(mesh: trimesh.Trimesh, n: int, spread_mm: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    on, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return on + rng.normal(size=(n, 3)) * spread_mm


def _true_distance(mesh: trimesh.Trimesh, points: np.ndarray, closed: bool) -> np.ndarray:
    true = point_mesh_distance(points, np.asarray(mesh.triangles, dtype=np.float64))
    if closed:
        true[mesh.contains(points)] = 0.0
    return true


def test_surface_distances_are_exact(mold):
    rng = np.random.default_rng(3)
    lo, hi = mold.bounds
    points = np.concatenate([_near_surface_points(mold, 1500, 2.0, 3),
                             lo - 50 + rng.random((300, 3)) * (hi - lo + 100)])  # far ones read every triangle
    tris = np.asarray(mold.triangles, dtype=np.float64)
    got = surface_distances(tris, points, cap_mm=3.0)
    assert np.allclose(got, point_mesh_distance(points, tris), rtol=0, atol=1e-9)
    assert len(surface_distances(tris, points[:0], cap_mm=3.0)) == 0
    assert np.isinf(surface_distances(tris[:0], points[:4], cap_mm=3.0)).all()


@pytest.mark.parametrize("case", ["closed", "open", "cropped"])
def test_the_bound_stays_below_the_distance_and_is_within_2h_in_the_band(mold, mold_grid, mold_points, case):
    if case == "open":
        mesh = _sheet()
        grid = build_distance_grid(mesh, PITCH, closed=False)
        points = np.concatenate([_near_surface_points(mesh, 4000, 1.5, 5), _near_surface_points(mesh, 2000, 4.0, 6)])
        true = _true_distance(mesh, points, False)
    elif case == "closed":
        grid, (points, true) = mold_grid, mold_points
    else:
        lo, hi = mold.bounds
        bounds = np.array([lo + 0.15 * (hi - lo), hi - 0.15 * (hi - lo)])
        grid = build_distance_grid(mold, PITCH, closed=True, bounds_mm=bounds)
        points, true = mold_points
        kept = ((points > bounds[0]) & (points < bounds[1])).all(axis=1)
        points, true = points[kept], true[kept]
    bound = grid.lower_bound_np(points)
    assert (bound <= true + 1e-9).all()
    # A point 2h .. band - 2h outside: its nearest cell centre is outside, farther than h from the
    # surface and within the band, so the bound is off by at most twice the lookup offset.
    h = 0.5 * np.sqrt(3.0) * PITCH
    band = (true > 2 * h + 1e-3) & (true < EXACT_BAND_MM - 2 * h)
    assert band.sum() > 200
    assert (true[band] - bound[band]).max() <= 2 * grid.margin_mm


def test_without_the_exact_band_the_bound_is_looser(mold, mold_grid, mold_points, monkeypatch):
    """The band is what makes the 2h figure above true (the EDT alone is off by up to 4h)."""
    points, true = mold_points
    tight = mold_grid.lower_bound_np(points)
    monkeypatch.setattr(grid_module, "EXACT_BAND_MM", -1.0)
    monkeypatch.setattr(grid_module, "JITTER_SAFE_MM", np.inf)
    loose = build_distance_grid(mold, PITCH).lower_bound_np(points)
    assert (loose <= tight).all() and (loose < tight - 0.3).sum() > 500
    h = 0.5 * np.sqrt(3.0) * PITCH
    band = (true > 2 * h + 1e-3) & (true < EXACT_BAND_MM - 2 * h)
    assert (true[band] - loose[band]).max() > 2 * (0.5 * np.sqrt(3.0) * PITCH) + 0.1


def _reach_case(mold):
    """A short path beside the mold (two points 30 mm apart, 2 mm off its top) and a reach of 12 mm
    about it: the exact band is made only near the path."""
    lo, hi = mold.bounds
    top = hi[2] + 2.0
    a = np.array([lo[0] + 0.3 * (hi[0] - lo[0]), 0.5 * (lo[1] + hi[1]), top])
    path = a + np.linspace(0.0, 1.0, 16)[:, None] * np.array([30.0, 0.0, 0.0])
    return path, Reach.of_points(path, 12.0)


def test_a_reach_mask_holds_every_cell_within_the_reach():
    rng = np.random.default_rng(11)
    points = rng.uniform(-20.0, 20.0, (40, 3))
    reach = Reach.of_points(points, 7.3)
    origin, shape, pitch, slack = np.array([-31.2, -29.9, -30.4]), (120, 115, 118), 0.5, 0.43
    mask = reach.mask(origin, shape, pitch, slack)
    centres = origin + np.argwhere(np.ones(shape, dtype=bool)) * pitch
    nearest = np.full(len(centres), np.inf)
    for p in points:
        nearest = np.minimum(nearest, np.linalg.norm(centres - p, axis=1))
    within = (nearest <= reach.radius_mm + slack).reshape(shape)
    assert within.sum() > 10_000 and not (within & ~mask).any()
    # a superset by at most the cubes' diagonal (and the EDT's rounding)
    assert not (mask.ravel() & (nearest > reach.radius_mm + slack + 2 * np.sqrt(3.0) * reach.cell_mm + 2e-3)).any()


def test_a_grid_made_for_a_reach_is_the_whole_grid_there_and_a_lower_bound_everywhere(mold, mold_grid):
    path, reach = _reach_case(mold)
    grid = build_distance_grid(mold, PITCH, reach=reach)
    assert grid.shape == mold_grid.shape
    # looser (the distance transform's bound) only outside the reach, where the band was not made
    assert (grid.dist_mm <= mold_grid.dist_mm).all() and (grid.dist_mm < mold_grid.dist_mm).sum() > 10_000
    # every lookup within the reach reads the whole grid's numbers: points about the path, out to
    # the edge of the reach (on the sphere of its radius about a path point)
    rng = np.random.default_rng(12)
    direction = rng.normal(size=(6000, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    radius = reach.radius_mm * np.concatenate([np.ones(3000), np.sqrt(rng.random(3000))])
    points = path[rng.integers(0, len(path), 6000)] + direction * radius[:, None]
    assert np.array_equal(grid.lower_bound_np(points), mold_grid.lower_bound_np(points))
    # still a lower bound anywhere, near the body in and out of the reach
    anywhere = np.concatenate([_near_surface_points(mold, 3000, 2.0, 13), points])
    assert (grid.lower_bound_np(anywhere) <= _true_distance(mold, anywhere, True) + 1e-9).all()


def test_the_distance_transform_of_bytes_is_that_of_bools():
    """``distance_transform`` hands edt the mask as 0/1 bytes (faster than its bool path): the
    floats are the bool path's, on masks from nearly empty to nearly full and at several pitches."""
    import edt

    from ncfix.collision.voxelize import distance_transform

    rng = np.random.default_rng(5)
    for density in (0.001, 0.02, 0.3, 0.7, 0.98, 0.9999):
        free = rng.random((37, 23, 41)) > density
        free[5:9, 3:20, 7] = False  # a sheet, as a surface marks
        for pitch in (0.5, 0.3, 2.0 / 3.0, 1.0):
            want = edt.edt(free, anisotropy=(pitch,) * 3, black_border=False, parallel=2)
            got = distance_transform(free, pitch)
            assert got.dtype == np.float32 and np.array_equal(got, want)
