"""Orientation words the profile does not read are an error, never ignored; --machine auto picks the
one profile that reads a program's words, or names the candidates."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

from ncfix.config import Options
from ncfix.errors import NcfixError, ProgramError
from ncfix.nc.modal import Interpreter
from ncfix.pipeline import run
from ncfix.profiles import builtin_names, load_profile

from conftest import corpus_path

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
GOLDEN = Path(__file__).parent / "golden"
TDR_PROFILE = str(Path(__file__).parent / "profiles" / "linuxcnc-xyzab-tdr.toml")

# Which built-in profiles read each orientation word (written out here, not derived from the code).
AC = ["linuxcnc-xyzac-trt", "table-ac"]
BC_ONLY = ["head-bc", "head-bc-tcpoff", "head-table-bc", "linuxcnc-xyzbc-trt", "multiaxis-3dp-bc",
           "s3-deformfdm-bc", "table-bc"]
OWNERS = {
    "I": ["ijk"], "J": ["ijk"], "K": ["ijk"],
    "A3": ["sinumerik-vector"], "B3": ["sinumerik-vector"], "C3": ["sinumerik-vector"], "TRAORI": ["sinumerik-vector"],
    "TX": ["heidenhain-ln"], "TY": ["heidenhain-ln"], "TZ": ["heidenhain-ln"], "LN": ["heidenhain-ln"],
    "A": AC, "B": BC_ONLY, "C": sorted(AC + BC_ONLY),
    "A2": [], "B2": [], "C2": [], "LEAD": [], "TILT": [],
}
ASSIGNED = {"A3", "B3", "C3", "A2", "B2", "C2", "LEAD", "TILT"}
READS = {  # the orientation words of the vocabulary that each profile reads (A: S3's filament)
    "ijk": {"I", "J", "K"}, "sinumerik-vector": {"A3", "B3", "C3", "TRAORI"}, "heidenhain-ln": {"TX", "TY", "TZ", "LN"},
    "table-ac": {"A", "C"}, "linuxcnc-xyzac-trt": {"A", "C"}, "s3-deformfdm-bc": {"A", "B", "C"},
    **{name: {"B", "C"} for name in BC_ONLY if name != "s3-deformfdm-bc"},
}


def test_the_table_covers_every_built_in_profile():
    assert sorted(READS) == builtin_names()


def _block(profile_name: str, word: str) -> str:
    """One motion block of this profile's dialect that carries ``word``."""
    value = "=0.5" if word in ASSIGNED else ("" if word in ("TRAORI", "LN") else "0.5")
    if load_profile(profile_name).dialect == "heidenhain":
        return f"L X+1 Y+2 Z+3 {word}{value} F100\n"
    return f"G1 X1 Y2 Z3 {word}{value} F100\n"


def _read(profile_name: str, text: str) -> None:
    interp = Interpreter(load_profile(profile_name), "t.nc")
    for lineno, line in enumerate(text.splitlines(keepends=True), 1):
        interp.feed(lineno, line)


@pytest.mark.parametrize("profile_name", sorted(READS))
@pytest.mark.parametrize("word", sorted(OWNERS))
def test_each_profile_refuses_each_orientation_word_it_does_not_read(profile_name, word):
    block = _block(profile_name, word)
    if word in READS[profile_name]:
        _read(profile_name, "G21 G90\n" + block)  # read, no error
        return
    with pytest.raises(ProgramError) as caught:
        _read(profile_name, "G21 G90\n" + block)
    message = str(caught.value)
    shown = f"{word}=" if word in ASSIGNED else word
    assert message.startswith(f"t.nc:2: {shown} ")
    if OWNERS[word]:
        assert f"of {', '.join(OWNERS[word])}" in message and f"not of {profile_name}" in message
        assert message.endswith("or --machine auto)")
        if len(OWNERS[word]) == 1:
            assert f"use --machine {OWNERS[word][0]}" in message
    else:
        assert "that no built-in machine profile reads" in message


