"""The compiled exact part test (``ncfix.collision.proximity``) against coal, and its pieces."""

from pathlib import Path

import coal
import numpy as np
import pytest
import trimesh

from ncfix.collision import proximity
from ncfix.collision import near as near_module
from ncfix.collision.grid import build_distance_grid
from ncfix.collision.proximity import CAP_MM, SLACK_MM, HeadProximity, build_arrays, cached_head_proximity
from ncfix.geometry.frames import minimal_rotation
from ncfix.collision.exact import bvh as _bvh

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _tri_distance(a, b):
    """Distance between triangles a and b (3, 3) from coal (0 when they meet)."""
    ta, tb = (_bvh(trimesh.Trimesh(vertices=t, faces=[[0, 1, 2]], process=False)) for t in (a, b))
    return max(coal.distance(ta, coal.Transform3s(), tb, coal.Transform3s(), coal.DistanceRequest(),
                             coal.DistanceResult()), 0.0)


def _within(a, b, d):
    return bool(proximity._tris_within(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64),
                                       (d + SLACK_MM) ** 2))


FLAT = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])


@pytest.mark.parametrize("other, distance", [
    (FLAT + [0.0, 0.0, 1.0], 1.0),  # parallel, one above the other: vertex-face
    (np.array([[2.0, 2.0, -3.0], [2.0, 2.0, 3.0], [3.0, 3.0, 2.0]]), 0.0),  # edges through the face
    (np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [1.0, 2.0, 0.0]]), 0.0),  # coplanar, inside
    (np.array([[-1.0, 5.0, 0.0], [11.0, 5.0, 0.0], [5.0, 20.0, 0.0]]), 0.0),  # coplanar, edges crossing
    (np.array([[12.0, -5.0, 2.0], [12.0, 5.0, 2.0], [20.0, 0.0, 9.0]]), np.hypot(2.0, 2.0)),  # edge-edge
    (np.array([[3.0, 3.0, 0.5], [30.0, 3.0, 40.0], [3.0, 30.0, 40.0]]), 0.5),  # steep, a corner over the face
])
def test_triangle_pairs(other, distance):
    """Each way two triangles come near (vertex-face, edge-face crossing, coplanar overlap,
    edge-edge): within exactly their distance, not within less."""
    assert _tri_distance(FLAT, other) == pytest.approx(distance, abs=1e-9)
    assert _within(FLAT, other, distance) and _within(other, FLAT, distance)
    if distance > 1e-6:
        assert not _within(FLAT, other, distance - 1e-6) and not _within(other, FLAT, distance - 1e-6)


def test_random_triangle_pairs_match_coal():
    """Random pairs at every scale of closeness: the answer is coal's distance compared with d."""
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(3000):
        a = rng.normal(size=(3, 3)) * rng.uniform(0.2, 5.0)
        b = rng.normal(size=(3, 3)) * rng.uniform(0.2, 5.0) + rng.normal(size=3) * rng.uniform(0.0, 4.0)
        true = _tri_distance(a, b)
        for d in (0.0, 0.3, 1.0, 2.0):
            if abs(true - d) < 1e-7:
                continue
            assert _within(a, b, d) == (true < d), (a, b, d, true)
            checked += 1
    assert checked > 10000


@pytest.fixture(scope="module")
def sample():
    head = trimesh.load(SAMPLES / "deposition_head.stl")
    mold = trimesh.load(SAMPLES / "recreated_mold.stl")
    grid = build_distance_grid(mold, 0.5, name="mold")
    return head, mold, grid, HeadProximity(build_arrays(head, mold.triangles), mold.triangles, grid)


def _poses(mold, n, seed):
    """Tips near the mold's surface (up to 8 mm off it), the tool axis within 50° of its normal:
    every kind of near miss and contact."""
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mold, n, seed=seed)
    normals = mold.face_normals[faces]
    tips = points + normals * rng.uniform(-0.5, 8.0, (n, 1))
    axes = normals + rng.normal(size=(n, 3)) * 0.5
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return tips, minimal_rotation(axes)


