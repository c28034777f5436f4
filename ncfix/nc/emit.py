"""Rewrite a changed block in place: only the words whose printed value changes, in the input's style.

A word keeps its place, its spelling (case, ``=``, blanks) and its number style: the number of
decimals, a forced ``+`` sign, a trailing ``.``, a missing leading zero. Words a dialect needs
but the line lacks are added after the last position or orientation word, formatted like their
siblings on the line (or by the profile's defaults).
"""

from __future__ import annotations

import re

from ncfix.nc.dialects import DIALECTS
from ncfix.nc.lexer import decimals_of, split_eol, word_spans
from ncfix.profiles import Profile

_CHECKSUM_RE = re.compile(r"\*(\d+)([ \t]*)$")


def format_value(value: float, default_decimals: int, like: str | None = None, force_sign: bool = False,
                 force_point: bool = False, trim: bool | None = None) -> str:
    """``value`` printed in the style of the value text ``like`` (or by the defaults).

    A ``like`` with as many decimals as the default or more is a fixed-decimals post: keep its
    count. One with fewer is a post that trims zeros (`X10.`, `I0.258819`, `X-49.65`): print the
    default decimals and trim. ``trim`` overrides that guess (the line's other words may show it).
    A leading `+`, a trailing `.` and a missing leading zero carry over.
    """
    decimals = default_decimals
    if like is not None:
        bare = like.lstrip("+- \t")
        force_sign = force_sign or like.lstrip(" \t").startswith("+")
        force_point = force_point or bare.endswith(".")
        if trim is None:
            trim = trims_zeros(like, default_decimals)
        if not trim:
            decimals = max(default_decimals, decimals_of(like))
    text = f"{value:.{decimals}f}"
    if float(text) == 0.0:
        text = f"{0.0:.{decimals}f}"  # never `-0.000`
    if trim and "." in text:
        text = text.rstrip("0").rstrip(".")
    if force_point and "." not in text:
        text += "."
    if like is not None and like.lstrip("+- \t").startswith(".") and text.lstrip("-").startswith("0."):
        text = text.replace("0.", ".", 1)
    if force_sign and not text.startswith("-"):
        text = "+" + text
    return text


def trims_zeros(like: str, default_decimals: int) -> bool:
    """Whether a value text looks printed by a post that trims trailing zeros."""
    return decimals_of(like) < default_decimals


def rewrite_line(raw: str, profile: Profile, values: dict[str, float], required: tuple[str, ...] = ()) -> str:
    """Set ``values`` (letter → value in program units) on the line ``raw``.

    Words whose printed value would not change are left byte for byte; ``required`` letters
    are added when missing (e.g. all of I J K).
    """
    body, eol = split_eol(raw)
    spans = _first_spans(body)
    kin = profile.kinematics
    fmt = profile.number_format
    defaults, trim = _line_style(spans, profile)

    def kind_of(letter: str) -> str:
        return word_kind(profile, letter)

    edits: list[tuple[int, int, str]] = []
    missing: list[str] = []
    for letter in kin.letters:
        if letter not in values:
            continue
        if letter in required and letter not in spans:
            missing.append(letter)
            continue
        span = spans.get(letter)
        if span is None:
            missing.append(letter)
            continue
        new_text = format_value(values[letter], defaults[kind_of(letter)], span.value, fmt.force_sign,
                                fmt.force_decimal_point, trim[kind_of(letter)])
        old_text = span.value
        try:
            if float(old_text.replace(" ", "").replace("\t", "")) == float(new_text):
                continue  # same printed value: keep the input's bytes
        except ValueError:
            pass
        edits.append((span.value_start, span.value_end, new_text))

    if missing:
        anchor = max((spans[l].value_end for l in kin.letters if l in spans), default=None)
        if anchor is None:
            anchor = _code_end(body)
        sep = "" if " " not in body.strip() else " "
        lower = bool(spans) and body[min(s.start for s in spans.values())].islower()
        pieces = []
        for letter in missing:
            siblings = [spans[l] for l in kin.letters if l in spans and kind_of(l) == kind_of(letter)]
            like = siblings[0].value if siblings else None
            text = format_value(values[letter], defaults[kind_of(letter)], like, fmt.force_sign,
                                fmt.force_decimal_point, trim[kind_of(letter)] if like is not None else None)
            address = letter.lower() if lower else letter
            pieces.append(f"{sep}{address}{DIALECTS[profile.dialect].joiner(letter)}{text}")
        edits.append((anchor, anchor, "".join(pieces)))

    if not edits:
        return raw
    out = body
    for start, end, text in sorted(edits, key=lambda e: e[0], reverse=True):
        out = out[:start] + text + out[end:]
    out = _refresh_checksum(out, profile)
    return out + eol


