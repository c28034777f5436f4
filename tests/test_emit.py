"""Rewriting a changed block: only the words whose printed value changes, in the input's style."""

from __future__ import annotations


import pytest

from ncfix.nc.emit import format_value, rewrite_line
from ncfix.nc.modal import Interpreter
from ncfix.nc.writer import Writer
from ncfix.profiles import load_profile


@pytest.mark.parametrize(
    "value, decimals, like, expected",
    [
        (12.3456, 3, "10.000", "12.346"),  # fixed decimals kept
        (12.3456, 3, "10.00000", "12.34560"),  # more decimals than the default: kept too
        (0.258819, 6, "0.", "0.258819"),  # a post that trims zeros
        (1.0, 6, "1.", "1."),  # ... and keeps the point
        (-49.6, 3, "-49.65", "-49.6"),
        (0.5, 3, ".250", ".500"),  # no leading zero
        (12.0, 3, "+1.000", "+12.000"),  # forced sign
        (-0.0001, 3, "1.000", "0.000"),  # never -0.000
        (7.2, 3, "  7.259", "7.200"),
        (3.0, 3, None, "3.000"),
    ],
)
def test_values_are_printed_in_the_style_of_the_word_they_replace(value, decimals, like, expected):
    assert format_value(value, decimals, like) == expected


@pytest.mark.parametrize(
    "machine, line, values, expected",
    [
        ("table-ac", "N60 X20. A15. C90. (keep me)\n", {"A": 17.5}, "N60 X20. A17.5 C90. (keep me)\n"),
        ("table-ac", "G1  X   7.259  A -53.585  C -257.043  F 636\r\n", {"A": -50.0, "C": -250.1234},
         "G1  X   7.259  A -50.000  C -250.123  F 636\r\n"),
        ("table-ac", "g1 x30 y5 a-30 c-30 f107.331\n", {"A": -31.0}, "g1 x30 y5 a-31 c-30 f107.331\n"),
        ("table-ac", "X20. C90.\n", {"A": 5.0}, "X20. C90. A5.\n"),  # a missing word is added beside its sibling
        ("ijk", "N50 X20. Y0. Z5. I0.258819 J0. K0.965926\n", {"I": 0.1, "J": 0.2, "K": 0.974679},
         "N50 X20. Y0. Z5. I0.1 J0.2 K0.974679\n"),
        ("ijk", "N50 X20. Y0. Z5. I0.258819\n", {"I": 0.1, "J": 0.2, "K": 0.974679},
         "N50 X20. Y0. Z5. I0.100000 J0.200000 K0.974679\n"),  # no sign of trimming: fixed decimals
        ("sinumerik-vector", "N80 X20 Y0 Z5 A3=0.258819 B3=0 C3=0.965926 ; c\n",
         {"A3": 0.1, "B3": 0.2, "C3": 0.974679}, "N80 X20 Y0 Z5 A3=0.1 B3=0.2 C3=0.974679 ; c\n"),
        ("sinumerik-vector", "N80 X20 A3=0.258819 B3=0.000000 C3=0.965926\n",
         {"A3": 0.1, "B3": 0.2, "C3": 0.974679}, "N80 X20 A3=0.100000 B3=0.200000 C3=0.974679\n"),
        ("heidenhain-ln", "8 LN X+20 Y+0 Z+5 TX+0.258819 TY+0 TZ+0.9659258 F1200\n",
         {"TX": 0.1, "TY": 0.2, "TZ": 0.974679}, "8 LN X+20 Y+0 Z+5 TX+0.1 TY+0.2 TZ+0.974679 F1200\n"),
    ],
)
def test_changed_blocks_keep_every_other_byte(machine, line, values, expected):
    profile = load_profile(machine)
    required = profile.kinematics.orientation_letters if profile.is_vector else ()
    assert rewrite_line(line, profile, values, required) == expected


def test_unchanged_printed_values_keep_their_bytes():
    profile = load_profile("table-ac")
    line = "X20. A15.0004 C90.\n"
    assert rewrite_line(line, profile, {"A": 15.00041}) == line  # same value at the printed precision


