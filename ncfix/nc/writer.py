"""Renders blocks: unchanged ones as their raw bytes, changed ones rewritten in place (ncfix.nc.emit)."""

from __future__ import annotations

import math
import re

from ncfix.nc.block import Block
from ncfix.nc.emit import rewrite_line
from ncfix.nc.modal import MM_PER_INCH
from ncfix.profiles import Profile

_HEIDENHAIN_L = re.compile(r"^(\s*\d*\s*)L(\s)")


class Writer:
    """Keeps what was emitted so that incremental (G91) blocks after a change stay right."""

    def __init__(self, profile: Profile):
        self.profile = profile
        kin = profile.kinematics
        self.letters = kin.letters
        self.orientation = set(kin.orientation_letters)
        self.vector_letters = kin.orientation_letters if profile.is_vector else ()
        self.emitted: list[float] | None = None  # last motion block's words as written
        self.programmed: list[float] | None = None  # ... and as the input had them

    def render(self, block: Block) -> str:
        if block.words is None:
            return block.raw
        target = block.new_words if block.new_words is not None else block.words
        previous_emitted, previous_programmed = self.emitted, self.programmed
        self.emitted, self.programmed = list(target), list(block.words)
        needs_rewrite = block.new_words is not None or (
            block.incremental and previous_emitted is not None and previous_emitted != previous_programmed)
        if not needs_rewrite:
            return block.raw
        values: dict[str, float] = {}
        scale = MM_PER_INCH if block.inch else 1.0
        for i, letter in enumerate(self.letters):
            new, old = target[i], block.words[i]
            is_linear = letter in ("X", "Y", "Z")
            factor = scale if is_linear else 1.0
            if block.incremental and letter not in self.vector_letters and previous_emitted is not None:
                new_inc = new - previous_emitted[i]
                old_inc = old - previous_programmed[i]
                if not math.isclose(new_inc, old_inc, abs_tol=1e-12):
                    values[letter] = new_inc / factor
            elif not math.isclose(new, old, abs_tol=1e-12):
                values[letter] = new / factor
        required: tuple[str, ...] = ()
        if self.vector_letters and any(l in values for l in self.vector_letters):
            for i, letter in enumerate(self.letters):
                if letter in self.vector_letters:
                    values[letter] = target[i]
            required = self.vector_letters
        if not values:
            return block.raw
        raw = block.raw
        if self.profile.dialect == "heidenhain" and required:
            raw = _HEIDENHAIN_L.sub(r"\1LN\2", raw, count=1)
        return rewrite_line(raw, self.profile, values, required)
