"""The exact deposit test's bucket grid of bead chunks (``exact_beads.BeadBuckets``)."""

import numpy as np
import pytest

from ncfix.collision.exact_beads import CELL_MM, CHUNK_BEADS, CHUNK_DEV_MM, CHUNK_MM, MAX_CELLS, BeadBuckets


def _numpy_region(beads, seq, lo, hi):
    """The bucketed region as numpy states it: (index, beads, seq, lo, cell, dims)."""
    lo = np.maximum(np.asarray(lo, dtype=np.float64), beads.min(axis=0) if len(beads) else lo)
    hi = np.minimum(np.asarray(hi, dtype=np.float64), beads.max(axis=0) if len(beads) else hi)
    inside = np.nonzero((beads >= lo).all(axis=1) & (beads <= hi).all(axis=1))[0] if len(beads) else \
        np.zeros(0, dtype=np.int64)
    cell = CELL_MM
    extent = np.maximum(hi - lo, 0.0) if len(inside) else np.zeros(3)
    while np.prod(np.floor(extent / cell) + 1) > MAX_CELLS:
        cell *= 2.0
    dims = (np.floor(extent / cell) + 1).astype(np.int64)
    return inside, beads[inside], np.asarray(seq, dtype=np.int64)[inside], lo, cell, dims


def _cases():
    rng = np.random.default_rng(7)
    for k in range(40):
        n = int(rng.integers(0, 2500))
        if k % 2:  # scattered beads: chunks of one or two
            beads = rng.uniform(-50.0, 50.0, (n, 3))
            beads[: n // 3] = np.round(beads[: n // 3] / CELL_MM) * CELL_MM  # on cell faces and box faces
        else:  # a printed path: straight runs, turns, jumps, a wobble
            step = rng.normal(0.0, 1.0, (n, 3))
            step[rng.random(n) < 0.9] = [0.25, 0.0, 0.0]
            beads = np.cumsum(step, axis=0) + rng.normal(0.0, 0.02, (n, 3)) * (rng.random((n, 1)) < 0.3)
        seq = rng.integers(-1, 100, n)
        lo = rng.uniform(-60.0, 10.0, 3)
        hi = lo + rng.uniform(-5.0, 90.0, 3)  # sometimes empty on an axis
        if k % 8 == 0:
            lo, hi = lo - 5e4, hi + 5e4  # a huge box: clipped to the beads
        if k % 8 == 1 and n:
            lo, hi = beads[0] - 1e-9, beads[0]  # one bead on the box's face
        yield beads, seq, lo, hi


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: f"{len(c[0])}")
def test_buckets_hold_each_bead_once_in_a_chunk_that_bounds_it(case):
    """The compiled filter keeps exactly the beads of the numpy formulation; every kept bead is in
    exactly one chunk, with its sequence number and radius; a chunk is a run of consecutive beads
    in laying order, at most CHUNK_BEADS long with ends at most CHUNK_MM apart, each bead within
    the chunk's dev of its segment; the chunk's sequence number is its beads' smallest; chunks are
    listed under the cell of their segment's middle and within chunk_reach of it."""
    beads, seq, lo, hi = case
    radii = np.linspace(0.2, 0.5, len(beads))
    got = BeadBuckets(beads, seq, lo, hi, radii)
    want = _numpy_region(beads, seq, lo, hi)
    for name, value in zip(("index", "beads", "seq", "lo", "cell", "dims"), want):
        mine = np.asarray(getattr(got, name))
        assert mine.dtype == np.asarray(value).dtype, name
        assert np.array_equal(mine, value), name
    index = want[0]
    first, seg = got.chunk_first, got.chunk_seg
    assert first[0] == 0 and first[-1] == len(index) and (np.diff(first) >= 1).all()
    assert (np.diff(first) <= CHUNK_BEADS).all()
    # Which kept bead each chunk position holds: chunks are runs of consecutive kept beads.
    where = {tuple(b): i for i, b in enumerate(got.beads)} if len(got.beads) == len(np.unique(got.beads, axis=0)) \
        else None
    taken = []
    d0, d1, d2 = (int(v) for v in got.dims)
    for c in range(len(seg)):
        members = got.chunk_beads[first[c]:first[c + 1]]
        a, b, dev = seg[c, :3], seg[c, 3:6], seg[c, 6]
        assert np.array_equal(members[0], a) and np.array_equal(members[-1], b)
        assert np.linalg.norm(b - a) <= CHUNK_MM
        u = b - a
        t = np.clip(((members - a) @ u) / max(u @ u, 1e-300), 0.0, 1.0) if u @ u > 0 else np.zeros(len(members))
        assert (np.linalg.norm(members - (a + t[:, None] * u), axis=1) <= dev).all() and dev <= CHUNK_DEV_MM + 1e-5
        assert got.chunk_seq[c] == got.chunk_bseq[first[c]:first[c + 1]].min()
        mid = 0.5 * (a + b)
        assert (np.linalg.norm(members - mid, axis=1) <= got.chunk_reach).all()
        cells = np.searchsorted(got.chunk_start, c, side="right") - 1
        ijk = np.minimum(np.floor((mid - got.lo) / got.cell).astype(np.int64), got.dims - 1)
        assert cells == (ijk[0] * d1 + ijk[1]) * d2 + ijk[2]
        if where is not None:
            order = [where[tuple(m)] for m in members]
            assert order == list(range(order[0], order[0] + len(order)))
            taken += order
    if where is not None:
        assert sorted(taken) == list(range(len(index)))
        pos = np.array([where[tuple(m)] for m in got.chunk_beads], dtype=np.int64)
        assert np.array_equal(got.chunk_bseq, got.seq[pos]) and np.array_equal(got.chunk_radii, radii[index][pos])
    assert len(got.chunk_start) == d0 * d1 * d2 + 1 and got.chunk_start[-1] == len(seg)


