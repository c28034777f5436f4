"""The orientation graph: cheapest smooth path around obstacles, anchored to the programmed orientation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from numba import njit

from ncfix.collision import split
from ncfix.correct import candidates
from ncfix.correct.candidates import SphereGrid, level_candidates, nearest
from ncfix.correct.graph import LIMIT_SLACK, LayeredGraph, _dense_min, cheapest_path
from ncfix.geometry.frames import angle_between_deg, rotation_from_z


def test_sphere_grid_covers_the_cap_at_its_resolution():
    grid = SphereGrid(1.0)
    cands, valid = level_candidates(grid, np.array([[0, 0, 1.0], [np.sin(0.3), 0, np.cos(0.3)]]), 30.0)
    assert np.allclose(np.linalg.norm(cands, axis=2), 1.0)
    assert np.allclose(cands[:, 0], [[0, 0, 1.0], [np.sin(0.3), 0, np.cos(0.3)]])  # programmed first
    for level in range(2):
        dev = angle_between_deg(cands[level][valid[level]], cands[level, 0])
        assert dev.max() <= 30.0 + 1e-9
        # every direction of the cap is within one resolution of a candidate
        rng = np.random.default_rng(level)
        t = np.radians(rng.uniform(0, 29, 2000))
        a = rng.uniform(0, 2 * np.pi, 2000)
        probe = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
        probe = probe @ np.asarray(rotation_from_z(cands[level, 0])).reshape(3, 3).T
        nearest = np.degrees(np.arccos(np.clip((probe @ cands[level][valid[level]].T).max(axis=1), -1, 1)))
        assert nearest.max() < 1.0


def test_consecutive_levels_share_candidates():
    grid = SphereGrid(1.0)
    a = np.array([0.0, 0.0, 1.0])
    b = np.array([np.sin(0.02), 0.0, np.cos(0.02)])
    cands, valid = level_candidates(grid, np.stack([a, b]), 10.0)
    shared = set(map(tuple, cands[0][valid[0]][1:])) & set(map(tuple, cands[1][valid[1]][1:]))
    assert len(shared) > 0.8 * valid[0].sum()


def obstacle_case(levels=40, blocked=range(15, 25), need_deg=8.0):
    programmed = np.tile([0.0, 0.0, 1.0], (levels, 1))
    cands, valid = level_candidates(SphereGrid(1.0), programmed, 30.0)
    tilt_x = np.degrees(np.arctan2(cands[..., 0], cands[..., 2]))
    free = valid.copy()
    for level in blocked:
        free[level] &= tilt_x[level] > need_deg  # only tilting toward +X by more than need_deg is free
    return programmed, cands, free


def _levels(seed: int):
    """(points, among) pairs as the graph's seeding meets them: a level's candidates (the grid's
    cap about a programmed vector, and that vector), the coarse grid's cap against them, and the
    level's candidates against a tested subset of them."""
    rng = np.random.default_rng(seed)
    fine, coarse = SphereGrid(1.0), SphereGrid(4.0)
    programmed = rng.normal(size=(3, 3)) * [0.2, 0.2, 1.0]
    programmed /= np.linalg.norm(programmed, axis=1, keepdims=True)
    cands, valid = level_candidates(fine, programmed, 30.0)
    for level, n0 in enumerate(programmed):
        idx = np.flatnonzero(valid[level])
        yield coarse.points[coarse.cap(n0, 30.0)], cands[level, idx]
        tested = np.sort(rng.choice(idx, size=len(idx) // 16, replace=False))
        yield cands[level, np.setdiff1d(idx, tested)], cands[level, tested]


@pytest.mark.parametrize("seed", range(3))
def test_the_nearest_candidate_is_the_one_the_dense_product_picks(seed, monkeypatch):
    # On real levels, on random vectors, and where ties are exact (duplicates: the lowest index).
    rng = np.random.default_rng(100 + seed)
    random = rng.normal(size=(500, 3)), rng.normal(size=(300, 3))
    random = tuple(v / np.linalg.norm(v, axis=1, keepdims=True) for v in random)
    tied = random[1][rng.integers(0, 300, 200)]
    cases = [*_levels(seed), random, (random[0], np.concatenate([tied, random[1], tied]))]
    fallbacks = []
    dense = candidates._nearest

    def counted(points, among, margin):
        out, clear = dense(points, among, margin)
        fallbacks.append(not clear)
        return out, clear

    monkeypatch.setattr(candidates, "_nearest", counted)
    for points, among in cases:
        assert np.array_equal(nearest(points, among), np.argmax(points @ among.T, axis=1))
    # Only the exact ties took the dense product (where its own products of equal vectors may
    # differ in the last place: the loop could not have chosen as it does).
    assert fallbacks[-1] and not any(fallbacks[:-1])


def test_path_avoids_the_obstacle_with_small_steps_and_comes_back():
    programmed, cands, free = obstacle_case()
    path = cheapest_path(cands, free, programmed, max_step_deg=2.0)
    assert path is not None
    chosen = cands[np.arange(len(path)), path]
    assert free[np.arange(len(path)), path].all()
    steps = angle_between_deg(chosen[1:], chosen[:-1])
    assert steps.max() <= 2.0 + 1e-9
    assert path[0] == 0 and path[-1] == 0  # anchored at both ends
    dev = angle_between_deg(chosen, programmed)
    assert dev[15:25].min() > 8.0 and dev.max() < 12.0  # just enough
    assert (dev[:5] == 0).all() and (dev[-5:] == 0).all()  # far blocks untouched


def test_no_path_when_the_ramp_is_too_short_for_the_step_limit():
    programmed, cands, free = obstacle_case(levels=8, blocked=range(3, 5), need_deg=8.0)
    assert cheapest_path(cands, free, programmed, max_step_deg=2.0) is None


def test_no_path_when_nothing_is_free():
    programmed, cands, free = obstacle_case()
    free[20] = False
    assert cheapest_path(cands, free, programmed, max_step_deg=2.0) is None


def test_wide_steps_search_every_edge_and_banned_edges_are_avoided():
    """With θ = 30° a level's free vertices can lie far from every free vertex of the level
    before: the nearest-neighbour edges would find no path through them (the bathtub sample
    left 56 blocks colliding so); the dense levels search every edge within θ. A banned edge
    (a move found to collide) is never taken."""

    grid = SphereGrid(1.0)
    programmed = np.tile([0.0, 0.0, 1.0], (5, 1))
    cands, valid = level_candidates(grid, programmed, 30.0)
    tilt = angle_between_deg(cands, programmed[:, None, :])
    x = cands[..., 0]
    free = valid.copy()
    # level 1: only tilts of 20-25° toward +x; level 2: only 20-25° toward -x (40-50° from level 1's)
    free[1] &= (tilt[1] >= 20) & (tilt[1] <= 25) & (x[1] > 0.3)
    free[2] &= (tilt[2] >= 0) & (tilt[2] <= 12) & (x[2] < -0.05)
    free[[0, 4], 1:] = False
    graph = LayeredGraph(cands, valid, programmed, 30.0)
    path = graph.cheapest(free)
    assert path is not None
    N = cands[np.arange(5), path]
    assert free[np.arange(5), path].all()
    assert (angle_between_deg(N[1:], N[:-1]) <= 30.0 + 1e-9).all()
    # ban the chosen move from level 1 to level 2: the next path avoids it
    graph.ban(2, np.array([path[1]]), np.array([path[2]]))
    again = graph.cheapest(free)
    assert again is not None and (again[1], again[2]) != (path[1], path[2])


@pytest.mark.parametrize("seed", range(3))
def test_a_search_resumed_from_the_last_one_finds_what_a_new_graph_finds(seed):
    """``cheapest`` computes again only the levels from the first one whose allowed vertices,
    penalty or bans changed: each search of a lazy loop (vertices let in or out, bans, penalties
    changed, late levels first and early ones too) gives the path and the costs a graph built
    anew and searched once gives, on nearest-neighbour levels (θ = 3°) and dense ones (θ = 8°)."""
    rng = np.random.default_rng(seed)
    levels = 12
    programmed = np.tile([0.0, 0.0, 1.0], (levels, 1))
    cands, valid = level_candidates(SphereGrid(1.0), programmed, 10.0)
    limits = np.where(np.arange(levels) % 2 == 0, 3.0, 8.0)
    graph = LayeredGraph(cands, valid, programmed, limits)
    bans = []
    allowed = valid & (rng.random(valid.shape) < 0.85)
    allowed[:, 0] = True
    penalty = np.zeros(valid.shape)
    resumed, found = [], 0
    for change in range(10):
        level = int(rng.integers(1, levels)) if change % 3 else int(rng.integers(levels // 2, levels))
        if change % 4 == 1:
            ban = (level, rng.choice(np.flatnonzero(valid[level - 1]), 30), rng.choice(np.flatnonzero(valid[level]), 30))
            bans.append(ban)
            graph.ban(*ban)
        elif change % 4 == 2:
            penalty[level, rng.integers(0, valid.shape[1], 20)] += 1.0
        elif change:
            allowed[level] = valid[level] & (rng.random(valid.shape[1]) < 0.85)
            allowed[level, 0] = True  # the programmed path stays (as the strategy keeps it)
        path = graph.cheapest(allowed, penalty)
        resumed.append(graph._last.start)
        found += path is not None
        fresh = LayeredGraph(cands, valid, programmed, limits)
        for ban in bans:
            fresh.ban(*ban)
        assert np.array_equal(fresh.cheapest(allowed, penalty), path)
        np.testing.assert_array_equal(fresh._last.costs, graph._last.costs)
    assert resumed[0] == 1 and max(resumed) > levels // 2 and found > 5  # resumed, late as well as early
    graph.cheapest(allowed)
    assert graph._last.start == 1  # a search without a penalty after one with it: anew


@pytest.mark.parametrize("threads", ["2", "5"])
def test_the_dense_step_is_the_same_on_any_number_of_threads(monkeypatch, threads):
    """The dense levels' targets are cut into runs for the cores (``split.map_runs``): each target
    is searched on its own, so the costs and sources are those of one thread, bans included."""
    grid = SphereGrid(1.0)
    programmed = np.tile([0.0, 0.0, 1.0], (4, 1))
    cands, valid = level_candidates(grid, programmed, 30.0)
    rng = np.random.default_rng(7)
    graph = LayeredGraph(cands, valid, programmed, 30.0)
    graph.ban(2, rng.choice(np.flatnonzero(valid[1]), 200), rng.choice(np.flatnonzero(valid[2]), 300))
    ok = valid & (rng.random(valid.shape) < 0.6)
    cost = np.where(ok[1], rng.random(valid.shape[1]) * 10.0, np.inf)
    monkeypatch.setenv("NCFIX_THREADS", "1")
    best_one, back_one = graph._dense_step(2, cost, ok)
    monkeypatch.setenv("NCFIX_THREADS", threads)
    assert len(split.runs(int(ok[2].sum()), int(threads))) > 1
    best, back = graph._dense_step(2, cost, ok)
    np.testing.assert_array_equal(best, best_one)
    np.testing.assert_array_equal(back, back_one)
    assert np.isfinite(best_one).sum() > 100


class _ToyEpisode:
    """An episode for ``GraphStrategy.solve`` without a machine: the words are the tool vector,
    levels 3 and 4 collide as programmed (vertical), level 3 is free only in a narrow band (tilt
    9-10.5° toward +X, which the coarse first tests miss) and level 4 wherever it tilts 6° or
    more; a move collides where its end pose does, or where it starts at a colliding pose."""

    def __init__(self, levels: int = 8):
        from types import SimpleNamespace

        self.rows = np.arange(levels)
        self.lines = self.rows + 1
        self.N0 = np.tile([0.0, 0.0, 1.0], (levels, 1))
        self.programmed = self.N0.copy()
        self.colliding = np.array([3, 4])
        self.is_colliding = np.isin(self.rows, self.colliding)
        self.tcp = np.zeros(levels, dtype=bool)
        self.before_words, self.after_row = self.N0[0].copy(), None
        self.N_before, self.N_after = self.N0[0].copy(), None
        self.max_step = 30.0
        self.limits = self.step_limits = np.full(levels, 30.0)
        self.turns = np.tile(np.eye(3), (levels, 1, 1))
        self.path = SimpleNamespace(forward=lambda w, tcp: (None, w / np.linalg.norm(w, axis=1, keepdims=True), None))

    def pose_free(self, level, N) -> np.ndarray:
        level, N = np.asarray(level), N / np.linalg.norm(N, axis=1, keepdims=True)
        tilt = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0)))
        azimuth = np.degrees(np.abs(np.arctan2(N[:, 1], N[:, 0])))
        out = np.ones(len(level), dtype=bool)
        out[level == 3] = ((tilt >= 9.0) & (tilt <= 10.5) & (azimuth <= 20.0))[level == 3]
        out[level == 4] = (tilt >= 6.0)[level == 4]
        return out

    start_known = True

    def free(self, level, N, beads=True) -> np.ndarray:
        return self.pose_free(level, N)

    def orient(self, level, N):
        return N / np.linalg.norm(N, axis=1, keepdims=True), None, np.ones(len(N), dtype=bool)

    def moves_hit_parts(self, level, start_words, N) -> np.ndarray:
        return ~self.pose_free(np.full(len(N), level), N) | ~self.pose_free(np.full(len(N), level - 1), start_words)

    def programmed_free(self) -> np.ndarray:
        return self.pose_free(self.rows, self.N0)

    def words_of(self, N, programmed) -> np.ndarray:
        return np.where(programmed[:, None], self.programmed, N)

    def recheck(self, words) -> np.ndarray:
        ok = self.pose_free(self.rows, words)
        return ~ok | np.concatenate([[False], ~ok[:-1]])


def test_a_level_given_up_after_a_colliding_one_is_searched_again_once_that_one_is_freed():
    """The first paths leave level 3 colliding (its free band is not found yet), so the move into
    level 4 collides whatever its end and level 4 is given up. Once level 3 is freed, level 4 must
    be searched again: both end free (before, level 4 stayed given up and was reported as having
    no free orientation)."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    ep = _ToyEpisode()
    solution = GraphStrategy(SimpleNamespace(max_tilt=30.0, max_step=30.0, resolution=2.0)).solve(ep)
    assert solution.unresolved == []
    assert not ep.recheck(solution.words).any()
    tilt = angle_between_deg(solution.words, ep.N0)
    assert 9.0 - 1e-9 <= tilt[3] <= 10.5 + 1e-9 and tilt[4] >= 6.0 - 1e-9


def test_a_search_cut_off_by_its_round_limit_says_so(monkeypatch):
    """With too few rounds to find level 3's narrow band, the blocks are left colliding and the
    report's reason names the round limit, not a claim about the orientations."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    monkeypatch.setattr(GraphStrategy, "MAX_ROUNDS", 4)
    solution = GraphStrategy(SimpleNamespace(max_tilt=30.0, max_step=30.0, resolution=2.0)).solve(_ToyEpisode())
    assert 3 in solution.unresolved
    assert "4-round limit" in solution.reasons[3]
    assert "failed it most often" not in solution.reasons[3]  # its rounds went to candidate tests


class _BlockedEpisode(_ToyEpisode):
    """Levels 3-7 collide as programmed; level 3 has no free orientation, levels 4-7 are free
    wherever they tilt 6° or more. Counts its re-checks."""

    def __init__(self):
        super().__init__(levels=11)
        self.colliding = np.arange(3, 8)
        self.is_colliding = np.isin(self.rows, self.colliding)
        self.rechecks = 0

    def pose_free(self, level, N) -> np.ndarray:
        level, N = np.asarray(level), N / np.linalg.norm(N, axis=1, keepdims=True)
        tilt = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0)))
        return np.where(level == 3, False, np.where((level >= 4) & (level <= 7), tilt >= 6.0, True))

    def recheck(self, words) -> np.ndarray:
        self.rechecks += 1
        return super().recheck(words)