def replace_values(raw: str, profile: Profile, texts: dict[str, str]) -> str:
    """Set the value text of the first word of each letter in ``texts`` (printed already, e.g. by
    ncfix.correct.extrusion) on the line ``raw``; every other byte stays. A letter the line
    lacks is left out (a caller only rewrites words the line has)."""
    body, eol = split_eol(raw)
    spans = _first_spans(body)
    edits = [(spans[letter].value_start, spans[letter].value_end, text)
             for letter, text in texts.items() if letter in spans and spans[letter].value != text]
    if not edits:
        return raw
    for start, end, text in sorted(edits, key=lambda e: e[0], reverse=True):
        body = body[:start] + text + body[end:]
    return _refresh_checksum(body, profile) + eol


def printed_decimals(raw: str, profile: Profile) -> dict[str, int]:
    """The decimals ``rewrite_line`` prints each kind of word with on the line ``raw``:
    ``{"linear": .., "angle": .., "vector": ..}`` (the profile's default, or more where the
    line's own words of that kind have more)."""
    return _line_style(_first_spans(split_eol(raw)[0]), profile)[0]


def word_kind(profile: Profile, letter: str) -> str:
    """"linear", "angle" or "vector": which number format a position/orientation letter takes."""
    if letter in profile.kinematics.orientation_letters:
        return "vector" if profile.is_vector else "angle"
    return "linear"


def _first_spans(body: str) -> dict:
    spans = {}
    for span in word_spans(body):
        if span.address not in spans:
            spans[span.address] = span
    return spans


def _line_style(spans: dict, profile: Profile) -> tuple[dict[str, int], dict[str, bool]]:
    """Decimals per kind of word, and whether the line's post trims zeros, from the line's words."""
    fmt = profile.number_format
    defaults = {"linear": fmt.linear, "angle": fmt.angle, "vector": fmt.vector}
    # A post trims zeros for all words of a kind or for none: one trimmed sibling tells.
    trim = {kind: False for kind in defaults}
    for letter in profile.kinematics.letters:
        if letter in spans:
            kind = word_kind(profile, letter)
            trim[kind] = trim[kind] or trims_zeros(spans[letter].value, defaults[kind])
            defaults[kind] = max(defaults[kind], decimals_of(spans[letter].value))
    return defaults, trim


def _code_end(body: str) -> int:
    """Where the code of a line ends (before a trailing comment or checksum)."""
    end = len(body)
    for mark in ("(", ";", "*"):
        pos = body.find(mark)
        if 0 <= pos < end:
            end = pos
    return len(body[:end].rstrip(" \t"))


def _refresh_checksum(body: str, profile: Profile) -> str:
    """RepRap host checksums (`*93`): XOR of every byte before the `*` (not Heidenhain's `*`)."""
    if not DIALECTS[profile.dialect].star_checksum:
        return body
    m = _CHECKSUM_RE.search(body)
    if not m:
        return body
    head = body[: m.start()]
    checksum = 0
    for ch in head:
        checksum ^= ord(ch)
    return f"{head}*{checksum}{m.group(2)}"
