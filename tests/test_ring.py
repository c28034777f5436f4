"""The S3-Slicer ring printer (`s3-deformfdm-bc`): its head-table kinematics against the program's
own waypoint files, and words ↔ pose round trips (reference: s3-ring-kinematics.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ncfix.errors import ProfileError
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile

from conftest import corpus_path

PROFILE = "s3-deformfdm-bc"
WAYPOINT_LAYERS = (0, 60, 120, 180, 244)
SINGULAR_DEG = 6.0  # the slicer writes no tilt below this (B = 0, or B held at the cone's edge)


def ring_layers(profile) -> list[list[tuple[int, np.ndarray]]]:
    """(line, words X Y Z C B) of the blocks that carry all of X Y Z B C A, per layer; a layer
    starts at its `G1 F650` (layer 0) or `G1 F750` line."""
    interp = Interpreter(profile, "ring_Gcode.txt")
    layers: list[list[tuple[int, np.ndarray]]] = []
    with open(corpus_path("s3_deformfdm", "ring_Gcode.txt"), "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            text = raw.decode("ascii")
            block = interp.feed(lineno, text)
            if text.startswith(("G1 F650", "G1 F750")):
                layers.append([])
            elif layers and block.motion == 1 and {w[0] for w in text.split()} >= set("XYZBCA"):
                layers[-1].append((lineno, np.array(block.words)))
    return layers


def waypoints(layer: int) -> tuple[np.ndarray, np.ndarray]:
    """The layer's waypoints turned Z-up ((x, y, z) → (x, −z, y)) and its tool axes (tip → head:
    the files store the opposite direction), unit length."""
    data = np.loadtxt(corpus_path("s3_deformfdm", "ring_waypoint", f"{layer}.txt"))
    points = np.stack([data[:, 0], -data[:, 2], data[:, 1]], axis=1)
    axes = -np.stack([data[:, 3], -data[:, 5], data[:, 4]], axis=1)
    return points, axes / np.linalg.norm(axes, axis=1, keepdims=True)


def slicer_smoothed(points: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """The tool axes the slicer posts: 10 in-place passes of n_i ← unit(n_{i−1} + n_i/2 + n_{i+1}),
    the first and last point and both ends of every jump (> 4 mm) held (S3_DeformFDM
    GcodeGeneration `_cal_Dist`, `_initialSmooth`)."""
    axes = axes.copy()
    held = np.zeros(len(points), dtype=bool)
    held[[0, -1]] = True
    jumps = np.flatnonzero(np.linalg.norm(np.diff(points, axis=0), axis=1) > 4.0)
    held[jumps] = held[jumps + 1] = True
    for _ in range(10):
        for i in np.flatnonzero(~held):
            v = axes[i - 1] + 0.5 * axes[i] + axes[i + 1]
            axes[i] = v / np.linalg.norm(v)
    return axes


@pytest.fixture(scope="module")
def profile():
    return load_profile(PROFILE)


@pytest.fixture(scope="module")
def layers(profile):
    return ring_layers(profile)


def test_the_ring_program_takes_the_poses_of_its_waypoints(profile, layers):
    """Every block of the five waypoint layers: the tip within 0.02 mm of its waypoint; the tool
    axis within 0.3° of the slicer's smoothed axis wherever that lies outside the slicer's 6° cone
    (inside it the slicer writes B = 0, or holds B at ±6° across the stretch: no axis to match)."""
    assert len(layers) == 245
    matched = tilted = axis_checked = 0
    for k in WAYPOINT_LAYERS:
        points, raw_axes = waypoints(k)
        rows = layers[k]
        assert len(rows) == len(points), k
        words = np.array([w for _, w in rows])
        p, n, rot = profile.kinematics.forward(words, tcp=False)
        tip_error = np.linalg.norm(p - points, axis=1)
        assert tip_error.max() < 0.02, (k, rows[int(tip_error.argmax())][0], tip_error.max())
        smoothed = slicer_smoothed(points, raw_axes)
        outside = np.degrees(np.arccos(np.clip(smoothed[:, 2], -1.0, 1.0))) >= SINGULAR_DEG
        angle = np.degrees(np.arccos(np.clip((n * smoothed).sum(axis=1), -1.0, 1.0)))
        bad = outside & (angle > 0.3)
        assert not bad.any(), (k, [rows[i][0] for i in np.flatnonzero(bad)], angle[bad])
        b = words[:, 4]
        # The tilted blocks the axis test leaves out are those at the cone's edge: B = ±6.00.
        assert np.all(np.abs(np.abs(b[(np.abs(b) >= SINGULAR_DEG) & ~outside]) - SINGULAR_DEG) < 1e-9)
        assert np.all((b == 0) | (np.abs(b) >= SINGULAR_DEG))
        assert np.allclose(rot[:, :, 2], n) and np.allclose(np.linalg.det(rot), 1.0)
        matched += len(rows)
        tilted += int((np.abs(b) >= SINGULAR_DEG).sum())
        axis_checked += int(outside.sum())
    assert (matched, tilted, axis_checked) == (1146, 556, 532)


def test_the_ring_map_is_the_fitted_closed_form(profile):
    """s3-ring-kinematics.md: X = Rz(−C)·(p + 0.3 e_z) + 77.36·(0, sin B, cos B − 1) and
    N = (−sin C sin B, cos C sin B, cos B), for any C and B (both signs); A is the filament."""
    assert profile.kinematics.orientation_letters == ("C", "B") and profile.extrusion_letter == "A"
    rng = np.random.default_rng(41)
    p = rng.uniform(-60, 60, (200, 3))
    c, b = rng.uniform(-300, 300, 200), rng.uniform(-40, 40, 200)
    cr, br = np.radians(c), np.radians(b)
    q = p + [0.0, 0.0, 0.3]
    machine = np.stack([q[:, 0] * np.cos(cr) + q[:, 1] * np.sin(cr),
                        -q[:, 0] * np.sin(cr) + q[:, 1] * np.cos(cr) + 77.36 * np.sin(br),
                        q[:, 2] - 77.36 * (1 - np.cos(br))], axis=1)
    words = np.column_stack([machine, c, b])
    p_back, n, _ = profile.kinematics.forward(words, tcp=False)
    assert np.abs(p_back - p).max() < 1e-9
    expected = np.stack([-np.sin(cr) * np.sin(br), np.cos(cr) * np.sin(br), np.cos(br)], axis=1)
    assert np.abs(n - expected).max() < 1e-12


def test_the_ring_blocks_round_trip_through_the_inverse(profile, layers):
    """pose → words with the previous block as reference gives back the program's own words
    (within its 2-decimal rounding) on the waypoint layers: same branch, C unwound in the layer,
    C held where B = 0 (the pole)."""
    kin = profile.kinematics
    for k in WAYPOINT_LAYERS:
        words = np.array([w for _, w in layers[k]])
        p, n, _ = kin.forward(words, tcp=False)
        for i in range(1, len(words)):
            back = kin.inverse(p[i], n[i], words[i - 1], tcp=False)
            assert np.abs(back - words[i]).max() < 1e-6, (k, layers[k][i][0], back, words[i])


def test_a_turn_within_a_layer_is_written_unwound(profile):
    """A pose written next to C = 170°: the new C lies within 180° of it (here 190°, not −170°)."""
    kin = profile.kinematics
    b, c = math.radians(20.0), math.radians(-170.0)
    n = np.array([-math.sin(c) * math.sin(b), math.cos(c) * math.sin(b), math.cos(b)])
    words = kin.inverse(np.array([1.0, 2.0, 3.0]), n, np.array([0.0, 0.0, 0.0, 170.0, 20.0]), tcp=False)
    assert words[3] == pytest.approx(190.0) and words[4] == pytest.approx(20.0)
    p_back, n_back, _ = kin.forward(words[None], tcp=False)
    assert np.allclose(p_back[0], [1.0, 2.0, 3.0]) and np.allclose(n_back[0], n)


def test_a_geometry_key_of_another_family_is_refused(tmp_path):
    """`offset_mm` is table_table's: a head_table profile that gives it fails, never ignores it."""
    text = load_profile(PROFILE).source
    body = open(text, encoding="utf-8").read().replace("part_origin_mm", "offset_mm")
    path = tmp_path / "ring.toml"
    path.write_text(body)
    with pytest.raises(ProfileError) as err:
        load_profile(str(path))
    assert "key 'tcp_off_geometry.offset_mm' belongs to kinematics 'table_table', not 'head_table'" in str(err.value)


