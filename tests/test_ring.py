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


def ring_layers(profile, printing: bool = True) -> list[list[tuple[int, np.ndarray, bool]]]:
    """(line, words X Y Z C B, TCP as read) of the blocks that carry all of X Y Z B C A (of every
    motion block with ``printing=False``), per layer; a layer starts at its `G1 F650` (layer 0)
    or `G1 F750` line."""
    interp = Interpreter(profile, "ring_Gcode.txt")
    layers: list[list[tuple[int, np.ndarray, bool]]] = []
    with open(corpus_path("s3_deformfdm", "ring_Gcode.txt"), "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            text = raw.decode("ascii")
            block = interp.feed(lineno, text)
            if text.startswith(("G1 F650", "G1 F750")):
                layers.append([])
            elif layers and block.motion is not None and (
                    not printing or block.motion == 1 and {w[0] for w in text.split()} >= set("XYZBCA")):
                layers[-1].append((lineno, np.array(block.words), block.tcp))
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
        assert not any(tcp for _, _, tcp in rows)  # the profile reads the program with TCP off
        words = np.array([w for _, w, _ in rows])
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


def test_the_ring_profile_is_the_head_table_family_as_the_machine_is(profile):
    """The profile states the machine with the head-table family's own keys, nothing special to
    it: the first axis C turns the table about Z (continuous: written unwound), the second B tilts
    the head about X around its 77.36 mm pivot, the part frame 0.3 mm above the table, TCP off
    whatever the program says, A the filament."""
    from ncfix.kinematics.head_table import HeadTable
    from ncfix.kinematics.rotary import TwoAxisChain

    kin = profile.kinematics
    assert profile.kinematics_name == "head_table" and type(kin) is TwoAxisChain
    assert type(kin.transform) is HeadTable and profile.tcp == "never" and profile.extrusion_letter == "A"
    c, b = kin.axes
    assert (c.letter, c.direction, c.sign, c.mode, c.on_head) == ("C", (0.0, 0.0, 1.0), 1, "continuous", False)
    assert (b.letter, b.direction, b.sign, b.on_head) == ("B", (1.0, 0.0, 0.0), -1, True)
    assert kin.transform.pivot_length_mm == 77.36
    assert kin.transform.o.tolist() == [0.0, 0.0, 0.3] and kin.transform.c.tolist() == [0.0, 0.0, 0.0]
    interp = Interpreter(profile, "ring")
    assert not interp.feed(1, "G43.4 H1\n").tcp and not interp.feed(2, "G1 X1 Y2 Z3 B10 C20 A1\n").tcp


def test_the_ring_blocks_round_trip_through_the_inverse(profile, layers):
    """pose → words with the previous block as reference gives back the program's own words
    (within its 2-decimal rounding) on the waypoint layers: same branch, C unwound in the layer,
    C held where B = 0 (the pole)."""
    kin = profile.kinematics
    for k in WAYPOINT_LAYERS:
        words = np.array([w for _, w, _ in layers[k]])
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
    b_turn = 0.0
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
        b_turn = max(b_turn, abs(new.words[4] - old.words[4]))
        # only position and orientation words change: the filament (A) and feed stay as written
        assert [w for w in a.split() if w[0] not in "XYZBC"] == [w for w in b.split() if w[0] not in "XYZBC"]
    assert b_turn > 1.0  # B turns: its point kept in place needs the 77.36 mm pivot in the inverse
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

PLATFORM = str(corpus_path("s3_deformfdm", "platform_converted.stl"))


def placed_platform(raise_mm: float = 0.0) -> list:
    """platform_converted.stl as --platform places it with this profile (its [platform]), then
    raised by ``raise_mm`` (``@translate``, applied after the profile's placement)."""
    import ncfix.config
    from ncfix.pipeline import load_parts

    path = PLATFORM + (f"@translate=0,0,{raise_mm:g}" if raise_mm else "")
    return load_parts(ncfix.config.Options(platform=path), load_profile(PROFILE))


def test_the_profile_places_the_platform_as_the_printer_has_it(profile, layers):
    """The Y-up platform (400 x 20 x 400 mm, top face at y = 0) turned Z-up ((x, y, z) → (x, −z, y))
    with its top 0.3 mm under the part frame, where the table is: under the first layer, whose
    tips lie 0.33-0.73 mm above it; raised 1 mm, its top is above all of them."""
    import trimesh

    raw = trimesh.load(PLATFORM)
    (placed,) = placed_platform()
    turned = np.stack([raw.vertices[:, 0], -raw.vertices[:, 2], raw.vertices[:, 1] - 0.3], axis=1)
    assert np.abs(placed.mesh.vertices - turned).max() < 1e-9
    assert np.abs(placed.mesh.bounds - [[-200.0, -200.0, -20.3], [200.0, 200.0, -0.3]]).max() < 1e-4
    tips, _, _ = profile.kinematics.forward(np.array([w for _, w, _ in layers[0]]), tcp=False)
    assert 0.3 < tips[:, 2].min() + 0.3 and tips[:, 2].max() + 0.3 < 0.75
    (raised,) = placed_platform(1.0)
    assert raised.mesh.bounds[1, 2] == pytest.approx(0.7, abs=1e-4) and tips[:, 2].max() < 0.7


def ring_print(check: bool, out: Path, raise_mm: float = 0.0):
    """The ring with its nozzle and the platform placed by the profile (--platform), deposit
    model off: --head-axis 0,1,0 turns the nozzle's +Y onto the tool axis."""
    import ncfix

    platform = PLATFORM + (f"@translate=0,0,{raise_mm:g}" if raise_mm else "")
    return ncfix.process(str(corpus_path("s3_deformfdm", "ring_Gcode.txt")), str(out), machine=PROFILE,
                         head=str(corpus_path("s3_deformfdm", "nozzle_converted.stl")), head_axis=(0.0, 1.0, 0.0),
                         platform=platform, standoff=0.0, bead_radius=0.0, check=check, device="cpu")


@pytest.mark.heavy  # three runs over 68,866 blocks and the 400 mm platform's grid: about 2 minutes
def test_the_ring_prints_clear_of_its_platform_and_a_raised_platform_is_hit(tmp_path):
    """With its nozzle (axis +Y in its mesh: --head-axis 0,1,0) and its platform, deposit model
    off: --check flags nothing, and a fix run writes the program byte for byte. With the platform
    1 mm higher (into the first layer) the first layer's blocks are flagged, and no other: its 334
    printing blocks and the lift that leaves it."""
    source = corpus_path("s3_deformfdm", "ring_Gcode.txt")
    report = ring_print(True, tmp_path / "check.nc")
    assert report.summary["colliding_blocks_before"] == 0 and report.exit_code == 0

    report = ring_print(False, tmp_path / "fix.nc")
    assert report.summary["colliding_blocks_before"] == 0 and report.summary["changed_blocks"] == 0
    assert (tmp_path / "fix.nc").read_bytes() == source.read_bytes()

    report = ring_print(True, tmp_path / "raised.nc", raise_mm=1.0)
    lines = source.read_text().splitlines()
    first, second = [i + 1 for i, text in enumerate(lines) if text in ("G1 F650", "G1 F750")][:2]
    printing = [n for n in range(first + 1, second) if {w[0] for w in lines[n - 1].split()} >= set("XYZBCA")]
    lift = printing[-1] + 1
    assert lines[lift - 1].startswith("G1 Z") and len(printing) == 334
    assert {c["line"] for c in report.collisions} == set(printing) | {lift}


@pytest.mark.heavy  # one check of 68,866 blocks with the deposit model on: 1-2 minutes
def test_the_ring_prints_clear_of_its_own_material(tmp_path):
    """The recipe (samples/ring.toml: nozzle, platform, round beads 0.8 mm wide): the program
    printed, and --check flags nothing. Its tilted layers open with 2 mm plunges up to 31° off the
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


LAYER_SURFACES = (0, 120, 244)  # ring_layer/: the slicer's layer surfaces (Y-up, like its waypoints)


@pytest.mark.heavy  # exact mesh distances along five layers' moves and a second read of the program: 20-30 s
def test_the_nozzle_keeps_clear_of_the_layer_surfaces_it_prints_on(profile, layers):
    """What the deposit model's empty answer means in the print's own geometry. The slicer's layer
    surfaces, turned Z-up like the waypoints, hold their layer's printing tips (median 0.003 mm
    away). At every motion block of such a layer and of the layer after it, and along their
    moves (poses at most 0.25 mm of tip path and 0.5° of C or B apart, the axes interpolated
    linearly as the controller does with TCP off), the nozzle above its 1 mm tip allowance keeps
    0.89 mm or more from the surface (exact mesh distance; a hit would be ≤ 0): 0.8997 mm at
    layer 0, 0.97 at layers 120 and 244, 1.75 at layer 1 over the layer-0 surface."""
    import trimesh

    from ncfix.collision.exact import ExactParts, clip_head
    from ncfix.geometry.mesh import load_head

    kin = profile.kinematics
    head = load_head(str(corpus_path("s3_deformfdm", "nozzle_converted.stl")), axis=(0.0, 1.0, 0.0)).mesh
    above_allowance = clip_head(head, 1.0)  # samples/ring.toml: tip_allowance = 1.0
    moves = ring_layers(profile, printing=False)
    least: dict[tuple[int, int], float] = {}
    for k in LAYER_SURFACES:
        surface = trimesh.load(corpus_path("s3_deformfdm", "ring_layer", f"{k}.obj"), force="mesh")
        surface.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
        tips, _, _ = kin.forward(np.array([w for _, w, _ in layers[k]]), tcp=False)
        assert np.median(trimesh.proximity.closest_point(surface, tips)[1]) < 0.01
        exact = ExactParts(above_allowance, {"layer": surface}, open_parts=("layer",))
        for layer in (k, k + 1)[:len(moves) - k]:
            ends = np.array([w for _, w, _ in moves[layer]])
            starts = np.vstack([moves[layer - 1][-1][1] if layer else ends[0], ends[:-1]])
            a, _, _ = kin.forward(starts, tcp=False)
            b, _, _ = kin.forward(ends, tcp=False)
            steps = np.maximum(np.linalg.norm(b - a, axis=1) / 0.25, np.abs(ends - starts)[:, 3:].max(axis=1) / 0.5)
            poses = np.vstack([s + t * (e - s) for s, e, m in zip(starts, ends, np.ceil(steps).astype(int))
                               for t in np.linspace(0.0, 1.0, max(m, 1) + 1)[1:, None]])
            tip, _, rot = kin.forward(poses, tcp=False)
            least[layer, k] = float(exact.clearances(tip, rot)[0].min())
    assert min(least.values()) >= 0.89, least
    assert set(least) == {(0, 0), (1, 0), (120, 120), (121, 120), (244, 244)}