def test_a_straight_path_makes_full_chunks():
    """A straight run of beads 0.25 mm apart is cut into chunks of CHUNK_BEADS beads, dev ~ 0."""
    beads = np.column_stack([np.arange(400) * 0.25, np.zeros(400), np.zeros(400)])
    got = BeadBuckets(beads, np.zeros(400, np.int64), beads.min(axis=0), beads.max(axis=0))
    assert len(got.chunk_seg) == 400 // CHUNK_BEADS
    assert (got.chunk_seg[:, 6] < 1e-5).all()


def test_bead_cells_find_every_bead_within_the_ball():
    """``BeadCells.near`` names every cell holding a bead within the radius (whole cells: a
    superset), ``take`` gives those cells' beads in laying order within each cell, and each cell's
    ball holds its beads."""
    from ncfix.collision.deposit import BeadCells

    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 40.0 * np.pi, 4000)
    points = np.column_stack([30.0 * np.cos(t), 30.0 * np.sin(t), t / 8.0]) + rng.normal(0.0, 0.2, (len(t), 3))
    cells = BeadCells(points, 4.0)
    beads, counts, centre, radius = cells.take()
    assert len(beads) == len(points) and counts.sum() == len(points)
    owner = np.repeat(np.arange(len(counts)), counts)
    assert (np.linalg.norm(beads - centre[owner], axis=1) <= radius[owner] + 1e-9).all()
    for _ in range(30):
        c, r = rng.uniform(-40.0, 40.0, 3), float(rng.uniform(0.5, 60.0))
        sel = cells.near(c, r)
        got, n, _, _ = cells.take(sel)
        want = points[np.linalg.norm(points - c, axis=1) <= r]
        assert set(map(tuple, want)) <= set(map(tuple, got))
        # within a cell, the beads keep the order they were given in
        index = {tuple(p): i for i, p in enumerate(points)}
        first = 0
        for m in n:
            order = [index[tuple(p)] for p in got[first:first + m]]
            assert order == sorted(order)
            first += m
    # ``gather`` is take(near): balls holding every cell take them all without a query.
    reach = np.linalg.norm(np.maximum(np.abs(centre.min(axis=0)), np.abs(centre.max(axis=0))))
    for r in (5.0, 40.0, reach - 1.0, reach + 1e-6, reach + 50.0):
        for c in (np.zeros(3), np.array([3.0, -2.0, 1.0])):
            want = cells.take(cells.near(c, r))
            got = cells.gather(c, r)
            assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert len(cells.gather(np.zeros(3), reach + 50.0)[1]) == len(counts)
    empty = BeadCells(np.zeros((0, 3)), 4.0)
    assert len(empty.take()[0]) == 0 and len(empty.gather(np.zeros(3), 10.0)[0]) == 0