@pytest.mark.parametrize("profile_name, text", [
    # I J K are arc centres on G2/G3, also on a modal arc block, and cycle parameters.
    ("table-ac", "G17 G2 X10 Y0 I5 J0 F100\nX0 Y0 I-5 J0\nG3 X10 Y0 R5\n"),
    ("linuxcnc-xyzbc-trt", "G18 G3 X10 Z0 I5 K0\n"),
    ("sinumerik-vector", "TRAORI\nG2 X10 Y0 I5 J0 F100\nG3 X0 Y10 I=AC(0) J=AC(0)\n"),
    ("table-bc", "G87 X1 Y2 Z-5 R2 I1 J0 K3 F100\n"),
    ("table-ac", "G68.2 X0 Y0 Z0 I0 J45 K0\n"),
    # firmware settings on printers: letters are the M code's parameters
    ("ijk", "M205 B20000 S0 T0\nM900 K0.05\nM201 A500\n"),
    ("table-ac", "M900 K0.05\n"),
    # data blocks
    ("ijk", "G10 L2 P1 X0 Y0 Z0 A0 B0\n"),
    ("table-ac", "G92 X0 Y0 Z0 I0\nG1 X1\n"),
    # a letter without a value is no word (Heidenhain's C arc keyword)
    ("heidenhain-ln", "CC X+0 Y+0\nC X+10 Y+0 DR+\n"),
    # S3's filament on A, reset by G92
    ("s3-deformfdm-bc", "G92 A0\nG1 X1 Y2 Z3 B10 C20 A1.5\n"),
])
def test_words_that_are_no_orientation_in_context_are_read(profile_name, text):
    _read(profile_name, text)


def test_ijk_on_a_g1_after_an_arc_is_refused_on_a_rotary_profile():
    with pytest.raises(ProgramError, match=r"^t.nc:3: I on a G0/G1 block is a tool-vector word of ijk"):
        _read("table-ac", "G2 X10 Y0 I5 J0 F100\nX0 Y0 I-5 J0\nG1 X5 I0.1 J0 K1\n")


def _ncfix(*args, stdin=None, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "ncfix", *args], capture_output=True, cwd=cwd,
                          input=stdin)


def test_a_siemens_program_under_ijk_stops_before_writing_anything():
    """The issue: the bathtub's Siemens program under ijk (samples/ncfix.toml's head and mold) ran
    for minutes and wrote Siemens blocks with I J K added."""
    done = _ncfix("samples/bathtub_273_sinumerik.mpf", "--machine", "ijk")
    assert done.returncode == 2 and done.stdout == b""
    assert done.stderr.decode() == (
        "ncfix: error: samples/bathtub_273_sinumerik.mpf:4: TRAORI is a tool-orientation word of sinumerik-vector, "
        "not of ijk (use --machine sinumerik-vector, or --machine auto)\n")


def test_an_ac_program_checked_under_ijk_is_refused_not_misread():
    """The issue: --check of the A/C sample under ijk reported 125 collisions that do not exist."""
    done = _ncfix("samples/bathtub_273_table_ac.nc", "--check", "--machine", "ijk")
    assert done.returncode == 2 and done.stdout == b""
    assert done.stderr.decode() == (
        "ncfix: error: samples/bathtub_273_table_ac.nc:7: C is a tool-orientation word of "
        f"{', '.join(sorted(AC + BC_ONLY))}, not of ijk "
        "(use --machine with the profile of this machine (ncfix --list-machines), or --machine auto)\n")


def _pass(path: Path, machine: str) -> tuple[bytes, list[str], str]:
    data = path.read_bytes()
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, Options(machine=machine), path.name)
    assert out.getvalue() == data
    return data, report.notes, report.machine


