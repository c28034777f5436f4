"""The correction stage reuses detection results (``CorrectStage._detect``): only rows whose move
or nearby beads an episode changed are checked again. Reuse must not change anything: the same
output and report as checking everything again, and at every detection the same result as a
fresh check of all the rows.

The program: pass 1 deposits along x at y = 0; the head's body meets a box part over a few
blocks (episode 1). The strategy here moves every level of an episode 5 mm along +y (no search:
fast, and the beads of pass 1 move with it). Pass 2 runs along x at y = 5 with its tip 1.5 mm
below pass 1's beads: 5 mm beside the beads as programmed (free), right under the moved ones
(the nozzle meets them: episode 2, which only a detection that sees the corrected beads finds).
"""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pytest
import trimesh

import ncfix.correct.solve as solve
import ncfix.correct.strategies as registry
import ncfix.pipeline as pipeline
from ncfix.collision.path import MoveHits
from ncfix.config import Options
from ncfix.correct.solve import Solution
from ncfix.correct.stage import CorrectStage
from ncfix.pipeline import run
from test_epa_strategy import HEAD

SHIFT_MM = 5.0


class ShiftStrategy:
    """Every level of an episode moves SHIFT_MM along +y; nothing is left unresolved."""

    name = "shift"

    def __init__(self, options):
        self.episodes = []

    def solve(self, ep):
        self.episodes.append((int(ep.first), int(ep.last)))
        words = ep.programmed.copy()
        words[:, 1] += SHIFT_MM
        return Solution(words)


def _program() -> bytes:
    def move(code, x, y, z):
        return f"{code} X{x:.3f} Y{y:.3f} Z{z:.3f} I0 J0 K1\n"

    lines = ["%\n", "O0001 (DETECT REUSE)\n", "G21 G90 G94 G17\n", "G54\n", "G43.5 H1\n",
             move("G0", -100.0, 0.0, 20.0), move("G1", -100.0, 0.0, 0.0) + "M3\n"]
    lines += [move("G1", x, 0.0, 0.0) for x in np.arange(-90.0, 100.0 + 1e-9, 10.0)]
    lines += ["M5\n", move("G0", 100.0, 0.0, 50.0), move("G0", -130.0, SHIFT_MM, 50.0),
              move("G0", -130.0, SHIFT_MM, -7.5)]
    lines += [move("G1", x, SHIFT_MM, -7.5) for x in np.arange(-120.0, 130.0 + 1e-9, 10.0)]
    lines += [move("G0", 130.0, SHIFT_MM, 50.0), "M30\n", "%\n"]
    return "".join(lines).encode()


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """Met by pass 1's body (3.5 mm deep: 28 mm from the axis, 24 mm up), 1.5 mm clear of pass 2's."""
    path = tmp_path_factory.mktemp("reuse") / "box.stl"
    trimesh.creation.box(bounds=[[-10.0, -40.0, 30.0], [10.0, -24.5, 45.0]]).export(path)
    return str(path)


def _collect(monkeypatch, owner, name, made_by):
    """Replace owner.name by a wrapper that records what each call makes (``made_by(original,
    *args, **kw)`` returns it); the list of them."""
    made = []
    original = getattr(owner, name)

    def spy(*args, **kw):
        made.append(made_by(original, *args, **kw))
        return made[-1] if name != "__init__" else None

    monkeypatch.setattr(owner, name, spy)
    return made


@pytest.fixture
def strategies(monkeypatch):
    """The ShiftStrategy objects the stage makes (in place of the real strategy)."""
    return _collect(monkeypatch, registry, "make_strategy", lambda _, options: ShiftStrategy(options))


@pytest.fixture
def stages(monkeypatch):
    """The CorrectStage objects the pipeline makes."""
    def init(original, self, *args, **kw):
        original(self, *args, **kw)
        return self

    return _collect(monkeypatch, CorrectStage, "__init__", init)


@pytest.fixture
def shadow(monkeypatch):
    """Compares every detection with a fresh check of all its rows; collects the differences."""
    differences = []
    detect = CorrectStage._detect

    def checked(self, a, b):
        result = detect(self, a, b)
        full, known = result  # rows a..known-1 have a current result: those are compared
        m = known - a  # (rows stop early only with reuse, where a row's sample is its own index)
        hits = full if known == b else MoveHits(full.part_hit[:m], full.deposit_hit[:m], full.deposit_clearance[:m],
                                                full.sample[:m], full.C[:m], full.R[:m], full.samples)
        fresh, _ = self.path.check(self.moves(a, known), self.store, 0, commit=False)
        rows = np.nonzero((hits.part_hit != fresh.part_hit).any(axis=1) | (hits.deposit_hit != fresh.deposit_hit)
                          | (hits.deposit_clearance != fresh.deposit_clearance)
                          | ((hits.sample >= 0) != (fresh.sample >= 0)))[0]
        same = np.nonzero(hits.sample >= 0)[0]
        same = same[np.isin(same, rows, invert=True)]
        moved = ~np.all(hits.C[hits.sample[same]] == fresh.C[fresh.sample[same]], axis=1)
        differences.extend((a + int(r)) for r in np.concatenate([rows, same[moved]]))
        return result

    monkeypatch.setattr(CorrectStage, "_detect", checked)
    return differences


