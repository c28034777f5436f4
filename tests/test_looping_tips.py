"""Looping tips: a move whose tip runs a path longer than the programmed one lays a thinner strand.

With TCP off the controller moves its axes linearly, so a move that turns C by 90° near the B = 0
pole takes the nozzle round a loop many times its programmed length while it extrudes the E
programmed for that length. The rule (docs/deposit.md "Looping tips"): the strand's section is
the stated section times programmed length / tip path length; it is held as a thinner bead
(``BeadShape.strand``) along the tip's path. A straight move keeps the stated bead, and the exact
reference (``ncfix.reference``) holds each bead at the same size.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from ncfix.collision.deposit import LOOP_RATIO, BeadShape, BeadStore
from ncfix.collision.path import PathChecker
from ncfix.collision.stage import MotionRows
from ncfix.config import Options
from ncfix.nc.modal import Interpreter
from ncfix.pipeline import read_chunks
from ncfix.profiles import load_profile

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
HEAD = SAMPLES / "deposition_head.stl"
MACHINE = "multiaxis-3dp-bc"  # B/C table-table, TCP off
WIDTH, HEIGHT, PITCH = 1.0, 0.64, 0.5


def words(p, c_deg: float, b_deg: float) -> str:
    """The block's XYZ B C words that put the tip on the part-frame point p (TCP off)."""
    kin = load_profile(MACHINE).kinematics
    r1, r2 = kin.rotations(np.array([[0.0, 0.0, 0.0, c_deg, b_deg]]))
    x, y, z = kin.transform.to_machine(np.asarray(p, dtype=np.float64)[None], r1, r2)[0]
    return f"X{x:.4f} Y{y:.4f} Z{z:.4f} B{b_deg:.3f} C{c_deg:.3f}"


def flip_program() -> str:
    """A straight stretch at B 3°, then a C flip of 90° over 1 mm of part path (a loop), then
    another straight stretch."""
    return "\n".join([
        "G90 G21 M82",
        f"G0 {words((6.0, -4.0, 1.0), 0.0, 3.0)}",
        f"G1 {words((6.0, -1.0, 1.0), 0.0, 3.0)} E1.0 F600",
        f"G1 {words((6.0, 0.0, 1.0), 0.0, 3.0)} E1.3",
        f"G1 {words((6.0, 1.0, 1.0), 90.0, 3.0)} E1.6",  # the flip
        f"G1 {words((6.0, 4.0, 1.0), 90.0, 3.0)} E2.5",
        "M30", ""])


def laid(text: str, bead: BeadShape):
    """Per motion block (in order): (its beads (m, 3), their radii (m,), the block's words)."""
    from types import SimpleNamespace

    profile = load_profile(MACHINE)
    checker = SimpleNamespace(bead_radius_mm=bead.radius_mm, bead_drop_mm=bead.drop_mm, bead_shape=bead)
    path = PathChecker(checker, profile, 0.0, PITCH)
    rows_of = MotionRows(path, profile, Options(standoff=0.0, pitch=PITCH))
    out = []
    for chunk in read_chunks(io.BytesIO(text.encode()), Interpreter(profile, "<test>", None)):
        rows = np.nonzero(chunk.motion >= 0)[0]
        _, moves = rows_of.moves(chunk, rows, rows_of.deposit(chunk))
        for j in range(len(moves.w_end)):
            from ncfix.collision.path import Moves
            one = Moves(moves.w_start[j:j + 1], moves.w_end[j:j + 1], moves.tcp[j:j + 1],
                        moves.known_start[j:j + 1], moves.deposit[j:j + 1], moves.arc[j:j + 1])
            b, r = path.bead_points(one, radii=True)
            out.append((b, np.full(len(b), bead.radius_mm) if r is None else r, one))
    return out, path


def tip_path_length(path: PathChecker, move, k: int = 20000) -> tuple[float, float]:
    """(programmed length, tip path length) of one move, the path finely sampled."""
    t = np.linspace(0.0, 1.0, k + 1)
    w = move.w_start[0] + t[:, None] * (move.w_end[0] - move.w_start[0])
    P, _, _ = path.forward(w, np.zeros(len(t), dtype=bool))
    return float(np.linalg.norm(P[-1] - P[0])), float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())


