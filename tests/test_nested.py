"""A body wholly inside another collides, whatever the meshes hold: a part file of several bodies
with one inside the head, a body of the head inside a part, the head inside a hollow part's wall
(and free in its cavity), beads inside the head. Checked through the command line (the case as a
user meets it) and on random poses against the exact reference (which tests every connected body
for containment, not only triangle pairs), through the checker and through the corrector's
candidate tests (``Checker.poses_free``, which every strategy's ``Episode.free`` calls, and the
bounds-only ``Checker.free_poses``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import corpus_path, oracle
from ncfix.cli import main
from ncfix.collision.checker import Checker
from ncfix.collision.deposit import BeadStore
from ncfix.collision.head import build_head_model
from ncfix.geometry.distance import winding_numbers
from ncfix.geometry.mesh import load_head
from ncfix.collision.near import surface_distances

REPO = Path(__file__).resolve().parents[1]
HEAD = REPO / "samples" / "deposition_head.stl"
PITCH = 0.5

# -- the reported case, through the command line ----------------------------------------------

# Five blocks along X under a vertical head: a 1 mm cube 20 mm above the tip (26 mm above P with
# the 6 mm standoff) lies inside the head's body at every one of them, touching no triangle.
PROGRAM = b"G90\nG1 X9.8 Y0 Z0 I0 J0 K1 F100\nX9.9\nX10.0\nX10.1\nX10.2\n"


def _cube(centre, size=1.0) -> trimesh.Trimesh:
    cube = trimesh.creation.box([size] * 3)
    cube.apply_translation(centre)
    return cube


@pytest.mark.parametrize("files", [
    [["inside"]],
    [["inside", "far"]],
    [["far", "inside"]],
    [["inside"], ["far"]],
], ids=["one body", "two bodies in one file", "the other order", "two files"])
def test_a_part_body_wholly_inside_the_head_is_flagged_at_every_block(tmp_path, files):
    bodies = {"inside": _cube((10.0, 0.0, 26.0)), "far": _cube((200.0, 0.0, 0.0))}
    program = tmp_path / "in.nc"
    program.write_bytes(PROGRAM)
    args = [str(program), "--head", str(HEAD), "--bead-radius", "0", "--check", "-q",
            "-o", str(tmp_path / "out.nc"), "--report", str(tmp_path / "report.json")]
    for k, names in enumerate(files):
        path = tmp_path / f"part{k}.stl"
        trimesh.util.concatenate([bodies[name] for name in names]).export(path)
        args += ["--part", str(path)]
    assert main(args) == 1
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["summary"]["colliding_blocks_before"] == 5
    assert [c["line"] for c in report["collisions"]] == [2, 3, 4, 5, 6]
    assert all(c["bodies"] == ["part:part0.stl"] for c in report["collisions"])
    assert (tmp_path / "out.nc").read_bytes() == PROGRAM


# -- random poses against the exact reference ---------------------------------------------------

HEADS = {
    "sample": (None, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "sample with a separate body": (None, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "extruderHead": (("multiaxis_3dp_motionplanning", "extruderHead_converted.stl"), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "nozzle": (("s3_deformfdm", "nozzle_converted.stl"), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
}
PART_POSES = 6000  # per head: 24,000 in all
HEAVY_PART_POSES = 20000  # per head, other poses (heavy)
HOLLOW_POSES = 800
BEAD_POSES = 1500
# Every head with every pose in CI's heavy step; the fast run, one head (the one with a separate
# body) with a quarter of the poses.
FAST_HEAD, FAST_SHARE = "sample with a separate body", 0.25
BEAD_RADIUS = 0.4
SEED = 42
REGION_MM = 25.0  # the small bodies lie within this of the origin


def _rotations(rng, n: int) -> np.ndarray:
    """(n, 3, 3) uniformly random rotations (from unit quaternions)."""
    q = rng.normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def _place(R: np.ndarray, world: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Tips (n, 3) that put head-frame points local (n, 3) at world points (n, 3) under R (n, 3, 3)."""
    return world - np.einsum("nij,nj->ni", R, local)


