"""The exact deposit test's bucket grid (``exact_beads.BeadBuckets``)."""

import numpy as np
import pytest

from ncfix.collision.exact_beads import CELL_MM, MAX_CELLS, BeadBuckets


def _numpy_buckets(beads, seq, lo, hi):
    """The bucket grid as numpy states it (the formulation the compiled counting sort replaced):
    (index, beads, seq, lo, cell, dims, cell_beads, cell_start)."""
    lo = np.maximum(np.asarray(lo, dtype=np.float64), beads.min(axis=0) if len(beads) else lo)
    hi = np.minimum(np.asarray(hi, dtype=np.float64), beads.max(axis=0) if len(beads) else hi)
    inside = np.nonzero((beads >= lo).all(axis=1) & (beads <= hi).all(axis=1))[0] if len(beads) else \
        np.zeros(0, dtype=np.int64)
    cell = CELL_MM
    extent = np.maximum(hi - lo, 0.0) if len(inside) else np.zeros(3)
    while np.prod(np.floor(extent / cell) + 1) > MAX_CELLS:
        cell *= 2.0
    dims = (np.floor(extent / cell) + 1).astype(np.int64)
    kept = beads[inside]
    if len(inside):
        ijk = np.minimum(np.floor((kept - lo) / cell).astype(np.int64), dims - 1)
        flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    else:
        flat = np.zeros(0, dtype=np.int64)
    counts = np.bincount(flat, minlength=int(np.prod(dims)))
    return (inside, kept, np.asarray(seq, dtype=np.int64)[inside], lo, cell, dims,
            np.argsort(flat, kind="stable"), np.concatenate([[0], np.cumsum(counts)]))


def _cases():
    rng = np.random.default_rng(7)
    for k in range(40):
        n = int(rng.integers(0, 2500))
        beads = rng.uniform(-50.0, 50.0, (n, 3))
        beads[: n // 3] = np.round(beads[: n // 3] / CELL_MM) * CELL_MM  # on cell faces and box faces
        seq = rng.integers(-1, 100, n)
        lo = rng.uniform(-60.0, 10.0, 3)
        hi = lo + rng.uniform(-5.0, 90.0, 3)  # sometimes empty on an axis
        if k % 8 == 0:
            lo, hi = lo - 5e4, hi + 5e4  # a huge box: clipped to the beads
        if k % 8 == 1 and n:
            lo, hi = beads[0] - 1e-9, beads[0]  # one bead on the box's face
        yield beads, seq, lo, hi


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: f"{len(c[0])}")
def test_buckets_are_the_numpy_formulation(case):
    """The compiled filter and counting sort give exactly the arrays of the numpy formulation
    (the order inside a cell is the beads' order, which the exact test's tie-breaks follow)."""
    beads, seq, lo, hi = case
    got = BeadBuckets(beads, seq, lo, hi)
    want = _numpy_buckets(beads, seq, lo, hi)
    names = ("index", "beads", "seq", "lo", "cell", "dims", "cell_beads", "cell_start")
    for name, value in zip(names, want):
        mine = np.asarray(getattr(got, name))
        assert mine.dtype == np.asarray(value).dtype, name
        assert np.array_equal(mine, value), name


def test_every_bead_inside_is_in_its_cell():
    """Each kept bead lies in the box of the cell it is listed under."""
    beads, seq, lo, hi = next(c for c in _cases() if len(c[0]) > 500)
    got = BeadBuckets(beads, seq, lo - 1e3, hi + 1e3)
    assert len(got.beads) == len(beads)
    d0, d1, d2 = got.dims
    for c in range(int(d0 * d1 * d2)):
        members = got.beads[got.cell_beads[got.cell_start[c]:got.cell_start[c + 1]]]
        ijk = np.array([c // (d1 * d2), (c // d2) % d1, c % d2])
        low = got.lo + ijk * got.cell
        assert (members >= low - 1e-9).all()
        top = ijk < got.dims - 1  # the last cell of an axis takes what lies beyond it
        assert (members[:, top] < (low + got.cell)[top] + 1e-9).all()


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


def test_store_near_gives_each_levels_ball_query_in_its_order():
    """``BeadStore.near`` gives, level by level, exactly what each level's k-d tree's ball query
    gives, in its order (the EPA strategy keeps the first bead of each cell in that order): balls
    that cut the levels, hold some whole (no query then) or all, or end at a box's far corner."""
    from ncfix.collision.deposit import BeadStore

    rng = np.random.default_rng(12)
    t = np.linspace(0.0, 30.0 * np.pi, 9000)
    beads = np.column_stack([50.0 * np.cos(t), 25.0 * np.sin(t), t / 6.0]) + rng.normal(0.0, 0.1, (len(t), 3))
    store = BeadStore(1.0, exact_max=8000)
    for part in np.array_split(beads, 7):
        store.add(part)
    levels = store.trees()
    assert len(levels) >= 3
    wholes = 0
    for c in (np.zeros(3), np.array([40.0, -10.0, 5.0]), np.array([-30.0, 20.0, 12.0])):
        far = max(float(np.linalg.norm(np.maximum(np.abs(tree.mins - c), np.abs(tree.maxes - c)))) for tree, _ in levels)
        for r in (3.0, 20.0, 45.0, far, far + 1e-6, far + 30.0):
            got = store.near(c, r)
            want = [pts[np.asarray(tree.query_ball_point(c, r), dtype=np.int64)] for tree, pts in levels]
            assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
            wholes += sum(len(g) == len(pts) for g, (_, pts) in zip(got, levels))
    assert wholes >= 3 * len(levels)