def ring_pose(words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fitted map of s3-ring-kinematics.md inverted by hand (not through ncfix.kinematics):
    words (n, 5) X Y Z C B → tip points and tool axes in the part frame."""
    x, y, z, c, b = (words[:, i] for i in range(5))
    cr, br = np.radians(c), np.radians(b)
    y0, z0 = y - 77.36 * np.sin(br), z + 77.36 * (1 - np.cos(br)) - 0.3
    p = np.stack([x * np.cos(cr) - y0 * np.sin(cr), x * np.sin(cr) + y0 * np.cos(cr), z0], axis=1)
    return p, np.stack([-np.sin(cr) * np.sin(br), np.cos(cr) * np.sin(br), np.cos(br)], axis=1)


def fix_and_read_back(data: bytes, monkeypatch, standoff: float, **settings) -> int:
    """Fix ``data`` with this profile; every rewritten line states the words the corrector
    checked (as printed), they give the same tip and axis through the fitted map (by hand), the
    tips stay where they were (to the 2-decimal print: --pivot tip), the lines not changed are the
    input's bytes, and a check of the output finds nothing. Returns the number of changed lines."""
    import io

    import ncfix
    from ncfix.correct.stage import CorrectStage

    profile = load_profile(PROFILE)
    checked: dict[int, np.ndarray] = {}
    apply = CorrectStage._apply

    def spy(self, first, last, words, collided):
        rows = np.arange(first, last + 1)
        for row, printed in zip(rows, self.as_printed(rows, words)):
            checked[int(self.rows.line[row])] = printed
        return apply(self, first, last, words, collided)

    monkeypatch.setattr(CorrectStage, "_apply", spy)
    settings = dict(machine=PROFILE, standoff=standoff, bead_radius=0.0, device="cpu", **settings)
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(data), out, **settings)
    assert report.summary["colliding_blocks_before"] > 0 and report.exit_code == 0
    changed = {c["line"] for c in report.changes}
    before, after = data.decode().splitlines(True), out.getvalue().decode().splitlines(True)
    assert changed and [i + 1 for i, (a, b) in enumerate(zip(before, after)) if a != b] == sorted(changed)
    interp_in, interp_out = Interpreter(profile, "in.nc"), Interpreter(profile, "out.nc")
    for lineno, (a, b) in enumerate(zip(before, after), start=1):
        old, new = interp_in.feed(lineno, a), interp_out.feed(lineno, b)
        if lineno not in changed:
            continue
        words = np.array(new.words)[None]
        assert np.array_equal(words[0], checked[lineno])  # the words the corrector checked
        p_check, n_check, _ = profile.kinematics.forward(checked[lineno][None], tcp=False)
        p_read, n_read = ring_pose(words)
        assert np.abs(p_read - p_check).max() < 1e-9 and np.abs(n_read - n_check).max() < 1e-12
        p_old, n_old = ring_pose(np.array(old.words)[None])
        assert np.abs(p_read + standoff * n_read - (p_old + standoff * n_old)).max() < 0.03
        # only position and orientation words change: the filament (A) and feed stay as written
        assert [w for w in a.split() if w[0] not in "XYZBC"] == [w for w in b.split() if w[0] not in "XYZBC"]
    again = ncfix.process(io.BytesIO(out.getvalue()), io.BytesIO(), check=True, **settings)
    assert again.summary["colliding_blocks_before"] == 0
    return len(changed)


