"""The bead field's chord stamp cut into slabs of the grid's rows for several threads: the slabs
cover the rows once, a slab's stamp writes only its rows and every cell of them, and the grid
comes out the same to the bit for any cut and any number of threads."""

from __future__ import annotations

import numpy as np
import pytest

from ncfix.collision import deposit
from ncfix.collision.split import map_parts
from ncfix.collision.deposit import (
    FIELD_SLACK_MM,
    FINE_LEVELS,
    BeadField,
    _stamp_kernels,
    bead_samples,
    stamp_slabs,
)

H, RADIUS, STEP = 0.5, 1.0, 3.0 / FINE_LEVELS
REACH = STEP * FINE_LEVELS + RADIUS + FIELD_SLACK_MM


@pytest.mark.parametrize("threads", [1, 2, 3, 8])
@pytest.mark.parametrize("count", [0, 1, 2, 5, 40])
def test_map_parts_does_every_part_once_in_order(threads, count):
    import threading

    seen = []
    got = map_parts(lambda lo, hi: seen.append(threading.get_ident()) or list(range(lo, hi)),
                    [(10 * i, 10 * i + 10) for i in range(count)], threads)
    assert got == [list(range(10 * i, 10 * i + 10)) for i in range(count)] and len(seen) == count


def test_map_parts_raises_a_parts_error():
    def call(i):
        if i == 3:
            raise ValueError("part 3")
        return i

    with pytest.raises(ValueError, match="part 3"):
        map_parts(call, [(i,) for i in range(8)], 2)


def _random_chords(seed: int, count: int, span_mm: float):
    """Chords of every kind: slanted, vertical, level, single beads, some reaching off the grid."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-2.0, span_mm + 2.0, (count, 3))
    b = a + rng.normal(0.0, 1.5, (count, 3))
    b[1::5, :2] = a[1::5, :2]
    b[2::5, 2] = a[2::5, 2]
    b[::7] = a[::7]
    return a, b, rng.uniform(0.0, 0.01, count)


def _wall_chords(layers: int, width_mm: float):
    """The chords of a zigzag wall's bead chain (as ``BeadField.add`` makes them)."""
    ends = [np.array([0.0 if k % 2 == 0 else width_mm, 0.3 * k, 0.5 * k]) for k in range(layers + 1)]
    starts, stops = np.array(ends[:-1]), np.array(ends[1:])
    counts, t = bead_samples(starts, stops, 0.25)
    move = np.repeat(np.arange(len(starts)), counts)
    pts = starts[move] + t[:, None] * (stops - starts)[move]
    field = BeadField(RADIUS, H)
    a, b, dev, _ = field._chords(pts)
    return a, b, dev


def _clustered_chords():
    """Chords packed into the low fifth of the x range."""
    a, b, dev = _random_chords(9, 80, 12.0)
    squeeze = np.array([0.2, 1.0, 1.0])
    return a * squeeze, b * squeeze, dev


CHORD_SETS = {
    "random": _random_chords(3, 60, 10.0),
    "few": _random_chords(5, 3, 4.0),
    "wall": _wall_chords(12, 14.0),
    "clustered": _clustered_chords(),
}
GRIDS = [((1, 8, 8), (-2, -2, -2)), ((2, 5, 40), (3, -4, -4)), ((7, 30, 30), (-4, -4, -4)),
         ((33, 17, 29), (-6, -2, -3)), ((40, 40, 40), (-4, -4, -4))]


def _one_thread(shape, lo, a, b, dev):
    grid = np.full(shape, FINE_LEVELS, dtype=np.uint8)
    _stamp_kernels().stamp_slab(grid, lo, H, a, b, dev, RADIUS, STEP, FINE_LEVELS, FIELD_SLACK_MM, 0, shape[0])
    return grid


@pytest.mark.parametrize("name", list(CHORD_SETS))
@pytest.mark.parametrize("shape, lo", GRIDS)
def test_each_slab_stamps_exactly_its_rows(name, shape, lo):
    """Stamped alone into a fresh grid, a slab changes no cell outside its rows, and the slabs of
    every cut together give every cell its one-thread value (an edge row lost or stamped twice,
    or a slab reaching past its edge, would show)."""
    a, b, dev = CHORD_SETS[name]
    lo = np.array(lo, dtype=np.int64)
    whole = _one_thread(shape, lo, a, b, dev)
    assert (whole < FINE_LEVELS).any()
    nx = shape[0]
    cuts = [[0, nx]] + [[0, x, nx] for x in range(1, nx)] + [list(range(nx + 1))]
    for edges in cuts:
        joined = np.full(shape, FINE_LEVELS, dtype=np.uint8)
        for x0, x1 in zip(edges[:-1], edges[1:]):
            part = np.full(shape, FINE_LEVELS, dtype=np.uint8)
            _stamp_kernels().stamp_slab(part, lo, H, a, b, dev, RADIUS, STEP, FINE_LEVELS, FIELD_SLACK_MM, x0, x1)
            assert (part[:x0] == FINE_LEVELS).all() and (part[x1:] == FINE_LEVELS).all()
            assert np.array_equal(part[x0:x1], whole[x0:x1])
            np.minimum(joined, part, out=joined)
        assert np.array_equal(joined, whole)


@pytest.mark.parametrize("name", list(CHORD_SETS))
@pytest.mark.parametrize("shape, lo", GRIDS)
@pytest.mark.parametrize("count", [2, 3, 5, 64])
def test_slabs_cover_the_rows_once_in_order(name, shape, lo, count):
    a, b, dev = CHORD_SETS[name]
    slabs = stamp_slabs(shape, np.array(lo, dtype=np.int64), H, a, b, dev, REACH, count, least=0)
    assert slabs[0][0] == 0 and slabs[-1][1] == shape[0]
    assert all(x0 < x1 for x0, x1 in slabs) and all(p[1] == q[0] for p, q in zip(slabs, slabs[1:]))
    assert len(slabs) <= count