def test_head_against_the_mold_matches_coal(sample):
    """On 1,500 poses of the sample head about the sample mold and distances 0 to the cap: within
    exactly when coal's collision test with that security margin says so (coal's distance
    decides the pairs closer than 1e-6 mm to d; none of them may be called apart), and the
    pose at the cap is always tested."""
    head, mold, _, near = sample
    head_bvh, mold_bvh = _bvh(head), _bvh(mold)
    identity = coal.Transform3s()
    tips, rotations = _poses(mold, 1500, 11)
    counts = np.zeros(2, dtype=int)
    for c, r, d in zip(tips, rotations, np.resize([0.0, 0.05, 0.5, 1.0, CAP_MM], len(tips))):
        request = coal.CollisionRequest()
        request.security_margin = d
        want = coal.collide(head_bvh, coal.Transform3s(r, c), mold_bvh, identity, request, coal.CollisionResult()) > 0
        got = near.within(c, r, d)
        if got != want:
            gap = coal.distance(head_bvh, coal.Transform3s(r, c), mold_bvh, identity, coal.DistanceRequest(),
                                coal.DistanceResult())
            assert got and abs(gap - d) < 1e-6, (c, r, d, gap)
        counts[int(want)] += 1
    assert counts.min() > 300  # both answers well represented


def test_a_large_part_gets_larger_cells_and_the_same_answers(sample, monkeypatch):
    """A part whose box would need more than MAX_CELLS cells (here the sample mold, the limit
    lowered to 20,000 from its 190,000 cells of 2 mm) gets cells large enough, and the answers
    stay coal's."""
    head, mold, grid, _ = sample
    monkeypatch.setattr(near_module, "MAX_CELLS", 20_000)
    arrays = build_arrays(head, mold.triangles)
    assert float(arrays["cell_mm"]) > 4.0 and int(np.prod(arrays["dims"])) <= 20_000
    near = HeadProximity(arrays, mold.triangles, grid)
    head_bvh, mold_bvh = _bvh(head), _bvh(mold)
    tips, rotations = _poses(mold, 400, 2)
    answers = []
    for c, r, d in zip(tips, rotations, np.resize([0.0, 0.3, 1.0, CAP_MM], len(tips))):
        request = coal.CollisionRequest()
        request.security_margin = d
        want = coal.collide(head_bvh, coal.Transform3s(r, c), mold_bvh, coal.Transform3s(), request,
                            coal.CollisionResult()) > 0
        got = near.within(c, r, d)
        if got != want:  # only where coal's distance is d to rounding, and then never "apart"
            gap = coal.distance(head_bvh, coal.Transform3s(r, c), mold_bvh, coal.Transform3s(),
                                coal.DistanceRequest(), coal.DistanceResult())
            assert got and abs(gap - d) < 1e-6
        answers.append(want)
    assert 50 < sum(answers) < 350


def test_distance_beyond_the_cap_is_refused(sample):
    _, _, _, near = sample
    with pytest.raises(ValueError, match="outside"):
        near.within(np.zeros(3), np.eye(3), CAP_MM + 0.1)


def test_cached_arrays_give_the_same_answers(sample, tmp_path):
    """Built, then read back from the cache folder: the same arrays and answers."""
    head, mold, grid, near = sample
    built = cached_head_proximity(head, mold, grid, cache_dir=str(tmp_path))
    assert len(list(tmp_path.glob("proximity-*.npz"))) == 1
    read = cached_head_proximity(head, mold, grid, cache_dir=str(tmp_path))
    for name in ("head", "center", "radius", "child_start", "child_count", "part", "lo", "dims", "start", "listed"):
        assert np.array_equal(getattr(read, name), getattr(near, name)), name
        assert np.array_equal(getattr(built, name), getattr(near, name)), name
    tips, rotations = _poses(mold, 200, 5)
    assert [read.within(c, r, 0.5) for c, r in zip(tips, rotations)] == \
        [near.within(c, r, 0.5) for c, r in zip(tips, rotations)]


def test_recent_pairs_tried_first_give_the_descent_s_answers(sample):
    """Poses one after another (each tip stepping 0.3 mm at a time across the mold): the
    answers with the recent pairs tried first are those of the descent alone, most of the
    contacts found by a recent pair."""
    _, mold, _, near = sample
    tips, rotations = _poses(mold, 60, 8)
    walk = [(tip + step * np.array([0.3, 0.0, 0.0]), rotation) for tip, rotation in zip(tips, rotations)
            for step in range(8)]
    recent, none = np.full((proximity.RECENT_PAIRS, 2), -1, dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    codes = [near.test(c, r, d, recent) for (c, r), d in zip(walk, np.resize([0.0, 0.5, CAP_MM], len(walk)))]
    alone = [near.test(c, r, d, none) for (c, r), d in zip(walk, np.resize([0.0, 0.5, CAP_MM], len(walk)))]
    assert [code > 0 for code in codes] == [code > 0 for code in alone]
    assert set(alone) == {0, 1} and codes.count(2) > codes.count(1) > 20