def test_reprap_checksums_are_recomputed():
    profile = load_profile("ijk")
    out = rewrite_line("N65048 G1 X136.689 Y160.389 E6563.257*93\n", profile, {"X": 136.5})
    head, _, tail = out.rstrip("\n").partition("*")
    checksum = 0
    for ch in head:
        checksum ^= ord(ch)
    assert head == "N65048 G1 X136.500 Y160.389 E6563.257" and tail == str(checksum) != "93"


def run_with_changes(text: str, machine: str, changes: dict[int, dict[str, float]]) -> str:
    """Read ``text``, set new words on the given lines (letter → value in mm/deg), write it back."""
    profile = load_profile(machine)
    chunk = Interpreter(profile).feed_chunk(text.encode().splitlines(keepends=True), 1)
    for lineno, values in changes.items():
        i = lineno - 1
        words = chunk.words[i].copy()
        for letter, value in values.items():
            words[profile.kinematics.letters.index(letter)] = value
        chunk.new_words[i] = words
    return Writer(profile).render(chunk).decode()


def test_incremental_blocks_after_a_change_stay_on_the_programmed_path():
    text = "G90 G1 X0 Y0 Z0 A0 C0\nG91 X1\nX1\nX1\n"
    out = run_with_changes(text, "table-ac", {2: {"X": 1.5}})
    assert out == "G90 G1 X0 Y0 Z0 A0 C0\nG91 X1.5\nX0.5\nX1\n"


def test_words_a_change_altered_are_restated_on_the_next_block_that_leaves_them_out():
    text = "G90 G1 X0. Y0. Z0. A0. C0.\nG1 X2. A5. C10.\nG1 Y3.\nG1 X4.\n(end)\nG1 Y5.\n"
    out = run_with_changes(text, "table-ac", {2: {"X": 2.5, "A": 6.0, "C": 12.0}})
    # line 3 would inherit X2.5 A6 C12: it restates X, A and C (like a sibling on the line, else in
    # the profile's format); line 4 states X itself and the rest is as programmed again
    assert out == "G90 G1 X0. Y0. Z0. A0. C0.\nG1 X2.5 A6. C12.\nG1 Y3. X2. C10.000 A5.000\nG1 X4.\n(end)\nG1 Y5.\n"


def test_a_vector_block_without_vector_words_after_a_change_restates_the_vector():
    text = "G1 X0 Y0 Z0 I0 J0 K1\nG1 X1 I0.1 J0 K0.994987\nG1 X2\nG1 X3 K1\n"
    out = run_with_changes(text, "ijk", {2: {"I": 0.2, "K": 0.979796}})
    lines = out.splitlines()
    assert lines[2] == "G1 X2 I0.100000 J0.000000 K0.994987"  # kept the programmed vector, now said
    assert lines[3] == "G1 X3 K1"  # says some vector words: the rest are 0 anyway


def test_inch_programs_are_written_back_in_inches():
    text = "G20 G90 G1 X1.0000 Y0.0000 Z0.0000 A0 C0\n"
    out = run_with_changes(text, "table-ac", {1: {"X": 2 * 25.4}})
    assert out == "G20 G90 G1 X2.0000 Y0.0000 Z0.0000 A0 C0\n"


def test_heidenhain_l_block_gains_vectors_as_ln():
    text = "7 LN X+10 Y+0 Z+5 TX+0 TY+0 TZ+1 F1200\n8 L X+20 F1200\n"
    out = run_with_changes(text, "heidenhain-ln", {2: {"TX": 0.6, "TZ": 0.8}})
    assert out.splitlines()[1] == "8 LN X+20 TX+0.6000000 TY+0.0000000 TZ+0.8000000 F1200"


def test_writer_without_changes_is_byte_exact():
    text = "G91 G1 X1 Y0 Z0 A0 C0\r\nX1 (c)\n\nX1"
    assert run_with_changes(text, "table-ac", {}) == text
