"""ncfix's lexer and modal state against pygcode, an independent G-code reader, on the ISO corpus.

pygcode parses each line into words and runs a virtual machine over the blocks (distance mode,
units, motion mode, position). Where both readers understand a line they must agree: the same
words with the same values, and after every motion block the same absolute X Y Z and rotary
positions. Lines pygcode cannot read (LinuxCNC's `M428`-style user codes, blanks inside numbers)
are compared on the words alone where pygcode can split them.
"""

from __future__ import annotations

import math

import pytest

from ncfix.nc.lexer import code_of, parse_number, split_eol, word_spans
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile

from conftest import corpus_path

pygcode = pytest.importorskip("pygcode", reason="pygcode is a test extra: pip install '.[test]'")

PROGRAMS = [
    ("linuxcnc/boat-xyzac.ngc", "linuxcnc-xyzac-trt"),
    ("linuxcnc/boat-xyzbc.ngc", "linuxcnc-xyzbc-trt"),
    ("linuxcnc/impeller-7bl-xyzac.ngc", "linuxcnc-xyzac-trt"),
]


class _Machine(pygcode.Machine):
    axes = {"X", "Y", "Z", "A", "B", "C"}
    ignore_invalid_modal = True  # LinuxCNC's user M-codes (M428 TCP on): no effect on positions


def _pygcode_line(text: str):
    """pygcode's parse of one line, or None where it does not know a code of it."""
    try:
        return pygcode.Line(text)
    except Exception:  # noqa: BLE001 - pygcode raises bare exceptions for codes it lacks
        return None


def _ncfix_words(body: str) -> list[tuple[str, float]]:
    out = []
    for span in word_spans(body):
        try:
            out.append((span.address, parse_number(span.value)))
        except ValueError:
            out.append((span.address, math.nan))
    return out


def _same_words(ours: list[tuple[str, float]], theirs) -> bool:
    theirs = [(w.letter.upper(), float(w.value)) for w in theirs]
    if len(ours) != len(theirs):
        return False
    return all(a == b and math.isclose(x, y, abs_tol=1e-12) for (a, x), (b, y) in zip(ours, theirs))


@pytest.mark.parametrize("name, machine", PROGRAMS)
def test_words_and_positions_agree_with_pygcode(name, machine):
    path = corpus_path(*name.split("/"))
    profile = load_profile(machine)
    interp = Interpreter(profile, str(path))
    letters = profile.kinematics.letters
    vm = _Machine()
    compared_words = compared_positions = 0
    with open(path, "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            text = raw.decode("latin-1")
            block = interp.feed(lineno, text)
            body, _ = split_eol(text)
            code = code_of(body).strip()
            if not code or code == "%":
                continue
            line = _pygcode_line(body)
            if line is None:
                continue
            assert _same_words(_ncfix_words(body), line.block.words), f"{name}:{lineno}: words differ: {body!r}"
            compared_words += 1
            vm.process_block(line.block)
            if block.motion is None or block.words is None:
                continue
            position = vm.pos.values
            for letter, value in zip(letters, block.words):
                if math.isnan(value):
                    continue  # ncfix has not been told this axis yet; pygcode starts it at 0
                assert math.isclose(value, position[letter], abs_tol=1e-9), \
                    f"{name}:{lineno}: {letter} is {value} in ncfix, {position[letter]} in pygcode"
            compared_positions += 1
    # The comparison covers the programs, not a handful of lines pygcode happened to accept.
    assert compared_words > 1000 and compared_positions > 1000, (compared_words, compared_positions)


def test_the_crosscheck_sees_a_wrong_position():
    """The harness itself: a reader that drops G91 would be caught (the test can fail)."""
    vm = _Machine()
    for text in ("G90 G21", "G1 X1 Y2 Z3", "G91", "X1"):
        vm.process_block(pygcode.Line(text).block)
    assert vm.pos.values["X"] == 2.0
    profile = load_profile("linuxcnc-xyzac-trt")
    interp = Interpreter(profile, "t.ngc")
    blocks = [interp.feed(i, t + "\n") for i, t in enumerate(("G90 G21", "G1 X1 Y2 Z3", "G91", "X1"), start=1)]
    assert blocks[-1].words[0] == vm.pos.values["X"]
