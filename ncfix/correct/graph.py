"""Orientation graph + shortest path (seed steps 1–3, after Nishat et al.), as a layered dynamic program.

Levels are consecutive blocks of an episode with its ramps, vertices their candidate orientations,
edges join consecutive levels within the step limit θ, weighted by the step plus a penalty on the
target's deviation from the programmed orientation (as Fang et al. and Plakhotnik et al. do). Both
end levels are anchored to candidate 0. On a layered DAG Dijkstra's result equals the level-by-level
minimum computed here. The edges are found once (``LayeredGraph``); each search of the lazy loop
takes a mask of the vertices allowed: one pass over the edges of the levels from the first one
that changed since the last search (docs/correction.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ncfix.collision.split import map_runs

# Weight of the deviation from the programmed orientation against the angular variation. Small:
# the path stays close to what the CAM system programmed, and smoothness still dominates.
DEVIATION_WEIGHT = 0.2
# Edges kept per vertex: the nearest candidates of the level before within the step limit. Where
# the limit is θ (1-2°) this is every neighbour; only where the program itself turns by tens of
# degrees between two blocks are farther neighbours dropped (fewer choices, never a wrong edge).
NEIGHBOURS = 48
# Levels whose step limit is wider than this (degrees) take every allowed source (``cheapest``).
DENSE_ABOVE_DEG = 6.0
# A step is allowed up to its limit times this (float noise never refuses a step at the limit);
# ``LayeredGraph.steps`` and the compiled dense step (``_dense_min``) both apply it.
LIMIT_SLACK = 1.0 + 1e-12
# Sources screened at once by the dense step's compiled loop (``_dense_min``): a block is one
# vectorised pass without square roots, and most blocks hold no pair worth a closer look.
DENSE_BLOCK = 16


@dataclass
class _LastSearch:
    """What ``LayeredGraph.cheapest`` computed in its last search: its inputs (the allowed vertices,
    the penalty, the bans per level as counted then), every level's costs (after the level's
    mask) and chosen sources, and the last level whose costs it computed. ``start``: the level
    the search using this record computes first."""

    ok: np.ndarray  # (L, K) bool
    penalty: np.ndarray | None  # (L, K)
    costs: np.ndarray  # (L, K)
    back: np.ndarray  # (L, K) int64
    bans: np.ndarray  # (L,) int64
    reached: int = 0
    start: int = 1


class LayeredGraph:
    """The edges between consecutive levels of candidate orientations.

    candidates : (L, K, 3) unit vectors per level; valid : (L, K) bool (padding is not valid);
    programmed : (L, 3); max_step_deg : θ, or (L,) where entry l bounds the step into level l.
    turns : optional (L, 3, 3) rotations; the step into level l is then measured from the
        previous orientation turned by turns[l] (where the program itself turns, what ncfix adds to
        the turn); the identity measures the plain angle.
    plain_limit : optional (L,) degrees, with ``turns``: where level l turns (turns[l] is not the
        identity), a step whose plain angle is at most plain_limit[l] is allowed too, whatever its
        turned step (a step within θ is within the contract wherever the program turns). Its
        weight is still the turned step. Such levels are searched densely.
    penalty : optional (L, K) cost added to a vertex (e.g. for one left colliding).
    """

    def __init__(self, candidates: np.ndarray, valid: np.ndarray, programmed: np.ndarray,
                 max_step_deg: float | np.ndarray, deviation_weight: float = DEVIATION_WEIGHT,
                 neighbours: int = NEIGHBOURS, turns: np.ndarray | None = None,
                 plain_limit: float | np.ndarray | None = None):
        self.candidates = np.asarray(candidates, dtype=np.float64)
        levels, k = valid.shape
        self.valid = valid.copy()
        limit = np.broadcast_to(np.asarray(max_step_deg, dtype=np.float64), (levels,))
        chords = 2.0 * np.sin(np.radians(np.minimum(limit, 180.0)) / 2.0) * LIMIT_SLACK
        self.deviation = np.degrees(np.arccos(np.clip(
            np.einsum("lkj,lj->lk", self.candidates, programmed), -1.0, 1.0)))
        self.deviation_weight = float(deviation_weight)
        self.limit = limit
        self.turns = None if turns is None else np.asarray(turns, dtype=np.float64)
        # Where the step limit is wide, the nearest ``neighbours`` sources would cut most edges
        # off: those levels are searched densely, over the allowed vertices of a search.
        self.dense = limit > DENSE_ABOVE_DEG
        self.plain = None
        if self.turns is not None and plain_limit is not None:
            turning = np.abs(self.turns - np.eye(3)).max(axis=(1, 2)) > 0.0
            self.plain = np.where(turning, np.broadcast_to(np.asarray(plain_limit, dtype=np.float64), (levels,)), -1.0)
            self.dense |= turning
        self.banned: dict[int, set[tuple[int, int]]] = {}
        self._ban_arrays: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # of ``banned``, made when searched
        self._bans = np.zeros(levels, dtype=np.int64)  # calls of ``ban`` per level (what a search read)
        self._last: _LastSearch | None = None  # ``cheapest``'s previous search, resumed where it differs
        # Per level l >= 1: for each vertex, up to ``neighbours`` sources at level l-1 and the angle.
        self.source: list[np.ndarray] = [np.zeros((k, 0), dtype=np.int64)]
        self.weight: list[np.ndarray] = [np.zeros((k, 0))]
        for level in range(1, levels):
            src = np.flatnonzero(self.valid[level - 1])
            # A level of a few vertices (an anchor) gets every source: the cap must not cut it off.
            width = len(src) if self.valid[level].sum() <= 4 else min(neighbours, len(src))
            if width == 0 or self.dense[level]:  # a dense level's edges are found by each search
                self.source.append(np.zeros((k, 0), dtype=np.int64))
                self.weight.append(np.zeros((k, 0)))
                continue
            sources = self.candidates[level - 1][src]
            if turns is not None:
                sources = sources @ np.asarray(turns[level], dtype=np.float64).T
            from scipy.spatial import cKDTree  # 0.1 s to import: only a graph search pays

            tree = cKDTree(sources)
            dist, idx = tree.query(self.candidates[level], k=width, distance_upper_bound=chords[level])
            dist, idx = dist.reshape(k, width), idx.reshape(k, width)
            found = np.isfinite(dist) & self.valid[level][:, None]
            step = np.degrees(2.0 * np.arcsin(np.clip(np.where(found, dist, 0.0) / 2.0, 0.0, 1.0)))
            source = np.where(found, src[np.where(found, idx, 0)], -1)
            weight = np.where(found, step, np.inf)
            # The edge from the previous level's candidate 0 (the programmed orientation) is always
            # considered, so the programmed path stays a path whatever the neighbour cap drops.
            zero = self.candidates[level - 1][0]
            if turns is not None:
                zero = np.asarray(turns[level], dtype=np.float64) @ zero
            gap = np.linalg.norm(self.candidates[level] - zero, axis=1)
            ok0 = (gap <= chords[level]) & self.valid[level] & bool(self.valid[level - 1, 0])
            step0 = np.degrees(2.0 * np.arcsin(np.clip(gap / 2.0, 0.0, 1.0)))
            self.source.append(np.column_stack([source, np.where(ok0, 0, -1)]))
            self.weight.append(np.column_stack([weight, np.where(ok0, step0, np.inf)]))

    def ban(self, level: int, sources: np.ndarray, targets: np.ndarray) -> None:
        """Remove the edges from any of ``sources`` (vertices of level - 1) to any of ``targets``
        (vertices of ``level``): moves found to collide (a lazy search's edge check)."""
        targets = np.asarray(targets, dtype=np.int64)
        if level <= 0 or len(targets) == 0:
            return
        self._bans[level] += 1
        pairs = self.banned.setdefault(level, set())
        pairs.update((int(a), int(b)) for a in np.asarray(sources).reshape(-1) for b in targets)
        self._ban_arrays.pop(level, None)
        weight = self.weight[level][targets]
        weight[np.isin(self.source[level][targets], np.asarray(sources, dtype=np.int64))] = np.inf
        self.weight[level][targets] = weight

    def cheapest(self, allowed: np.ndarray, penalty: np.ndarray | None = None) -> np.ndarray | None:
        """The cheapest sequence of allowed vertices from level 0's candidate 0 to the last level's.

        allowed : (L, K) bool. Returns the chosen index per level (L,) int, or None when no path
        of allowed vertices keeps every step within its limit. ``penalty`` (L, K): extra cost of
        a vertex.

        A level's costs depend only on the levels up to it: a search that differs from the
        previous one (its allowed vertices, penalties, bans) first at level m takes that search's
        costs and choices up to m - 1 as they were, and computes the levels from m on.
        """
        levels, k = allowed.shape
        ok = allowed & self.valid
        ok[0, 1:] = False
        ok[-1, 1:] = False
        last = self._resume(ok, penalty)
        start, costs, back = last.start, last.costs, last.back
        cost = np.where(ok[0], 0.0, np.inf) if start == 1 else costs[start - 1]
        rows = np.arange(k)
        for level in range(start, levels):
            if self.dense[level]:
                best, back[level] = self._dense_step(level, cost, ok)
            else:
                src = self.source[level]
                if src.shape[1] == 0:
                    last.reached = level - 1
                    return None
                total = np.where(src >= 0, cost[np.maximum(src, 0)] + self.weight[level], np.inf)
                pick = np.argmin(total, axis=1)
                best = total[rows, pick]
                back[level] = src[rows, pick]
            cost = best + self.deviation_weight * self.deviation[level]
            if penalty is not None:
                cost = cost + penalty[level]
            cost = np.where(ok[level], cost, np.inf)
            costs[level] = cost
            if not np.isfinite(cost).any():
                last.reached = level - 1
                return None
        last.reached = levels - 1
        if not np.isfinite(cost[0]):
            return None
        path = np.zeros(levels, dtype=np.int64)
        for level in range(levels - 1, 0, -1):
            path[level - 1] = back[level, path[level]]
        return path

    def _resume(self, ok: np.ndarray, penalty: np.ndarray | None) -> _LastSearch:
        """This search's record (``_LastSearch``): the previous one's, with ``start`` at the first
        level whose allowed vertices, penalty or bans differ from it (or past the last level it
        reached), or a new one starting at level 1."""
        last = self._last
        if last is None or last.ok.shape != ok.shape or (last.penalty is None) != (penalty is None):
            levels, k = ok.shape
            last = _LastSearch(ok, None, np.zeros((levels, k)), np.zeros((levels, k), dtype=np.int64), self._bans.copy())
        else:
            differs = (last.ok != ok).any(axis=1) | (last.bans != self._bans)
            if penalty is not None:
                differs |= (last.penalty != penalty).any(axis=1)
            first = int(np.argmax(differs)) if differs.any() else len(differs)
            last.start = max(1, min(first, last.reached + 1))  # level 0's vertices are the first costs
            last.ok, last.bans = ok, self._bans.copy()
        last.penalty = None if penalty is None else np.array(penalty, dtype=np.float64)
        last.reached = last.start - 1
        self._last = last
        return last

    def steps(self, level: int, sources: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The steps from orientations ``sources`` (a, 3) at level - 1 to ``targets`` (b, 3) at
        ``level``: their weights (b, a) in degrees (the turned step) and whether each is allowed.
        The rule is this; the dense search's compiled loop (``_dense_min``) applies the same one
        pair by pair, and tests/test_graph.py holds the two together."""
        turned = sources @ self.turns[level].T if self.turns is not None else sources
        step = np.degrees(np.arccos(np.clip(targets @ turned.T, -1.0, 1.0)))
        allowed = step <= self.limit[level] * LIMIT_SLACK
        if self.plain is not None and self.plain[level] >= 0.0:
            plain = np.degrees(np.arccos(np.clip(targets @ sources.T, -1.0, 1.0)))
            allowed |= plain <= self.plain[level] * LIMIT_SLACK
        return step, allowed

    def _ban_pairs(self, level: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The banned edges into ``level`` as (sources, targets) arrays, or None."""
        if not self.banned.get(level):
            return None
        if level not in self._ban_arrays:
            pairs = np.array(list(self.banned[level]), dtype=np.int64)
            self._ban_arrays[level] = (pairs[:, 0], pairs[:, 1])
        return self._ban_arrays[level]

    def _dense_step(self, level: int, cost: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One level of the search over every edge between the reachable vertices of the level
        before and the allowed vertices of this one: (best cost (K,), its source (K,))."""
        k = ok.shape[1]
        best, back = np.full(k, np.inf), np.zeros(k, dtype=np.int64)
        src = np.flatnonzero(np.isfinite(cost) & self.valid[level - 1])
        dst = np.flatnonzero(ok[level])
        if len(src) == 0 or len(dst) == 0:
            return best, back
        sources = self.candidates[level - 1][src]
        turned = sources @ self.turns[level].T if self.turns is not None else sources
        plain = self.plain[level] if self.plain is not None else -1.0
        banned = np.zeros((0, 0), dtype=np.bool_)
        pairs = self._ban_pairs(level)
        if pairs is not None:
            a, b = pairs
            i, j = np.searchsorted(dst, b), np.searchsorted(src, a)
            hit = (i < len(dst)) & (j < len(src))
            hit[hit] = (dst[i[hit]] == b[hit]) & (src[j[hit]] == a[hit])
            if hit.any():
                banned = np.zeros((len(dst), len(src)), dtype=np.bool_)
                banned[i[hit], j[hit]] = True
        c = cost[src]
        targets, order = np.ascontiguousarray(self.candidates[level][dst]), np.argsort(c, kind="stable")
        turned, sources = np.ascontiguousarray(turned), np.ascontiguousarray(sources)
        limit, plain = float(self.limit[level] * LIMIT_SLACK), float(plain * LIMIT_SLACK)

        def run(lo: int, hi: int):  # each target on its own: the cut does not change the answer
            return _dense_min(targets[lo:hi], turned, sources, c, order, limit, plain,
                              banned[lo:hi] if banned.shape[0] else banned)

        parts = map_runs(run, len(dst))
        best[dst] = np.concatenate([total for total, _ in parts])
        back[dst] = src[np.concatenate([pick for _, pick in parts])]
        return best, back


def _dense_min(targets, turned, sources, cost, order, limit, plain, banned):
    """For each target (b, 3): the cheapest cost[j] + step over the sources j (a, 3) whose step is
    allowed (``LayeredGraph.steps``: turned step <= limit, or plain angle <= plain when plain >= 0;
    not ``banned`` (b, a), when that is not empty). (total (b,), source index (b,); inf and 0 where
    none is allowed.) The sources are visited in ``order`` of cost and a target stops at the first
    costing more than its best so far (a step is never negative), and a pair whose chord alone
    costs more is skipped, so the angles of most pairs are never computed; ties go to the lowest
    source index, as an argmin over the sources would.

    The sources go DENSE_BLOCK at a time: a block is screened first, without square roots, for a
    pair the pair-by-pair test could take (chord within the limit, cost plus chord within the
    best); a block with none is passed over whole. The screen's bounds are widened far beyond
    rounding (it may let through a pair the test refuses, never the reverse), and the pairs it
    lets through go to the test as they are: the answer is the pair-by-pair loop's, bit for bit."""
    nb, na = targets.shape[0], turned.shape[0]
    total = np.full(nb, np.inf)
    pick = np.zeros(nb, dtype=np.int64)
    use_ban = banned.shape[0] > 0
    to_deg = 180.0 / np.pi
    # The screen: chord² = 2 - 2·cos; its degrees and the limit's, squared, with the slack.
    scale2 = (to_deg * (1.0 - 1e-9)) ** 2 * (1.0 - 1e-12)
    reach2 = (limit / (to_deg * (1.0 - 1e-9))) ** 2 * (1.0 + 1e-12) if plain < 0.0 else np.inf
    # The sources in order of cost, padded to whole blocks with unreachable ones.
    padded = (na + DENSE_BLOCK - 1) // DENSE_BLOCK * DENSE_BLOCK
    cs = np.full(padded, np.inf)
    sx, sy, sz = np.zeros(padded), np.zeros(padded), np.zeros(padded)
    for k in range(na):
        j = order[k]
        cs[k], sx[k], sy[k], sz[k] = cost[j], turned[j, 0], turned[j, 1], turned[j, 2]
    for i in range(nb):
        tx, ty, tz = targets[i, 0], targets[i, 1], targets[i, 2]
        best, arg = np.inf, -1
        for lo in range(0, padded, DENSE_BLOCK):
            if cs[lo] > best:
                break
            tol = 1e-12 * (abs(best) + 1.0)
            maybe = False
            for k in range(lo, lo + DENSE_BLOCK):
                m = 2.0 - 2.0 * min(max(tx * sx[k] + ty * sy[k] + tz * sz[k], -1.0), 1.0)
                gap = best - cs[k] + tol
                maybe |= (m <= reach2) & (gap >= 0.0) & (m * scale2 <= gap * gap)
            if not maybe:
                continue
            stop = False
            for k in range(lo, min(lo + DENSE_BLOCK, na)):
                c = cs[k]
                if c > best:
                    stop = True
                    break
                j = order[k]
                if use_ban and banned[i, j]:
                    continue
                d = min(max(tx * sx[k] + ty * sy[k] + tz * sz[k], -1.0), 1.0)
                # The chord 2·sin(φ/2) = sqrt(2 - 2d) is never longer than the arc φ (a hair less
                # here, for rounding): a cheap lower bound that skips most arc-cosines.
                chord = np.sqrt(max(2.0 - 2.0 * d, 0.0)) * to_deg * (1.0 - 1e-9)
                if c + chord > best or (chord > limit and plain < 0.0):
                    continue
                step = np.arccos(d) * to_deg
                if not step <= limit:
                    if plain < 0.0:
                        continue
                    e = min(max(tx * sources[j, 0] + ty * sources[j, 1] + tz * sources[j, 2], -1.0), 1.0)
                    if not np.arccos(e) * to_deg <= plain:
                        continue
                t = c + step
                if t < best or (t == best and j < arg):
                    best, arg = t, j
            if stop:
                break
        if arg >= 0:
            total[i], pick[i] = best, arg
    return total, pick


_dense_min = njit(cache=True, nogil=True)(_dense_min)


def cheapest_path(candidates: np.ndarray, free: np.ndarray, programmed: np.ndarray,
                  max_step_deg: float | np.ndarray, deviation_weight: float = DEVIATION_WEIGHT,
                  neighbours: int = NEIGHBOURS) -> np.ndarray | None:
    """One search on the free vertices (``LayeredGraph`` built on them); None when no path exists."""
    graph = LayeredGraph(candidates, free, programmed, max_step_deg, deviation_weight, neighbours)
    return graph.cheapest(free)
