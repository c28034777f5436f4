"""Modal state: turns each line into a Block that knows where the machine words stand.

Tracks G90/G91, G20/G21 (Siemens G70/G71/G700/G710, Heidenhain ``BEGIN PGM … INCH``),
G0/G1/G2/G3, G93/G94/G95, TCP on/off per profile, extrusion (M82/M83, ``G92 E``), the
deposit codes, and the modal rule of vector words (none → previous vector; some → the missing
ones are 0). On G2/G3, I J K are arc centres, never tool vectors; the arc forms ncfix follows
are listed on ``Interpreter._arc``.
"""

from __future__ import annotations

import math
import re

from ncfix.errors import ProgramError
import numpy as np

from ncfix.nc.block import Block, ModalState
from ncfix.nc.chunk import Chunk
from ncfix.nc.dialects import DIALECTS
from ncfix.nc.lexer import WORD_RE, code_of, parse_number
from ncfix.nc.orientation import BlockWords, foreign_word_error, owned_words, vocabulary
from ncfix.nc.plain import PlainReader
from ncfix.profiles import Profile

NAN = math.nan
MM_PER_INCH = 25.4

# G codes whose axis words are not a move to a workpiece point.
_NON_MOTION_G = {4.0, 10.0, 28.0, 30.0, 53.0, 92.0, 28.1, 30.1, 92.1, 92.2, 92.3}
_MIN_RUN = 8  # shorter runs of plain lines are cheaper one by one than as arrays
# A position farther than this from the origin (mm) is a typo or a unit mistake, not a machine's
# travel: `Y99999999999999999999` would otherwise be checked pitch by pitch (10^20 samples).
TRAVEL_LIMIT_MM = 1.0e6
# Lines read with the numpy plain reader before a run that has not loaded numba switches to the
# compiled one: numba's start (import, compiler target, cached code: about 0.5 s of CPU) costs
# about what the numpy reader spends on this many lines (2-3 µs each, the compiled one 0.2-0.3).
# A short program never pays for numba; a long one pays at most about that much twice.
COMPILED_AFTER_LINES = 200_000
# Words of an arc: centre offsets and radius (Siemens CR=; Klartext CR is a block keyword, no value).
_ARC_WORDS = {"I", "J", "K", "R", "CR"}
# Non-finite values as float() would read them: `Xnan`, `Kinf`, `Xinfinity` (the lexer sees one
# letter run). Longest first, so `XINFINITY` is not read as `XINFINI` + `TY`.
_NON_FINITE = ("INFINITY", "NAN", "INF")
# A number followed by a lower-case exponent (`X1e999`, `I1.5e-05`): what a program printed by
# Python or C looks like; upper case `X1E5` is a compact `X1 E5` and stays two words.
_EXPONENT_RE = re.compile(r"(?<![A-Za-z])([A-Za-z]+)[ \t]*([+\-]?[\d.]+e[+\-]?\d+)")
# Plane code -> index of the axis normal to it, and the plane's two axes (right-handed with it).
_PLANES = {17.0: 2, 18.0: 1, 19.0: 0}
_PLANE_AXES = {2: (0, 1), 1: (2, 0), 0: (1, 2)}
_DR_RE = re.compile(r"\bDR\s*([+-])", re.IGNORECASE)


def _code_key(code: str) -> tuple[str, float | str]:
    """Normalise a profile code: 'G43.4' → ('G', 43.4); 'TRAORI' → ('KW', 'TRAORI')."""
    code = code.strip().upper()
    if " " in code:
        return ("TEXT", code)
    head, tail = code[0], code[1:]
    try:
        return (head, float(tail))
    except ValueError:
        return ("KW", code)


