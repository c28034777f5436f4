"""Renders chunks: unchanged lines as their raw bytes, changed blocks rewritten in place (ncfix.nc.emit).

Modal carry-over. A program states a word only when its value changes (``G1 Y50.`` keeps X, B and
C). After a changed block, the next motion block that leaves out a word the change altered would
inherit the changed value: the writer restates the programmed value on that block (in the
input's style) and lists it in ``restored``; the pipeline reports it as a ``blend`` change.
Incremental (G91) blocks after a change are rewritten so that they arrive where the input did.
"""

from __future__ import annotations

import math

import numpy as np

from ncfix.nc.chunk import Chunk
from ncfix.nc.dialects import DIALECTS
from ncfix.nc.emit import replace_values, rewrite_line
from ncfix.nc.lexer import code_of, word_spans
from ncfix.nc.modal import MM_PER_INCH
from ncfix.profiles import Profile


class Writer:
    """Keeps what was emitted so that incremental (G91) blocks after a change stay right."""

    def __init__(self, profile: Profile):
        self.profile = profile
        self.dialect = DIALECTS[profile.dialect]
        kin = profile.kinematics
        self.letters = kin.letters
        self.vector_letters = kin.orientation_letters if profile.is_vector else ()
        self.emitted: np.ndarray | None = None  # last motion block's words as written
        self.programmed: np.ndarray | None = None  # ... and as the input had them
        self.restored: list[int] = []  # lines of the last rendered chunk rewritten only to restate words

    def render(self, chunk: Chunk) -> bytes:
        self.restored = []
        moving = np.flatnonzero(chunk.motion >= 0)
        drifted = self.emitted is not None and not np.array_equal(self.emitted, self.programmed, equal_nan=True)
        if not chunk.new_words and not chunk.new_text and not drifted:
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
        text = self._moved_line(chunk, i)
        texts = chunk.new_text.get(i)
        if texts:
            text = replace_values(text if text is not None else chunk.lines[i].decode("latin-1"), self.profile, texts)
        return text

    def _moved_line(self, chunk: Chunk, i: int) -> str | None:
        words = chunk.words[i]
        target = chunk.new_words.get(i, words)
        previous_emitted, previous_programmed = self.emitted, self.programmed
        self.emitted, self.programmed = np.array(target, dtype=np.float64), words.copy()
        incremental = bool(chunk.incremental[i])
        changed = i in chunk.new_words
        drifted = previous_emitted is not None and not np.array_equal(previous_emitted, previous_programmed,
                                                                        equal_nan=True)
        if not changed and not drifted:
            return None
        values: dict[str, float] = {}
        scale = MM_PER_INCH if chunk.inch[i] else 1.0
        if drifted and not incremental:
            values = self._restated(chunk, i, previous_emitted, previous_programmed, scale)
            if not changed:
                if not values:
                    return None
                if i not in chunk.new_text:  # else reported already (ncfix.correct.extrusion)
                    self.restored.append(i)
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
        if required:  # a block gaining tool-vector words may need another keyword (Klartext L → LN)
            raw = self.dialect.with_vector_keyword(raw)
        return rewrite_line(raw, self.profile, values, required)

    def _restated(self, chunk: Chunk, i: int, emitted: np.ndarray, programmed: np.ndarray, scale: float) -> dict:
        """Words an absolute line leaves out whose carried-over value the output changed: letter →
        the programmed value (program units). A vector profile's block without any vector word
        keeps the previous vector, so all of them are restated; with some, the rest are 0."""
        said = {span.address.upper() for span in word_spans(code_of(chunk.lines[i].decode("latin-1").rstrip("\r\n")))}
        words = chunk.words[i]
        out: dict[str, float] = {}
        vector_said = any(letter in said for letter in self.vector_letters)
        for k, letter in enumerate(self.letters):
            if letter in said or math.isnan(float(words[k])):
                continue
            if letter in self.vector_letters and vector_said:
                continue
            if math.isclose(float(emitted[k]), float(programmed[k]), abs_tol=1e-12):
                continue
            out[letter] = float(words[k]) / (scale if letter in ("X", "Y", "Z") else 1.0)
        if self.vector_letters and any(letter in out for letter in self.vector_letters):
            for k, letter in enumerate(self.letters):
                if letter in self.vector_letters:
                    out[letter] = float(words[k])
        return out