def test_the_run_held_by_a_block_left_colliding_is_given_up_in_one_round():
    """Level 3 cannot be freed: every move out of it collides, and out of the levels after it as
    long as they keep a colliding programmed pose. They are left with it, with that reason, in
    one round (before, the search gave them up one re-check at a time)."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    ep = _BlockedEpisode()
    solution = GraphStrategy(SimpleNamespace(max_tilt=30.0, max_step=30.0, resolution=2.0)).solve(ep)
    assert solution.unresolved == [3, 4, 5, 6, 7, 8]  # 8 is free as programmed; its move starts at 7
    assert "no free orientation" in solution.reasons[3]
    assert all(solution.reasons[i] == "its move starts at the block before, which is left colliding"
               for i in range(4, 9))
    assert np.array_equal(solution.words[3:9], ep.programmed[3:9])
    # One re-check finds the run held, one passes, then the open rounds (one at a time: 8 here).
    assert ep.rechecks <= 2 + GraphStrategy.OPEN_ROUNDS, ep.rechecks


class _CornerEpisode(_BlockedEpisode):
    """As ``_BlockedEpisode``, but level 3 is free in ``_ToyEpisode``'s narrow band, and every
    move into it collides (as a move across a corner of the part does, whatever its end poses)."""

    def pose_free(self, level, N) -> np.ndarray:
        level, N = np.asarray(level), N / np.linalg.norm(N, axis=1, keepdims=True)
        tilt = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0)))
        azimuth = np.degrees(np.abs(np.arctan2(N[:, 1], N[:, 0])))
        band = (tilt >= 9.0) & (tilt <= 10.5) & (azimuth <= 20.0)
        return np.where(level == 3, band, np.where((level >= 4) & (level <= 7), tilt >= 6.0, True))

    def moves_hit_parts(self, level, start_words, N) -> np.ndarray:
        return np.full(len(N), level == 3) | super().moves_hit_parts(level, start_words, N)

    def recheck(self, words) -> np.ndarray:
        bad = super().recheck(words)
        bad[3] = True
        return bad


def test_a_block_no_move_can_free_is_left_at_once_with_why():
    """Level 3's end poses are free at a tilt, but every move into them collides. The search
    checks those moves once, leaves the block as programmed with that reason, and settles in a
    few re-checks (before, it banned the moves a neighbourhood at a time until its round limit,
    and the reason named the limit)."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    ep = _CornerEpisode()
    solution = GraphStrategy(SimpleNamespace(max_tilt=30.0, max_step=30.0, resolution=2.0)).solve(ep)
    assert solution.unresolved == [3, 4, 5, 6, 7, 8]
    assert solution.reasons[3].startswith("no move frees it"), solution.reasons[3]
    assert np.array_equal(solution.words[3:9], ep.programmed[3:9])
    assert ep.rechecks <= 2 + GraphStrategy.OPEN_ROUNDS, ep.rechecks


