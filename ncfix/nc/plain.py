"""Vectorised reading of plain lines: thousands of `G1 X.. Y.. Z.. A.. C.. F..` lines per numpy pass.

A *plain* line holds only upper-case single-letter words of the profile (and N, G, F, the
extrusion letter), each followed directly by a decimal number, separated by blanks; `G` may be
only 0 or 1. A line that is only a comment (`; …` or one `( … )`) or blank is *neutral*. Every
other line is left to the full reader (ncfix.nc.modal), which reads plain lines the same way: a
test runs both over every corpus program.

Numbers are converted exactly as ``float()`` does: the digits form an integer below 2**53 and one
correctly rounded division by a power of ten gives the nearest double.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_DIGITS = 15  # beyond this the integer of digits may not be exact in float64


@dataclass
class PlainParse:
    """Per line of a chunk: ``plain`` (words read here), ``neutral`` (no words), and the values.

    values : (n, len(letters)) float64, NaN where the line has no such word.
    """

    plain: np.ndarray
    neutral: np.ndarray
    values: np.ndarray


class PlainReader:
    """Reads the plain lines of a chunk with array operations; see the module docstring.

    Dense passes over the characters are comparisons and ``flatnonzero`` (cheap); everything
    else works on the sparse positions of letters, dots, signs and run boundaries.
    """

    def __init__(self, letters: tuple[str, ...]):
        self.letters = letters
        self.column = np.full(256, -1, dtype=np.int64)
        for i, letter in enumerate(letters):
            self.column[ord(letter)] = i
        self.g_column = letters.index("G")

    def parse(self, lines: list[bytes]) -> PlainParse:
        n = len(lines)
        ncol = len(self.letters)
        lens = np.fromiter(map(len, lines), dtype=np.int64, count=n)
        data = np.frombuffer(b"".join(lines), dtype=np.uint8)
        size = len(data)
        starts = np.zeros(n, dtype=np.int64)
        np.cumsum(lens[:-1], out=starts[1:])
        ends = starts + lens

        def line_of(positions: np.ndarray) -> np.ndarray:
            return np.searchsorted(starts, positions, side="right") - 1

        def count_per_line(positions: np.ndarray) -> np.ndarray:
            return np.bincount(line_of(positions), minlength=n)

        is_digit = (data >= 48) & (data <= 57)
        is_upper = (data >= 65) & (data <= 90)
        blank = (data == 32) | (data == 9)
        eol = (data == 10) | (data == 13)
        is_dot = data == 46
        is_sign = (data == 43) | (data == 45)
        is_num = is_digit | is_dot | is_sign

        # -- neutral lines: blank, `; …`, or a single `( … )` ----------------------------------
        solid = np.flatnonzero(~(blank | eol))
        first_i = np.searchsorted(solid, starts)
        last_i = np.searchsorted(solid, ends) - 1
        has_solid = first_i <= last_i
        solid_ch = np.append(data[solid], 0)  # a sentinel for lines with nothing solid
        first_ch = np.where(has_solid, solid_ch[np.minimum(first_i, len(solid))], 0)
        last_ch = np.where(has_solid, solid_ch[np.where(has_solid, last_i, len(solid))], 0)
        opens = count_per_line(np.flatnonzero(data == 40))
        closes = count_per_line(np.flatnonzero(data == 41))
        semis = count_per_line(np.flatnonzero(data == 59))
        neutral = ~has_solid | (first_ch == 59) | ((first_ch == 40) & (last_ch == 41) & (opens == 1) & (closes == 1))

        # -- plain lines: blanks, numbers and the profile's letters, nothing else ----------------
        others = np.flatnonzero(~(is_num | is_upper | blank | eol))
        bad = (count_per_line(others) > 0) | (semis > 0)
        letter_pos = np.flatnonzero(is_upper)
        col = self.column[data[letter_pos]]
        bad |= count_per_line(letter_pos[col < 0]) > 0
        tok_line = line_of(letter_pos)
        keep = ~neutral[tok_line] & (col >= 0)
        letter_pos, tok_line, col = letter_pos[keep], tok_line[keep], col[keep]
        ntok = len(letter_pos)

        # runs of number characters; each must start right after a letter (its word)
        edge = np.flatnonzero(is_num[1:] != is_num[:-1]) + 1
        run_start = np.concatenate(([0] if size and is_num[0] else [], edge[is_num[edge]])).astype(np.int64)
        run_end = np.concatenate((edge[~is_num[edge]], [size] if size and is_num[-1] else [])).astype(np.int64)
        orphan = run_start[(run_start == 0) | ~is_upper[np.maximum(run_start - 1, 0)]]
        bad |= count_per_line(orphan) > 0
        v_start = letter_pos + 1
        run_start_s = np.append(run_start, size + 1)  # sentinels: no run starts there
        run_end_s = np.append(run_end, size + 1)
        k = np.searchsorted(run_start_s, v_start)
        has_value = run_start_s[k] == v_start
        v_end = np.where(has_value, run_end_s[k], v_start)
        bad |= np.bincount(tok_line[~has_value], minlength=n) > 0

        # a value: one optional sign in front, at most one dot, 1..MAX_DIGITS digits
        digit_pos = np.flatnonzero(is_digit)
        dot_pos = np.flatnonzero(is_dot)
        sign_pos = np.flatnonzero(is_sign)
        first_digit = np.searchsorted(digit_pos, v_start)
        ndigits = np.searchsorted(digit_pos, v_end) - first_digit
        first_dot = np.searchsorted(dot_pos, v_start)
        ndots = np.searchsorted(dot_pos, v_end) - first_dot
        inner_signs = np.searchsorted(sign_pos, v_end) - np.searchsorted(sign_pos, v_start + 1)
        bad_tok = (ndots > 1) | (ndigits == 0) | (ndigits > MAX_DIGITS) | (inner_signs > 0)
        bad |= np.bincount(tok_line[bad_tok], minlength=n) > 0

        # value = ± (integer of the digits) / 10**(digits after the dot), words that are well formed
        good = np.flatnonzero(~bad_tok)
        counts = ndigits[good]
        seg_start = np.cumsum(counts) - counts
        owner = np.repeat(np.arange(len(good)), counts)
        used = first_digit[good][owner] + (np.arange(len(owner)) - seg_start[owner])
        power = counts[owner] - (np.arange(len(owner)) - seg_start[owner]) - 1
        terms = (data[digit_pos[used]] - 48.0) * _POW10[power]
        value = np.zeros(ntok)
        if len(good):
            value[good] = np.add.reduceat(terms, seg_start)
        dot_at = np.append(dot_pos, size)[first_dot]
        frac = np.where(ndots == 1, np.searchsorted(digit_pos, v_end) - np.searchsorted(digit_pos, dot_at), 0)
        value = value / _POW10[np.clip(frac, 0, MAX_DIGITS)]
        sign_char = np.append(data, 0)[v_start]
        value = np.where(sign_char == 45, -value, value)

        cell = tok_line * ncol + col
        repeats = np.bincount(cell, minlength=n * ncol)[cell] > 1
        bad |= np.bincount(tok_line[repeats], minlength=n) > 0

        values = np.full((n, ncol), np.nan)
        values[tok_line, col] = value
        g = values[:, self.g_column]
        bad |= ~np.isnan(g) & (g != 0.0) & (g != 1.0)
        plain = ~bad & ~neutral
        return PlainParse(plain=plain, neutral=neutral, values=values)


_POW10 = 10.0 ** np.arange(MAX_DIGITS + 1)
