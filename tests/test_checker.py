"""The collision checker: zero misses against the exact reference, few false alarms, deposit model,
streaming through the pipeline, and identical decisions on CPU and CUDA."""

from __future__ import annotations

import io
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import oracle
from ncfix.collision.checker import Checker, _balls_box
from ncfix.collision.stage import CheckStage
from ncfix.collision.deposit import BeadStore, DepositRule, choose_rule, depositing
from ncfix.collision.grid import build_distance_grid
from ncfix.collision.head import build_head_model
from ncfix.config import Options
from ncfix.geometry.distance import point_mesh_distance
from ncfix.geometry.frames import rotation_from_z
from ncfix.geometry.mesh import load_head, load_mesh
from ncfix.nc.post import post_program
from ncfix.pipeline import run
from ncfix.profiles import load_profile

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
HEAD = SAMPLES / "deposition_head.stl"
MOLD = SAMPLES / "recreated_mold.stl"
sys.path.insert(0, str(SAMPLES))
from make_samples import bathtub_path  # noqa: E402

PITCH = 0.5


@pytest.fixture(scope="module")
def meshes():
    return load_head(HEAD).mesh, load_mesh(MOLD, "part").mesh


@pytest.fixture(scope="module")
def checker(meshes):
    head, mold = meshes
    model = build_head_model(head, PITCH)
    return Checker(head, model, [("part:recreated_mold.stl", mold, True)], pitch_mm=PITCH, device="cpu")


def _rates(name: str, flagged: np.ndarray, truth: np.ndarray) -> tuple[int, float]:
    misses = int((truth & ~flagged).sum())
    false = int((flagged & ~truth).sum())
    rate = false / len(truth)
    print(f"\n{name}: {len(truth)} poses, {int(truth.sum())} colliding, misses {misses}, "
          f"false alarms {false} ({rate:.2%})")
    return misses, rate