class Scene:
    """A head (one of HEADS), its interior points with their depth, and checkers of it against a
    part of several small bodies (and an 8 mm block), a hollow box, and beads."""

    def __init__(self, name: str, share: float = 1.0):
        self.poses = {what: int(share * n) for what, n in
                      (("part", PART_POSES), ("hollow", HOLLOW_POSES), ("bead", BEAD_POSES))}
        where, tip, axis = HEADS[name]
        path = HEAD if where is None else corpus_path(*where)
        head = load_head(path, tip, axis).mesh
        self.rng = np.random.default_rng(SEED)
        lo, hi = head.bounds
        self.satellite = None
        if name == "sample with a separate body":  # a 2 mm cube 10 mm beside the head's box
            self.satellite = np.array([lo[0] - 10.0, 0.0, 0.5 * (lo[2] + hi[2])])
            head = trimesh.util.concatenate([head, _cube(self.satellite, 2.0)])
        self.head = head
        self.size = float((hi - lo).max())
        # Points inside the head with their distance to its surface, and points on its surface
        # with their normals.
        tris = np.asarray(head.triangles)
        pts = self.rng.uniform(lo, hi, (8000, 3))
        pts = pts[winding_numbers(pts, tris) > 0.5][:1500]
        self.interior, self.depth = pts, surface_distances(tris, pts, 2.0)
        area = np.asarray(head.area_faces)
        face = self.rng.choice(len(area), 1500, p=area / area.sum())
        u, v = self.rng.random((2, 1500, 1))
        flip = (u + v) > 1.0
        u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
        t = tris[face]
        self.surface = t[:, 0] + u * (t[:, 1] - t[:, 0]) + v * (t[:, 2] - t[:, 0])
        self.normal = np.asarray(head.face_normals)[face]
        # The part: small boxes and balls (0.2-6 mm, most smaller than the head's section), an
        # 8 mm block, and a body far away: one mesh of many bodies.
        bodies, self.centres, self.radii = [], [], []
        for k in range(24):
            s = float(np.exp(self.rng.uniform(np.log(0.2), np.log(6.0))))
            body = _cube((0, 0, 0), s) if k % 2 else trimesh.creation.icosphere(1, s / 2)
            body.apply_transform(trimesh.transformations.random_rotation_matrix(self.rng.random(3)))
            centre = self.rng.uniform(-REGION_MM, REGION_MM, 3)
            body.apply_translation(centre)
            bodies.append(body)
            self.centres.append(centre)
            self.radii.append(float(np.linalg.norm(body.vertices - centre, axis=1).max()))
        self.block = np.array([0.0, 0.0, -REGION_MM - 10.0])
        bodies += [_cube(self.block, 8.0), _cube((2.5 * REGION_MM, 0.0, 0.0))]
        self.centres, self.radii = np.array(self.centres), np.array(self.radii)
        self.part = trimesh.util.concatenate(bodies)
        assert self.part.body_count == 26
        self.model = model = build_head_model(head, PITCH)
        self.checker = Checker(head, model, [("part:bodies", self.part, True)], pitch_mm=PITCH,
                               bead_radius_mm=0.0, device="cpu")

    def part_poses(self, n: int, rng: np.random.Generator | None = None):
        """Poses (C, R) and which of them certainly hold a small body inside the head (its ball
        around an interior point deeper than its radius): a body at an interior point (40%), the
        same moved a little (30%), anywhere about the bodies (20%), and the head's separate body
        in the block (10%, where the head has one). Drawn from ``rng``, else the scene's."""
        rng = self.rng if rng is None else rng
        R = _rotations(rng, n)
        k = rng.integers(0, len(self.centres), n)
        i = rng.integers(0, len(self.interior), n)
        C = _place(R, self.centres[k], self.interior[i])
        inside = self.radii[k] < self.depth[i] - 1e-6
        kind = rng.random(n)
        moved = kind >= 0.4
        C[moved] += rng.normal(0.0, 0.05 * self.size, (int(moved.sum()), 3))
        inside &= ~moved
        anywhere = kind >= 0.7
        C[anywhere] = rng.uniform(-REGION_MM - 0.5 * self.size, REGION_MM + 0.5 * self.size, (int(anywhere.sum()), 3))
        if self.satellite is not None:
            held = kind >= 0.9  # the 2 mm cube's centre within 2 mm of the 8 mm block's: inside it
            m = int(held.sum())
            C[held] = _place(R[held], self.block + rng.uniform(-2.0, 2.0, (m, 3)), np.tile(self.satellite, (m, 1)))
        return C, R, inside

    def hollow(self):
        """A checker against a hollow box (cavity and walls wider than the head's bounding ball), and
        poses: the ball's centre in the cavity (half of them) or anywhere about the box, known to
        collide where the ball lies in the wall, known free where it lies in the cavity."""
        v = np.asarray(self.head.vertices)
        self.ball_centre = v.mean(axis=0)
        ball = float(np.linalg.norm(v - self.ball_centre, axis=1).max())
        cavity, outer = 2.5 * ball, 6.0 * ball
        box = trimesh.creation.box([2 * outer] * 3)
        hole = trimesh.creation.box([2 * cavity] * 3)
        hole.invert()
        part = trimesh.util.concatenate([box, hole])
        pitch = ball / 10.0
        checker = Checker(self.head, build_head_model(self.head, pitch), [("part:hollow", part, True)],
                          pitch_mm=pitch, bead_radius_mm=0.0, device="cpu")
        rng = self.rng
        n = self.poses["hollow"]
        R = _rotations(rng, n)
        where = rng.uniform(-1.0, 1.0, (n, 3)) * np.where(rng.random((n, 1)) < 0.5, cavity, outer + ball)
        C = _place(R, where, np.tile(self.ball_centre, (n, 1)))
        a = np.abs(where).max(axis=1)
        in_wall = (a > cavity + ball) & (a < outer - ball)
        in_cavity = a < cavity - ball
        return checker, C, R, in_wall, in_cavity

    def bead_case(self, n: int):
        """A checker of the head against beads (radius BEAD_RADIUS, the 1 mm tip allowance), the
        beads, and poses: a bead at an interior point (40%), a bead within 2 mm of the surface
        (30%), anywhere about the beads (30%); and which poses certainly hold a bead inside the
        head above the allowance."""
        checker = Checker(self.head, self.model, [], pitch_mm=PITCH, bead_radius_mm=BEAD_RADIUS, tip_allowance_mm=1.0,
                          device="cpu")
        rng = self.rng
        beads = rng.uniform(-REGION_MM, REGION_MM, (60, 3))
        R = _rotations(rng, n)
        j = rng.integers(0, len(beads), n)
        i = rng.integers(0, len(self.interior), n)
        C = _place(R, beads[j], self.interior[i])
        inside = (self.depth[i] > BEAD_RADIUS + 1e-6) & (self.interior[i, 2] > 1.0 + BEAD_RADIUS)
        kind = rng.random(n)
        near = kind >= 0.4
        f = rng.integers(0, len(self.surface), int(near.sum()))
        local = self.surface[f] + self.normal[f] * rng.uniform(-2.0, 2.0, (len(f), 1))
        C[near] = _place(R[near], beads[j[near]], local)
        anywhere = kind >= 0.7
        C[anywhere] = rng.uniform(-REGION_MM - 0.5 * self.size, REGION_MM + 0.5 * self.size, (int(anywhere.sum()), 3))
        return checker, beads, C, R, inside & ~near


