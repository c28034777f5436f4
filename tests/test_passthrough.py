"""With nothing to fix, ncfix is an exact pass-through: corpus programs and random text (the
golden pass-through cases: tests/golden/passthrough_*, run by test_golden.py)."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ncfix.config import Options
from ncfix.errors import NcfixError
from ncfix.pipeline import run

from conftest import CORPUS, corpus_programs

# The profile each corpus program is read with (others use the default, ijk).
CORPUS_MACHINES = {
    "model_1_Gcode.txt": "multiaxis-3dp-bc",
    "ring_Gcode.txt": "s3-deformfdm-bc",
    "boat-xyzac.ngc": "linuxcnc-xyzac-trt",
    "impeller-7bl-xyzac.ngc": "linuxcnc-xyzac-trt",
    "boat-xyzbc.ngc": "linuxcnc-xyzbc-trt",
    "xyzab-tdr-demo.ngc": str(Path(__file__).parent / "profiles" / "linuxcnc-xyzab-tdr.toml"),
}


def passthrough(data: bytes, **options) -> bytes:
    out = io.BytesIO()
    run(io.BytesIO(data), out, Options(**options), "t.nc")
    return out.getvalue()


@pytest.mark.parametrize("path", corpus_programs(), ids=lambda p: p.name)
def test_corpus_programs_pass_through_byte_for_byte(path):
    data = path.read_bytes()
    machine = CORPUS_MACHINES.get(path.name, "ijk")
    assert passthrough(data, machine=machine) == data
    assert passthrough(data, machine=machine, check=True) == data


def test_corpus_through_the_command_line_check():
    programs = corpus_programs()
    if not programs:
        pytest.skip("corpus absent")
    path = CORPUS / "linuxcnc" / "boat-xyzac.ngc"
    done = subprocess.run([sys.executable, "-m", "ncfix", "--check", "-q", "--machine", "linuxcnc-xyzac-trt", str(path)],
                          capture_output=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout == path.read_bytes()
    assert done.stderr == b""


SAFE_LINES = st.sampled_from([
    "G1 X1 Y2 Z3 I0 J0 K1", "G0 X-1.5 Y.5", "(comment)", "; note", "%", "O1234", "N10 G90 G21", "M3 S1000",
    "G1 X1 (a) ; b", "/G1 X2", "g1 x 1 0", "TRAFOOF", "CYCLE800(1,2)", "X=R1", "\tG1\tX1\t", "", "G2 X1 Y1 I1 J0",
    "G93 G1 X1 F100", "G91 X1", "G90", "G92 E0", "G1 X1 E2.5", "M83", "T1 M6",
])
GARBAGE = st.text(alphabet=st.characters(min_codepoint=0, max_codepoint=255, blacklist_characters="\n\r"), max_size=40)
ENDINGS = st.sampled_from(["\n", "\r\n", ""])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.one_of(SAFE_LINES, GARBAGE), ENDINGS), max_size=30))
def test_random_text_passes_through_or_fails_cleanly(lines):
    data = "".join(body + (end or "\n") for body, end in lines[:-1])
    if lines:
        data += lines[-1][0] + lines[-1][1]
    raw = data.encode("latin-1")
    try:
        assert passthrough(raw) == raw
    except NcfixError as exc:
        assert exc.where and exc.where.startswith("t.nc:")  # names the line


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(SAFE_LINES, ENDINGS), max_size=40))
def test_valid_programs_always_pass_through(lines):
    data = "".join(body + (end or "\n") for body, end in lines).encode("latin-1")
    assert passthrough(data) == data