def test_a_small_stamp_is_one_slab():
    a, b, dev = CHORD_SETS["few"]
    shape, lo = (40, 40, 40), np.array([-4, -4, -4], dtype=np.int64)
    assert stamp_slabs(shape, lo, H, a, b, dev, REACH, 2) == [(0, 40)]
    assert len(stamp_slabs(shape, lo, H, a, b, dev, REACH, 2, least=0)) == 2
    assert stamp_slabs(shape, lo, H, a, b, dev, REACH, 1, least=0) == [(0, 40)]


def test_slabs_follow_where_the_chords_are():
    """Chords packed at the low x end: the slabs there are narrow, and each slab gets about the
    same share of the stamp's work (timed one after the other, in one thread, by cells written)."""
    rng = np.random.default_rng(4)
    a = rng.uniform(0.0, 20.0, (300, 3))
    a[:, 0] = rng.uniform(0.0, 3.0, 300)
    a[:30, 0] = rng.uniform(3.0, 40.0, 30)
    b = a + rng.normal(0.0, 0.4, (300, 3))
    dev = np.zeros(300)
    shape, lo = (100, 60, 60), np.array([-10, -10, -10], dtype=np.int64)
    slabs = stamp_slabs(shape, lo, H, a, b, dev, REACH, 2, least=0)
    assert len(slabs) == 2 and slabs[0][1] - slabs[0][0] < 0.35 * shape[0]
    # Cells each chord's stamp reaches, per slab: the work counted in reached cells (no timing).
    whole = _one_thread(shape, lo, a, b, dev)
    reached = [0, 0]
    for s in range(len(a)):
        g = _one_thread(shape, lo, a[s:s + 1], b[s:s + 1], dev[s:s + 1])
        rows = (g < FINE_LEVELS).sum(axis=(1, 2))
        for n, (x0, x1) in enumerate(slabs):
            reached[n] += int(rows[x0:x1].sum())
    assert (whole < FINE_LEVELS).any()
    assert 0.6 < reached[0] / reached[1] < 1.6


@pytest.mark.parametrize("name", list(CHORD_SETS))
@pytest.mark.parametrize("shape, lo", GRIDS)
@pytest.mark.parametrize("threads", [2, 3, 4])
def test_the_threaded_stamp_equals_the_one_thread_stamp(monkeypatch, name, shape, lo, threads):
    monkeypatch.setattr(deposit, "STAMP_SPLIT_COLUMNS", 0)
    a, b, dev = CHORD_SETS[name]
    lo = np.array(lo, dtype=np.int64)
    whole = _one_thread(shape, lo, a, b, dev)
    assert len(stamp_slabs(shape, lo, H, a, b, dev, REACH, threads)) > 1 or shape[0] == 1
    for _ in range(3):  # threads race differently each time
        grid = np.full(shape, FINE_LEVELS, dtype=np.uint8)
        _stamp_kernels().stamp_chords(grid, lo, H, a, b, dev, RADIUS, STEP, FINE_LEVELS, FIELD_SLACK_MM, threads)
        assert np.array_equal(grid, whole)
    for setting in ("1", str(threads)):
        monkeypatch.setenv("NCFIX_THREADS", setting)
        grid = np.full(shape, FINE_LEVELS, dtype=np.uint8)
        _stamp_kernels().stamp_chords(grid, lo, H, a, b, dev, RADIUS, STEP, FINE_LEVELS, FIELD_SLACK_MM)
        assert np.array_equal(grid, whole)


def _helix(turns: float, seed: int) -> np.ndarray:
    """Bead centres of a rising helix with a jump in it (two chains), 0.25 mm apart."""
    s = np.arange(0.0, turns * 2 * np.pi * 8.0, 0.25)
    pts = np.stack([8.0 * np.cos(s / 8.0), 8.0 * np.sin(s / 8.0), 0.02 * s], axis=1)
    cut = np.random.default_rng(seed).integers(len(pts) // 4, 3 * len(pts) // 4)
    pts[cut:] += [3.0, 0.0, 0.0]
    return pts


def test_a_bead_field_and_its_overlays_come_out_the_same_on_several_threads(monkeypatch):
    """Beads added and growing overlays (which start from the last overlay's stamps) give the same
    grids split on three threads as on one (``NCFIX_THREADS=1``)."""
    monkeypatch.setattr(deposit, "STAMP_SPLIT_COLUMNS", 0)
    pts = _helix(8.0, 1)
    fields = {}
    for setting in ("1", "3"):
        monkeypatch.setenv("NCFIX_THREADS", setting)
        field = BeadField(RADIUS, H)
        field.add(pts[:400])
        field.add(pts[400:900])
        seen = []
        hits = 0
        for end in range(950, len(pts), 150):
            last = field._overlaid
            hits += last is not None and np.array_equal(last[0], pts[900:900 + len(last[0])])
            with field.overlay(pts[900:end]):
                seen.append((field.fine.copy(), field.coarse.copy()))
        field.add(pts[900:])
        fields[setting] = (field, seen, hits)
    one, three = fields["1"], fields["3"]
    assert one[2] == three[2] >= 3  # the overlays did reuse the last one's stamps
    assert np.array_equal(one[0].fine, three[0].fine) and np.array_equal(one[0].fine_lo, three[0].fine_lo)
    assert np.array_equal(one[0].coarse, three[0].coarse)
    assert len(one[1]) == len(three[1]) > 3
    for (f1, c1), (f3, c3) in zip(one[1], three[1]):
        assert np.array_equal(f1, f3) and np.array_equal(c1, c3)