@pytest.mark.heavy  # a fix run with a cold cache: 25 s on the busy 2-core machine
def test_a_rewritten_block_reads_back_to_the_pose_that_was_checked(tmp_path, monkeypatch):
    """A program posted for this printer: a pass at 8° tilt whose head body meets a wall, all of
    it turned 35° about Z, so C, B and X Y Z all change where the fix tilts the head."""
    import trimesh

    from ncfix.nc.post import post_program

    profile = load_profile(PROFILE)
    turn = trimesh.transformations.rotation_matrix(math.radians(35.0), [0, 0, 1])
    xs = np.arange(-100.0, 101.0, 10.0)
    points = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 8.0)], axis=1) @ turn[:3, :3].T
    tilt = math.radians(8.0)
    vectors = np.tile(turn[:3, :3] @ [0.0, -math.sin(tilt), math.cos(tilt)], (len(xs), 1))
    data = "".join(post_program(profile, points, vectors, title="ring round trip")).encode()
    wall = trimesh.creation.box(bounds=[[-50.0, 22.0, 30.0], [50.0, 40.0, 60.0]])
    wall.apply_transform(turn)
    wall.export(tmp_path / "wall.stl")
    head = str(Path(__file__).resolve().parents[1] / "samples" / "deposition_head.stl")
    assert fix_and_read_back(data, monkeypatch, 6.0, head=head, part=[str(tmp_path / "wall.stl")]) > 0


@pytest.mark.heavy  # a fix run with a cold cache: about 30 s on the busy 2-core machine
def test_rewritten_ring_blocks_read_back_to_the_pose_that_was_checked(tmp_path, monkeypatch):
    """The ring's own lines: its preamble and the first 35 blocks of layer 180 (B about 23°), with a
    small block at the rim of the nozzle's cone as placed at the layer's 30th block. The rewritten
    lines keep their A and F words and read back to the checked poses."""
    import trimesh

    profile = load_profile(PROFILE)
    lines = corpus_path("s3_deformfdm", "ring_Gcode.txt").read_text().splitlines(True)
    start = [i for i, text in enumerate(lines) if text.strip() in ("G1 F650", "G1 F750")][180]
    program = lines[:10] + lines[start:start + 36]
    interp = Interpreter(profile, "ring")
    words = [np.array(b.words) for b in (interp.feed(n, t) for n, t in enumerate(program, 1))
             if b.motion is not None and " X" in b.raw]
    p, _, rot = profile.kinematics.forward(np.array(words[30])[None], tcp=False)
    obstacle = trimesh.creation.box(bounds=[[10.8, -0.5, 6.9], [11.6, 0.5, 7.5]])  # the cone: r 11 at 7 mm
    place = np.eye(4)
    place[:3, :3], place[:3, 3] = rot[0], p[0]
    obstacle.apply_transform(place)
    obstacle.export(tmp_path / "obstacle.stl")
    head = str(corpus_path("s3_deformfdm", "nozzle_converted.stl"))
    assert fix_and_read_back("".join(program).encode(), monkeypatch, 0.0, head=head, head_axis=(0.0, 1.0, 0.0),
                             part=[str(tmp_path / "obstacle.stl")]) > 0


