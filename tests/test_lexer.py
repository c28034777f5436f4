"""The tokenizer: every line round-trips byte for byte, and words are read as a controller would."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ncfix.nc.lexer import code_of, parse_number, scan, tokens, word_spans

from conftest import corpus_programs

EDGE_LINES = [
    "G1 X1 (c) ; c\n",
    "%\n",
    "O1001 (NCFIX F1 FANUC G43.4 AC)\r\n",
    "/N10 G1 x10.0 y 2.5 (block delete, lower case, spaced number)\n",
    "N20 G0X +0. 12 34Y 7 ; LinuxCNC reads X0.1234 Y7\n",
    "N30 G1 X007 Y.5 Z-0.000 F1200. (leading zeros, leading dot, negative zero)\n",
    "N65048 G1 X136.689 Y160.389 E6563.257*93\n",
    "N80 X20 Y0 Z5 A3=0.258819 B3=0 C3=0.965926\n",
    "N30 TRAORI\n",
    "N40 CYCLE800(1,\"TABLE\",200000,57,0,0,0,0,0,0,0,0,0,-1,100,1)\n",
    "G1 X=R1 Y=IC(5)\n",
    "8 LN X+20 Y+0 Z+5 TX+0.258819 TY+0 TZ+0.9659258 F1200\n",
    "\tG1\tX1\t  \n",
    "   \n",
    "\n",
    "G1 X-0. Y.5",
    "(unterminated comment\n",
    "G1 X1 (\xff\xfe not utf-8)\n",
    "g10 l20 p0 x-[#<_hal[a.b]>+#<_hal[c]>] y-#<_hal[x]>\n",
]


@pytest.mark.parametrize("line", EDGE_LINES)
def test_tokens_join_to_the_line(line):
    assert "".join(t.text for t in tokens(line)) == line


def test_every_corpus_line_round_trips_through_tokens():
    programs = corpus_programs()
    if not programs:
        pytest.skip("corpus absent")
    for path in programs:
        with open(path, "rb") as handle:
            for raw in handle:
                line = raw.decode("latin-1")
                assert "".join(t.text for t in tokens(line)) == line, (path, raw)


def _words(line):
    return {(a or b).upper(): (av if a else v).strip() for a, av, b, v in scan(code_of(line))}


@pytest.mark.parametrize(
    "line, expected",
    [
        ("G1 X1 (X9) ; Y9", {"G": "1", "X": "1"}),
        ("N20 G0X +0. 12 34Y 7", {"N": "20", "G": "0", "X": "+0. 12 34", "Y": "7"}),
        ("G1 X007 Y.5 Z-0.000 F1200.", {"G": "1", "X": "007", "Y": ".5", "Z": "-0.000", "F": "1200."}),
        ("X20 A3=0.258819 B3=0 C3=0.965926", {"X": "20", "A3": "0.258819", "B3": "0", "C3": "0.965926"}),
        ("LN X+20 TX+0.258819 TY+0 TZ+0.9659258 F1200",
         {"LN": "", "X": "+20", "TX": "+0.258819", "TY": "+0", "TZ": "+0.9659258", "F": "1200"}),
        ("G1  X   7.259  A -53.585  F 636", {"G": "1", "X": "7.259", "A": "-53.585", "F": "636"}),
        ("G1 X1.5e-3", {"G": "1", "X": "1.5", "E": "-3"}),
    ],
)
def test_words_are_read_as_a_controller_reads_them(line, expected):
    assert _words(line) == expected


@pytest.mark.parametrize("text, value", [("+0. 12 34", 0.1234), ("007", 7.0), (".5", 0.5), ("-0.000", 0.0),
                                          ("1200.", 1200.0), ("+10", 10.0), ("- 5", -5.0)])
def test_numbers_parse(text, value):
    assert parse_number(text) == value


@pytest.mark.parametrize("text", ["", ".", "1.2.3", "-", "#100", "[1+2]", "1..2"])
def test_malformed_numbers_are_refused(text):
    with pytest.raises(ValueError):
        parse_number(text)


def test_word_spans_point_at_the_value_text():
    body = "N10 G1 X 10.5  Y-2 (Z9) A3=0.25"
    spans = {s.address: s for s in word_spans(body)}
    assert body[spans["X"].value_start:spans["X"].value_end] == "10.5"
    assert body[spans["Y"].value_start:spans["Y"].value_end] == "-2"
    assert body[spans["A3"].value_start:spans["A3"].value_end] == "0.25"
    assert "Z" not in spans


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.characters(min_codepoint=0, max_codepoint=255), max_size=120))
def test_any_latin1_text_round_trips(text):
    assert "".join(t.text for t in tokens(text)) == text
