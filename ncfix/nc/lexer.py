"""Exact tokenizer for NC lines: ``''.join(token texts) == line`` for every line, whatever it holds.

Lines are ``str`` decoded as latin-1, so every byte maps to one character and back: comments
with bytes that are not UTF-8 survive untouched.

The hot path (:func:`scan`) returns ``(address, value text)`` pairs for one line's code (comments
removed) with a single ``findall``; the value text is captured permissively (``1.2.3``, ``1 2``)
and converted strictly later, so a malformed number is found rather than silently shortened.
:func:`tokens` and :func:`word_spans` give exact positions, and are used only for the lines that
ncfix rewrites and for tests.
"""

from __future__ import annotations

import re
from typing import NamedTuple

# `( ... )` (an unterminated one runs to the end of the line) and `; ...` to the end of the line.
_COMMENT = r"\([^)\r\n]*\)?|;[^\r\n]*"
COMMENT_RE = re.compile(_COMMENT)

# A value: optional sign, then digits/dots/blanks (LinuxCNC allows blanks inside numbers), or the
# start of an expression (`#100`, `[1+2]`, Heidenhain `Q5`), which makes the word opaque.
_VALUE = r"[+\-]?[ \t]*(?:[\d.][\d. \t]*|[#\[]|Q\d)"
# Siemens `A3=0.1`, `X=R1`, `X=IC(5)`: NAME = value-up-to-blank.
_ASSIGN = r"([A-Za-z_][A-Za-z0-9_]*)[ \t]*=[ \t]*([^\s;(]*)"
# A letter run and its value (empty when none follows: `TRAORI`, `LN`, `FMAX`).
_WORD = r"([A-Za-z]+)[ \t]*(" + _VALUE + r")?"
WORD_RE = re.compile(_ASSIGN + "|" + _WORD)

_TOKEN_RE = re.compile(
    r"(?P<comment>" + _COMMENT + r")"
    r"|(?P<assign>[A-Za-z_][A-Za-z0-9_]*[ \t]*=[ \t]*[^\s;(]*)"
    r"|(?P<word>[A-Za-z]+[ \t]*(?:" + _VALUE + r")?)"
    r"|(?P<space>[ \t]+)"
    r"|(?P<eol>\r?\n)"
    r"|(?P<other>.)",
    re.DOTALL,
)


class Token(NamedTuple):
    kind: str  # comment | assign | word | space | eol | other
    text: str
    start: int


class WordSpan(NamedTuple):
    """One word of a line: ``line[value_start:value_end]`` is its value text, blanks trimmed."""

    address: str  # upper case, e.g. "X", "A3", "TX"
    value: str  # the value text as written, blanks trimmed
    start: int  # where the address starts
    value_start: int
    value_end: int


def split_eol(line: str) -> tuple[str, str]:
    """Split a line into its body and its line ending ('\\r\\n', '\\n' or '')."""
    if line.endswith("\n"):
        if line.endswith("\r\n"):
            return line[:-2], "\r\n"
        return line[:-1], "\n"
    return line, ""


def code_of(body: str) -> str:
    """The body with comments blanked out (same length, so positions still match)."""
    if "(" not in body and ";" not in body:
        return body
    return COMMENT_RE.sub(lambda m: " " * len(m.group()), body)


def scan(code: str) -> list[tuple[str, str, str, str]]:
    """All words of a comment-free line: ``(assign name, assign value, address, value)`` tuples.

    Exactly one of the two pairs is filled for each match (``findall`` of :data:`WORD_RE`).
    """
    return WORD_RE.findall(code)


def tokens(line: str) -> list[Token]:
    """Every character of ``line`` in exactly one token, in order."""
    out = []
    for m in _TOKEN_RE.finditer(line):
        kind = m.lastgroup or "other"
        out.append(Token(kind, m.group(), m.start()))
    return out


def word_spans(body: str) -> list[WordSpan]:
    """The words of a line body with exact positions of their values (comments skipped)."""
    code = code_of(body)
    spans = []
    for m in WORD_RE.finditer(code):
        if m.group(1) is not None:
            addr, vstart, vend = m.group(1), m.start(2), m.end(2)
        else:
            addr = m.group(3)
            vstart, vend = (m.start(4), m.end(4)) if m.group(4) is not None else (m.end(3), m.end(3))
        text = code[vstart:vend]
        stripped = text.rstrip(" \t")
        vend -= len(text) - len(stripped)
        spans.append(WordSpan(addr.upper(), stripped, m.start(), vstart, vend))
    return spans


def parse_number(text: str) -> float:
    """Strict conversion of a value text; raises ValueError when it is not one number."""
    if not text:
        raise ValueError("no number")
    try:
        return float(text)
    except ValueError:
        pass
    compact = text.replace(" ", "").replace("\t", "")
    if not compact or compact[0] in "#[Q" or compact[-1:] in "+-":
        raise ValueError(text)
    return float(compact)


def decimals_of(text: str) -> int:
    """Digits after the decimal point in a value text (``10.`` → 0, ``.250`` → 3)."""
    dot = text.find(".")
    if dot < 0:
        return 0
    return sum(ch.isdigit() for ch in text[dot + 1 :])