def test_store_near_gives_the_ball_in_laying_order_whatever_the_levels():
    """``BeadStore.near`` gives, level by level, exactly the centres each level's k-d tree's ball
    query finds, in laying order (the EPA strategy keeps the first bead of each cell): balls that
    cut the levels, hold some whole (no query then) or all, or end at a box's far corner. Joined,
    they are the same for a store queried between its adds, whose levels are other ones."""
    from ncfix.collision.deposit import BeadStore

    rng = np.random.default_rng(12)
    t = np.linspace(0.0, 30.0 * np.pi, 9000)
    beads = np.column_stack([50.0 * np.cos(t), 25.0 * np.sin(t), t / 6.0]) + rng.normal(0.0, 0.1, (len(t), 3))
    store, queried = BeadStore(1.0, exact_max=8000), BeadStore(1.0, exact_max=8000)
    for part in np.array_split(beads, 7):
        store.add(part)
        for half in np.array_split(part, 2):
            queried.add(half)
            queried.near(half[0], 1.0)  # closes its open beads into a level
    levels = store.trees()
    assert len(levels) >= 3
    assert [len(pts) for _, pts in queried.trees()] != [len(pts) for _, pts in levels]
    wholes = 0
    for c in (np.zeros(3), np.array([40.0, -10.0, 5.0]), np.array([-30.0, 20.0, 12.0])):
        far = max(float(np.linalg.norm(np.maximum(np.abs(tree.mins - c), np.abs(tree.maxes - c)))) for tree, _ in levels)
        for r in (3.0, 20.0, 45.0, far, far + 1e-6, far + 30.0):
            got = store.near(c, r)
            want = [pts[np.sort(np.asarray(tree.query_ball_point(c, r), dtype=np.int64))] for tree, pts in levels]
            assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
            assert np.array_equal(np.concatenate(got), np.concatenate(queried.near(c, r)))
            wholes += sum(len(g) == len(pts) for g, (_, pts) in zip(got, levels))
    assert wholes >= 3 * len(levels)


@pytest.mark.parametrize("allowance", [0.2, 1.0])
def test_runs_that_gather_once_keep_each_poses_candidates(monkeypatch, allowance):
    """Consecutive poses gather their bead chunks once per run (``first_bead_hits``, ``shared``):
    every pose keeps the hit, clearance, candidates and exact tests it gets visiting every chunk
    of its cells itself. Real poses: the first layer of the corpus print model_1 with its recipe,
    at its tip allowance (1 mm) and at 0.2 mm, where the beads under the nozzle are candidates and
    the poses hit them."""
    import io

    import ncfix
    from conftest import REPO, corpus_path
    from ncfix.collision import checker, exact_beads

    path = corpus_path("multiaxis_3dp_motionplanning", "model_1_Gcode.txt")
    corpus_path("multiaxis_3dp_motionplanning", "extruderHead_converted.stl")
    lines = path.read_bytes().splitlines(keepends=True)[:1200] + [b"M30\n"]
    seen = {"poses": 0, "gathered": 0, "candidates": 0, "hits": 0}
    real = exact_beads.first_bead_hits

    def both(C, R, *args, **kw):
        shared = real(C, R, *args, **kw)
        alone = real(C, R, *args, **kw, shared=False)
        for a, b in zip(shared, alone):
            np.testing.assert_array_equal(a, b)
        p0 = 0
        while p0 < len(C):  # the poses the shared path took in runs it gathered for
            p1 = exact_beads._run_end(np.ascontiguousarray(C), np.ascontiguousarray(R), p0, len(C))
            seen["gathered"] += p1 - p0 if p1 - p0 >= exact_beads.RUN_MIN else 0
            p0 = p1
        seen["poses"] += len(C)
        seen["candidates"] += int(shared[2].sum())
        seen["hits"] += int(shared[0].sum())
        return shared

    monkeypatch.setattr(checker, "first_bead_hits", both)
    ncfix.process(io.BytesIO(b"".join(lines)), io.BytesIO(), config=REPO / "samples" / "model_1.toml", check=True,
                  quiet=True, tip_allowance=allowance)
    assert seen["gathered"] > seen["poses"] // 2
    if allowance < 1.0:
        assert seen["candidates"] > 1000 and seen["hits"] > 100, seen
