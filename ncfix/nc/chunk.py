"""A chunk of consecutive lines and, per line, what the modal state says it does (numpy columns)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Chunk:
    """Lines ``first_lineno ..`` of the input (raw bytes, ends kept) and their meaning.

    motion : (n,) int8, -1 where the line does not move, else 0/1/2/3 (G0..G3)
    words : (n, k) float64, the profile's machine words after modal carry-over (mm, degrees),
        NaN on lines that do not move and for axes the program has not set
    e_delta : (n,) float64, extrusion of the line, NaN without an extrusion word
    tcp, inch, incremental, opaque : (n,) bool
    feed_mode : (n,) int16 (93, 94, 95); deposit_on : (n,) int8 (-1 when no deposit codes)
    e_relative : (n,) bool, extrusion words are relative (M83) on the line
    arc : (n, 5) float64, on G2/G3 blocks whose arc ncfix can follow: the centre (x, y, z; mm,
        absolute), the index (0, 1, 2) of the axis normal to the arc's plane and the sense
        (+1 counter-clockwise seen from that axis's + side, G3; -1 clockwise, G2); NaN elsewhere
    new_words : line index in the chunk → new words (k,), set by the stages that change blocks
    new_text : line index → {letter: value text} of other words a stage rewrites (E, F: see
        ncfix.correct.extrusion), printed already
    """

    first_lineno: int
    lines: list[bytes]
    motion: np.ndarray
    words: np.ndarray
    e_delta: np.ndarray
    tcp: np.ndarray
    inch: np.ndarray
    incremental: np.ndarray
    opaque: np.ndarray
    feed_mode: np.ndarray
    deposit_on: np.ndarray
    arc: np.ndarray
    e_relative: np.ndarray
    new_words: dict[int, np.ndarray] = field(default_factory=dict)
    new_text: dict[int, dict[str, str]] = field(default_factory=dict)
    reasons: dict[int, str] = field(default_factory=dict)

    @classmethod
    def empty(cls, first_lineno: int, lines: list[bytes], nwords: int) -> "Chunk":
        n = len(lines)
        return cls(
            first_lineno=first_lineno, lines=lines,
            motion=np.full(n, -1, dtype=np.int8), words=np.full((n, nwords), np.nan),
            e_delta=np.full(n, np.nan), tcp=np.zeros(n, dtype=bool), inch=np.zeros(n, dtype=bool),
            incremental=np.zeros(n, dtype=bool), opaque=np.zeros(n, dtype=bool),
            feed_mode=np.full(n, 94, dtype=np.int16), deposit_on=np.full(n, -1, dtype=np.int8),
            arc=np.full((n, 5), np.nan), e_relative=np.zeros(n, dtype=bool),
        )

    def __len__(self) -> int:
        return len(self.lines)