def _about_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def test_a_step_within_the_limit_is_allowed_where_the_program_turns():
    """The program turns by 40° into level 1 (θ = 10°). A candidate 8° from the orientation
    before is 32° off the turned one: the turned rule alone refuses it, but a step within θ is
    within the contract wherever the program turns, so with ``plain_limit`` it is an edge (its
    weight is still the turned step)."""
    z = np.array([0.0, 0.0, 1.0])
    turned, near = _about_y(40.0) @ z, _about_y(8.0) @ z
    cands = np.array([[z, z], [turned, near], [near, near]])
    valid = np.ones((3, 2), dtype=bool)
    turns = np.stack([np.eye(3), _about_y(40.0), np.eye(3)])
    allowed = np.array([[True, False], [False, True], [True, False]])
    strict = LayeredGraph(cands, valid, cands[:, 0], 10.0, turns=turns)
    assert strict.cheapest(allowed) is None
    relaxed = LayeredGraph(cands, valid, cands[:, 0], 10.0, turns=turns, plain_limit=10.0)
    assert relaxed.cheapest(allowed).tolist() == [0, 1, 0]
    step, ok = relaxed.steps(1, cands[0], cands[1])
    assert ok[:, 0].tolist() == [True, True] and np.allclose(step[:, 0], [0.0, 32.0], atol=1e-5)
    # Not at a level the program does not turn into: there the step is the plain angle already.
    assert relaxed.plain[2] < 0 and not relaxed.steps(2, cands[1, :1], cands[2, :1])[1].any()


