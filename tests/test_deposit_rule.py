"""Where the deposit model lays material: plunges and lifts at their lower end, beads below the tip.

The rule (docs/contract.md, docs/deposit.md): a depositing move within ``AXIAL_DEG`` of the tool axis,
or one whose nozzle ploughs through its own extrudate (the head's shape decides), lays one bead, at
its lower end; any other depositing move lays beads along it; G0 never deposits.
A bead of width w and height h hangs below the nozzle tip with --standoff 0 (top at the tip) and
is centred on P with a standoff; the checker's sphere of radius max(w, h)/2 contains it.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

import ncfix
from ncfix.collision.deposit import AXIAL_DEG, BeadShape
from ncfix.collision.path import PathChecker
from ncfix.collision.stage import MotionRows
from ncfix.config import Options
from ncfix.errors import ConfigError
from ncfix.nc.modal import Interpreter
from ncfix.pipeline import read_chunks
from ncfix.profiles import load_profile

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
HEAD = SAMPLES / "deposition_head.stl"


def laid_beads(text: str, *, standoff: float = 0.0, width: float = 0.8, height: float = 0.8,
               pitch: float = 0.5, head: trimesh.Trimesh | None = None) -> np.ndarray:
    """The bead centres (m, 3) an ijk program lays, in laying order (as the check stage lays them);
    with ``head`` (head frame) the moves that plough through their extrudate are found too."""
    profile = load_profile("ijk")
    bead = BeadShape.stated(0.5 * width, width, height, standoff)
    checker = SimpleNamespace(bead_radius_mm=bead.radius_mm, bead_drop_mm=bead.drop_mm, head=head)
    path = PathChecker(checker, profile, standoff, pitch)
    options = Options(standoff=standoff, pitch=pitch)
    rows_of = MotionRows(path, profile, options)
    out = []
    for chunk in read_chunks(io.BytesIO(text.encode()), Interpreter(profile, "<test>", None)):
        rows = np.nonzero(chunk.motion >= 0)[0]
        dep = rows_of.deposit(chunk)
        _, moves = rows_of.moves(chunk, rows, dep)
        out.append(path.bead_points(moves))
    return np.concatenate(out)


def program(*blocks: str) -> str:
    return "\n".join(["G90 G21", "G0 X0 Y0 Z10 I0 J0 K1", *blocks, "M30", ""])


def test_a_plunge_that_extrudes_lays_one_bead_at_its_bottom():
    beads = laid_beads(program("G1 Z0.5 E2.0 F600"), height=0.6)
    # one bead, under the nozzle at the plunge's lower end (top at the tip: centre 0.3 below it)
    np.testing.assert_allclose(beads, [[0.0, 0.0, 0.2]], atol=1e-12)


def test_a_lift_that_extrudes_lays_one_bead_at_its_bottom():
    beads = laid_beads(program("G1 Z0.5 E1.0 F600", "G1 Z8 E2.0"), height=0.6)
    np.testing.assert_allclose(beads, [[0.0, 0.0, 0.2], [0.0, 0.0, 0.2]], atol=1e-12)


def test_a_travel_g0_and_a_retraction_lay_nothing():
    beads = laid_beads(program("G1 Z0.5 E1.0 F600", "G1 X5 E0.5", "G0 Z5 E3.0", "G0 X20 E4.0", "G1 X25 E3.5"))
    assert len(beads) == 1  # only the plunge's bottom bead: E falls on G1, and G0 never deposits


@pytest.mark.parametrize(("angle_deg", "axial"), [(0.0, True), (AXIAL_DEG - 2, True), (AXIAL_DEG + 5, False),
                                                  (45.0, False), (90.0, False)])
def test_moves_within_the_angle_of_the_axis_deposit_at_their_lower_end(angle_deg, axial):
    """A move descending 6 mm at angle_deg from the tool axis (vertical): one bead within the angle,
    a chain along it (<= pitch/2 apart) beyond it."""
    a = math.radians(angle_deg)
    length = 6.0
    x, z = length * math.sin(a), 10.0 - length * math.cos(a)
    beads = laid_beads(program(f"G1 X{x:.6f} Z{z:.6f} E2.0 F600"), height=0.6)
    bottom = [x, 0.0, z - 0.3]
    if axial:
        np.testing.assert_allclose(beads, [bottom], atol=1e-6)
    else:
        assert len(beads) >= length / 0.25 + 1
        np.testing.assert_allclose(beads[0], [0.0, 0.0, 9.7], atol=1e-6)
        np.testing.assert_allclose(beads[-1], bottom, atol=1e-6)
        assert np.linalg.norm(np.diff(beads, axis=0), axis=1).max() <= 0.25 + 1e-9


def nozzle(tip_radius: float = 0.5, half_angle_deg: float = 57.5, gap: float = 0.0) -> trimesh.Trimesh:
    """A revolved nozzle (head frame): a flat tip of ``tip_radius`` (``gap`` above the tip point),
    a cone widening at ``half_angle_deg`` from the axis to radius 6, then a body to 30 mm."""
    rise = (6.0 - tip_radius) / math.tan(math.radians(half_angle_deg))
    profile = [[0.0, gap], [tip_radius, gap], [6.0, gap + rise], [6.0, 30.0], [0.0, 30.0]]
    return trimesh.creation.revolve(np.array(profile), sections=96)


@pytest.mark.parametrize(("angle_deg", "ploughs"), [(0.0, True), (12.0, True), (40.0, True), (50.0, True),
                                                    (70.0, False), (90.0, False), (180.0, False)])
def test_a_move_whose_nozzle_passes_through_its_extrudate_lays_it_at_the_lower_end(angle_deg, ploughs):
    """A 2 mm move at angle_deg from straight down under a nozzle with a flat tip 1 mm across and a
    cone widening at 45° from the axis: where the tip's earlier positions lie inside the nozzle
    (within the cone, and at 50° too: over 2 mm the flat tip still covers them, the path leaves
    the nozzle only after 4.07 mm) one bead, at the bottom; at 70° the path leaves the nozzle
    after 0.84 mm, and the material stays along the move, as it does for any move across the
    axis or a lift (180°)."""
    a = math.radians(angle_deg)
    x, z = 2.0 * math.sin(a), 10.0 - 2.0 * math.cos(a)
    head = nozzle(half_angle_deg=45.0)
    beads = laid_beads(program(f"G1 X{x:.6f} Z{z:.6f} E2.0 F600"), height=0.6, head=head)
    lower = [x, 0.0, min(z, 10.0) - 0.3]
    if ploughs:
        np.testing.assert_allclose(beads, [lower], atol=1e-6)
    elif angle_deg < 180.0:
        assert len(beads) >= 2.0 / 0.25 + 1  # laid along the move
    else:
        assert len(beads) == 1  # a lift along the axis: the 10° rule, at its lower end (the start)


def test_the_plough_test_is_the_head_s_shape():
    """Against points sampled along each segment (trimesh's containment): the same answer, and a
    nozzle modelled from 0.3 mm above its tip never ploughs (its tip's path starts outside it)."""
    from ncfix.collision.plough import ploughing_moves

    rng = np.random.default_rng(7)
    head = nozzle(half_angle_deg=50.0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= rng.uniform(0.2, 8.0, size=(400, 1))
    eye = np.repeat(np.eye(3)[None], 400, axis=0)
    got = ploughing_moves(np.asarray(head.triangles), d, np.zeros((400, 3)), eye, eye)
    s = np.linspace(0.0, 1.0, 161)[1:]
    inside = head.contains((s[None, :, None] * d[:, None, :]).reshape(-1, 3)).reshape(400, len(s)).all(axis=1)
    assert got.sum() > 30 and (~got).sum() > 30
    assert (got == inside).all()
    lifted = ploughing_moves(np.asarray(nozzle(gap=0.3).triangles), d, np.zeros((400, 3)), eye, eye)
    assert not lifted.any()


def test_beads_hang_below_the_tip_along_a_tilted_axis_and_sit_on_p_with_a_standoff():
    n = np.array([0.0, math.sin(math.radians(30)), math.cos(math.radians(30))])
    text = program(f"G0 X0 Y0 Z0 I{n[0]:.9f} J{n[1]:.9f} K{n[2]:.9f}", "G1 X4 E2 F600")
    filament = laid_beads(text, width=1.0, height=0.6)
    on_path = filament + 0.3 * n  # the top of each bead is at the tip, on the path
    assert np.abs(on_path[:, 1:]).max() < 1e-9 and on_path[-1, 0] == pytest.approx(4.0)
    standoff = laid_beads(text, standoff=6.0, width=1.0, height=0.6)
    assert np.abs(standoff[:, 1:]).max() < 1e-9  # centred on P
    np.testing.assert_allclose(filament, standoff - 0.3 * n, atol=1e-12)


def _section_points(width: float, height: float, k: int = 4001) -> np.ndarray:
    """Points (k·6, 3) on the boundary of the stated bead (BeadShape doc) in its own frame: the
    obround width × height in the plane of the axis (z) and one radial direction, turned about z."""
    a, b = 0.5 * abs(width - height), 0.5 * min(width, height)
    t = np.linspace(0.0, 2.0 * np.pi, k)
    if width >= height:  # a disc of radius a, grown by b: the section's rim is x = ±a + b·cos, z = b·sin
        x = np.sign(np.cos(t)) * a + b * np.cos(t)
        z = b * np.sin(t)
    else:  # a segment of length 2a along the axis, grown by b
        x = b * np.cos(t)
        z = np.sign(np.sin(t)) * a + b * np.sin(t)
    out = []
    for phi in np.linspace(0.0, np.pi, 6):
        out.append(np.stack([x * np.cos(phi), x * np.sin(phi), z], axis=1))
    return np.concatenate(out)


@pytest.mark.parametrize(("width", "height"), [(0.8, 0.8), (1.0, 0.64), (2.5, 0.4), (0.5, 1.2), (6.0, 2.0)])
def test_the_checkers_sphere_contains_the_stated_bead(width, height):
    bead = BeadShape.stated(0.5, width, height, 0.0)
    pts = _section_points(width, height)
    dist = np.linalg.norm(pts, axis=1)
    assert dist.max() <= bead.radius_mm + 1e-12
    # and it is the smallest sphere about the centre that does: the section reaches it
    assert dist.max() == pytest.approx(bead.radius_mm, abs=1e-6)
    assert bead.drop_mm == pytest.approx(0.5 * height)


def _bead_solid(width: float, height: float) -> trimesh.Trimesh:
    """The stated bead as a closed mesh whose vertices lie on its surface (inside it: convex)."""
    pts = _section_points(width, height, k=181)
    rim = []
    for phi in np.linspace(0.0, 2 * np.pi, 48, endpoint=False):
        rim.append(np.stack([pts[:181, 0] * np.cos(phi), pts[:181, 0] * np.sin(phi), pts[:181, 2]], axis=1))
    return trimesh.convex.convex_hull(np.concatenate(rim))


def test_no_pose_that_touches_the_stated_bead_is_called_free():
    """Poses of the sample head around one flat bead laid by a short move: wherever the head above
    the tip allowance meets the bead as stated (the exact mesh test of coal against the bead's
    solid, its vertices on the true surface), the checker says the pose collides."""
    import coal

    from ncfix.collision.checker import Checker
    from ncfix.collision.head import cached_head_model
    from ncfix.collision.deposit import BeadStore
    from ncfix.geometry.mesh import load_head
    from ncfix.geometry.frames import minimal_rotation
    from ncfix.collision.exact import bvh as _bvh, clip_head as _clip_head

    width, height, allowance = 2.5, 0.8, 1.0
    bead = BeadShape.stated(0.5, width, height, 0.0)
    head = load_head(str(HEAD), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)).mesh
    ck = Checker(head, cached_head_model(head, 0.5), [], pitch_mm=0.5, bead_radius_mm=bead.radius_mm,
                 tip_allowance_mm=allowance, device="cpu", bead_drop_mm=bead.drop_mm)
    centre = np.array([0.0, 0.0, -bead.drop_mm])  # laid with the tip at the origin, axis +Z
    store = BeadStore(bead.radius_mm)
    store.add(centre[None])
    solid = _bead_solid(width, height)
    solid.apply_translation(centre)
    clipped = _clip_head(head, allowance)

    head_bvh, bead_bvh = _bvh(clipped), _bvh(solid)
    rng = np.random.default_rng(3)
    touching = 0
    for _ in range(300):
        axis = rng.normal(size=3)
        axis[2] = abs(axis[2]) + 0.3
        axis /= np.linalg.norm(axis)
        R = minimal_rotation(axis)[0]
        C = centre + rng.uniform(-2.5, 2.5, 3) + np.array([0.0, 0.0, 0.5])
        result = coal.CollisionResult()
        coal.collide(head_bvh, coal.Transform3s(R, C), bead_bvh, coal.Transform3s(), coal.CollisionRequest(), result)
        exact = result.isCollision()
        hit = not ck.poses_free(C[None], R[None], np.zeros(1, dtype=np.int64), store, np.zeros((0, 3)),
                                np.zeros(0, dtype=np.int64))[0]
        touching += exact
        if exact:
            assert hit, f"a pose touching the stated bead was called free: C={C}, axis={axis}"
    assert touching >= 20  # the test exercises contacts


@pytest.mark.parametrize(("cli", "message"), [
    ({"bead_width": 1.0}, "--bead-width needs --bead-height too"),
    ({"bead_height": 0.5}, "--bead-height needs --bead-width too"),
    ({"bead_width": 1.0, "bead_height": 0.5, "bead_radius": 0}, "--bead-radius is 0 (no deposit model)"),
    ({"bead_width": -1.0, "bead_height": 0.5}, "--bead-width has a bad value -1.0 (give a number above 0 up to 100)"),
])
def test_a_bead_section_is_a_width_and_a_height(cli, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ncfix.config.build_options({}, cli)


@pytest.mark.parametrize("machine, letter", [("multiaxis-3dp-bc", "E"), ("s3-deformfdm-bc", "A")])
def test_the_report_names_the_profiles_extrusion_word(machine, letter):
    """The extrusion rule reads the profile's extrusion word (A on the S3 ring printer), and the
    report says which word it read."""
    data = f"G90\nG1 X0 Y0 Z5 B0 C0 F600\nG1 X1 {letter}0.1\nG1 X2 {letter}0.2\n".encode()
    report = ncfix.process(io.BytesIO(data), io.BytesIO(), machine=machine, check=True, standoff=0.0,
                           head=str(HEAD))
    assert report.summary["deposit_rule"] == f"extrusion words ({letter} grows)"
