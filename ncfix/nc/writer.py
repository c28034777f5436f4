"""Renders chunks: unchanged lines as their raw bytes, changed blocks rewritten in place (ncfix.nc.emit)."""

from __future__ import annotations

import math
import re

import numpy as np

from ncfix.nc.chunk import Chunk
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
        self.vector_letters = kin.orientation_letters if profile.is_vector else ()
        self.emitted: np.ndarray | None = None  # last motion block's words as written
        self.programmed: np.ndarray | None = None  # ... and as the input had them

    def render(self, chunk: Chunk) -> bytes:
        moving = np.flatnonzero(chunk.motion >= 0)
        drifted = self.emitted is not None and not np.array_equal(self.emitted, self.programmed, equal_nan=True)
        if not chunk.new_words and not drifted:
            if len(moving):
                last = chunk.words[moving[-1]]
                self.emitted, self.programmed = last.copy(), last.copy()
            return b"".join(chunk.lines)
        out = list(chunk.lines)
        for i in moving.tolist():
            text = self._line(chunk, i)
            if text is not None:
                out[i] = text.encode("latin-1")
        return b"".join(out)

    def _line(self, chunk: Chunk, i: int) -> str | None:
        words = chunk.words[i]
        target = chunk.new_words.get(i, words)
        previous_emitted, previous_programmed = self.emitted, self.programmed
        self.emitted, self.programmed = np.array(target, dtype=np.float64), words.copy()
        incremental = bool(chunk.incremental[i])
        changed = i in chunk.new_words
        if not changed and not (incremental and previous_emitted is not None
                                and not np.array_equal(previous_emitted, previous_programmed, equal_nan=True)):
            return None
        values: dict[str, float] = {}
        scale = MM_PER_INCH if chunk.inch[i] else 1.0
        for k, letter in enumerate(self.letters):
            new, old = float(target[k]), float(words[k])
            if math.isnan(new):
                continue  # an axis the program has not set is never written
            factor = scale if letter in ("X", "Y", "Z") else 1.0
            if incremental and letter not in self.vector_letters and previous_emitted is not None:
                new_inc = new - float(previous_emitted[k])
                old_inc = old - float(previous_programmed[k])
                if not math.isnan(new_inc) and not math.isclose(new_inc, old_inc, abs_tol=1e-12):
                    values[letter] = new_inc / factor
            elif not math.isclose(new, old, abs_tol=1e-12):
                values[letter] = new / factor
        required: tuple[str, ...] = ()
        if self.vector_letters and any(letter in values for letter in self.vector_letters):
            for k, letter in enumerate(self.letters):
                if letter in self.vector_letters:
                    values[letter] = float(target[k])
            required = self.vector_letters
        if not values:
            return None
        raw = chunk.lines[i].decode("latin-1")
        if self.profile.dialect == "heidenhain" and required:
            raw = _HEIDENHAIN_L.sub(r"\1LN\2", raw, count=1)
        return rewrite_line(raw, self.profile, values, required)