@pytest.mark.parametrize("seed", range(4))
def test_the_dense_levels_pick_what_every_pair_says(seed):
    # The compiled dense step (sources by cost, stopping early) against every pair's total at
    # once: the same cost and source for every target, with turns, plain steps and bans.

    rng = np.random.default_rng(seed)
    a, b = 300, 200

    def unit(n):
        v = rng.normal(size=(n, 3)) * [0.3, 0.3, 1.0] + [0.0, 0.0, 2.0]
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    sources, targets = unit(a), unit(b)
    turn = _about_y(25.0)
    turned = sources @ turn.T
    cost = np.round(rng.uniform(0.0, 40.0, a), 1)  # ties, on purpose
    limit, plain = 12.0, 9.0 if seed % 2 else -1.0
    banned = rng.random((b, a)) < 0.2 if seed >= 2 else np.zeros((0, 0), dtype=bool)
    total, pick = _dense_min(targets, turned, sources, cost, np.argsort(cost, kind="stable"), limit, plain, banned)

    # Every pair's step and whether it is allowed, as the graph's one rule says (LayeredGraph.steps).
    rule = SimpleNamespace(turns=np.stack([np.eye(3), turn]), limit=np.array([0.0, limit / LIMIT_SLACK]),
                           plain=np.array([-1.0, plain / LIMIT_SLACK]) if plain >= 0 else None)
    step, ok = LayeredGraph.steps(rule, 1, sources, targets)
    if banned.size:
        ok &= ~banned
    every = np.where(ok, cost[None, :] + step, np.inf)
    want = every.min(axis=1)
    assert np.isfinite(want).sum() > b // 2 and (~np.isfinite(want)).any()  # both kinds of target
    np.testing.assert_allclose(total, want, rtol=0, atol=1e-9)
    found = np.isfinite(want)
    assert np.all(every[found, pick[found]] <= want[found] + 1e-9)
    assert np.all(pick[~found] == 0)