# Every sample and corpus program: its documented profile (samples/README.md, tests/test_passthrough.py)
# and what auto says: that profile, or exit 2 naming the candidates where the words cannot tell.
BC_CANDIDATES = "head-bc, head-bc-tcpoff, head-table-bc, multiaxis-3dp-bc, table-bc"
PROGRAMS = [
    ("samples/bathtub_273.nc", "ijk", "ijk (I/J/K from line 7)"),
    ("samples/bathtub_5000.nc", "ijk", "ijk (I/J/K from line 7)"),
    ("samples/deposit_wall.nc", "ijk", "ijk (I/J/K from line 9)"),
    ("samples/fixture_f2_ijk.nc", "ijk", "ijk (I/J/K from line 6)"),
    ("samples/bathtub_273_table_ac.nc", "table-ac", "table-ac (A/C from line 7)"),
    ("samples/bathtub_5000_table_ac.nc", "table-ac", "table-ac (A/C from line 7)"),
    ("samples/bathtub_273_sinumerik.mpf", "sinumerik-vector", "sinumerik-vector (TRAORI/A3=/B3=/C3= from line 4)"),
    ("samples/bathtub_5000_sinumerik.mpf", "sinumerik-vector", "sinumerik-vector (TRAORI/A3=/B3=/C3= from line 4)"),
    ("golden/passthrough_fanuc_ijk_crlf/input.nc", "ijk", "ijk (I/J/K from line 5)"),
    ("golden/passthrough_sinumerik_vector/input.nc", "sinumerik-vector", "sinumerik-vector (TRAORI/A3=/B3=/C3= from line 3)"),
    ("golden/passthrough_heidenhain_ln/input.nc", "heidenhain-ln", "heidenhain-ln (LN/TX/TY/TZ from line 7)"),
    ("golden/passthrough_linuxcnc_torture/input.nc", "linuxcnc-xyzac-trt",
     "linuxcnc-xyzac-trt (A/C from line 5; M428 on line 4)"),
    ("golden/passthrough_printer_bc_no_final_newline/input.nc", "multiaxis-3dp-bc",
     f"golden/passthrough_printer_bc_no_final_newline/input.nc:3: machine auto cannot tell which machine reads B/C: "
     f"{BC_CANDIDATES} all do (give --machine NAME)"),
    ("corpus/linuxcnc/boat-xyzac.ngc", "linuxcnc-xyzac-trt", "linuxcnc-xyzac-trt (A/C from line 13; M428 on line 2)"),
    ("corpus/linuxcnc/boat-xyzbc.ngc", "linuxcnc-xyzbc-trt", "linuxcnc-xyzbc-trt (B/C from line 11; M428 on line 2)"),
    ("corpus/linuxcnc/impeller-7bl-xyzac.ngc", "linuxcnc-xyzac-trt",
     "linuxcnc-xyzac-trt (A/C from line 8; M428 on line 4)"),
    ("corpus/s3_deformfdm/ring_Gcode.txt", "s3-deformfdm-bc", "s3-deformfdm-bc (B/C/A from line 11)"),
    ("corpus/multiaxis_3dp_motionplanning/model_1_Gcode.txt", "multiaxis-3dp-bc",
     "corpus/multiaxis_3dp_motionplanning/model_1_Gcode.txt:3: machine auto cannot tell which machine reads B/C: "
     f"{BC_CANDIDATES} all do (give --machine NAME)"),
    ("corpus/linuxcnc/xyzab-tdr-demo.ngc", TDR_PROFILE,
     "corpus/linuxcnc/xyzab-tdr-demo.ngc:8: machine auto: no built-in profile reads A/B together (give --machine "
     "PATH of a profile file for this machine; see the README, Machine profiles)"),
]


def _program_path(name: str) -> Path:
    folder, _, rest = name.partition("/")
    if folder == "corpus":
        return corpus_path(*rest.split("/"))
    return (SAMPLES if folder == "samples" else GOLDEN) / rest


@pytest.mark.parametrize("name, machine, auto", PROGRAMS, ids=[p[0] for p in PROGRAMS])
def test_every_sample_and_corpus_program_is_read_by_its_profile_and_auto_agrees(name, machine, auto):
    path = _program_path(name)
    _pass(path, machine)  # accepted under its documented profile, byte for byte
    if auto.startswith(name + ":"):  # genuinely ambiguous, or no built-in profile: exit 2 naming them
        with pytest.raises(NcfixError) as caught:
            run(io.BytesIO(path.read_bytes()), io.BytesIO(), Options(machine="auto"), name)
        assert str(caught.value) == auto
    else:
        _, notes, chosen = _pass(path, "auto")
        assert (chosen, notes) == (machine, [f"machine: auto -> {auto}"])


