"""The plain-line reader compiled with numba: one pass over the bytes of a chunk.

Same contract and same results as :class:`ncfix.nc.plain.PlainReader` (a test runs both over the
corpus); compiled once and cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ncfix.nc.plain import MAX_DIGITS, PlainParse, PlainReader


_POW10 = 10.0 ** np.arange(MAX_DIGITS + 1)


def _scan(data, starts, ends, column, g_column, pow10, plain, neutral, values):  # pragma: no cover - compiled
    n = starts.shape[0]
    for line in range(n):
        a = starts[line]
        b = ends[line]
        # neutral: blank, `; …`, or a single `( … )`
        first = -1
        last = -1
        opens = 0
        closes = 0
        for i in range(a, b):
            ch = data[i]
            if ch == 40:
                opens += 1
            elif ch == 41:
                closes += 1
            if ch != 32 and ch != 9 and ch != 10 and ch != 13:
                if first < 0:
                    first = ch
                last = ch
        if first < 0 or first == 59 or (first == 40 and last == 41 and opens == 1 and closes == 1):
            neutral[line] = True
            continue
        ok = True
        i = a
        while i < b and ok:
            ch = data[i]
            if ch == 32 or ch == 9 or ch == 10 or ch == 13:
                i += 1
                continue
            if ch < 65 or ch > 90 or column[ch] < 0:
                ok = False
                break
            col = column[ch]
            if not np.isnan(values[line, col]):
                ok = False  # the same word twice
                break
            i += 1
            negative = False
            if i < b and (data[i] == 43 or data[i] == 45):
                negative = data[i] == 45
                i += 1
            mantissa = 0.0
            digits = 0
            frac = 0
            dots = 0
            while i < b:
                ch = data[i]
                if 48 <= ch <= 57:
                    mantissa = mantissa * 10.0 + (ch - 48)
                    digits += 1
                    if dots:
                        frac += 1
                elif ch == 46:
                    dots += 1
                elif ch == 43 or ch == 45:
                    dots = 99  # a sign inside a number
                else:
                    break
                i += 1
            if digits == 0 or digits > 15 or dots > 1:
                ok = False
                break
            value = mantissa / pow10[frac]
            values[line, col] = -value if negative else value
        if ok:
            g = values[line, g_column]
            if not np.isnan(g) and g != 0.0 and g != 1.0:
                ok = False
        plain[line] = ok


class PlainReaderJit(PlainReader):
    """Drop-in for PlainReader (see the module docstring)."""

    def __init__(self, letters: tuple[str, ...]):
        super().__init__(letters)
        self._scan = _compiled()

    def parse(self, lines: list[bytes]) -> PlainParse:
        n = len(lines)
        lens = np.fromiter(map(len, lines), dtype=np.int64, count=n)
        data = np.frombuffer(b"".join(lines), dtype=np.uint8)
        starts = np.zeros(n, dtype=np.int64)
        np.cumsum(lens[:-1], out=starts[1:])
        plain = np.zeros(n, dtype=bool)
        neutral = np.zeros(n, dtype=bool)
        values = np.full((n, len(self.letters)), np.nan)
        self._scan(data, starts, starts + lens, self.column, self.g_column, _POW10, plain, neutral, values)
        values[~plain] = np.nan
        return PlainParse(plain=plain, neutral=neutral, values=values)


_COMPILED = None


def _compiled():
    global _COMPILED
    if _COMPILED is None:
        _COMPILED = njit(cache=True, nogil=True)(_scan)
    return _COMPILED
