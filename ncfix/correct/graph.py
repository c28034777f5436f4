"""Orientation graph + shortest path (seed steps 1–3, after Nishat et al.), as a layered dynamic program.

Levels are consecutive blocks of a collision episode with ramps before and after; vertices are the
free candidate orientations of each block; an edge joins consecutive levels where the angle between
the two orientations is at most θ (--max-step); its weight is that angle plus a penalty on the
deviation of the target from the programmed orientation (as Fang et al. and Plakhotnik et al. do).
Both end levels are anchored to the programmed orientation. On a layered DAG, Dijkstra's result
equals the level-by-level minimum computed here, all candidates of a level at once.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# Weight of the deviation from the programmed orientation against the angular variation. Small:
# the path stays close to what the CAM system programmed, and smoothness still dominates.
DEVIATION_WEIGHT = 0.2


def cheapest_path(candidates: np.ndarray, free: np.ndarray, programmed: np.ndarray, max_step_deg: float,
                  deviation_weight: float = DEVIATION_WEIGHT, neighbours: int = 48) -> np.ndarray | None:
    """The cheapest sequence of free candidates from the first level's programmed orientation to the last's.

    candidates : (L, K, 3) unit vectors per level; free : (L, K) bool; programmed : (L, 3).
    Returns the chosen index per level (L,) int, or None when no path keeps every step ≤ θ.
    Levels 0 and L-1 are anchored: only candidate 0 (the programmed orientation) is allowed there.
    Edges are found with a k-d tree (the ``neighbours`` nearest within θ), so a level costs
    O(K·neighbours), not O(K²).
    """
    levels, k = free.shape
    allowed = free.copy()
    allowed[0, 1:] = False
    allowed[-1, 1:] = False
    chord = 2.0 * np.sin(np.radians(max_step_deg) / 2.0) * (1.0 + 1e-12)
    deviation = np.degrees(np.arccos(np.clip(np.einsum("lkj,lj->lk", candidates, programmed), -1.0, 1.0)))
    cost = np.where(allowed[0], 0.0, np.inf)
    back = np.zeros((levels, k), dtype=np.int64)
    width = min(k, neighbours)
    for level in range(1, levels):
        source = np.flatnonzero(np.isfinite(cost))
        if len(source) == 0:
            return None
        tree = cKDTree(candidates[level - 1][source])
        dist, idx = tree.query(candidates[level], k=min(width, len(source)), distance_upper_bound=chord)
        dist, idx = dist.reshape(k, -1), idx.reshape(k, -1)
        found = np.isfinite(dist)
        prev = source[np.where(found, idx, 0)]
        step = np.degrees(2.0 * np.arcsin(np.clip(dist / 2.0, 0.0, 1.0)))
        total = np.where(found, cost[prev] + step, np.inf)
        pick = np.argmin(total, axis=1)
        rows = np.arange(k)
        cost = total[rows, pick] + deviation_weight * deviation[level]
        cost = np.where(allowed[level], cost, np.inf)
        back[level] = prev[rows, pick]
    if not np.isfinite(cost[0]):
        return None
    path = np.zeros(levels, dtype=np.int64)
    for level in range(levels - 1, 0, -1):
        path[level - 1] = back[level, path[level]]
    return path