@pytest.fixture(scope="module", params=[
    pytest.param((FAST_HEAD, FAST_SHARE), id=f"{FAST_HEAD}, a quarter of the poses"),
    *(pytest.param((name, 1.0), id=name, marks=pytest.mark.heavy) for name in HEADS)])
def scene(request):
    return Scene(*request.param)


def _report(what: str, n: int, truth: np.ndarray, free: np.ndarray, seconds: float) -> tuple[int, int]:
    misses = int((truth & free).sum())
    alarms = int((~truth & ~free).sum())
    print(f"\n{what}: {n} poses, {int(truth.sum())} colliding, misses {misses}, "
          f"false alarms {alarms}, {seconds:.1f} s")
    return misses, alarms


def test_multi_body_parts_no_misses_in_the_checker_and_the_candidate_tests(scene):
    _no_misses_among_part_bodies(scene, *scene.part_poses(scene.poses["part"]))


@pytest.mark.heavy
def test_multi_body_parts_no_misses_at_20000_poses_per_head(scene):
    """The same at 20,000 more poses of each head, from a generator of their own (the same poses
    whichever tests ran before)."""
    _no_misses_among_part_bodies(scene, *scene.part_poses(HEAVY_PART_POSES, np.random.default_rng(SEED + 1)))


def _no_misses_among_part_bodies(scene, C: np.ndarray, R: np.ndarray, inside: np.ndarray) -> None:
    """The checker (``check_parts``) and the corrector's candidate tests (``poses_free``, the
    bounds-only ``free_poses``) against the exact reference at poses C, R: no miss; the first two
    no false alarm either (an undecided pose goes to the exact test)."""
    ck = scene.checker
    truth = np.array([oracle(ck).collides(c, r) for c, r in zip(C, R)])
    # The reference sees every body placed inside the head (a miss of mesh-mesh collision alone).
    assert inside.sum() > 0.1 * len(C) and truth[inside].all()
    none = BeadStore(0.0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    start = time.perf_counter()
    hit = ck.check_parts(C, R, np.zeros(len(C))).any(axis=1)
    misses, alarms = _report("check_parts", len(C), truth, ~hit,
                             time.perf_counter() - start)
    assert misses == 0 and alarms == 0
    start = time.perf_counter()
    free = ck.poses_free(C, R, np.arange(len(C)), *none)
    misses, alarms = _report("poses_free", len(C), truth, free, time.perf_counter() - start)
    assert misses == 0 and alarms == 0
    start = time.perf_counter()
    free = ck.free_poses(C, R, np.arange(len(C)), *none)
    misses, alarms = _report("free_poses (bounds only)", len(C), truth, free, time.perf_counter() - start)
    assert misses == 0
    assert (truth.sum() > 0.3 * len(C)) and ((~truth).sum() > 0.1 * len(C))


def test_the_head_in_a_hollow_parts_wall_collides_and_in_its_cavity_is_free(scene):
    ck, C, R, in_wall, in_cavity = scene.hollow()
    truth = np.array([oracle(ck).collides(c, r) for c, r in zip(C, R)])
    assert in_wall.sum() > 0.05 * len(C) and in_cavity.sum() > 0.01 * len(C)
    assert truth[in_wall].all() and not truth[in_cavity].any()
    none = BeadStore(0.0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    start = time.perf_counter()
    hit = ck.check_parts(C, R, np.zeros(len(C))).any(axis=1)
    assert _report("hollow: check_parts", len(C), truth, ~hit, time.perf_counter() - start) == (0, 0)
    assert _report("hollow: poses_free", len(C), truth, ck.poses_free(C, R, np.arange(len(C)), *none), 0.0) == (0, 0)
    free = ck.free_poses(C, R, np.arange(len(C)), *none)
    assert _report("hollow: free_poses", len(C), truth, free, 0.0)[0] == 0


def test_beads_wholly_inside_the_head_collide(scene):
    ck, beads, C, R, inside = scene.bead_case(scene.poses["bead"])
    ref = oracle(ck)
    truth = np.array([ref.bead_collides(c, r, beads, BEAD_RADIUS) for c, r in zip(C, R)])
    assert inside.sum() > 0.1 * len(C) and truth[inside].all()
    store = BeadStore(BEAD_RADIUS)
    store.add(beads)
    none = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    seq = np.arange(len(C))
    start = time.perf_counter()
    hit, _ = ck.check_deposit(C, R, np.zeros(len(C)), seq, store, *none)
    assert _report("beads: check_deposit", len(C), truth, ~hit, time.perf_counter() - start)[0] == 0
    assert _report("beads: poses_free", len(C), truth, ck.poses_free(C, R, seq, store, *none), 0.0)[0] == 0
    assert _report("beads: free_poses", len(C), truth, ck.free_poses(C, R, seq, store, *none), 0.0)[0] == 0
