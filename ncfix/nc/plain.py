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

    Each byte gets a class from one table lookup; a line with a byte of no plain class is either
    neutral (its stripped text is tested: such lines are few) or left to the full reader. The
    values are read on a (bytes, words) array of the bytes after each letter, as wide as the
    longest value, so past a few dense passes over the bytes the cost follows the words.
    """

    def __init__(self, letters: tuple[str, ...]):
        self.letters = letters
        self.column = np.full(256, -1, dtype=np.int64)
        for i, letter in enumerate(letters):
            self.column[ord(letter)] = i
        self.g_column = letters.index("G")
        self.kind = _KINDS.copy()
        self.kind[self.column >= 0] = _LETTER

    def parse(self, lines: list[bytes]) -> PlainParse:
        n = len(lines)
        ncol = len(self.letters)
        lens = np.fromiter(map(len, lines), dtype=np.int64, count=n)
        ends = np.cumsum(lens)
        starts = ends - lens
        data = np.frombuffer(b"".join(lines), dtype=np.uint8)
        kind = self.kind[data]

        # -- lines with a byte no plain line holds: neutral (`; …`, one `( … )`) or the full reader's --
        other = _per_line(kind == _OTHER, starts, lens) > 0
        blank = _per_line(kind != _BLANK, starts, lens) == 0
        neutral = blank.copy()
        for i in np.flatnonzero(other).tolist():
            text = lines[i].strip(b" \t\r\n")
            neutral[i] = text[0] == 59 or (text[0] == 40 and text[-1] == 41 and text.count(b"(") == 1
                                           and text.count(b")") == 1)
        candidate = ~(other | blank)

        # -- the words of the other lines: a letter of the profile, then its number ------------------
        numeric = (kind >= _DIGIT) & (kind <= _SIGN)
        letter_pos = np.flatnonzero(kind == _LETTER)
        tok_line = np.searchsorted(ends, letter_pos, side="right")
        keep = candidate[tok_line]
        letter_pos, tok_line = letter_pos[keep], tok_line[keep]
        col = self.column[data[letter_pos]]
        stops = np.append(np.flatnonzero(~numeric), len(data))  # where a number ends
        v_start = letter_pos + 1
        length = np.minimum(stops[np.searchsorted(stops, v_start)], ends[tok_line]) - v_start
        # A number that does not follow a letter (`N10 5`): its bytes are in no word's value.
        bad = np.zeros(n, dtype=bool)
        bad[candidate] = (_per_line(numeric, starts, lens)[candidate]
                          != np.bincount(tok_line, weights=length, minlength=n)[candidate])

        # a value: one optional sign in front, at most one dot, 1..MAX_DIGITS digits; read on a
        # (bytes, words) array of the bytes after each letter, as far as the longest valid value
        width = min(int(length.max(initial=0)), MAX_VALUE_BYTES)
        window = np.append(data, _PAD)[v_start + np.arange(width)[:, None]]
        wkind = self.kind[window]
        in_value = np.arange(width)[:, None] < length
        is_digit = (wkind == _DIGIT) & in_value
        is_dot = (wkind == _DOT) & in_value
        ndigits = is_digit.sum(axis=0)
        ndots = is_dot.sum(axis=0)
        inner_signs = ((wkind[1:] == _SIGN) & in_value[1:]).any(axis=0)
        bad_tok = ((length > MAX_VALUE_BYTES) | (ndots > 1) | (ndigits == 0) | (ndigits > MAX_DIGITS)
                   | inner_signs)
        bad |= np.bincount(tok_line[bad_tok], minlength=n) > 0

        # value = ± (integer of the digits) / 10**(digits after the dot): the integer is exact
        # (below 2**53), then one correctly rounded division, as float() gives
        digits = np.zeros(len(v_start))
        frac = np.zeros(len(v_start), dtype=np.int64)
        after_dot = np.zeros(len(v_start), dtype=bool)
        for k in range(width):
            digits = np.where(is_digit[k], digits * 10.0 + (window[k] - 48.0), digits)
            after_dot |= is_dot[k]
            frac += is_digit[k] & after_dot
        value = digits / _POW10[np.clip(frac, 0, MAX_DIGITS)]
        if width:
            value = np.where(window[0] == 45, -value, value)

        cell = tok_line * ncol + col
        repeats = np.bincount(cell, minlength=n * ncol)[cell] > 1
        bad |= np.bincount(tok_line[repeats], minlength=n) > 0

        values = np.full((n, ncol), np.nan)
        values[tok_line, col] = value
        g = values[:, self.g_column]
        bad |= ~np.isnan(g) & (g != 0.0) & (g != 1.0)
        plain = candidate & ~bad
        values[~plain] = np.nan
        return PlainParse(plain=plain, neutral=neutral, values=values)


def _per_line(mask: np.ndarray, starts: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """How many bytes of each line ``mask`` marks (one pass; an empty line counts none)."""
    counts = np.add.reduceat(np.append(mask, False), starts, dtype=np.int64)
    counts[lens == 0] = 0
    return counts


# Byte classes: what may stand in a plain line (a letter of the profile is set per reader).
_OTHER, _BLANK, _DIGIT, _DOT, _SIGN, _LETTER = range(6)
_KINDS = np.full(256, _OTHER, dtype=np.uint8)
_KINDS[[32, 9, 10, 13]] = _BLANK
_KINDS[48:58] = _DIGIT
_KINDS[46] = _DOT
_KINDS[[43, 45]] = _SIGN
MAX_VALUE_BYTES = MAX_DIGITS + 2  # a sign, the digits and a dot
_PAD = np.full(MAX_VALUE_BYTES, 32, dtype=np.uint8)  # read past the last byte: not a number
_POW10 = 10.0 ** np.arange(MAX_DIGITS + 1)
