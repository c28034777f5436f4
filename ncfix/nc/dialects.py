"""Controller dialects: what ISO, Siemens SINUMERIK and Heidenhain Klartext spell differently.

One :class:`Dialect` per ``dialect`` of a profile (docs/profiles.md). The reader (ncfix.nc.modal),
the in-place writer (ncfix.nc.writer, ncfix.nc.emit) and the post (ncfix.nc.post) ask it instead of
testing the dialect's name, so what one controller does differently is read here in one place.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass


@dataclass(frozen=True)
class Dialect:
    """How one controller family reads and writes blocks (the fields say what differs)."""

    name: str
    # The posted program around its motion blocks: (blocks, title, number, vector, tcp) → lines.
    post_frame: Callable[[list[str], str, int, bool, bool], Iterator[str]]
    # Keywords without a value that give a block its kind (Klartext `L X+1`, `C X+1 DR+`, `CC X+0`):
    # linear moves, arcs, and the pole of later arcs. A block of such a dialect without one is no move.
    linear_kinds: frozenset[str] = frozenset()
    arc_kinds: frozenset[str] = frozenset()
    pole_kind: str | None = None
    pole_arc: str | None = None  # the arc about the last pole (Klartext C)
    radius_arc: str | None = None  # the arc given by its radius R (Klartext CR)
    rapid_word: str = ""  # on a linear block: a rapid move (Klartext FMAX)
    initial_motion: int | None = None  # the motion mode before any block sets one
    incremental_prefix: str = ""  # `IX+5`: X incremental on this block only (Klartext)
    unit_header: str = ""  # the header line that sets the units: `BEGIN PGM NAME INCH`
    function_word: str = ""  # `FUNCTION TCPM ...`: a code spelled as text
    arc_sense_word: bool = False  # arcs turn as DR+/DR- say, in the XY plane; I J K are no centres
    orientation_switch: str | None = None  # the word that switches on orientation programming
    plain_words: bool = False  # single-letter words only: the vectorised plain-line reader applies
    named_joiner: str = ""  # between a multi-letter word and its value: Siemens `A3=0.1`
    star_checksum: bool = False  # `*93` ends a line with a RepRap checksum (Klartext `*` is no checksum)
    signed_numbers: bool = False  # a profile's default: numbers carry their sign (`X+10`)
    # When a block gains tool-vector words its keyword changes: Klartext `L` becomes `LN`.
    vector_keyword: tuple[re.Pattern[str], str] | None = None
    # The post: motion keywords (rapid, feed; the vector form), whether every block states every
    # word, the feed on rapid blocks, and how a comment line is written.
    post_keywords: tuple[str, str] = ("G0", "G1")
    post_vector_keyword: str | None = None
    post_every_word: bool = False
    post_rapid_feed: str | None = None  # the feed of a rapid block when every block has one (FMAX)
    comment_prefix: str | None = None  # None: `(TEXT IN CAPITALS)`

    @property
    def block_kinds(self) -> frozenset[str]:
        return self.linear_kinds | self.arc_kinds | ({self.pole_kind} if self.pole_kind else frozenset())

    @property
    def reads_text(self) -> bool:
        """Whether :meth:`read_text` has anything to read on a block."""
        return bool(self.block_kinds or self.unit_header or self.function_word)

    def joiner(self, letter: str) -> str:
        """What goes between ``letter`` and its value (`A3=` on Siemens, nothing for `X`)."""
        return self.named_joiner if len(letter) > 1 else ""

    def read_text(self, upper: str, kind: str | None, inch: bool) -> tuple[bool, str | None, int | None, bool]:
        """What a block's text says beyond its words (``upper``: its code in capitals; ``kind``: its
        block keyword): the units after it, a text code (`FUNCTION TCPM ...`) or None, the motion
        mode it sets or None, and whether its axis words are no move."""
        if self.unit_header and self.unit_header in upper:
            inch = upper.rstrip().endswith("INCH")
        text = None
        if self.function_word and self.function_word in upper:
            text = " ".join(upper.split())
            text = text[text.index(self.function_word):]
        motion = None
        if kind in self.linear_kinds:
            motion = 0 if self.rapid_word and self.rapid_word in upper else 1
        elif kind in self.arc_kinds:
            motion = 2
        return inch, text, motion, motion is None

    def with_vector_keyword(self, raw: str) -> str:
        """The line ``raw`` with the keyword a block carrying tool-vector words needs."""
        if self.vector_keyword is None:
            return raw
        pattern, replacement = self.vector_keyword
        return pattern.sub(replacement, raw, count=1)

    def post_line(self, rapid: bool, vector: bool, words: str, feed_mm_min: float) -> str:
        """A posted motion block: its keyword and ``words``, with the feed where the dialect puts it
        on every block (a dialect that does not gets it from the caller on the first feed block)."""
        keyword = self.post_keywords[0 if rapid else 1]
        if vector and self.post_vector_keyword:
            keyword = self.post_vector_keyword
        if self.post_rapid_feed is None:
            return f"{keyword} {words}"
        feed = self.post_rapid_feed if rapid else f"F{feed_mm_min:.0f}"
        return f"{keyword} {words} {feed}"

    def comment(self, text: str) -> str:
        return f"{self.comment_prefix}{text}" if self.comment_prefix is not None else f"({text.upper()})"


def _iso_frame(body: list[str], title: str, number: int, vector: bool, tcp: bool) -> Iterator[str]:
    """`%`, `O0001 (TITLE)`, N-numbered blocks with TCP on (G43.5 for a vector, G43.4 for angles)."""
    tcp_code = "G43.5 H1" if vector else "G43.4 H1"
    yield "%\n"
    yield f"O{number:04d} ({title.upper()})\n"
    yield "(POSTED FOR NCFIX SAMPLES: TIP POINTS, TCP ON)\n"
    lines = ["G21 G90 G94 G17", "G54", tcp_code if tcp else "G49", *body, "G49", "M30"]
    n = 0
    for line in lines:
        if line.startswith("("):
            yield line + "\n"
            continue
        n += 10
        yield f"N{n} {line}\n"
    yield "%\n"


def _siemens_frame(body: list[str], title: str, number: int, vector: bool, tcp: bool) -> Iterator[str]:
    """An MPF: `; %_N_TITLE_MPF`, TRAORI with ORIVECT, N-numbered blocks."""
    name = title.upper().replace(" ", "_")
    head = [f"; %_N_{name}_MPF", f"; {title} (posted for ncfix samples)", "G17 G71 G90 G94", "TRAORI",
            "ORIWKS", "ORIVECT"]
    tail = ["TRAFOOF", "M30"]
    for line in head[:2]:
        yield line + "\n"
    for i, line in enumerate(head[2:] + body + tail):
        yield f"N{10 * (i + 1)} {line}\n"


def _klartext_frame(body: list[str], title: str, number: int, vector: bool, tcp: bool) -> Iterator[str]:
    """`BEGIN PGM TITLE MM` … `END PGM`, blocks numbered from 0, TCP by M128/M129."""
    name = title.upper().replace(" ", "_")
    lines = [f"BEGIN PGM {name} MM", "TOOL CALL 1 Z S0", "M128", *body, "M129", f"END PGM {name} MM"]
    for i, line in enumerate(lines):
        yield f"{i} {line}\n"


ISO = Dialect("iso", _iso_frame, plain_words=True, star_checksum=True)
SINUMERIK = Dialect("sinumerik", _siemens_frame, orientation_switch="TRAORI", named_joiner="=", star_checksum=True,
                    comment_prefix="; ")
HEIDENHAIN = Dialect(
    "heidenhain", _klartext_frame, linear_kinds=frozenset({"L", "LN"}), arc_kinds=frozenset({"C", "CR", "CT", "CP"}), pole_kind="CC",
    pole_arc="C", radius_arc="CR", rapid_word="FMAX", initial_motion=1, incremental_prefix="I",
    unit_header="BEGIN PGM", function_word="FUNCTION", arc_sense_word=True, orientation_switch="LN", signed_numbers=True,
    vector_keyword=(re.compile(r"^(\s*\d*\s*)L(\s)"), r"\1LN\2"),
    post_keywords=("L", "L"), post_vector_keyword="LN", post_every_word=True, post_rapid_feed="FMAX",
    comment_prefix="; ")

DIALECTS = {d.name: d for d in (ISO, SINUMERIK, HEIDENHAIN)}
