"""One line of the program: its raw text and what the modal state says it does."""

from __future__ import annotations


class ModalState:
    """The modal settings a block runs under; shared by consecutive blocks until one changes."""

    __slots__ = ("tcp", "inch", "incremental", "feed_mode", "deposit_on")

    def __init__(self, tcp: bool, inch: bool, incremental: bool, feed_mode: int, deposit_on: bool | None):
        self.tcp = tcp
        self.inch = inch
        self.incremental = incremental
        self.feed_mode = feed_mode
        self.deposit_on = deposit_on  # state of --deposit-codes, None when they are not given


class Block:
    """A line of the input. Unchanged blocks are written as ``raw``, byte for byte.

    ``words`` holds, for a motion block, the absolute value of every machine word of the
    profile (``profile.kinematics.letters``: X Y Z and the orientation words) after modal
    carry-over, in mm and degrees; NaN where the program has not said (or said with an
    expression ncfix cannot evaluate). The pipeline carries the same facts in chunk columns
    (ncfix.nc.chunk); a Block is the line-by-line reader's answer for one line.
    """

    __slots__ = ("lineno", "raw", "motion", "words", "state", "opaque", "e_delta", "arc")

    def __init__(self, lineno: int, raw: str, state: ModalState):
        self.lineno = lineno
        self.raw = raw
        self.state = state
        self.motion: int | None = None  # RAPID/LINEAR/ARC_* when the block moves, else None
        self.words: tuple[float, ...] | None = None
        self.opaque = False  # an axis word holds an expression (`X#1`, `X=R1`)
        self.e_delta: float | None = None  # extrusion of this block, None without an E word
        # G2/G3 that ncfix can follow: (cx, cy, cz, normal axis 0/1/2, +1 ccw / -1 cw); see Chunk.arc
        self.arc: tuple[float, float, float, int, int] | None = None

    tcp = property(lambda self: self.state.tcp)
    inch = property(lambda self: self.state.inch)
    incremental = property(lambda self: self.state.incremental)
    feed_mode = property(lambda self: self.state.feed_mode)
    deposit_on = property(lambda self: self.state.deposit_on)

    def __repr__(self) -> str:
        return f"Block({self.lineno}, {self.raw!r}, motion={self.motion})"