# -- the ring as a real print: its nozzle, its platform where the printer has it ----------------

def placed_platform(folder: Path, raise_mm: float = 0.0) -> str:
    """platform_converted.stl (Y-up, top face at y = 0) as the printer has it in the part frame:
    turned Z-up ((x, y, z) → (x, −z, y), a turn of +90° about X) and moved by −0.3 mm in Z (the
    table's top, 0.3 mm under the slicer's frame, so under the first layer); ``raise_mm`` lifts it."""
    import trimesh

    mesh = trimesh.load(corpus_path("s3_deformfdm", "platform_converted.stl"))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
    mesh.apply_translation([0.0, 0.0, -0.3 + raise_mm])
    path = folder / f"platform_{raise_mm:g}.stl"
    mesh.export(path)
    return str(path)


def ring_print(check: bool, platform: str, out: Path):
    import ncfix

    return ncfix.process(str(corpus_path("s3_deformfdm", "ring_Gcode.txt")), str(out), machine=PROFILE,
                         head=str(corpus_path("s3_deformfdm", "nozzle_converted.stl")), head_axis=(0.0, 1.0, 0.0),
                         part=[platform], standoff=0.0, bead_radius=0.0, check=check, device="cpu")


@pytest.mark.heavy  # three runs over 68,866 blocks and the 400 mm platform's grid: about 2 minutes
def test_the_ring_prints_clear_of_its_platform_and_a_raised_platform_is_hit(tmp_path):
    """With its nozzle (axis +Y in its mesh: --head-axis 0,1,0) and its platform, deposit model
    off: --check flags nothing, and a fix run writes the program byte for byte. With the platform
    1 mm higher (into the first layer) the first layer's blocks are flagged, and no other: its 334
    printing blocks and the lift that leaves it."""
    source = corpus_path("s3_deformfdm", "ring_Gcode.txt")
    platform = placed_platform(tmp_path)
    report = ring_print(True, platform, tmp_path / "check.nc")
    assert report.summary["colliding_blocks_before"] == 0 and report.exit_code == 0

    report = ring_print(False, platform, tmp_path / "fix.nc")
    assert report.summary["colliding_blocks_before"] == 0 and report.summary["changed_blocks"] == 0
    assert (tmp_path / "fix.nc").read_bytes() == source.read_bytes()

    report = ring_print(True, placed_platform(tmp_path, raise_mm=1.0), tmp_path / "raised.nc")
    lines = source.read_text().splitlines()
    first, second = [i + 1 for i, text in enumerate(lines) if text in ("G1 F650", "G1 F750")][:2]
    printing = [n for n in range(first + 1, second) if {w[0] for w in lines[n - 1].split()} >= set("XYZBCA")]
    lift = printing[-1] + 1
    assert lines[lift - 1].startswith("G1 Z") and len(printing) == 334
    assert {c["line"] for c in report.collisions} == set(printing) | {lift}


@pytest.mark.heavy  # one check of 68,866 blocks with the deposit model on: 1-2 minutes
def test_the_ring_prints_clear_of_its_own_material(tmp_path):
    """The recipe (samples/ring.toml: nozzle, platform, round beads 0.8 mm wide): the program
    printed, and --check flags nothing. Its tilted layers open with 2 mm plunges 12° off the
    nozzle's axis that extrude on the way down; the nozzle's flat cone passes through their
    material, which therefore ends at their lower ends (``ncfix.collision.plough``). Laid as
    columns, 4,727 blocks were flagged."""
    import ncfix

    source = corpus_path("s3_deformfdm", "ring_Gcode.txt")
    out = tmp_path / "check.nc"
    config = Path(__file__).resolve().parents[1] / "samples" / "ring.toml"
    report = ncfix.process(str(source), str(out), config=str(config), check=True, device="cpu")
    assert report.summary["colliding_blocks_before"] == 0 and report.exit_code == 0
    assert out.read_bytes() == source.read_bytes()