def _pair_by_pair(targets, turned, sources, cost, order, limit, plain, banned):
    """The dense step's rule over every pair, sources in index order: the cheapest cost + step of
    an allowed pair, the lowest source on a tie (what the compiled ``_dense_min``, sources by cost,
    stopping early and screening blocks, must give bit for bit; ``order`` is not needed)."""
    nb, na = targets.shape[0], turned.shape[0]
    total, pick = np.full(nb, np.inf), np.zeros(nb, dtype=np.int64)
    to_deg = 180.0 / np.pi
    for i in range(nb):
        for j in range(na):
            if banned.shape[0] > 0 and banned[i, j]:
                continue
            cos_turned = targets[i, 0] * turned[j, 0] + targets[i, 1] * turned[j, 1] + targets[i, 2] * turned[j, 2]
            step = np.arccos(min(max(cos_turned, -1.0), 1.0)) * to_deg
            cos_plain = targets[i, 0] * sources[j, 0] + targets[i, 1] * sources[j, 1] + targets[i, 2] * sources[j, 2]
            if step <= limit or (plain >= 0.0 and np.arccos(min(max(cos_plain, -1.0), 1.0)) * to_deg <= plain):
                if cost[j] + step < total[i]:
                    total[i], pick[i] = cost[j] + step, j
    return total, pick


