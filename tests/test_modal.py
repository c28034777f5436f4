"""Modal state: positions, vectors, units, increments and extrusion, read as the controller would."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ncfix.errors import ProgramError
from ncfix.nc import modal
from ncfix.nc.modal import Interpreter
from ncfix.pipeline import CHUNK_LINES
from ncfix.profiles import load_profile

from conftest import corpus_path


def interpret(text: str, machine: str = "ijk", **kwargs):
    interp = Interpreter(load_profile(machine), "t.nc", **kwargs)
    return [interp.feed(i, line) for i, line in enumerate(text.splitlines(keepends=True), start=1)]


def motion_words(text: str, machine: str = "ijk", **kwargs):
    return [b.words for b in interpret(text, machine, **kwargs) if b.motion is not None]


def printed_points(gcode, machine: str, limit: int | None = None) -> np.ndarray:
    """Workpiece points (n, 3) of a printer program's extruding G1 blocks that carry X and B."""
    profile = load_profile(machine)
    interp = Interpreter(profile, str(gcode))
    words = []
    with open(gcode, "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            block = interp.feed(lineno, raw.decode("latin-1"))
            if block.motion == 1 and block.e_delta is not None and b" X" in raw and b" B" in raw:
                words.append(block.words)
            if len(words) == limit:
                break
    return profile.kinematics.forward(np.array(words), tcp=False)[0]


def test_model_1_reads_as_its_34114_waypoints():
    gcode = corpus_path("multiaxis_3dp_motionplanning", "model_1_Gcode.txt")
    folder = corpus_path("multiaxis_3dp_motionplanning", "model_1", "waypoint")
    expected = np.concatenate([np.loadtxt(folder / f"{i}.txt")[:, :3] for i in range(1, 18)])
    p = printed_points(gcode, "multiaxis-3dp-bc")
    assert len(p) == 34114 == len(expected)
    assert np.abs(p - expected).max() < 0.005


def test_model_1_vectors_match_the_waypoint_normals_in_direction():
    gcode = corpus_path("multiaxis_3dp_motionplanning", "model_1_Gcode.txt")
    normals = np.loadtxt(corpus_path("multiaxis_3dp_motionplanning", "model_1", "waypoint", "1.txt"))[:, 3:]
    profile = load_profile("multiaxis-3dp-bc")
    interp = Interpreter(profile)
    words = []
    with open(gcode, "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            block = interp.feed(lineno, raw.decode("latin-1"))
            if block.motion == 1 and "X" in block.raw:
                words.append(block.words)
            if len(words) == len(normals):
                break
    _, n, _ = profile.kinematics.forward(np.array(words), tcp=False)
    # The slicer smooths B/C, so the programmed axis stays within a few degrees of the normals.
    angle = np.degrees(np.arccos(np.clip(np.sum(n * normals, axis=1), -1, 1)))
    assert np.median(angle) < 3.0


def test_vector_words_follow_the_modal_rule():
    words = motion_words("G1 X0 Y0 Z0 I0 J0 K1\nG1 X1\nG1 X2 I1\nG1 X3 J1 K1\n")
    vectors = [w[3:] for w in words]
    assert vectors == [(0.0, 0.0, 1.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 1.0)]


def test_arc_ijk_are_centres_not_vectors():
    words = motion_words("G1 X0 Y0 Z0 I0.6 J0 K0.8\nG2 X10 Y0 I5 J0\nG1 X20\n")
    assert [w[3:] for w in words] == [(0.6, 0.0, 0.8)] * 3


def test_words_carry_over_and_increments_add():
    words = motion_words("G90 G1 X1 Y2 Z3 A10 C20\nX5\nG91 X1 C-5\nG90 Y0\n", machine="table-ac")
    # letters: X Y Z C A
    assert words == [(1, 2, 3, 20, 10), (5, 2, 3, 20, 10), (6, 2, 3, 15, 10), (6, 0, 3, 15, 10)]


def test_inch_programs_are_read_in_mm():
    words = motion_words("G20 G1 X1 Y0 Z0 I0 J0 K1\n")
    assert words[0][0] == pytest.approx(25.4)


def test_extrusion_absolute_relative_and_g92():
    blocks = interpret("G1 X0 Y0 Z0 E1\nG1 X1 E3\nG92 E0\nG1 X2 E0.5\nM83\nG1 X3 E0.25\nG0 X4\n")
    deltas = [b.e_delta for b in blocks]
    assert deltas == [1.0, 2.0, None, 0.5, None, 0.25, None]


def test_deposit_codes_switch_state():
    blocks = interpret("G1 X0 Y0 Z0\nM3\nG1 X1\nM5\nG1 X2\n", deposit_codes=("M3", "M5"))
    assert [b.deposit_on for b in blocks if b.motion is not None] == [False, True, False]


def test_tcp_switches_per_profile():
    blocks = interpret("G1 X0 Y0 Z0 A0 C0\nM428\nG1 X1\nM429\nG1 X2\n", machine="linuxcnc-xyzac-trt")
    assert [b.tcp for b in blocks if b.motion is not None] == [False, True, False]


def test_homing_leaves_positions_unknown():
    words = motion_words("G28 X0 Y0 Z230\nG0 X1 Y1\nG0 Z5\n", machine="ijk")
    assert math.isnan(words[0][2]) and words[1][2] == 5.0


def test_expressions_make_a_block_opaque_not_an_error():
    blocks = interpret("G1 X#100 Y2 Z0\nG1 X=R1\n", machine="sinumerik-vector")
    assert all(b.opaque for b in blocks)
    assert math.isnan(blocks[0].words[0])


@pytest.mark.parametrize("line", ["G1 X1.2.3", "G1 X", "G1 Y--5", "G0 Z.", "G1 I1 J0 K0\nG1 I0 J0 K0"])
def test_unreadable_axis_words_on_motion_blocks_fail_naming_the_line(line):
    with pytest.raises(ProgramError) as err:
        interpret("G21\n" + line + "\n")
    assert err.value.where == f"t.nc:{1 + line.count(chr(10)) + 1}"


def test_unreadable_words_outside_motion_pass():
    blocks = interpret("M104 S2.0.5\nG4 P1.2.3\n(X1.2.3)\n")
    assert all(b.motion is None for b in blocks)


def test_heidenhain_ln_blocks():
    text = ("0 BEGIN PGM F5 MM\n6 LN X+10 Y+0 Z+25 TX+0 TY+0 TZ+1 FMAX\n"
            "8 LN X+20 Y+0 Z+5 TX+0.258819 TY+0 TZ+0.9659258 F1200\n11 L Z+50 FMAX\n")
    blocks = [b for b in interpret(text, machine="heidenhain-ln") if b.motion is not None]
    assert [b.motion for b in blocks] == [0, 1, 0]
    assert blocks[1].words == (20.0, 0.0, 5.0, 0.258819, 0.0, 0.9659258)
    assert blocks[2].words[3:] == blocks[1].words[3:]


EQUIVALENCE_PROGRAM = """G21 G90 G94
G1 X1 Y2 Z3 I0 J0 K1 F1200
X5 E1.5
G01 X6. Y.5 Z-0. J1 E2
G0 X7 Y8 Z9 I0.6 J0 K0.8
G91
G1 X1 Y-1 E0.5
G90 G20
G1 X1 Y1 Z1
M83
G1 X2 E0.1
X1E5
G1 X+3 Y-.25 Z1.
"""


def chunked(data: bytes, machine: str, size: int, **kwargs):
    interp = Interpreter(load_profile(machine), **kwargs)
    lines = data.splitlines(keepends=True)
    return [interp.feed_chunk(lines[i:i + size], i + 1) for i in range(0, len(lines), size)]


def assert_chunks_match_lines(data: bytes, machine: str, size: int, **kwargs):
    """The vectorised chunk reader must read every line exactly as the line-by-line reader."""
    slow = Interpreter(load_profile(machine))
    lineno = 0
    for chunk in chunked(data, machine, size, **kwargs):
        for i, raw in enumerate(chunk.lines):
            lineno += 1
            block = slow.feed(lineno, raw.decode("latin-1"))
            where = (machine, lineno, raw)
            assert chunk.motion[i] == (-1 if block.motion is None else block.motion), where
            if block.motion is not None:
                assert np.allclose(chunk.words[i], block.words, equal_nan=True, rtol=0, atol=1e-9), where
            assert (np.isnan(chunk.e_delta[i]) and block.e_delta is None) or np.isclose(
                chunk.e_delta[i], block.e_delta, rtol=0, atol=1e-9), where
            assert (chunk.tcp[i], chunk.inch[i], chunk.incremental[i], chunk.feed_mode[i], chunk.opaque[i]) == (
                block.tcp, block.inch, block.incremental, block.feed_mode, block.opaque), where


@pytest.mark.parametrize("machine", ["ijk", "table-ac", "multiaxis-3dp-bc"])
@pytest.mark.parametrize("size", [4096, 9, 1])
@pytest.mark.parametrize("reader", ["numpy", "compiled", "numpy then compiled"])
def test_chunk_reader_agrees_with_the_line_reader(machine, size, reader, monkeypatch):
    """With either plain-line reader, and switching from the numpy one to the compiled one mid-program
    (as a long pass-through does)."""
    text = EQUIVALENCE_PROGRAM
    if machine != "ijk":  # the same moves with this profile's rotary words (I J K would be an error)
        c, tilt = load_profile(machine).kinematics.orientation_letters
        for vector, angles in (("I0.6 J0 K0.8", f"{tilt}10 {c}20"), ("I0 J0 K1", f"{tilt}0 {c}0"), ("J1", f"{tilt}1")):
            text = text.replace(vector, angles)
    if reader == "numpy then compiled":
        monkeypatch.setattr(modal, "COMPILED_AFTER_LINES", 5 * text.count("\n"))
    assert_chunks_match_lines((text * 30).encode(), machine, size, compiled_reader=reader == "compiled")


def test_a_long_program_switches_to_the_compiled_reader(monkeypatch):
    """Read with numpy while short, compiled from ``COMPILED_AFTER_LINES`` lines on (and from the
    start with ``compiled_reader``): the test above compares what each reads."""
    from ncfix.nc.plain import PlainReader
    from ncfix.nc.plain_jit import PlainReaderJit

    monkeypatch.setattr(modal, "COMPILED_AFTER_LINES", 20)
    lines = [b"G1 X1 Y2 Z3\n"] * 10
    interp = Interpreter(load_profile("ijk"))
    readers = []
    for first in (1, 11, 21):
        interp.feed_chunk(lines, first)
        readers.append(type(interp._plain))
    assert readers == [PlainReader, PlainReader, PlainReaderJit]
    compiled = Interpreter(load_profile("ijk"), compiled_reader=True)
    compiled.feed_chunk(lines, 1)
    assert type(compiled._plain) is PlainReaderJit


@pytest.mark.heavy
@pytest.mark.parametrize("name, machine", [
    ("multiaxis_3dp_motionplanning/model_1_Gcode.txt", "multiaxis-3dp-bc"),
    ("s3_deformfdm/ring_Gcode.txt", "s3-deformfdm-bc"),
    ("linuxcnc/boat-xyzac.ngc", "linuxcnc-xyzac-trt"),
    ("linuxcnc/boat-xyzbc.ngc", "linuxcnc-xyzbc-trt"),
    ("linuxcnc/impeller-7bl-xyzac.ngc", "linuxcnc-xyzac-trt"),
    ("linuxcnc/xyzab-tdr-demo.ngc", str(Path(__file__).parent / "profiles" / "linuxcnc-xyzab-tdr.toml")),
])
def test_chunk_reader_agrees_on_the_corpus(name, machine):
    data = corpus_path(*name.split("/")).read_bytes()
    assert_chunks_match_lines(data, machine, 4096)
    assert_chunks_match_lines(data, machine, 4096, compiled_reader=True)
    assert_chunks_match_lines(data[:200_000], machine, 37)


@pytest.mark.parametrize("name", ["multiaxis_3dp_motionplanning/model_1_Gcode.txt", "s3_deformfdm/ring_Gcode.txt",
                                  "linuxcnc/boat-xyzac.ngc", "linuxcnc/impeller-7bl-xyzac.ngc"])
def test_compiled_plain_reader_agrees_with_the_array_reader(name):
    """Every line of each program, in the chunks a run reads: a pass-through reads with the numpy
    reader, a check (and a long pass-through) with the compiled one."""
    from ncfix.nc.plain import PlainReader
    from ncfix.nc.plain_jit import PlainReaderJit

    letters = ("N", "G", "F", "E", "X", "Y", "Z", "C", "B", "A")
    lines = corpus_path(*name.split("/")).read_bytes().splitlines(keepends=True)
    extra = [b"G1 X1.2.3\n", b"X1-2\n", b"G1 X+-1\n", b"(c)\n", b"  \r\n", b"; x\n", b"G2 X1\n", b"N10 5 X1\n",
             b"G01 X007 Y+3", b"G1 X1 X2\n", b"G1 X12345678901234567\n", b"g1 x1\n", b"X.5 Y-.25 Z1.\n", b"",
             b"X-0 Y-.0\n", b"X1", b"5 Y2\n", b"X1.23456789012345\n", b"X-123456789012345.\n", b"X1 Y\n", b"X\n",
             b" (a) \n", b"(a)(b)\n", b"((a)\n", b"X1 (a)\n", b"G1X1Y2\n", b"X1.5E\n", b"X+\n", b""]
    for chunk in [lines[i:i + CHUNK_LINES] for i in range(0, len(lines), CHUNK_LINES)] + [extra]:
        a, b = PlainReader(letters).parse(chunk), PlainReaderJit(letters).parse(chunk)
        assert (a.plain == b.plain).all() and (a.neutral == b.neutral).all()
        assert np.array_equal(a.values[a.plain].view(np.int64), b.values[b.plain].view(np.int64))  # -0.0 too


def test_ring_program_reads_as_its_first_layer_waypoints():
    """S3_DeformFDM ring: A is the filament, C turns the table, B tilts the head; waypoints are Y-up (x, y, z) → (x, -z, y)."""
    gcode = corpus_path("s3_deformfdm", "ring_Gcode.txt")
    waypoints = np.loadtxt(corpus_path("s3_deformfdm", "ring_waypoint", "0.txt"))
    expected = np.stack([waypoints[:, 0], -waypoints[:, 2], waypoints[:, 1]], axis=1)
    p = printed_points(gcode, "s3-deformfdm-bc", limit=len(expected))
    # The program prints 2 decimals: each coordinate is within 0.005 mm, the point within 0.0087.
    assert np.abs(p - expected).max() < 0.0087
