"""Integer cell keys as one int64 each, in the order of their rows.

``np.unique(keys, axis=0)`` on (n, 3) int64 rows sorts a structured view of them, an order of
magnitude slower than sorting plain int64; the deposit's hot paths group thousands of beads into
cells many times a second. ``flat_keys`` maps each row to one int64 that sorts exactly as the rows
sort lexicographically, so ``np.unique`` on it gives the same cells in the same order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Above this many cells in the rows' bounding box the flat key could overflow: keep the rows.
_MAX_SPAN = 1 << 62


def flat_keys(rows: np.ndarray) -> np.ndarray | None:
    """(n,) int64 keys of (n, 3) int64 rows, ordered as the rows are lexicographically, or None
    when their bounding box is too large for one int64 (then sort the rows themselves)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64).reshape(-1, 3)
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    lo, hi = _box(rows)
    span = [int(b) - int(a) + 1 for a, b in zip(lo, hi)]
    if span[0] * span[1] * span[2] >= _MAX_SPAN:
        return None
    return _keys(rows, lo, span[1], span[2])


def _box(rows):  # pragma: no cover - compiled
    """The rows' smallest and largest value in each column (one pass; numpy's axis-0 min and max
    walk the columns with a stride, five times slower on these short arrays)."""
    lo = rows[0].copy()
    hi = rows[0].copy()
    for i in range(1, rows.shape[0]):
        for j in range(3):
            v = rows[i, j]
            if v < lo[j]:
                lo[j] = v
            elif v > hi[j]:
                hi[j] = v
    return lo, hi


def _keys(rows, lo, s1, s2):  # pragma: no cover - compiled
    out = np.empty(rows.shape[0], np.int64)
    for i in range(rows.shape[0]):
        out[i] = ((rows[i, 0] - lo[0]) * s1 + (rows[i, 1] - lo[1])) * s2 + (rows[i, 2] - lo[2])
    return out


# Fibonacci hashing's multiplier (2^64 / golden ratio, as a signed int64): spreads nearby keys.
_HASH = -7046029254386353131


def _first_of_keys(key):  # pragma: no cover - compiled
    """Indices (ascending) of the first occurrence of each distinct key, in one pass: a table of
    first indices, open addressing with linear probing (np.unique would sort the keys)."""
    n = key.shape[0]
    size = 16
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    out = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        v = key[i]
        h = ((v * _HASH) >> 20) & mask
        while True:
            j = table[h]
            if j < 0:
                table[h] = i
                out[k] = i
                k += 1
                break
            if key[j] == v:
                break
            h = (h + 1) & mask
    return out[:k]


_box = njit(cache=True, nogil=True)(_box)
_keys = njit(cache=True, nogil=True)(_keys)
_first_of_keys = njit(cache=True, nogil=True)(_first_of_keys)


def group_cells(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells of (n, 3) int64 rows: (cell of each row (n,), rows ordered by cell, stably (n,),
    rows per cell (k,)); cells in lexicographic order, as ``np.unique(rows, axis=0)`` numbers them."""
    key = flat_keys(rows)
    if key is None:
        _, cell_of, counts = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
        cell_of = cell_of.reshape(-1)
        return cell_of, np.argsort(cell_of, kind="stable"), counts
    members = np.argsort(key, kind="stable")
    ordered = key[members]
    new = np.empty(len(key), dtype=bool)
    new[:1] = True
    new[1:] = ordered[1:] != ordered[:-1]
    cell_of = np.empty(len(key), dtype=np.int64)
    cell_of[members] = np.cumsum(new) - 1
    starts = np.flatnonzero(new)
    counts = np.diff(np.append(starts, len(key)))
    return cell_of, members, counts


def first_of_each_cell(rows: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the first row of each distinct cell of (n, 3) int64 rows."""
    key = flat_keys(rows)
    if key is None:
        return np.sort(np.unique(rows, axis=0, return_index=True)[1])
    return _first_of_keys(key)