def test_auto_reads_standard_input_through_a_pipe_and_passes_it_through(tmp_path):
    data = (SAMPLES / "bathtub_273_sinumerik.mpf").read_bytes()
    done = _ncfix("-", "--machine", "auto", stdin=data, cwd=tmp_path)  # a pipe: cannot be rewound
    assert done.returncode == 0, done.stderr
    assert done.stdout == data
    assert "machine: auto -> sinumerik-vector (TRAORI/A3=/B3=/C3= from line 4)" in done.stderr.decode()


def test_auto_still_checks_every_block_after_the_ones_it_decided_on():
    head = "G21 G90\n" + "G1 X1 Y2 Z3 I0 J0 K1\n" * 150
    program = (head + "G1 X1\nG1 X2 A3=0 B3=0 C3=1\n").encode()
    with pytest.raises(ProgramError, match=r"^t.nc:153: A3= is a tool-orientation word of sinumerik-vector, not of"):
        run(io.BytesIO(program), io.BytesIO(), Options(machine="auto"), "t.nc")


def test_auto_without_orientation_words_keeps_the_default_profile():
    out = io.BytesIO()
    report = run(io.BytesIO(b"G21 G90\nG1 X1 Y2 Z3 F100\n"), out, Options(machine="auto"), "t.nc")
    assert report.machine == "ijk"
    assert report.notes == ["machine: auto -> ijk (no tool-orientation words: the tool stays vertical)"]


def test_auto_in_a_config_file(tmp_path):
    (tmp_path / "ncfix.toml").write_text('[ncfix]\nmachine = "auto"\n')
    program = tmp_path / "p.nc"
    program.write_bytes(b"G21 G90\nG1 X1 Y2 Z3 A10 C20 F100\nM30\n")
    done = subprocess.run([sys.executable, "-m", "ncfix", str(program), "--report", str(tmp_path / "r.json")],
                          capture_output=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "machine: auto -> table-ac (A/C from line 2)" in done.stderr.decode()
    assert '"machine": "table-ac"' in (tmp_path / "r.json").read_text()


# The golden fix cases (tests/golden/fix_*): auto picks the case's profile, or names the candidates.
# The xyzac-trt case switches TCP on with G43.4, not with the sim's M428, so auto reads it as the
# ISO table-ac it was posted like (under linuxcnc-xyzac-trt its TCP would stay off).
FIX_AUTO = {"ijk": "ijk", "sinumerik-vector": "sinumerik-vector", "heidenhain-ln": "heidenhain-ln",
            "table-ac": "table-ac", "linuxcnc-xyzac-trt": "table-ac"}


@pytest.mark.parametrize("path", sorted([*GOLDEN.glob("fix_*/input.*"), *GOLDEN.glob("fix_*/expected.out")]), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_golden_fix_cases_are_read_by_their_profile_and_auto_names_it(path):
    machine = path.parent.name[len("fix_"):]
    _pass(path, machine)
    if machine in FIX_AUTO:
        _, _, chosen = _pass(path, "auto")
        assert chosen == FIX_AUTO[machine]
    else:  # a B/C program: table or head, TCP on or off, the words cannot tell
        with pytest.raises(ProgramError, match="machine auto cannot tell which machine reads B/C: ") as caught:
            run(io.BytesIO(path.read_bytes()), io.BytesIO(), Options(machine="auto"), path.name)
        candidates = str(caught.value).split("reads B/C: ")[1].split(" all do")[0].split(", ")
        # The xyzbc-trt case is posted like the ISO machines (TCP by G43.4, no M428): not offered.
        assert (machine in candidates) == (machine != "linuxcnc-xyzbc-trt"), candidates