def _random_rotations(rng, n: int, max_tilt_deg: float) -> np.ndarray:
    """Head rotations with the axis within max_tilt of vertical and a random spin about it."""
    tilt = np.radians(max_tilt_deg) * np.sqrt(rng.random(n))
    phi = rng.random(n) * 2 * np.pi
    axis = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)], axis=1)
    spin = rng.random(n) * 2 * np.pi
    c, s = np.cos(spin), np.sin(spin)
    rz = np.zeros((n, 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    return rotation_from_z(axis) @ rz


# -- grid ------------------------------------------------------------------------------------


@pytest.mark.heavy  # test_grid.py holds the mold's grid to the same bound, and tighter, in the fast run
def test_distance_grid_lower_bound_never_exceeds_the_true_distance(meshes):
    _, mold = meshes
    grid = build_distance_grid(mold, PITCH)
    rng = np.random.default_rng(1)
    lo, hi = mold.bounds
    pts = lo - 20 + rng.random((3000, 3)) * (hi - lo + 40)
    true = point_mesh_distance(pts, np.asarray(mold.triangles))
    inside = mold.contains(pts)
    true[inside] = 0.0
    bound = grid.lower_bound_np(pts)
    assert (bound <= true + 1e-9).all()
    in_grid = ((pts >= grid.origin_mm) & (pts <= grid.origin_mm + (np.array(grid.shape) - 1) * PITCH)).all(axis=1)
    near = (~inside) & in_grid
    assert near.sum() > 500
    # Inside the grid, tight enough to be useful: off by at most a few half diagonals (the query
    # offset, the margin, and the surface band, whose square-edged slabs reach past the surface).
    assert (true[near] - bound[near]).max() <= 4 * grid.margin_mm


# -- parts: zero misses ------------------------------------------------------------------------


def test_bathtub_273_no_pose_the_reference_finds_colliding_is_missed(checker, meshes):
    _, mold = meshes
    P, N = bathtub_path(273, mold)
    C, R = P + 6.0 * N, rotation_from_z(N)
    flagged = checker.check_parts(C, R, np.zeros(len(C)))[:, 0]
    truth = np.array([oracle(checker).collides(c, r) for c, r in zip(C, R)])
    misses, rate = _rates("bathtub 273", flagged, truth)
    assert truth.sum() > 30
    assert misses == 0
    assert rate < 0.02


def test_bathtub_5000_subset_no_misses(checker, meshes):
    _, mold = meshes
    P, N = bathtub_path(5000, mold)
    P, N = P[::2], N[::2]
    C, R = P + 6.0 * N, rotation_from_z(N)
    flagged = checker.check_parts(C, R, np.zeros(len(C)))[:, 0]
    truth = np.array([oracle(checker).collides(c, r) for c, r in zip(C, R)])
    misses, rate = _rates("bathtub 5000 (every 2nd)", flagged, truth)
    assert misses == 0
    assert rate < 0.02


def _random_part_poses(mold, n: int, seed: int):
    rng = np.random.default_rng(seed)
    pts, face = mold.sample(n, return_index=True, seed=seed) if _sample_takes_seed() else mold.sample(n, return_index=True)
    normal = mold.face_normals[face]
    C = pts + normal * rng.uniform(2.0, 30.0, (n, 1)) + rng.normal(0, 1.0, (n, 3))
    return C, _random_rotations(rng, n, 45.0)


def _sample_takes_seed() -> bool:
    import inspect

    import trimesh

    return "seed" in inspect.signature(trimesh.Trimesh.sample).parameters


@pytest.mark.parametrize("n, seed", [(2000, 7), pytest.param(20000, 11, marks=pytest.mark.heavy)])
def test_random_poses_near_the_mold_no_misses(checker, meshes, n, seed):
    _, mold = meshes
    C, R = _random_part_poses(mold, n, seed=seed)
    flagged = checker.check_parts(C, R, np.zeros(len(C)))[:, 0]
    truth = np.array([oracle(checker).collides(c, r) for c, r in zip(C, R)])
    misses, rate = _rates(f"{n} random poses near the mold", flagged, truth)
    assert misses == 0
    assert rate < 0.02


def test_free_poses_are_free_and_fast_path_errs_toward_collides(checker, meshes):
    """free_poses has no exact fallback: every pose it calls free is free (exact reference), and
    it refuses at most a few free ones (those near contact)."""
    _, mold = meshes
    C, R = _random_part_poses(mold, 1500, seed=17)
    free = checker.free_poses(C, R, np.arange(len(C)), BeadStore(1.0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    truth = np.array([oracle(checker).collides(c, r) for c, r in zip(C, R)])
    assert not (free & truth).any()
    refused = int((~free & ~truth).sum())
    print(f"\nfree_poses: {int(free.sum())} free, {refused} free poses refused of {int((~truth).sum())}")
    assert refused < 0.2 * (~truth).sum()  # near contact (2-30 mm off the mold); bounds ~1 mm loose


def test_grouped_sweeps_decide_like_sample_by_sample(checker, meshes):
    """Certifying runs of samples together changes no decision (only how many tests run)."""
    _, mold = meshes
    P, N = bathtub_path(273, mold)
    C, R = P + 6.0 * N, rotation_from_z(N)
    step = np.r_[0.0, np.linalg.norm(np.diff(C, axis=0), axis=1)]
    turn = np.r_[0.0, np.arccos(np.clip((N[1:] * N[:-1]).sum(axis=1), -1, 1))] * 2  # spin changes too: generous
    lin, ang = 0.3 * step, 0.3 * turn
    alone = checker.sweep_parts(C, R, lin, ang)
    grouped = checker.sweep_parts(C, R, lin, ang, np.cumsum(step), np.cumsum(turn))
    assert (alone == grouped).all()


@pytest.mark.parametrize("margin_mm", [0.5, 2.0, 6.0])
def test_a_margin_is_honoured_exactly(checker, meshes, margin_mm):
    """With a margin (sweeps) a pose is flagged iff the exact distance (the reference: coal's
    mesh distance) is below it: no miss, and no false alarm (the checker's exact test: the
    compiled triangle pairs of ``proximity`` up to its cap (0.5, 2 mm), coal's collision test
    with the margin as its security margin beyond (6 mm))."""
    _, mold = meshes
    C, R = _random_part_poses(mold, 300, seed=3)
    flagged = checker.check_parts(C, R, np.full(len(C), margin_mm))[:, 0]
    values, _ = oracle(checker).clearances(C, R)
    truth = values < margin_mm
    ok = np.abs(values - margin_mm) > 1e-6  # the depth of a hit is a lower bound; only the sign is exact
    assert 0 < truth[ok].sum() < ok.sum()
    assert np.array_equal(flagged[ok], truth[ok])


# -- deposit -----------------------------------------------------------------------------------


def _wall_beads(spacing: float = 0.25) -> np.ndarray:
    """Bead centres of a thin wall: x in [-20, 20] at y = 0, layers 1.5 mm apart up to z = 36."""
    x = np.arange(-20.0, 20.0 + 1e-9, spacing)
    z = np.arange(0.0, 36.0 + 1e-9, 1.5)
    xx, zz = np.meshgrid(x, z, indexing="ij")
    return np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], axis=1)


def _exact_bead_clearance(ref, C, R, beads, radius):
    """Exact reference (n,): negative when some bead sphere meets the head above the allowance.

    Independent of the checker: coal's exact BVH distance from the clipped head mesh to the bead
    centres (a BVH of point triangles), minus the radius; a centre inside the clipped head
    (embree ray test) is a hit. Positive values are the exact clearance.
    """
    import coal

    head = ref._bead_head
    head_bvh = coal.BVHModelOBBRSS()
    head_bvh.beginModel(len(head.faces), len(head.vertices))
    head_bvh.addVertices(np.asarray(head.vertices, dtype=np.float64))
    head_bvh.addTriangles(np.asarray(head.faces, dtype=np.int64))
    head_bvh.endModel()
    points = coal.BVHModelOBBRSS()
    points.beginModel(len(beads), len(beads))
    points.addVertices(np.asarray(beads, dtype=np.float64))
    points.addTriangles(np.repeat(np.arange(len(beads))[:, None], 3, axis=1))
    points.endModel()
    lo, hi = head.bounds
    request = coal.DistanceRequest()
    out = np.empty(len(C))
    for i, (c, r) in enumerate(zip(C, R)):
        local = (beads - c) @ r
        box = ((local >= lo) & (local <= hi)).all(axis=1)
        if box.any() and head.contains(local[box]).any():
            out[i] = -radius
            continue
        result = coal.DistanceResult()
        out[i] = coal.distance(head_bvh, coal.Transform3s(r, c), points, coal.Transform3s(), request, result) - radius
    return out


def _random_bead_poses(n: int, seed: int):
    rng = np.random.default_rng(seed)
    C = np.stack([rng.uniform(-30, 30, n), rng.uniform(-25, 25, n), rng.uniform(-2, 45, n)], axis=1)
    return C, _random_rotations(rng, n, 45.0)


@pytest.fixture(scope="module")
def bead_checker(meshes):
    head, _ = meshes
    model = build_head_model(head, PITCH)
    return Checker(head, model, [], pitch_mm=PITCH, bead_radius_mm=1.0, tip_allowance_mm=1.0, device="cpu")


def _deposit_case(bead_checker, n: int, seed: int):
    beads = _wall_beads(0.5)
    store = BeadStore(1.0)
    store.add(beads)
    C, R = _random_bead_poses(n, seed)
    hit, _ = bead_checker.check_deposit(C, R, np.zeros(n), np.arange(n), store, np.zeros((0, 3)),
                                        np.zeros(0, dtype=np.int64))
    truth = _exact_bead_clearance(oracle(bead_checker), C, R, beads, 1.0) < 0
    return hit, truth


@pytest.mark.parametrize("n, seed", [(2000, 5), pytest.param(20000, 13, marks=pytest.mark.heavy)])
def test_random_poses_near_beads_no_misses(bead_checker, n, seed):
    hit, truth = _deposit_case(bead_checker, n, seed=seed)
    misses, rate = _rates(f"{n} random poses near a bead wall", hit, truth)
    assert truth.sum() > 0.05 * n
    assert misses == 0
    assert rate < 0.02


@pytest.mark.parametrize("cell_mm", [0.37, 1e4])
def test_exact_bead_test_is_the_same_whatever_cells_it_skips(bead_checker, monkeypatch, cell_mm):
    """The exact bead kernel skips the bucket cells that lie wholly outside a failing node's ball
    or wholly below the allowance plane. With cells of 0.37 mm (most of them skipped, beads on
    their faces) and with one cell holding every bead (none skipped), the hits, clearances,
    each pose's candidate beads and the exact tests are those of the 3 mm cells, with sweep margins and beads
    seen from later samples too (half the poses print: beads all about the plane)."""
    import ncfix.collision.checker as checker_module
    import ncfix.collision.exact_beads as exact_beads

    rng = np.random.default_rng(21)
    beads = _wall_beads(0.25)
    store = BeadStore(1.0)
    store.add(beads[: len(beads) // 2])
    pending = beads[len(beads) // 2:]
    n = 600
    C, R = _random_bead_poses(n, seed=17)
    # Half of them print: the tip 0-2 mm over a bead, tilted up to 25°, beads about the plane.
    half = n // 2
    C[:half] = beads[rng.integers(0, len(beads), half)] + np.column_stack(
        [rng.normal(0.0, 0.5, half), rng.normal(0.0, 0.5, half), rng.uniform(0.0, 2.0, half)])
    R[:half] = _random_rotations(rng, half, 25.0)
    seq = rng.integers(0, n, n)
    pending_seq = np.sort(rng.integers(0, n, len(pending)))
    lin = np.where(rng.random(n) < 0.5, rng.uniform(0.0, 0.4, n), 0.0)
    ang = np.where(rng.random(n) < 0.5, rng.uniform(0.0, 0.004, n), 0.0)

    kernel = checker_module.first_bead_hits
    calls = []  # each call's (hit, depth, candidate beads after every filter) per pose, and its tests

    def recorded(*args, **kwargs):
        calls.append(kernel(*args, **kwargs))
        return calls[-1]

    monkeypatch.setattr(checker_module, "first_bead_hits", recorded)

    def run():
        calls.clear()
        field = store.field(PITCH)
        with field.overlay(pending):
            hit, clearance = bead_checker._exact_kept(C, R, lin, ang, seq, store, pending, pending_seq, field)
        return hit, clearance, list(calls)

    want = run()
    candidates = np.concatenate([c[2] for c in want[2]])
    assert want[0].sum() > 20 and (~want[0]).sum() > 20 and candidates.sum() > 1000
    monkeypatch.setattr(exact_beads, "CELL_MM", cell_mm)
    got = run()
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert len(got[2]) == len(want[2])
    for mine, theirs in zip(got[2], want[2]):
        assert all(np.array_equal(a, b) for a, b in zip(mine, theirs))


def test_retired_beads_are_still_seen_conservatively(bead_checker):
    """With room for only 512 exact centres, most of the wall is retired into the old field:
    still no misses against the exact reference on every bead, only more false alarms, and the
    store keeps at most exact_max + exact_max/4 centres."""
    beads = _wall_beads(0.5)
    n = 2000
    C, R = _random_bead_poses(n, seed=5)
    truth = _exact_bead_clearance(oracle(bead_checker), C, R, beads, 1.0) < 0
    store = BeadStore(1.0, exact_max=512)
    store.field(PITCH)
    for part in np.array_split(beads, 20):  # laid in runs, as windows lay them
        store.add(part)
    assert store.retired > 0.5 * len(beads) and store.count - store.retired <= 512 + 128
    assert store.old is not None and store.old.count == store.retired
    kept = np.concatenate([pts for _, pts in store.trees()])
    assert len(kept) == store.count - store.retired  # the newest beads stay exact, in laying order
    assert np.array_equal(kept, beads[store.retired:])
    before = bead_checker.stats.retired_bead_hits
    hit, _ = bead_checker.check_deposit(C, R, np.zeros(n), np.arange(n), store, np.zeros((0, 3)),
                                        np.zeros(0, dtype=np.int64))
    assert not (truth & ~hit).any()
    assert bead_checker.stats.retired_bead_hits > before
    free = bead_checker.poses_free(C, R, np.arange(n), store, np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    assert not (truth & free).any()
    # The main field was cropped to the kept beads (its memory follows the newest material) and,
    # with the old field below it, still bounds the distance to every bead, retired ones too.
    from scipy.spatial import cKDTree

    field = store.field(PITCH)
    kept = beads[store.retired:]
    extent = np.array(field.fine.shape) * PITCH
    assert (extent <= kept.max(axis=0) - kept.min(axis=0) + 2 * (field._fine_reach() + 24.0) + 4 * PITCH).all()
    assert (extent < beads.max(axis=0) - beads.min(axis=0)).any()
    pts = np.random.default_rng(6).uniform(beads.min(axis=0) - 5, beads.max(axis=0) + 5, (20_000, 3))
    near = pts[np.abs(cKDTree(beads).query(pts)[0] - 1.0) < 3.0]  # within the fine reach of a bead surface
    truth = np.maximum(cKDTree(beads).query(near)[0] - 1.0, 0.0)  # the bound stops at 0 inside
    assert (field.lower_bound_np(near) <= truth + 1e-9).all()


def test_bead_field_is_a_lower_bound_on_the_distance_to_the_beads():
    """The rolling field (chains, isolated beads, two adds, an overlay) never exceeds the exact
    distance to the bead spheres, and comes back unchanged after the overlay."""
    from scipy.spatial import cKDTree

    from ncfix.collision.deposit import BeadField

    rng = np.random.default_rng(4)
    x = np.arange(0.0, 40.0, 0.25)
    chain = np.stack([x, 0.3 * np.sin(x / 3), 0.1 * x], axis=1)
    beads = [chain, rng.uniform(-10, 50, (60, 3)), chain + [0.0, 2.0, 0.0]]
    field = BeadField(1.0, PITCH)
    for b in beads:
        field.add(b)
    beads = np.concatenate(beads)
    pts = rng.uniform(-25, 65, (100_000, 3))
    true = np.maximum(cKDTree(beads).query(pts)[0] - 1.0, 0.0)
    bound = field.lower_bound_np(pts)
    assert (bound <= true + 1e-9).all()
    near = true < 2.0
    assert (true - bound)[near].mean() < 0.5  # useful: about the lattice offset
    extra = rng.uniform(0, 20, (30, 3))
    with field.overlay(extra):
        both = field.lower_bound_np(pts)
    true_both = np.maximum(cKDTree(np.concatenate([beads, extra])).query(pts)[0] - 1.0, 0.0)
    assert (both <= true_both + 1e-9).all()
    assert np.array_equal(field.lower_bound_np(pts), bound)


def test_overlays_of_a_growing_chain_stamp_as_a_fresh_overlay_would():
    """Overlays whose points begin with the last overlay's (the pending beads of one detection's
    runs) start from what it stamped: the grids inside each are those of a field that stamps all
    the points afresh, whether the chain ends within a chord, goes on straight or turns, is cut
    short, starts elsewhere, or the field took beads between two overlays."""
    from ncfix.collision.deposit import BeadField

    x = np.arange(0.0, 120.0, 0.25)
    # straight (long chords), then a bend, then a gap (a chain of its own) and a curl
    chain = np.concatenate([np.stack([x[:200], 0 * x[:200], 0 * x[:200]], axis=1),
                            np.stack([x[199] + 3 * np.sin(x[:160] / 6), 3 - 3 * np.cos(x[:160] / 6),
                                      0.05 * x[:160]], axis=1),
                            np.stack([20 + np.cos(x[:120] / 2), 30 + np.sin(x[:120] / 2), 0.1 * x[:120]], axis=1)])
    base = [np.stack([x, 5 + 0 * x, 2 + 0 * x], axis=1)]

    def fresh_field():
        field = BeadField(1.0, PITCH)
        for b in base:
            field.add(b)
        return field

    field, reference = fresh_field(), fresh_field()
    for f in (field, reference):  # grids that hold every overlay: the same placement in both
        f._grow(chain)
    steps = [(0, 150), (0, 300), (0, 301), (0, 301), (0, 455), (0, 200), (0, 600), (5, 600), (0, 680), "add",
             (0, 500), (0, 680)]
    hits = 0
    for step in steps:
        if step == "add":
            extra = np.array([[60.0, 20.0, 1.0]])
            field.add(extra)
            reference.add(extra)
            continue
        pts = chain[step[0]:step[1]]
        hits += field._overlaid is not None and len(field._overlaid[0]) <= len(pts) and \
            np.array_equal(field._overlaid[0], pts[:len(field._overlaid[0])])
        reference._overlaid = None  # every point stamped
        before = field.fine.copy(), field.coarse.copy(), field.occupied.copy(), field.box.copy(), field.count
        with field.overlay(pts), reference.overlay(pts):
            assert np.array_equal(field.fine, reference.fine)
            assert np.array_equal(field.coarse, reference.coarse)
            assert np.array_equal(field.occupied, reference.occupied)
            assert np.array_equal(field.box, reference.box) and field.count == reference.count
        after = field.fine, field.coarse, field.occupied, field.box, field.count
        assert all(np.array_equal(u, v) for u, v in zip(before, after))
    assert hits >= 6  # the overlays did start from the last one's stamps


def test_stamping_gives_every_cell_the_least_value_of_the_chords_that_reach_it():
    """The compiled stamp (which walks each column of cells from the chord's nearest height up and
    down, stopping at the first cell out of reach) leaves every cell of the fine grid at the least
    of its chords' values, each computed in full: overlapping chords, vertical and level ones,
    single beads, cells already at 0."""
    from ncfix.collision.deposit import FIELD_SLACK_MM, FINE_LEVELS, _stamp_kernels

    rng = np.random.default_rng(8)
    h, radius, step = 0.5, 1.0, 3.0 / FINE_LEVELS
    lo = np.array([-4, -4, -4], dtype=np.int64)
    a = rng.uniform(0.0, 8.0, (40, 3))
    b = a + rng.normal(0.0, 2.0, (40, 3))
    b[1::5, :2] = a[1::5, :2]  # vertical chords
    b[2::5, 2] = a[2::5, 2]  # level chords
    b[::7] = a[::7]  # single beads
    dev = rng.uniform(0.0, 0.01, 40)
    grid = np.full((32, 32, 32), FINE_LEVELS, dtype=np.uint8)
    _stamp_kernels().stamp_chords(grid, lo, h, a, b, dev, radius, step, FINE_LEVELS, FIELD_SLACK_MM)
    # The reference: every chord's value at every cell, in the kernel's arithmetic, no skipping.
    p0, p1, p2 = np.meshgrid(*[(np.arange(32) + lo[k]) * h for k in range(3)], indexing="ij")
    expect = np.full(grid.shape, FINE_LEVELS, dtype=np.int64)
    for s in range(len(a)):
        cut = radius + dev[s] + FIELD_SLACK_MM
        reach = step * FINE_LEVELS + cut
        d0, d1, d2 = b[s] - a[s]
        length2 = d0 * d0 + d1 * d1 + d2 * d2
        inv = 1.0 / length2 if length2 > 0.0 else 0.0
        q0, q1, q2 = p0 - a[s, 0], p1 - a[s, 1], p2 - a[s, 2]
        t = np.clip((q0 * d0 + q1 * d1 + q2 * d2) * inv, 0.0, 1.0)
        e0, e1, e2 = q0 - t * d0, q1 - t * d1, q2 - t * d2
        dd = e0 * e0 + e1 * e1 + e2 * e2
        dist = np.sqrt(dd) - cut
        value = np.where(dist > 0.0, (dist * (1.0 / step)).astype(np.int64), 0)
        expect = np.where(dd < reach * reach, np.minimum(expect, value), expect)
    assert np.array_equal(grid, expect)
    assert (grid == 0).any() and (grid < FINE_LEVELS).mean() > 0.2


def test_beads_laid_after_a_pose_are_not_seen_by_it(bead_checker):
    beads = _wall_beads(0.5)
    C, R = _random_bead_poses(400, seed=9)
    truth = _exact_bead_clearance(oracle(bead_checker), C, R, beads, 1.0) < 0
    assert truth.any()
    store = BeadStore(1.0)
    # All beads pending with a sequence number after every pose: nothing is seen.
    hit, _ = bead_checker.check_deposit(C, R, np.zeros(len(C)), np.arange(len(C)), store, beads,
                                        np.full(len(beads), 10_000))
    assert not hit.any()
    hit, _ = bead_checker.check_deposit(C, R, np.zeros(len(C)), np.arange(len(C)), store, beads,
                                        np.zeros(len(beads), dtype=np.int64))
    assert (hit | ~truth).all()


@pytest.mark.parametrize(
    "e_delta, codes, rule",
    [
        ([np.nan, 1.0], False, DepositRule.EXTRUSION),
        ([np.nan, np.nan], True, DepositRule.CODES),
        ([np.nan, np.nan], False, DepositRule.EVERY_FEED),
    ],
)
def test_deposit_rule_is_chosen_from_the_first_window(e_delta, codes, rule):
    assert choose_rule(np.array(e_delta), codes, 1.0) is rule
    assert choose_rule(np.array(e_delta), codes, 0.0) is DepositRule.OFF


def test_rapids_never_deposit_and_e_must_grow():
    motion = np.array([0, 1, 1, 1, 2, -1], dtype=np.int8)
    e = np.array([1.0, 1.0, -0.5, np.nan, 0.2, 1.0])
    on = np.array([1, 1, 0, 1, 1, 1], dtype=np.int8)
    assert depositing(DepositRule.EXTRUSION, motion, e, on).tolist() == [False, True, False, False, True, False]
    assert depositing(DepositRule.CODES, motion, e, on).tolist() == [False, True, False, True, True, False]
    assert depositing(DepositRule.EVERY_FEED, motion, e, on).tolist() == [False, True, True, True, True, False]


# -- through the pipeline ----------------------------------------------------------------------


def _program(points, vectors, profile="ijk") -> bytes:
    return "".join(post_program(load_profile(profile), points, vectors, title="checker test")).encode()


def _run(data: bytes, **kw):
    options = replace(Options(head=str(HEAD), check=True, device="cpu"), **kw)
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, options, "test.nc")
    return out.getvalue(), report


def _motion_lines(data: bytes) -> list[int]:
    return [i + 1 for i, line in enumerate(data.decode().splitlines()) if line.split()[1:2] and
            line.split()[1] in ("G0", "G1") or (line.startswith("N") and " X" in line)]


@pytest.mark.heavy  # the whole 273-point program and the exact reference at every block
def test_bathtub_program_end_to_end_flags_every_colliding_block(checker, meshes):
    _, mold = meshes
    P, N = bathtub_path(273, mold)
    data = _program(P, N)
    out, report = _run(data, part=(str(MOLD),), bead_radius=0.0)
    assert out == data
    assert report.exit_code == 1
    flagged = {c["line"] for c in report.collisions}
    lines = data.decode().splitlines(keepends=True)
    feed_lines = [i + 1 for i, line in enumerate(lines) if " X" in line][1:-1]  # approach, retract
    assert len(feed_lines) == len(P)
    truth = np.array([oracle(checker).collides(c, r) for c, r in zip(P + 6 * N, rotation_from_z(N))])
    truth_lines = {feed_lines[i] for i in np.nonzero(truth)[0]}
    assert truth_lines <= flagged
    extra = flagged - truth_lines
    print(f"\nbathtub 273 program: {len(truth_lines)} blocks collide at their end pose, "
          f"{len(flagged)} flagged ({len(extra)} more: their sweeps from the previous point)")
    entry = report.collisions[0]
    assert entry["bodies"] == ["part:recreated_mold.stl"]
    assert set(entry) == {"line", "bodies", "penetration_mm", "clearance_mm", "where"}
    assert report.summary["colliding_blocks_before"] == len(flagged)


@pytest.mark.heavy
def test_fix_mode_lists_every_colliding_block_as_unresolved_when_none_can_tilt(meshes):
    _, mold = meshes
    P, N = bathtub_path(25, mold)
    data = _program(P, N)
    out, report = _run(data, part=(str(MOLD),), bead_radius=0.0, check=False, max_tilt=0.1)
    assert out == data
    assert report.summary["unresolved_blocks"] == report.summary["colliding_blocks_before"] > 0
    assert [u["line"] for u in report.unresolved] == [c["line"] for c in report.collisions]
    assert report.exit_code == 1
    json.dumps(report.to_json())


def _wall_program():
    """A wall printed in 25 layers (x from -20 to 20, 2 mm steps, y = 0, 1.5 mm apart), then a
    pass beside it at y = 20 whose body hangs over the wall, then one tilted 20° toward it."""
    pts, vecs = [], []
    for layer in range(25):
        xs = np.arange(-20.0, 20.0 + 1e-9, 2.0)
        if layer % 2:
            xs = xs[::-1]
        for x in xs:
            pts.append((x, 0.0, 1.5 * layer))
            vecs.append((0.0, 0.0, 1.0))
    wall = len(pts)
    for x in np.arange(-30.0, 30.0 + 1e-9, 3.0):
        pts.append((x, 20.0, 2.0))
        vecs.append((0.0, 0.0, 1.0))
    tilt = np.radians(20.0)
    for x in np.arange(30.0, -30.0 - 1e-9, -3.0):
        pts.append((x, 34.0, 2.0))
        vecs.append((0.0, -np.sin(tilt), np.cos(tilt)))
    return np.array(pts), np.array(vecs), wall


def _wall_lines():
    """The wall program as lines, with M3 after the plunge to the first point and M5 after the wall
    (run with --deposit-codes M3,M5), and the index of each point's line."""
    P, N, wall = _wall_program()
    lines = _program(P, N).decode().splitlines(keepends=True)
    feed = [i for i, line in enumerate(lines) if " X" in line][1:-1]
    lines.insert(feed[wall - 1] + 1, "M5\n")
    lines.insert(feed[0] + 1, "M3\n")
    feed = [i for i, line in enumerate(lines) if " X" in line][1:-1]
    return P, N, wall, lines, feed


def test_deposit_workload_collides_only_with_what_it_printed(bead_checker):
    P, N, wall, lines, feed = _wall_lines()
    data = "".join(lines).encode()
    out, report = _run(data, deposit_codes=("M3", "M5"))  # no --part: nothing else to hit
    assert out == data
    flagged = {c["line"] for c in report.collisions}
    assert flagged and all(c["bodies"] == ["deposit"] for c in report.collisions)

    # Reference: end poses of the passes against the wall's beads (sampled 4x denser).
    feed_lines = [i + 1 for i in feed]
    beads = []
    for a, b in zip(P[: wall - 1], P[1:wall]):
        t = np.linspace(0, 1, int(np.ceil(np.linalg.norm(b - a) / (PITCH / 8))) + 1)[:, None]
        beads.append(a + t * (b - a))
    beads = np.concatenate(beads)
    C, R = P + 6 * N, rotation_from_z(N)
    clear = _exact_bead_clearance(oracle(bead_checker), C[wall:], R[wall:], beads, 1.0)
    truth = {feed_lines[wall + i] for i in np.nonzero(clear < 0)[0]}
    assert truth, "the workload must collide"
    assert truth <= flagged
    # Flagged beyond the end poses: only blocks whose sweep enters the wall (next to a true one).
    assert all(line - 1 in truth or line + 1 in truth or line in truth for line in flagged)
    assert not any(line <= feed_lines[wall - 1] for line in flagged), "printing the wall hits nothing"
    print(f"\nwall workload: {len(truth)} colliding end poses, {len(flagged)} flagged blocks")

    _, off = _run(data, deposit_codes=("M3", "M5"), bead_radius=0.0)
    assert off.collisions == [] and off.exit_code == 0


def test_deposit_workload_with_most_beads_retired_flags_at_least_as_much(bead_checker, monkeypatch):
    """Bounded memory: with room for 256 exact centres the wall's lower layers are retired long
    before the pass beside it; every block flagged with all beads exact is still flagged."""
    P, N, wall, lines, feed = _wall_lines()
    data = "".join(lines).encode()
    _, exact = _run(data, deposit_codes=("M3", "M5"))
    monkeypatch.setattr("ncfix.collision.deposit.EXACT_BEADS_MAX", 256)
    out, bounded = _run(data, deposit_codes=("M3", "M5"))
    assert out == data
    flagged_exact = {c["line"] for c in exact.collisions}
    flagged_bounded = {c["line"] for c in bounded.collisions}
    assert flagged_exact and flagged_exact <= flagged_bounded


@pytest.mark.heavy
def test_extrusion_words_decide_which_moves_deposit(bead_checker):
    """Same wall, E words instead of codes: only the first layer extrudes, the passes hit nothing;
    with every layer extruding they hit the wall as with the codes."""
    results = []
    for layers in (1, 25):
        P, N, wall, lines, feed = _wall_lines()
        e = 0.0
        for j, i in enumerate(feed):
            if 1 <= j < min(wall, 21 * layers):
                e += 0.1
            lines[i] = lines[i].rstrip("\n") + f" E{e:.3f}\n"
        _, report = _run("".join(lines).encode())
        assert report.summary["deposit_rule"] == "extrusion words (E grows)"
        results.append({c["line"] for c in report.collisions})
    _, codes = _run("".join(_wall_lines()[3]).encode(), deposit_codes=("M3", "M5"))
    assert results[0] == set()
    assert results[1] == {c["line"] for c in codes.collisions}


def test_the_stage_gives_back_each_chunk_at_once(checker):
    from ncfix.nc.modal import Interpreter
    from ncfix.pipeline import read_chunks

    P, N = bathtub_path(12)
    data = _program(P + np.array([0, 0, 200.0]), N)
    profile = load_profile("ijk")
    options = Options(head=str(HEAD), check=True, window=16)
    from ncfix.report import Report

    report = Report(input="t", machine="ijk", options=options)
    stage = CheckStage(checker, profile, options, report)
    chunks = list(read_chunks(io.BytesIO(data), Interpreter(profile, "t", None), lines_per_chunk=10))
    for chunk in chunks:
        assert stage.push(chunk) == [chunk]
    assert list(stage.flush()) == []


@pytest.mark.heavy  # an end-to-end check with the exact reference at every block (golden fix cases: every profile)
def test_rotary_profile_program_is_checked_through_forward_kinematics(checker, meshes):
    _, mold = meshes
    P, N = bathtub_path(50, mold)
    data = _program(P, N, profile="table-bc")
    out, report = _run(data, part=(str(MOLD),), bead_radius=0.0, machine="table-bc")
    assert out == data
    profile = load_profile("table-bc")
    from ncfix.nc.modal import Interpreter
    from ncfix.pipeline import read_chunks

    chunk = next(read_chunks(io.BytesIO(data), Interpreter(profile, "t", None), lines_per_chunk=10_000))
    rows = np.nonzero(chunk.motion >= 1)[0]
    p, n, r = profile.kinematics.forward(chunk.words[rows], tcp=True)
    truth = {int(rows[i]) + 1 for i in range(len(rows)) if oracle(checker).collides(p[i] + 6 * n[i], r[i])}
    assert truth and truth <= {c["line"] for c in report.collisions}


def test_missing_head_file_is_an_input_error():
    from ncfix.errors import GeometryError

    with pytest.raises(GeometryError, match="does not exist"):
        _run(b"G1 X0 Y0 Z0\n", head="/nonexistent/head.stl")


# -- devices -----------------------------------------------------------------------------------


def test_cpu_and_cuda_make_identical_decisions(meshes):
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device on this machine")
    head, mold = meshes
    model = build_head_model(head, PITCH)
    C, R = _random_part_poses(mold, 3000, seed=21)
    Cb, Rb = _random_bead_poses(2000, seed=22)
    results = []
    for device in ("cpu", "cuda"):
        ck = Checker(head, model, [("part:mold", mold, True)], pitch_mm=PITCH, device=device)
        store = BeadStore(1.0)
        store.add(_wall_beads(0.5))
        seq = np.arange(len(Cb))
        results.append((ck.check_parts(C, R, np.full(len(C), 0.2)),
                        ck.free_poses(C, R, np.arange(len(C)), store, np.zeros((0, 3)), np.zeros(0, dtype=np.int64)),
                        ck.check_deposit(Cb, Rb, np.full(len(Cb), 0.2), seq, store, np.zeros((0, 3)),
                                         np.zeros(0, dtype=np.int64))[0]))
    for a, b in zip(*results):
        assert (a == b).all()


def test_grid_lookups_agree_between_numpy_and_torch(meshes):
    import torch

    _, mold = meshes
    grid = build_distance_grid(mold, 1.0)
    rng = np.random.default_rng(2)
    pts = mold.bounds[0] - 10 + rng.random((5000, 3)) * (mold.bounds[1] - mold.bounds[0] + 20)
    a = grid.lower_bound_np(pts)
    b = grid.lower_bound(torch.as_tensor(pts)).numpy()
    assert np.allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("compared", [24, pytest.param(60, marks=pytest.mark.heavy)])
def test_deposit_clearance_is_the_deepest_bead(bead_checker, compared):
    """A colliding pose reports the clearance of its deepest bead (the exact reference's minimum
    over every bead it sees), not that of the first touching bead the test happened to find: on
    ``compared`` colliding poses (the exact clearance takes about half a second a pose)."""
    beads = _wall_beads(0.5)
    store = BeadStore(1.0)
    store.add(beads)
    C, R = _random_bead_poses(600, seed=21)
    n = len(C)
    hit, clearance = bead_checker.check_deposit(C, R, np.zeros(n), np.arange(n), store, np.zeros((0, 3)),
                                                np.zeros(0, dtype=np.int64))
    ref = oracle(bead_checker)
    sel = np.nonzero(hit)[0][:compared]
    assert len(sel) > 20
    exact = np.array([ref.bead_clearance(C[i], R[i], beads, 1.0) for i in sel])
    assert np.allclose(clearance[sel], exact, atol=1e-9)


def test_compiled_descent_decides_like_the_torch_descent(checker, bead_checker, meshes):
    """The CPU's compiled sphere-tree descent (``descent``) gives exactly the torch descent's
    answers: undecided poses (with sweep margins and the per-level cap) and failing nodes, for a
    part's grid, a bead field, and a field whose retired beads lie in a second field below it."""
    from ncfix.collision import descent
    from ncfix.collision.checker import CANDIDATE_LEVEL, ENTRY_LEVEL

    _, mold = meshes
    C, R = _random_part_poses(mold, 1500, seed=31)
    Cb, Rb = _random_bead_poses(1500, seed=32)
    rng = np.random.default_rng(33)
    lin, ang = rng.uniform(0, 1.0, 1500), rng.uniform(0, 0.02, 1500)
    store = BeadStore(1.0, exact_max=512)
    store.field(PITCH)
    for part in np.array_split(_wall_beads(0.5), 20):
        store.add(part)
    field = store.field(PITCH)
    assert field.below is not None and field.below.count  # the MODE_FIELD_BELOW case
    fresh = BeadStore(1.0)
    fresh.add(_wall_beads(0.5)[::3])
    cases = [(checker, checker.tree, checker.parts[0].grid.lower_bound, C, R),
             (bead_checker, bead_checker.dep_tree, fresh.field(PITCH).lower_bound, Cb, Rb),
             (bead_checker, bead_checker.dep_tree, field.lower_bound, Cb, Rb)]
    for ck, tree, bound, P, Q in cases:
        t = ck._tensor
        # the bound itself, near the body and far from it (coarse grid, box), to rounding: torch's
        # CPU sqrt is not correctly rounded (1 ulp off at times), the compiled one is
        pts = P[rng.integers(0, len(P), 20000)] + rng.normal(0.0, 1.0, (20000, 3)) * rng.choice([1.0, 10.0, 60.0],
                                                                                               (20000, 1))
        assert np.allclose(descent.lower_bounds(bound, pts), bound(t(pts)).numpy(), rtol=0, atol=1e-9)
        for cap in (4, 32):
            want = ck._undecided(tree, bound, t(P), t(Q), t(lin), t(ang), cap)
            got = descent.undecided(tree.host, bound, P, Q, lin, ang, ck.clearance_mm, ENTRY_LEVEL, cap)
            assert 0 < want.sum() < len(P)
            assert np.array_equal(got, want)
        want = ck._failing_nodes(tree, bound, t(P), t(Q), t(lin), t(ang), CANDIDATE_LEVEL)
        got = descent.failing_nodes(tree.host, bound, P, Q, lin, ang, ck.clearance_mm, CANDIDATE_LEVEL, 1.0)
        assert len(want[0]) > len(P)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        # the box of the failing nodes' balls (widened by the pad), as numpy computes it, to rounding
        box = _balls_box(tree.host, P, Q, lin, ang, want[0], want[1], 1.0 + ck.clearance_mm)
        assert np.allclose(got[2], box, rtol=0, atol=1e-12)


@pytest.mark.parametrize("level", [3, 5, 6])
def test_deposit_answers_do_not_depend_on_the_candidate_level(bead_checker, monkeypatch, level):
    """The exact bead test fetches candidate beads near the failing nodes of one tree level
    (``CANDIDATE_LEVEL``): a touching bead is near a failing node at every level, so the hits and
    the clearances (the deepest bead of each hit) are the same at any level; only the work differs."""
    import ncfix.collision.checker as checker_module

    store = BeadStore(1.0)
    store.add(_wall_beads(0.5))
    C, R = _random_bead_poses(1200, seed=43)
    n = len(C)
    args = (C, R, np.linspace(0.0, 0.5, n), np.arange(n), store, np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    want = bead_checker.check_deposit(*args)
    monkeypatch.setattr(checker_module, "CANDIDATE_LEVEL", level)
    got = bead_checker.check_deposit(*args)
    assert 0 < want[0].sum() < n and np.isfinite(want[1]).sum() > 0
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize("threads", ["1", "3"])
def test_deposit_answers_do_not_depend_on_the_threads(bead_checker, monkeypatch, threads):
    """The compiled descent and exact bead test cut a batch into runs of poses for several threads
    (``split``): hits, clearances and the counts of exact tests are those of the default setting."""
    beads = _wall_beads(0.5)
    store = BeadStore(1.0)
    store.add(beads)
    C, R = _random_bead_poses(1200, seed=41)
    n = len(C)
    args = (C, R, np.linspace(0.0, 0.5, n), np.arange(n), store, np.zeros((0, 3)), np.zeros(0, dtype=np.int64))

    def run():
        before = dict(vars(bead_checker.stats))
        hit, clearance = bead_checker.check_deposit(*args)
        after = vars(bead_checker.stats)
        return hit, clearance, {k: after[k] - before[k] for k in before if isinstance(before[k], int)}

    want = run()
    monkeypatch.setenv("NCFIX_THREADS", threads)
    got = run()
    assert 0 < want[0].sum() < n
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert got[2] == want[2]


def test_deposit_free_is_the_exact_answer_at_many_orientations_about_few_tips(bead_checker):
    """``deposit_free`` (a correction's candidate test: many orientations about a few tips, the
    cells' and beads' bounds then the exact test in one compiled loop) calls a pose free exactly
    when the exact reference finds every bead sphere clear of the head above the allowance, both
    ways, with pending beads seen from their sequence number on."""
    beads = _wall_beads(0.5)
    store = BeadStore(1.0)
    store.add(beads[: len(beads) // 2])
    pending = beads[len(beads) // 2:]
    pending_seq = np.arange(len(pending)) // 200
    rng = np.random.default_rng(77)
    tips = np.stack([rng.uniform(-12, 12, 24), rng.uniform(-8, 8, 24), rng.uniform(0, 40, 24)], axis=1)
    which = np.repeat(np.arange(len(tips)), 60)
    C, R = tips[which], _random_rotations(rng, len(which), 40.0)
    seq = which * 4
    bead_checker._tip_cache = None
    free = bead_checker.deposit_free(C, R, seq, store, pending, pending_seq)
    clearance = np.empty(len(C))
    for s in np.unique(seq):
        sel = seq == s
        seen = np.concatenate([beads[: len(beads) // 2], pending[pending_seq <= s]])
        clearance[sel] = _exact_bead_clearance(oracle(bead_checker), C[sel], R[sel], seen, 1.0)
    decided = np.abs(clearance) > 1e-6  # exactly at contact either answer is right
    assert (free[decided] == (clearance[decided] > 0)).all()
    assert 0.1 * len(C) < (~free).sum() < 0.9 * len(C)


def test_deposit_free_reuses_a_tips_beads_only_while_they_hold(bead_checker):
    """``deposit_free`` keeps the beads it gathered per tip: asked again at the same tips (other
    orientations, other batch sizes) it answers as with nothing kept, and a store that grew, or
    other pending beads, are gathered afresh."""
    beads = _wall_beads(0.5)
    store = BeadStore(1.0)
    store.add(beads[: len(beads) // 2])
    rng = np.random.default_rng(51)
    tips = np.stack([rng.uniform(-30, 30, 12), rng.uniform(-25, 25, 12), rng.uniform(-2, 45, 12)], axis=1)
    pending, pending_seq = beads[len(beads) // 2:], np.arange(len(beads) - len(beads) // 2) // 40
    none = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)

    def ask(k, seed, extra=none):
        r = np.random.default_rng(seed)
        which = r.integers(0, len(tips), k)
        C, R, seq = tips[which], _random_rotations(r, k, 45.0), which * 3
        bead_checker._tip_cache = None
        fresh = bead_checker.deposit_free(C, R, seq, store, *extra)
        return C, R, seq, fresh

    checks = 0
    for extra in (none, (pending, pending_seq)):
        for k, seed in ((5, 1), (40, 2), (7, 3), (64, 4)):
            C, R, seq, fresh = ask(k, seed, extra)
            for _again in range(2):  # the first call fills the cache, the next ones use it
                assert np.array_equal(bead_checker.deposit_free(C, R, seq, store, *extra), fresh)
                checks += 1
        kept = bead_checker._tip_cache
        assert kept is not None and kept[3]
    C, R, seq, before = ask(64, 4, (pending, pending_seq))
    store.add(beads + [0.0, 2.5, 0.0])  # the store grows: what was kept no longer holds
    C, R, seq, fresh = ask(64, 4, (pending, pending_seq))
    bead_checker._tip_cache = kept
    assert np.array_equal(bead_checker.deposit_free(C, R, seq, store, pending, pending_seq), fresh)
    assert (before & ~fresh).any() and fresh.any() and checks == 16