_pair_by_pair = njit(cache=False)(_pair_by_pair)


@pytest.mark.parametrize("seed", range(6))
def test_the_screened_dense_step_is_the_pair_by_pair_loop_bit_for_bit(seed):
    # Levels as the graph meets them (the grid's caps about two programmed vectors 3° apart,
    # costs growing away from a preferred direction, exact ties, a level of 180°) and random ones
    # (turns, plain steps, bans).
    rng = np.random.default_rng(200 + seed)
    if seed < 3:
        programmed = np.array([[0.0, 0.0, 1.0], [np.sin(0.05), 0.0, np.cos(0.05)]])
        cands, valid = level_candidates(SphereGrid(1.0), programmed @ rotation_from_z(rng.normal(size=3) * [0.3, 0.3, 1]).T,
                                        30.0)
        sources, targets = cands[0][valid[0]], cands[1][valid[1]]
        toward = sources[rng.integers(len(sources))]
        cost = 0.2 * angle_between_deg(sources, toward) + rng.uniform(0.0, 2.0, len(sources))
        cost[rng.random(len(sources)) < 0.3] = 7.5  # ties
        cost[rng.random(len(sources)) < 0.1] += 1e4  # left colliding
        turned, plain, banned = sources, -1.0, np.zeros((0, 0), dtype=bool)
        limit = (10.0, 3.0, 180.0)[seed] * LIMIT_SLACK
    else:
        def unit(n):
            v = rng.normal(size=(n, 3)) * [0.3, 0.3, 1.0] + [0.0, 0.0, 2.0]
            return v / np.linalg.norm(v, axis=1, keepdims=True)

        sources, targets = unit(400), unit(300)
        turned = sources @ _about_y(25.0).T
        cost = np.round(rng.uniform(0.0, 40.0, len(sources)), 1)
        limit, plain = 12.0, (9.0 if seed % 2 else -1.0)
        banned = rng.random((len(targets), len(sources))) < 0.2 if seed == 5 else np.zeros((0, 0), dtype=bool)
    order = np.argsort(cost, kind="stable")
    total, pick = _dense_min(targets, turned, sources, cost, order, limit, plain, banned)
    want_total, want_pick = _pair_by_pair(targets, turned, sources, cost, order, limit, plain, banned)
    assert np.isfinite(want_total).sum() > len(targets) // 2
    np.testing.assert_array_equal(total, want_total)
    np.testing.assert_array_equal(pick, want_pick)


