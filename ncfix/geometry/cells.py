"""Integer cell keys as one int64 each, in the order of their rows.

``np.unique(keys, axis=0)`` on (n, 3) int64 rows sorts a structured view of them, an order of
magnitude slower than sorting plain int64; the deposit's hot paths group thousands of beads into
cells many times a second. ``flat_keys`` maps each row to one int64 that sorts exactly as the rows
sort lexicographically, so ``np.unique`` on it gives the same cells in the same order.
"""

from __future__ import annotations

import numpy as np

# Above this many cells in the rows' bounding box the flat key could overflow: keep the rows.
_MAX_SPAN = 1 << 62


def flat_keys(rows: np.ndarray) -> np.ndarray | None:
    """(n,) int64 keys of (n, 3) int64 rows, ordered as the rows are lexicographically, or None
    when their bounding box is too large for one int64 (then sort the rows themselves)."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, 3)
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    lo = rows.min(axis=0)
    span = [int(v) + 1 for v in rows.max(axis=0) - lo]
    if span[0] * span[1] * span[2] >= _MAX_SPAN:
        return None
    rel = rows - lo
    return (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]


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
    return np.sort(np.unique(key, return_index=True)[1])