def _fix(data: bytes, box: str, **kw):
    options = replace(Options(head=str(HEAD), part=(box,), check=False, device="cpu", deposit_codes=("M3", "M5"),
                              max_tilt=20.0, max_step=10.0), **kw)
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, options, "reuse.nc")
    return out.getvalue(), report


def _entries(report) -> tuple:
    return report.changes, report.unresolved, report.collisions, report.summary["colliding_blocks_before"]


@pytest.mark.parametrize("window, chunk_lines", [(2000, None), (7, 10)])
def test_reused_detection_changes_nothing(monkeypatch, box, strategies, stages, shadow, window, chunk_lines):
    if chunk_lines:  # chunks go out (and their rows leave the table) while later ones come in
        read_chunks = pipeline.read_chunks
        monkeypatch.setattr(pipeline, "read_chunks", lambda src, interp: read_chunks(src, interp, chunk_lines))
    data = _program()
    out, report = _fix(data, box, window=window)
    reused_rows = stages[-1].checked_rows
    assert shadow == []  # every detection equals a fresh check of all its rows
    episodes = strategies[-1].episodes
    assert len(episodes) == 2  # the box, then the moved beads
    bodies = {tuple(c["bodies"]) for c in report.collisions}
    assert ("part:box.stl",) in bodies and ("deposit",) in bodies

    monkeypatch.setattr(CorrectStage, "REUSE_DETECTION", False)
    again, report_again = _fix(data, box, window=window)
    assert again == out
    assert _entries(report_again) == _entries(report)
    assert strategies[-1].episodes == episodes
    # Detection after episode 1 checked again only the rows near its beads (and its row after).
    assert reused_rows < stages[-1].checked_rows
    print(f"\nwindow {window}: rows checked {reused_rows} with reuse, {stages[-1].checked_rows} without")


def test_rows_near_the_moved_beads_are_checked_again(monkeypatch, box, strategies, shadow):
    """Reuse that ignores the moved beads misses episode 2: the test above would see it."""
    monkeypatch.setattr(CorrectStage, "_forget", lambda self, before, first, end: None)
    _, report = _fix(_program(), box)
    assert len(strategies[-1].episodes) == 1
    assert shadow  # some detection differs from a fresh check
    assert ("deposit",) not in {tuple(c["bodies"]) for c in report.collisions}


class ProbeStrategy:
    """At the first episode, re-checks one episode spanning both passes (``Episode.recheck``, which
    reuses the last re-check's results) with several words, beside a fresh check of all its
    moves; leaves every episode as programmed."""

    name = "probe"

    def __init__(self, options):
        self.probes = []  # (re-check, fresh check, moves checked, moves) per words

    def solve(self, ep):
        if not self.probes:
            stage = ep.stage
            wide = solve.Episode(stage, ep.first, len(stage.rows) - 2, ep.colliding)
            pass_1 = np.nonzero(wide.stage.rows.deposit[wide.rows])[0]
            pass_2 = np.nonzero(wide.programmed[:, 2] < -1.0)[0]
            shifted = wide.programmed.copy()
            shifted[pass_1, 1] += SHIFT_MM  # the beads move under pass 2
            last_moved = shifted.copy()
            last_moved[pass_2[-1], 0] += 1.0  # and then only pass 2's last block
            for words in (wide.programmed, shifted, last_moved, wide.programmed):
                checked = wide.checks.checked
                self.probes.append((wide.recheck(words), _fresh(wide, words), wide.checks.checked - checked,
                                    len(wide.rows)))
            self.pass_2 = pass_2
        return Solution(ep.programmed.copy(), [int(r) for r in ep.colliding])


def _fresh(ep, words) -> np.ndarray:
    """Episode.recheck without reuse: every move checked."""
    stage, r = ep.stage, ep.stage.rows
    end = ep.last + 1 if ep.after_row is None else ep.last + 2
    saved = r.words[ep.first:end].copy()
    try:
        r.words[ep.first:ep.last + 1] = stage.as_printed(ep.rows, words)
        hits, _ = stage.path.check(stage.moves(ep.first, end), stage.store, 0, commit=False)
    finally:
        r.words[ep.first:end] = saved
    bad = hits.any
    out = bad[:len(ep.rows)].copy()
    if ep.after_row is not None and bad[-1]:
        out[-1] = True
    return out


