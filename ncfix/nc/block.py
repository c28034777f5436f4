"""One line of the program: its raw text and what the modal state says it does."""

from __future__ import annotations

RAPID, LINEAR, ARC_CW, ARC_CCW = 0, 1, 2, 3


class Block:
    """A line of the input. Unchanged blocks are written as ``raw``, byte for byte.

    ``words`` holds, for a motion block, the absolute value of every machine word of the
    profile (``profile.kinematics.letters``: X Y Z and the orientation words) after modal
    carry-over, in mm and degrees; NaN where the program has not said (or said with an
    expression ncfix cannot evaluate). ``new_words`` is set by the stages that change it.
    """

    __slots__ = (
        "lineno", "raw", "motion", "words", "tcp", "opaque", "inch", "incremental",
        "e_delta", "deposit_on", "feed_mode", "new_words", "reason",
    )

    def __init__(self, lineno: int, raw: str):
        self.lineno = lineno
        self.raw = raw
        self.motion: int | None = None  # RAPID/LINEAR/ARC_* when the block moves, else None
        self.words: tuple[float, ...] | None = None
        self.tcp = True
        self.opaque = False  # an axis word holds an expression (`X#1`, `X=R1`)
        self.inch = False
        self.incremental = False
        self.e_delta: float | None = None  # extrusion of this block, None without an E word
        self.deposit_on: bool | None = None  # state of --deposit-codes, None when not given
        self.feed_mode = 94
        self.new_words: tuple[float, ...] | None = None
        self.reason: str | None = None

    @property
    def changed(self) -> bool:
        return self.new_words is not None

    def __repr__(self) -> str:
        return f"Block({self.lineno}, {self.raw!r}, motion={self.motion})"