class _ShadowEpisode(_ToyEpisode):
    """Θ = 3° (every candidate is within the ban's neighbourhood of every other). Level 3 collides
    as programmed and is free tilted, but a tilted level 3 lays what the head at level 4 hits:
    level 4 is free only as programmed, and only after a programmed level 3. Levels 6 and 7
    collide as programmed and are free tilted, whatever happens at levels 3-4."""

    def __init__(self):
        super().__init__(levels=10)
        self.colliding = np.array([3, 6, 7])
        self.is_colliding = np.isin(self.rows, self.colliding)

    def pose_free(self, level, N) -> np.ndarray:
        level, N = np.asarray(level), N / np.linalg.norm(N, axis=1, keepdims=True)
        tilted = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0))) > 0.5
        return np.where(np.isin(level, [3, 6, 7]), tilted, np.where(level == 4, ~tilted, True))

    def recheck(self, words) -> np.ndarray:
        bad = super().recheck(words)
        tilt3 = np.degrees(np.arccos(np.clip(words[3, 2] / np.linalg.norm(words[3]), -1.0, 1.0)))
        bad[4] |= tilt3 > 0.5
        return bad


def test_a_failed_move_near_the_programmed_orientations_keeps_the_programmed_path():
    """The move into level 4 fails after every tilt of level 3, and the ban of a failed move takes
    the edges between the two neighbourhoods, which here hold every vertex: the programmed edge
    into level 4 must stay (before, it went too, no path was left, and the whole episode was left
    as programmed: levels 6 and 7 as well, which are free tilted)."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    ep = _ShadowEpisode()
    solution = GraphStrategy(SimpleNamespace(max_tilt=3.0, max_step=30.0, resolution=2.0)).solve(ep)
    assert solution.unresolved == [3, 4]
    assert solution.reasons[4] == "its move starts at the block before, which is left colliding"
    assert np.array_equal(solution.words[3:5], ep.programmed[3:5])
    assert (angle_between_deg(solution.words[6:8], ep.N0[6:8]) > 0.5).all()
    assert not ep.recheck(solution.words)[6:].any()


def test_a_search_cut_off_by_its_round_limit_names_the_moves_that_failed_its_rechecks(monkeypatch):
    """Cut off after a few rounds, the shadow episode's reason says where the search was stuck:
    the move into level 4 (line 5 here: the toy's lines are its rows + 1) failed its re-checks."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    monkeypatch.setattr(GraphStrategy, "MAX_ROUNDS", 4)
    solution = GraphStrategy(SimpleNamespace(max_tilt=3.0, max_step=30.0, resolution=2.0)).solve(_ShadowEpisode())
    assert solution.reasons[3].startswith("the search stopped at its 4-round limit"), solution.reasons[3]
    assert solution.reasons[3].endswith("; the moves into lines 5 (2x) failed it most often"), solution.reasons[3]


class _ShadowedProgrammedEpisode(_ToyEpisode):
    """Level 2 collides as programmed and is free tilted; levels 3 and 4 are free only as
    programmed, and level 4 collides once level 2 is tilted (what the tilted level 2 lays is in
    its way): the programmed move into it fails, from a programmed level 3."""

    def __init__(self):
        super().__init__(levels=10)
        self.colliding = np.array([2])
        self.is_colliding = np.isin(self.rows, self.colliding)

    def pose_free(self, level, N) -> np.ndarray:
        level, N = np.asarray(level), N / np.linalg.norm(N, axis=1, keepdims=True)
        tilted = np.degrees(np.arccos(np.clip(N[:, 2], -1.0, 1.0))) > 0.5
        return np.where(level == 2, tilted, np.where(np.isin(level, [3, 4]), ~tilted, True))

    def recheck(self, words) -> np.ndarray:
        bad = super().recheck(words)
        bad[4] |= np.degrees(np.arccos(np.clip(words[2, 2] / np.linalg.norm(words[2]), -1.0, 1.0))) > 0.5
        return bad


def test_a_fix_that_makes_a_free_block_collide_is_no_answer_and_the_reason_says_so():
    """Freeing level 2 makes level 4 collide, as programmed and free in the input: the programmed
    move's failure bans it, no path is left, and the episode stays as programmed with a reason
    that names the failing move (not a claim about the step limit)."""
    from types import SimpleNamespace

    from ncfix.correct.solve import GraphStrategy

    ep = _ShadowedProgrammedEpisode()
    solution = GraphStrategy(SimpleNamespace(max_tilt=30.0, max_step=30.0, resolution=2.0)).solve(ep)
    assert solution.unresolved == [2]
    assert np.array_equal(solution.words, ep.programmed)
    assert solution.reasons[2].startswith("every path within the limits that frees it makes a block collide"), \
        solution.reasons[2]
    assert "lines 5 (" in solution.reasons[2], solution.reasons[2]


def _tilt(deg: float, azimuth_deg: float) -> np.ndarray:
    t, a = np.radians(deg), np.radians(azimuth_deg)
    return np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])


