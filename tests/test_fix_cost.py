"""A fix costs what it changes: on a long program with one collision episode, the fix checks every
move once (detection) and then only the moves the episode changed. The re-checks start from what
detection found (``Rechecks`` takes the detection of the episode's rows), so a move the strategy
leaves as detected is not checked again, and nothing about the rest of the program is.

The program: one pass along x at y = 0, 5 mm blocks, no deposit (no beads: the only moves to check
again are the changed ones); the head's body meets a box part over a few blocks in the middle. The
strategy moves the colliding levels 5 mm along +y (clear of the box), re-checks that solution
once (``Episode.recheck``) and keeps it.
"""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pytest
import trimesh

import ncfix.correct.strategies as strategies_module
from ncfix.collision.path import PathChecker
from ncfix.config import Options
from ncfix.correct.solve import Solution
from ncfix.pipeline import run
from test_epa_strategy import HEAD

SHIFT_MM = 5.0


class ShiftColliding:
    """The colliding levels move SHIFT_MM along +y; the solution is re-checked once."""

    name = "shift-colliding"

    def __init__(self, options):
        self.episodes = []  # (levels, colliding levels, moves the solution changed, moves re-checked, re-check)

    def solve(self, ep):
        words = ep.programmed.copy()
        words[ep.is_colliding, 1] += SHIFT_MM
        checked = ep.checks.checked
        bad = ep.recheck(words)
        # The moves of the re-check (the levels and the one into the row after) whose words differ.
        end = len(ep.rows) + (ep.after_row is not None)
        changed_rows = np.append(ep.is_colliding, False)[:end]
        changed_moves = changed_rows | np.append(False, changed_rows[:-1])
        self.episodes.append((len(ep.rows), np.nonzero(ep.is_colliding)[0], int(changed_moves.sum()),
                              ep.checks.checked - checked, bad))
        return Solution(words, [int(r) for r in ep.rows[bad]])


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """Met by the pass's body (28 mm from the axis, 24 mm up) over a few blocks around x = 0."""
    path = tmp_path_factory.mktemp("cost") / "box.stl"
    trimesh.creation.box(bounds=[[-6.0, -40.0, 30.0], [6.0, -24.5, 45.0]]).export(path)
    return str(path)


def _program(half_length_mm: float) -> bytes:
    def move(code, x, y, z):
        return f"{code} X{x:.3f} Y{y:.3f} Z{z:.3f} I0 J0 K1\n"

    lines = ["%\n", "O0001 (FIX COST)\n", "G21 G90 G94 G17\n", "G54\n", "G43.5 H1\n",
             move("G0", -half_length_mm, 0.0, 20.0), move("G1", -half_length_mm, 0.0, 0.0)]
    lines += [move("G1", x, 0.0, 0.0) for x in np.arange(-half_length_mm + 5.0, half_length_mm + 1e-9, 5.0)]
    lines += [move("G0", half_length_mm, 0.0, 50.0), "M30\n", "%\n"]
    return "".join(lines).encode()


def _fix(monkeypatch, box, half_length_mm):
    """The fix of the program: (strategy, moves checked by every ``PathChecker.check``, motion rows)."""
    strategies = []
    monkeypatch.setattr(strategies_module, "make_strategy", lambda options: strategies.append(ShiftColliding(options))
                        or strategies[-1])
    checked = []
    original = PathChecker.check

    def spy(self, moves, *args, **kw):
        checked.append(len(moves))
        return original(self, moves, *args, **kw)

    monkeypatch.setattr(PathChecker, "check", spy)
    options = replace(Options(head=str(HEAD), part=(box,), check=False, device="cpu", bead_radius=0.0,
                              max_tilt=20.0, max_step=10.0), window=50)
    data = _program(half_length_mm)
    report = run(io.BytesIO(data), io.BytesIO(), options, "cost.nc")
    assert report.summary["unresolved_blocks"] == 0
    rows = report.summary["motion_blocks"]
    return strategies[-1], sum(checked), rows


@pytest.mark.parametrize("half_length_mm", [500.0, 1000.0])
def test_a_fix_checks_the_moves_it_changes_and_nothing_else(monkeypatch, box, half_length_mm):
    strategy, checked, rows = _fix(monkeypatch, box, half_length_mm)
    assert rows > 4 * 50  # several windows long
    assert len(strategy.episodes) == 1
    levels, colliding, changed_moves, rechecked, bad = strategy.episodes[0]
    assert len(colliding) >= 1 and np.all(np.diff(colliding) == 1)  # one run of colliding blocks
    assert not bad.any()
    assert levels > len(colliding) + 2  # the episode has ramp levels the solution leaves alone
    # The re-check checks the moves the solution changed, not the episode's levels: the rest keep
    # what detection found.
    assert rechecked == changed_moves < levels
    # Detection checks every motion row once; the episode adds its changed moves, whatever the length.
    assert checked == rows + changed_moves