def test_a_looping_tip_lays_a_thinner_strand_by_the_ratio_of_lengths():
    bead = BeadShape.stated(0.5, WIDTH, HEIGHT, 0.0)
    blocks, path = laid(flip_program(), bead)
    flip_beads, flip_r, flip = blocks[3]
    programmed, real = tip_path_length(path, flip)
    assert real > 4 * programmed  # the controller's path loops
    # The strand: the stated obround section times programmed / real, here below the round of
    # the height, so a round strand of that section.
    section = (WIDTH - HEIGHT) * HEIGHT + math.pi * HEIGHT ** 2 / 4
    strand = math.sqrt(section * programmed / real / math.pi)
    assert strand < 0.5 * HEIGHT
    # held as spheres that cover the strand between beads at most min(pitch/2, strand) apart
    step = min(0.5 * PITCH, strand)
    assert np.all(flip_r >= strand * (1 - 1e-3))
    assert np.all(flip_r <= math.hypot(strand, 0.5 * step) * (1 + 1e-2))
    assert np.all(flip_r < 0.5 * bead.radius_mm)
    # the path's beads first, from one end of the move to the other, top at the tip (the centre a
    # strand radius below it), then the straight line between the ends (deposit.strand_at_rest)
    P, N, _ = path.forward(np.stack([flip.w_start[0], flip.w_end[0]]), np.zeros(2, dtype=bool))
    a, b = P[0] - strand * N[0], P[1] - strand * N[1]
    np.testing.assert_allclose(flip_beads[0], a, atol=1e-3)
    end = int(np.argmin(np.linalg.norm(flip_beads - b, axis=1)))
    np.testing.assert_allclose(flip_beads[end], b, atol=1e-3)
    along, taut = flip_beads[:end + 1], flip_beads[end + 1:]
    assert np.linalg.norm(np.diff(along, axis=0), axis=1).max() <= step * 1.05
    np.testing.assert_allclose(taut[0], along[0], atol=1e-12)  # from one end to the other
    np.testing.assert_allclose(taut[-1], along[-1], atol=1e-12)
    assert np.linalg.norm(np.diff(taut, axis=0), axis=1).max() <= step * 1.05
    # at rest: nothing above the higher of its ends along the machine's vertical (the part
    # frame's vertical at the middle of the move, B 3°, C 45°: the tool axis there, on this
    # table-table machine); below that level, where the tip drew it
    _, mid, _ = path.forward(0.5 * (flip.w_start + flip.w_end), np.zeros(1, dtype=bool))
    up = mid[0]
    level = max(along[0] @ up, along[-1] @ up)
    assert (flip_beads @ up).max() <= level + 1e-9
    t = np.linspace(0.0, 1.0, 4001)
    w = flip.w_start[0] + t[:, None] * (flip.w_end[0] - flip.w_start[0])
    tip, axis, _ = path.forward(w, np.zeros(len(t), dtype=bool))
    drawn = tip - strand * axis
    assert (drawn @ up).max() > level + 0.01  # the loop rises above its ends: the rule lowers it
    rest = drawn - np.maximum(drawn @ up - level, 0.0)[:, None] * up
    near = np.min(np.linalg.norm(rest[:, None] - along[None], axis=2), axis=1)
    assert near.max() <= 0.5 * step * 1.05 + 1e-3  # the lowered path, beads along it


def test_straight_moves_keep_the_stated_bead():
    bead = BeadShape.stated(0.5, WIDTH, HEIGHT, 0.0)
    blocks, path = laid(flip_program(), bead)
    for index in (2, 4):
        beads, radii, move = blocks[index]
        programmed, real = tip_path_length(path, move)
        assert real <= programmed * LOOP_RATIO
        assert len(beads) and np.all(radii == bead.radius_mm)
        # laid as before: evenly from start to end, at most pitch/2 apart, centre height/2 below P
        P, N, _ = path.forward(np.stack([move.w_start[0], move.w_end[0]]), np.zeros(2, dtype=bool))
        np.testing.assert_allclose(beads[0], P[0] - 0.5 * HEIGHT * N[0], atol=1e-9)
        np.testing.assert_allclose(beads[-1], P[1] - 0.5 * HEIGHT * N[1], atol=1e-9)


