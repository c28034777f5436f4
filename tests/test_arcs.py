"""G2/G3 arcs: the reader finds their centres, the checker follows them (not their chord), beads
are laid along them, and the corrector leaves them as programmed."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix
from ncfix.collision.path import arc_extent, arc_points
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _arcs(profile: str, lines: list[str]) -> list:
    it = Interpreter(load_profile(profile))
    return [it.feed(i + 1, line) for i, line in enumerate(lines)]


@pytest.mark.parametrize("profile, lines, centre, axis, sense", [
    ("ijk", ["G1 X10 Y0 Z0", "G3 X0 Y10 I-10 J0"], (0, 0, 0), 2, 1),
    ("ijk", ["G1 X0 Y10 Z0", "G2 X10 Y0 R10"], (0, 0, 0), 2, -1),  # a quarter, clockwise
    ("ijk", ["G1 X10 Y0 Z0", "G3 X-10 Y0 R-10"], (0, 0, 0), 2, 1),  # a half: |R| = chord / 2
    ("ijk", ["G1 X10 Y0 Z0", "G2 X0 Y10 R10"], (10, 10, 0), 2, -1),  # a quarter clockwise about (10, 10)
    ("ijk", ["G1 X10 Y0 Z0", "G2 X0 Y10 R-10"], (0, 0, 0), 2, -1),  # three quarters clockwise
    ("ijk", ["G1 X-10 Y0 Z0", "G18 G2 X0 Z10 I10 K0"], (0, 0, 0), 1, -1),
    ("ijk", ["G1 X0 Y-10 Z0", "G19 G3 Y10 Z0 J10 K0"], (0, 0, 0), 0, 1),
    ("ijk", ["G1 X10 Y0 Z0", "G90.1 G3 X0 Y10 I0 J0"], (0, 0, 0), 2, 1),  # absolute centre
    ("ijk", ["G20", "G1 X1 Y0 Z0", "G3 X0 Y1 I-1 J0"], (0, 0, 0), 2, 1),  # inches: mm inside
    ("table-ac", ["G1 X10 Y0 Z0 A0 C0", "G3 X0 Y10 I-10 J0"], (0, 0, 0), 2, 1),
    ("sinumerik-vector", ["G1 X10 Y0 Z0", "G3 X0 Y10 CR=10"], (0, 0, 0), 2, 1),
    ("heidenhain-ln", ["L X+10 Y+0 Z+0", "CC X+0 Y+0", "C X+0 Y+10 DR+"], (0, 0, 0), 2, 1),
    ("heidenhain-ln", ["L X+10 Y+0 Z+0", "CR X+0 Y+10 R+10 DR-"], (10, 10, 0), 2, -1),
])
def test_arc_centres_axes_and_senses(profile, lines, centre, axis, sense):
    block = _arcs(profile, lines)[-1]
    assert block.arc is not None
    assert np.allclose(block.arc[:3], centre, atol=1e-9)
    assert block.arc[3:] == (axis, sense)


@pytest.mark.parametrize("profile, lines", [
    ("sinumerik-vector", ["G1 X10 Y0 Z0", "G3 X0 Y10 I=AC(0) J=AC(0)"]),  # absolute centre by expression
    ("ijk", ["G1 X10 Y0 Z0", "G3 X0 Y10"]),  # neither centre nor radius
    ("ijk", ["G1 X10 Y0 Z0", "G3 X-10 Y0 R5"]),  # radius shorter than half the chord
    ("heidenhain-ln", ["L X+10 Y+0 Z+0", "C X+0 Y+10 DR+"]),  # no pole yet
])
def test_arcs_ncfix_cannot_follow_have_no_arc(profile, lines):
    block = _arcs(profile, lines)[-1]
    assert block.motion is not None and block.arc is None


def test_a_siemens_arc_carries_its_tool_vector_and_i_j_k_stay_the_centre():
    """A3= B3= C3= on a G2/G3 orient the arc's end (they are not its centre); Fanuc I J K on an
    arc are the centre and leave the vector as it was."""
    siemens = _arcs("sinumerik-vector", ["G1 X10 Y0 Z0 A3=0 B3=0 C3=1", "G3 X0 Y10 CR=10 A3=0 B3=0.6 C3=0.8"])[-1]
    assert siemens.arc is not None and np.allclose(siemens.words[3:], [0, 0.6, 0.8])
    fanuc = _arcs("ijk", ["G1 X10 Y0 Z0 I0 J0 K1", "G3 X0 Y10 I-10 J0"])[-1]
    assert fanuc.arc is not None and np.allclose(fanuc.words[3:], [0, 0, 1])


def test_heidenhain_pole_does_not_move_the_machine():
    blocks = _arcs("heidenhain-ln", ["L X+10 Y+5 Z+1", "CC X+0 Y+0", "L Z+2"])
    assert blocks[2].words[:3] == (10.0, 5.0, 2.0)


def test_arc_points_follow_the_circle_in_its_sense():
    start, end = np.array([[10.0, 0, 0]]), np.array([[-10.0, 0, 4]])
    t = np.linspace(0, 1, 9)
    for sense, y_sign in ((1, 1), (-1, -1)):
        arc = np.array([[0.0, 0, 0, 2, sense]])
        pts = arc_points(np.repeat(start, 9, 0), np.repeat(end, 9, 0), np.repeat(arc, 9, 0), t)
        assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 10.0)
        assert np.allclose(pts[:, 2], 4 * t)  # a helix: the normal coordinate goes linearly
        assert np.sign(pts[4, 1]) == y_sign and np.allclose(pts[[0, -1]], [start[0], end[0]])
        sweep, length = arc_extent(start, end, arc)
        assert sweep[0] == pytest.approx(sense * math.pi) and length[0] >= 10 * math.pi
    full = arc_extent(start, start, np.array([[0.0, 0, 0, 2, -1]]))[0]
    assert full[0] == pytest.approx(-2 * math.pi)  # start == end: once round


def _program(arc_line: str) -> bytes:
    return ("%\nG21 G90 G17\nG0 X40. Y0. Z20.\nG1 X30. Y0. Z0. I0. J0. K1. F600.\n"
            f"{arc_line}\nG1 X-40. Y0. Z0.\nG0 Z30.\nM30\n%\n").encode()


@pytest.fixture()
def box(tmp_path) -> str:
    """A block under the arc's bulge at +Y, 2 mm above the nozzle tip: far from the chord."""
    mesh = trimesh.creation.box(extents=(10.0, 10.0, 18.0))
    mesh.apply_translation((0.0, 30.0, -1.0))  # top at z = 8; the tip runs at z = 6
    path = tmp_path / "block.stl"
    mesh.export(path)
    return str(path)