def test_a_solution_ends_each_block_in_the_pose_its_candidate_test_found_free():
    """An A/C table at the pole (A0, C86.25): two blocks tilted 5° toward azimuths 100° and 80°.
    ``Episode.orient`` (the candidate tests) takes for each the solution nearest its programmed
    words: C10/A-5 and C170/A5. Chosen next to the block before instead, the second block took
    C-10/A-5 (nearest C10/A-5): the same tool vector with the head spun 180° from the pose its test
    found free. ``words_of`` now writes the tested pose, unwound next to the block before."""
    from ncfix.correct.solve import Episode
    from ncfix.profiles import load_profile

    ep = Episode.__new__(Episode)
    ep.kin = load_profile("table-ac").kinematics
    ep.is_vector = False
    ep.programmed = np.tile([0.0, 0.0, 20.0, 2966.25, 0.0], (3, 1))
    ep.before_words = ep.programmed[0].copy()
    ep.tcp = np.ones(3, dtype=bool)
    ep.pivot_tip, ep.h = True, 6.0
    ep.P0, ep.N0, _ = ep.kin.forward(ep.programmed)
    ep.C0 = ep.P0 + ep.h * ep.N0
    N = np.array([_tilt(5.0, 100.0), _tilt(5.0, 80.0), [0.0, 0.0, 1.0]])
    words = ep.words_of(N, np.array([False, False, True]))
    tested, R_tested, ok = ep.orient(np.arange(2), N[:2])
    assert ok.all()
    assert np.allclose(tested[:, 3] % 360.0, [10.0, 170.0], atol=1e-6) and np.allclose(tested[:, 4], [-5.0, 5.0])
    R_written = ep.kin.forward(words[:2])[2]
    assert np.abs(R_written - R_tested).max() < 1e-9
    assert np.allclose(words[:2, 3], [2890.0, 3050.0], atol=1e-6)  # unwound: 86.25 → 10 → 170, no 360° jumps
    assert np.array_equal(words[2], ep.programmed[2])  # a block kept as programmed keeps its words