class Interpreter:
    """Feed it lines in order; it returns a :class:`Block` per line (the modal state it tracks:
    the module docstring).

    ``compiled_reader``: read plain lines with the compiled reader (ncfix.nc.plain_jit) from the
    first chunk, for a run that loads numba anyway (a check); otherwise with the numpy reader
    until ``COMPILED_AFTER_LINES`` lines, so a pass-through of a short program never loads numba.
    Both readers give the same blocks (a test runs both over the corpus)."""

    def __init__(self, profile: Profile, source: str = "<stdin>", deposit_codes: tuple[str, str] | None = None,
                 compiled_reader: bool = False):
        self.profile = profile
        self.source = source
        kin = profile.kinematics
        self.letters = kin.letters
        self.nletters = len(kin.letters)
        self.index = {letter: i for i, letter in enumerate(kin.letters)}
        self.vector_letters = set(kin.orientation_letters) if profile.is_vector else set()
        self.linear_index = {self.index["X"], self.index["Y"], self.index["Z"]}
        self.extrusion = profile.extrusion_letter
        self.dialect = dialect = DIALECTS[profile.dialect]
        self._kinds = dialect.block_kinds  # empty: no block keywords (tested per word: a local set)
        self._incremental_prefix = dialect.incremental_prefix
        self._reads_text = dialect.reads_text

        self.words = [NAN] * self.nletters
        if profile.is_vector:  # a vertical tool until the program says otherwise
            for letter, value in zip(kin.orientation_letters, (0.0, 0.0, 1.0)):
                self.words[self.index[letter]] = value
        self.motion: int | None = dialect.initial_motion
        self.incremental = False
        self.inch = False
        self.plane = 2  # G17: arcs in XY
        self.arc_centre_absolute = False  # G90.1 / G91.1
        self.pole: tuple[float, float] | None = None  # the last pole (Klartext CC): X, Y
        self.feed_mode = 94
        self.e_relative = False
        self.e_value = 0.0
        self.tcp = {"always": True, "never": False}.get(profile.tcp, profile.tcp_initial)
        self.tcp_on = [_code_key(c) for c in profile.tcp_on]
        self.tcp_off = [_code_key(c) for c in profile.tcp_off]
        self.deposit_codes = [_code_key(c) for c in deposit_codes] if deposit_codes else None
        self.deposit_on: bool | None = False if deposit_codes else None
        self._last_state: tuple | None = None
        self._snapshot: ModalState | None = None

        # The plain-line reader handles single-letter words of this profile and nothing else.
        kinds = {}
        for letter in kin.letters:
            kinds[letter] = 1 if letter in ("X", "Y", "Z") else (2 if letter in self.vector_letters else 0)
        self._plain_axes = tuple((letter, self.index[letter], kinds[letter]) for letter in kin.letters)
        self._vector_order = tuple(kin.orientation_letters) if profile.is_vector else ()
        self._vector_slot = {letter: i for i, letter in enumerate(self._vector_order)}
        plain_letters = tuple(dict.fromkeys(("N", "G", "F", self.extrusion, *kin.letters)))
        self._plain_cols = {letter: i for i, letter in enumerate(plain_letters)}
        self._plain_axis_cols = [self._plain_cols[letter] for letter in kin.letters]
        self._fast_ok = dialect.plain_words and all(len(letter) == 1 for letter in kin.letters)
        self._plain = PlainReader(plain_letters) if self._fast_ok else None
        self._plain_compiled = False
        self._lines_read = 0
        self._numpy_lines = 0 if compiled_reader else COMPILED_AFTER_LINES  # read before the compiled reader
        # Orientation words of other profiles (ncfix.nc.orientation): an error, never ignored. Plain
        # lines hold only this profile's letters, so only the full reader looks for them.
        self._foreign = BlockWords(vocabulary() - owned_words(profile))

    def _fail(self, lineno: int, message: str, fix: str) -> ProgramError:
        return ProgramError(message, where=f"{self.source}:{lineno}", fix=fix)

    def feed(self, lineno: int, raw: str) -> Block:
        """One line, read in full (the reference reading; :meth:`feed_chunk` agrees with it)."""
        return self._feed(lineno, raw)

    def feed_chunk(self, lines: list[bytes], first_lineno: int) -> Chunk:
        """Consecutive lines: plain ones vectorised (ncfix.nc.plain), the rest one by one."""
        chunk = Chunk.empty(first_lineno, lines, self.nletters)
        n = len(lines)
        if n == 0:
            return chunk
        parse = self._plain_reader().parse(lines) if self._fast_ok else None
        self._lines_read += n
        if parse is None:
            simple = np.zeros(n, dtype=bool)
        else:
            simple = parse.plain | parse.neutral
        start = 0
        for stop in [*np.flatnonzero(~simple).tolist(), n]:
            if stop - start >= _MIN_RUN:
                self._plain_run(parse, chunk, start, stop)
            else:
                for i in range(start, stop):
                    self._store(chunk, i, self._feed(first_lineno + i, lines[i].decode("latin-1")))
            if stop < n:
                self._store(chunk, stop, self._feed(first_lineno + stop, lines[stop].decode("latin-1")))
            start = stop + 1
        return chunk

    def _plain_reader(self) -> PlainReader:
        """The numpy reader, or the compiled one once numba is paid for or worth paying for."""
        if not self._plain_compiled and self._lines_read >= self._numpy_lines:
            from ncfix.nc.plain_jit import PlainReaderJit  # numba loads here, not with the module

            self._plain = PlainReaderJit(self._plain.letters)
            self._plain_compiled = True
        return self._plain

    def _store(self, chunk: Chunk, i: int, block: Block) -> None:
        if block.motion is not None:
            chunk.motion[i] = block.motion
            chunk.words[i] = block.words
        if block.e_delta is not None:
            chunk.e_delta[i] = block.e_delta
        state = block.state
        chunk.tcp[i] = state.tcp
        chunk.inch[i] = state.inch
        chunk.incremental[i] = state.incremental
        chunk.feed_mode[i] = state.feed_mode
        chunk.deposit_on[i] = -1 if state.deposit_on is None else int(state.deposit_on)
        chunk.opaque[i] = block.opaque
        chunk.e_relative[i] = self.e_relative
        if block.arc is not None:
            chunk.arc[i] = block.arc

    def _plain_run(self, parse, chunk: Chunk, a: int, b: int) -> None:
        """Lines a..b-1, all plain or neutral: the modal rules as array operations."""
        values = parse.values[a:b]
        cols = self._plain_cols
        g = values[:, cols["G"]]
        if self.motion not in (0, 1):
            # Axis words before the run's first G0/G1 are read by the full reader.
            has_g = np.flatnonzero(~np.isnan(g))
            head = b - a if len(has_g) == 0 else int(has_g[0])
            axes_before = ~np.isnan(values[:head][:, self._plain_axis_cols]).all(axis=1)
            if axes_before.any():
                cut = a + int(np.flatnonzero(axes_before)[0]) + 1
                for i in range(a, cut):
                    self._store(chunk, i, self._feed(chunk.first_lineno + i, chunk.lines[i].decode("latin-1")))
                if cut < b:
                    self._plain_run(parse, chunk, cut, b)
                return
        motion = _ffill(g, float(self.motion) if self.motion is not None else np.nan)
        m = b - a
        positions = np.empty((m, self.nletters))
        scale = MM_PER_INCH if self.inch else 1.0
        for letter, idx, kind in self._plain_axes:
            if kind == 2:
                continue
            column = values[:, cols[letter]]
            if kind == 1 and scale != 1.0:
                column = column * scale
            if self.incremental:
                positions[:, idx] = self.words[idx] + np.cumsum(np.nan_to_num(column, nan=0.0))
            else:
                positions[:, idx] = _ffill(column, self.words[idx])
            if kind == 1:
                far = np.abs(positions[:, idx]) > TRAVEL_LIMIT_MM
                if far.any():
                    row = int(np.flatnonzero(far)[0])
                    raise self._beyond_travel(chunk.first_lineno + a + row, letter, float(positions[row, idx]))
        if self._vector_order:
            vec_cols = [cols[letter] for letter in self._vector_order]
            comps = values[:, vec_cols]
            given = ~np.isnan(comps).all(axis=1)
            comps = np.where(given[:, None], np.nan_to_num(comps, nan=0.0), np.nan)
            zero = given & (comps == 0.0).all(axis=1)
            if zero.any():
                raise self._zero_vector(chunk.first_lineno + a + int(np.flatnonzero(zero)[0]))
            for j, letter in enumerate(self._vector_order):
                positions[:, self.index[letter]] = _ffill(comps[:, j], self.words[self.index[letter]])
        e = values[:, cols[self.extrusion]]
        has_e = ~np.isnan(e)
        if has_e.any():
            if self.e_relative:
                chunk.e_delta[a:b] = e
                self.e_value += float(np.nansum(e))
            else:
                e_abs = _ffill(e, self.e_value)
                before = np.concatenate(([self.e_value], e_abs[:-1]))
                chunk.e_delta[a:b] = np.where(has_e, e_abs - before, np.nan)
                self.e_value = float(e_abs[-1])
        moved = ~np.isnan(values[:, self._plain_axis_cols]).all(axis=1) & ~np.isnan(motion)
        chunk.motion[a:b] = np.where(moved, motion, -1).astype(np.int8)
        chunk.words[a:b][moved] = positions[moved]
        state = self._state()
        chunk.tcp[a:b] = state.tcp
        chunk.inch[a:b] = state.inch
        chunk.incremental[a:b] = state.incremental
        chunk.feed_mode[a:b] = state.feed_mode
        chunk.deposit_on[a:b] = -1 if state.deposit_on is None else int(state.deposit_on)
        chunk.e_relative[a:b] = self.e_relative
        self.words = positions[-1].tolist()
        last = motion[-1]
        self.motion = None if np.isnan(last) else int(last)

    def _no_exponents_or_infinities(self, lineno: int, code: str, pairs) -> None:
        """``X1e-05`` (a number as Python prints it) is read by a controller as ``X1`` and
        ``E-05``, and ``Xnan`` / ``Kinf`` as unknown words: each would move the machine
        somewhere the CAM did not mean, so each is an error naming the line."""
        m = _EXPONENT_RE.search(code)
        if m is not None:
            word = m.group(0).strip()
            raise self._fail(lineno, f"the {m.group(1).upper()} word '{word}' is written with an exponent, which "
                             f"a controller reads as two words", "write the value as a plain decimal number")
        for _, _, addr, value in pairs:
            upper = addr.upper()
            for tail in _NON_FINITE:
                head = upper[:-len(tail)]
                if upper.endswith(tail) and head and (head in self.index or head == self.extrusion
                                                      or head in _ARC_WORDS):
                    raise self._not_finite(lineno, head, addr[len(head):] + value)

    def _not_finite(self, lineno: int, letter: str, text: str) -> ProgramError:
        """``Xnan``, ``Kinf``, ``X1e999``: float() reads them, no machine can go there."""
        return self._fail(lineno, f"the {letter} word '{letter}{text}' is not a finite number",
                          "correct the value in the program; ncfix never guesses a position")

    def _beyond_travel(self, lineno: int, letter: str, value_mm: float) -> ProgramError:
        return self._fail(lineno, f"the {letter} position {value_mm:.6g} mm is beyond any machine's travel "
                          f"(more than {TRAVEL_LIMIT_MM / 1e6:g} km from the origin)",
                          "correct the value in the program, or its units: G20 inches, G21 mm")

    def _zero_vector(self, lineno: int) -> ProgramError:
        return self._fail(lineno, "the tool vector is (0, 0, 0)", "give a non-zero vector; a vertical tool is 0, 0, 1")

    def _feed(self, lineno: int, raw: str) -> Block:
        block = Block(lineno, raw, self._state())
        code = code_of(raw.rstrip("\r\n"))
        pairs = WORD_RE.findall(code)
        if not pairs:
            return block
        if "e" in code or "n" in code or "N" in code:
            self._no_exponents_or_infinities(lineno, code, pairs)

        given: dict[int, str | None] = {}  # None: an expression ncfix cannot evaluate
        gs: list[float] = []
        codes: list[tuple[str, float | str]] = []
        e_text: str | None = None
        opaque = False
        kind = None  # the block keyword of a dialect that has them (Klartext L, LN, C, CC ...)
        kinds = self._kinds
        prefix = self._incremental_prefix
        incremental_words: set[int] = set()  # words incremental on this block only (Klartext IX)
        arc_words: dict[str, str] = {}
        suspects = self._foreign.suspects(pairs)
        for aname, avalue, addr, value in pairs:
            if aname:
                addr, value = aname.upper(), avalue
                if value and not _is_plain_number(value):
                    if addr in self.index:
                        opaque = True
                        given[self.index[addr]] = None
                    if addr in _ARC_WORDS:
                        arc_words[addr] = ""  # an expression: the arc cannot be followed
                    continue
            else:
                addr = addr.upper()
            if addr in _ARC_WORDS and value:
                arc_words[addr] = value
                if _is_plain_number(value) and not math.isfinite(parse_number(value)):
                    raise self._not_finite(lineno, addr, value)
            if addr == "G":
                try:
                    gs.append(parse_number(value))
                except ValueError:
                    pass
                continue
            if kinds and kind is None and not value and addr in kinds:
                kind = addr
                continue
            idx = self.index.get(addr)
            if idx is None and prefix and len(addr) == 2 and addr[0] == prefix and addr[1:] in self.index:
                idx = self.index[addr[1:]]
                incremental_words.add(idx)
            if idx is not None:
                if value and value.lstrip("+- \t")[:1] in ("#", "[", "Q"):
                    opaque = True
                    given[idx] = None
                else:
                    given[idx] = value
                continue
            if addr == self.extrusion:
                e_text = value
                continue
            if value:
                try:
                    codes.append((addr, parse_number(value)))
                except ValueError:
                    pass
            else:
                codes.append(("KW", addr))

        # -- modal codes, in the order a controller applies them ---------------------------
        g92 = False
        non_motion = False
        for g in gs:
            if g in (0.0, 1.0, 2.0, 3.0):
                self.motion = int(g)
            elif g == 80.0:
                self.motion = None
            elif 81.0 <= g <= 89.0:
                self.motion = None  # canned cycles: not re-oriented by ncfix
            elif g == 90.0:
                self.incremental = False
            elif g == 91.0:
                self.incremental = True
            elif g in (20.0, 70.0, 700.0):
                self.inch = True
            elif g in (21.0, 71.0, 710.0):
                self.inch = False
            elif g in (93.0, 94.0, 95.0):
                self.feed_mode = int(g)
            elif g in _PLANES:
                self.plane = _PLANES[g]
            elif g == 90.1:
                self.arc_centre_absolute = True
            elif g == 91.1:
                self.arc_centre_absolute = False
            if g == 92.0:
                g92 = True
            if g in _NON_MOTION_G:
                non_motion = True
            self._switch(("G", g))
        for key in codes:
            if key == ("M", 82.0):
                self.e_relative = False
            elif key == ("M", 83.0):
                self.e_relative = True
            self._switch(key)
        if self._reads_text:
            self.inch, text, motion, no_move = self.dialect.read_text(code.upper(), kind, self.inch)
            if text is not None:
                self._switch(("TEXT", text))
            if motion is not None:
                self.motion = motion
            non_motion = non_motion or no_move
        if suspects:
            ms = [number for letter, number in codes if letter == "M"]
            found = self._foreign.orienting(suspects, None if non_motion else self.motion, gs, ms, kind)
            if found:
                raise foreign_word_error(*found[0], self.profile, f"{self.source}:{lineno}")

        # -- extrusion ----------------------------------------------------------------------
        if e_text is not None:
            try:
                e = parse_number(e_text)
            except ValueError:
                e = None
            if e is not None and not math.isfinite(e):
                raise self._not_finite(lineno, self.extrusion, e_text)
            if e is not None:
                if g92:
                    self.e_value = e
                elif self.e_relative:
                    block.e_delta = e
                    self.e_value += e
                else:
                    block.e_delta = e - self.e_value
                    self.e_value = e

        # -- axis words ----------------------------------------------------------------------
        start = [self.words[self.index[a]] for a in "XYZ"]  # a copy: the words change below
        if given:
            arc = self.motion in (2, 3)
            vector_given = False
            new = self.words
            scale = MM_PER_INCH if self.inch else 1.0
            for idx, text in given.items():
                letter = self.letters[idx]
                is_vector = letter in self.vector_letters
                if is_vector and arc and letter in _ARC_WORDS:
                    continue  # I J K on an arc are its centre (Siemens A3= B3= C3= orient it)
                if text is None:
                    new[idx] = NAN
                    continue
                try:
                    value = parse_number(text)
                except ValueError:
                    if self.motion is not None and not non_motion:
                        raise self._fail(lineno, f"the {letter} word '{letter}{text}' is not a number",
                                         "correct the value in the program; ncfix never guesses a position") from None
                    continue
                if not math.isfinite(value):
                    raise self._not_finite(lineno, letter, text)
                if is_vector:
                    vector_given = True
                    continue
                if idx in self.linear_index:
                    value *= scale
                if g92:
                    new[idx] = value
                elif self.incremental or idx in incremental_words:
                    new[idx] = new[idx] + value
                else:
                    new[idx] = value
            for idx in given:
                if idx in self.linear_index and abs(new[idx]) > TRAVEL_LIMIT_MM:
                    raise self._beyond_travel(lineno, self.letters[idx], new[idx])
            if vector_given:
                comps = []
                for letter in self.profile.kinematics.orientation_letters:
                    idx = self.index[letter]
                    text = given.get(idx, "")
                    comps.append(NAN if text is None else parse_number(text) if text else 0.0)
                if comps[0] == 0.0 and comps[1] == 0.0 and comps[2] == 0.0:
                    raise self._zero_vector(lineno)
                for letter, value in zip(self.profile.kinematics.orientation_letters, comps):
                    new[self.index[letter]] = value
            if kind is not None and kind == self.dialect.pole_kind:  # the pole of later arcs; no move
                end = [new[self.index[a]] for a in "XY"]
                self.pole = (end[0], end[1]) if all(math.isfinite(v) for v in end) else None
                for a, v in zip("XYZ", start):
                    new[self.index[a]] = v
            elif g92 or non_motion:
                if not g92:
                    for idx in given:  # homing / machine-coordinate moves: position now unknown
                        new[idx] = NAN
            elif self.motion is not None:
                block.motion = self.motion
                if self.motion in (2, 3) or kind in self.dialect.arc_kinds:
                    for addr, text in arc_words.items():  # "": an expression, the arc is not followed
                        if text and not _is_plain_number(text):
                            raise self._fail(lineno, f"the {addr} word '{addr}{text.strip()}' is not a number",
                                             "correct the arc's centre or radius in the program")
                    block.arc = self._arc(start, [new[self.index[a]] for a in "XYZ"], arc_words, code,
                                          kind)
        block.opaque = opaque
        block.state = self._state()
        if block.motion is not None:
            block.words = tuple(self.words)
        return block

    def _arc(self, start: list[float], end: list[float], words: dict[str, str], code: str,
             kind: str | None) -> tuple[float, float, float, int, int] | None:
        """The arc of a G2/G3 (Heidenhain C/CR) block from ``start`` to ``end`` (mm), or None when
        ncfix cannot follow it.

        Followed (``Block.arc``: centre, normal axis, sense): G17/G18/G19 planes; the centre from
        I J K (incremental from the start point, or absolute after G90.1) or from the radius (R,
        Siemens CR=; negative for more than 180°); Heidenhain ``C`` about the last ``CC`` pole and
        ``CR`` with R, both with DR+/DR-. Other forms (Siemens ``I=AC(..)``, Heidenhain CT/CP, an
        arc without a centre or radius) give None: they are checked along their chord and the
        report says so."""
        if not all(math.isfinite(v) for v in (*start, *end)) or "" in words.values():
            return None
        scale = MM_PER_INCH if self.inch else 1.0
        if self.dialect.arc_sense_word:
            axis = 2
            dr = _DR_RE.search(code)
            if dr is None:
                return None
            sense = 1 if dr.group(1) == "+" else -1
        else:
            axis = self.plane
            sense = 1 if self.motion == 3 else -1
        a, b = _PLANE_AXES[axis]
        centre = list(start)
        if kind is not None and kind == self.dialect.pole_arc:
            if self.pole is None:
                return None
            centre[0], centre[1] = self.pole
        elif not self.dialect.arc_sense_word and any(letter in words for letter in "IJK"):
            for k, letter in zip((a, b), ("IJK"[a], "IJK"[b])):
                offset = parse_number(words[letter]) * scale if letter in words else 0.0
                centre[k] = offset if self.arc_centre_absolute and letter in words else start[k] + offset
        elif ("R" in words or "CR" in words) and (kind is None or kind == self.dialect.radius_arc):
            radius = parse_number(words.get("CR", words.get("R", "0"))) * scale
            da, db = end[a] - start[a], end[b] - start[b]
            chord = math.hypot(da, db)
            if chord == 0.0 or abs(radius) < 0.5 * chord - 1e-6:
                return None
            rise = math.sqrt(max(radius * radius - 0.25 * chord * chord, 0.0))
            # Left of the chord (seen from +axis) for a counter-clockwise arc up to 180°.
            side = sense * (1.0 if radius > 0 else -1.0)
            centre[a] = 0.5 * (start[a] + end[a]) - side * rise * db / chord
            centre[b] = 0.5 * (start[b] + end[b]) + side * rise * da / chord
        else:
            return None
        return (centre[0], centre[1], centre[2], axis, sense)

    def _state(self) -> ModalState:
        """The current modal settings, as one object shared until a setting changes."""
        current = (self.tcp, self.inch, self.incremental, self.feed_mode, self.deposit_on)
        if current != self._last_state:
            self._last_state = current
            self._snapshot = ModalState(*current)
        return self._snapshot

    def _switch(self, key: tuple[str, float | str]) -> None:
        if self.profile.tcp == "program":
            if _matches(key, self.tcp_off):
                self.tcp = False
            elif _matches(key, self.tcp_on):
                self.tcp = True
        if self.deposit_codes is not None:
            if key == self.deposit_codes[0]:
                self.deposit_on = True
            elif key == self.deposit_codes[1]:
                self.deposit_on = False


def _ffill(column: np.ndarray, initial: float) -> np.ndarray:
    """Carry the last non-NaN value forward; ``initial`` before the first one."""
    present = ~np.isnan(column)
    index = np.where(present, np.arange(len(column)), -1)
    np.maximum.accumulate(index, out=index)
    return np.where(index >= 0, column[np.maximum(index, 0)], initial)


def _matches(key: tuple[str, float | str], codes: list[tuple[str, float | str]]) -> bool:
    if key[0] == "TEXT":  # Heidenhain `FUNCTION TCPM F TCP AXIS POS` starts with the code
        return any(c[0] == "TEXT" and str(key[1]).startswith(str(c[1])) for c in codes)
    return key in codes


def _is_plain_number(text: str) -> bool:
    try:
        parse_number(text)
    except ValueError:
        return False
    return True