@pytest.fixture
def probes(monkeypatch):
    return _collect(monkeypatch, registry, "make_strategy", lambda _, options: ProbeStrategy(options))


def test_a_recheck_reuses_only_what_the_changed_moves_leave_alone(box, probes):
    _fix(_program(), box)
    probe = probes[-1]
    (first, fresh_first, n_first, L), (shifted, fresh_shifted, _, _), (moved, fresh_moved, n_moved, _), \
        (again, fresh_again, _, _) = probe.probes
    # The programmed words are what detection checked: every move keeps detection's result.
    assert np.array_equal(first, fresh_first) and n_first == 0
    assert np.array_equal(shifted, fresh_shifted)
    assert np.array_equal(moved, fresh_moved)
    assert np.array_equal(again, fresh_again)
    # Pass 2 keeps its words but meets the moved beads: only a re-check that sees them finds it.
    assert not first[probe.pass_2].any() and shifted[probe.pass_2].any()
    # Moving pass 2's last block checks again that move and the one after it, not the episode.
    assert 0 < n_moved <= 2 < L


def test_a_recheck_that_ignores_the_moved_beads_would_miss_them(monkeypatch, box, probes):
    """The test above can fail: a re-check that reuses every unchanged move misses pass 2."""
    import ncfix.correct.stage as stage

    monkeypatch.setattr(stage, "near_beads", lambda *args: np.zeros(len(args[1]), dtype=bool))
    _fix(_program(), box)
    (_, _, _, _), (shifted, fresh_shifted, _, _) = probes[-1].probes[:2]
    assert not np.array_equal(shifted, fresh_shifted)


@pytest.mark.heavy
def test_rows_made_stale_wait_for_detection_to_reach_them(monkeypatch, stages):
    """A row an episode made stale is checked again when detection reaches it: past an episode seen
    whole (``CorrectStage._closed``), stale rows wait for it to be solved, since its beads may
    make them stale again. On bathtub_273, whose episodes' beads reach rows of the
    spiral's later turns, the fix then checks fewer rows than one that checks every stale row of
    the window after each episode, and writes the same program and report."""
    from pathlib import Path

    import ncfix

    samples = Path(__file__).resolve().parents[1] / "samples"

    def fix():
        out = io.BytesIO()
        report = ncfix.process(io.BytesIO((samples / "bathtub_273.nc").read_bytes()), out, config=samples / "ncfix.toml",
                               device="cpu")
        return out.getvalue(), report, stages[-1].checked_rows

    out, report, lazy_rows = fix()
    monkeypatch.setattr(CorrectStage, "_closed", lambda self, a, s: False)
    again, report_again, eager_rows = fix()
    assert again == out
    assert _entries(report_again) == _entries(report)
    assert report.summary["colliding_blocks_before"] > 50 and report.summary["changed_blocks"] > 50
    assert lazy_rows < eager_rows
    print(f"\nrows checked by detection: {lazy_rows}, {eager_rows} checking every stale row after each episode")


class BeadsProbe:
    """At each episode, an episode over both passes: its programmed beads and each one's level,
    beside ``PathChecker.bead_points`` of each level's programmed move on its own (the first
    from the row before as it will be written); leaves every episode as programmed."""

    name = "beads-probe"

    def __init__(self, options):
        self.seen = []

    def solve(self, ep):
        stage = ep.stage
        wide = solve.Episode(stage, ep.first, len(stage.rows) - 2, ep.colliding)
        pts, seq = [], []
        for i, row in enumerate(wide.rows):
            moves = stage.moves(int(row), int(row) + 1)
            moves.w_end = wide.programmed[i:i + 1]
            if i > 0:
                moves.w_start = wide.programmed[i - 1:i]
            beads = wide.path.bead_points(moves)
            pts.append(beads)
            seq.append(np.full(len(beads), i, dtype=np.int64))
        self.seen.append((wide.bead_pts, wide.bead_seq, np.concatenate(pts), np.concatenate(seq)))
        return Solution(ep.programmed.copy(), [int(r) for r in ep.colliding])


def test_an_episodes_programmed_beads_are_each_levels_own(monkeypatch, box):
    """``Episode``'s beads, laid in one batch of moves, are each level's move's, level by level."""
    made = _collect(monkeypatch, registry, "make_strategy", lambda _, options: BeadsProbe(options))
    _fix(_program(), box)
    assert made[-1].seen
    for pts, seq, each, each_seq in made[-1].seen:
        assert len(each) and len(np.unique(each_seq)) > 1
        assert np.array_equal(pts, each) and np.array_equal(seq, each_seq)