@pytest.mark.parametrize("arc_line, collides", [
    ("G3 X-30. Y0. I-30. J0.", True),  # counter-clockwise: over the block
    ("G3 X-30. Y0. R30.", True),
    ("G2 X-30. Y0. I-30. J0.", False),  # clockwise: the other half, nowhere near it
])
def test_the_check_follows_the_arc_not_its_chord(box, arc_line, collides):
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(_program(arc_line)), out, head=str(SAMPLES / "deposition_head.stl"),
                           part=[box], check=True, bead_radius=0.0)
    lines = [c["line"] for c in report.collisions]
    assert lines == ([5] if collides else [])
    assert not any("chord" in w for w in report.warnings)
    if collides:  # the exact reference agrees: the pose at the bulge hits the block
        from ncfix.geometry.frames import rotation_between
        from ncfix.geometry.mesh import load_head
        from ncfix.reference import ExactReference

        head = load_head(SAMPLES / "deposition_head.stl").mesh
        ref = ExactReference(head, {"block": trimesh.load(box)})
        R = rotation_between(np.array([0.0, 0, 1]), np.array([0.0, 0, 1])).reshape(3, 3)
        assert ref.collides(np.array([0.0, 30.0, 6.0]), R)


def test_an_arc_ncfix_cannot_follow_is_reported(box):
    report = ncfix.process(io.BytesIO(_program("G3 X-30. Y0.")), io.BytesIO(),
                           head=str(SAMPLES / "deposition_head.stl"), part=[box], check=True, bead_radius=0.0)
    assert any("1 G2/G3 arc blocks were checked along their chord" in w for w in report.warnings)


def test_beads_are_laid_along_the_arc():
    from ncfix.collision.path import Moves, PathChecker

    class _Checker:
        bead_radius_mm = 1.0

    path = PathChecker(_Checker(), load_profile("ijk"), 6.0, 0.5)
    ws = np.array([[10.0, 0, 0, 0, 0, 1]])
    we = np.array([[-10.0, 0, 0, 0, 0, 1]])
    moves = Moves(ws, we, np.ones(1, bool), np.ones(1, bool), np.ones(1, bool), np.array([[0.0, 0, 0, 2, 1]]))
    beads = path.bead_points(moves)
    assert np.allclose(np.hypot(beads[:, 0], beads[:, 1]), 10.0)
    assert (beads[:, 1] >= -1e-9).all()  # counter-clockwise from +X to -X: through +Y
    gaps = np.linalg.norm(np.diff(beads, axis=0), axis=1)
    assert gaps.max() <= 0.25 + 1e-9 and len(beads) >= 10 * math.pi / 0.25


def test_the_corrector_leaves_a_colliding_arc_as_programmed(box):
    program = _program("G3 X-30. Y0. I-30. J0.")
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(program), out, head=str(SAMPLES / "deposition_head.stl"), part=[box],
                           bead_radius=0.0)
    assert out.getvalue() == program
    assert report.exit_code == 1
    assert [u["line"] for u in report.unresolved] == [5]
    assert "arc" in report.unresolved[0]["reason"]