def test_the_exact_test_holds_each_bead_at_its_own_radius_as_the_reference_does():
    """Poses of the sample head about the loop: the checker's exact test and the corrector's
    candidate test (with the loop's thin beads) agree with the exact reference (coal, each bead at
    its radius), pose by pose; and some poses that the stated bead would hit are free of the
    strand."""
    from ncfix.collision.checker import Checker
    from ncfix.collision.head import cached_head_model
    from ncfix.geometry.frames import minimal_rotation
    from ncfix.geometry.mesh import load_head
    from ncfix.reference import ExactReference

    bead = BeadShape.stated(0.5, WIDTH, HEIGHT, 0.0)
    blocks, _ = laid(flip_program(), bead)
    beads, radii, _ = blocks[3]
    head = load_head(str(HEAD), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)).mesh
    allowance = 1.0
    ck = Checker(head, cached_head_model(head, PITCH), [], pitch_mm=PITCH, bead_radius_mm=bead.radius_mm,
                 tip_allowance_mm=allowance, device="cpu", bead_drop_mm=bead.drop_mm, bead_shape=bead)
    ref = ExactReference(head, {}, tip_allowance_mm=allowance)
    thin, stated = BeadStore(bead.radius_mm), BeadStore(bead.radius_mm)
    thin.add(beads, radii)
    stated.add(beads)
    rng = np.random.default_rng(7)
    lo, hi = beads.min(axis=0), beads.max(axis=0)
    n = 240
    axes = rng.normal(size=(n, 3))
    axes[:, 2] = np.abs(axes[:, 2]) + 0.5
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R = np.stack([minimal_rotation(a)[0] for a in axes])
    C = rng.uniform(lo - 1.5, hi + 1.5) - allowance * axes
    zero, seq = np.zeros(n), np.zeros(n, dtype=np.int64)
    none = np.zeros((0, 3))
    got, _ = ck.check_deposit(C, R, zero, seq, thin, none, np.zeros(0, dtype=np.int64))
    got_stated, _ = ck.check_deposit(C, R, zero, seq, stated, none, np.zeros(0, dtype=np.int64))
    exact = np.array([ref.bead_collides(c, r, beads, radii) for c, r in zip(C, R)])
    exact_stated = np.array([ref.bead_collides(c, r, beads, bead.radius_mm) for c, r in zip(C, R)])
    np.testing.assert_array_equal(got, exact)
    np.testing.assert_array_equal(got_stated, exact_stated)
    # the corrector's candidate test (``poses_free``: a batch of orientations) holds them alike
    free = ck.poses_free(C, R, seq, thin, none, np.zeros(0, dtype=np.int64))
    np.testing.assert_array_equal(free, ~exact)
    assert exact.sum() >= 10  # the test exercises contacts with the strand
    assert (exact_stated & ~exact).sum() >= 10  # and poses only the stated bead would hit


def test_the_reference_lays_the_same_thin_strand(tmp_path):
    """``label_program`` lays the loop's strand as the checker does: the same blocks collide."""
    import trimesh

    from ncfix.api import process
    from ncfix.reference import label_program

    # After the flip the nozzle passes under the loop (its strand 1.1 mm above the tip), ending
    # below it: the nozzle above its 1 mm allowance runs into the strand.
    text = flip_program().replace("M30\n", "\n".join([
        f"G0 {words((-3.0, -0.2, 6.0), 0.0, 0.0)}",
        f"G1 {words((-3.0, -0.2, -0.29), 0.0, 0.0)}",
        f"G1 {words((5.3, -0.2, -0.29), 0.0, 0.0)} F600",
        "M30", ""]))
    src = tmp_path / "flip.gcode"
    src.write_text(text)
    head = trimesh.load(str(HEAD))
    expected = label_program(str(src), MACHINE, head, {}, standoff_mm=0.0, bead_radius_mm=0.5,
                             tip_allowance_mm=1.0, bead_drop_mm=0.5 * HEIGHT,
                             bead_shape=BeadShape.stated(0.5, WIDTH, HEIGHT, 0.0))
    report = process(str(src), str(tmp_path / "out.gcode"), check=True, machine=MACHINE, head=str(HEAD),
                     standoff=0.0, bead_width=WIDTH, bead_height=HEIGHT, tip_allowance=1.0, pitch=PITCH)
    flagged = {c["line"] for c in report.collisions}
    hits = {line for line, bodies in expected if "deposit" in bodies}
    assert hits  # the reference finds the strand
    assert not hits - flagged
