"""The material and the feed follow a fix (ncfix.correct.extrusion): with --pivot tip the programmed
points of re-oriented blocks move, and the E words (absolute and relative) and inverse-time F of the
moves whose length changed are rewritten so that each keeps its programmed rate, the episode keeps
its extrusion, and no line outside the episode changes."""

from __future__ import annotations

import io
import re
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest

from ncfix.config import Options
from ncfix.pipeline import run

HERE = Path(__file__).parent
HEAD = HERE.parent / "samples" / "deposition_head.stl"
WALL = HERE / "golden" / "meshes" / "wall_x.stl"  # a box x -10..10, y 25..40: the head's body reaches it
STANDOFF = 6.0
STEP_MM = 4.0
E_PER_MM = 0.05
FEED = 1200.0  # mm/min
MOVE = re.compile(r"^G1 X(\S+) Y(\S+) Z(\S+) I\S+ J\S+ K\S+ (?:E(\S+))? ?(?:F(\S+))?")


def _program(e_mode: str | None, inverse_time: bool = False, sparse: bool = False) -> bytes:
    """A path of 4 mm blocks at 30° to the wall and past it, so that the tilt away from the wall
    moves P along the path and the moves get longer or shorter. ``e_mode``: "M82", "M83" or None
    (no E words); ``sparse``: the feed moves leave out I J K (posts that state only what changes)."""
    d = np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])
    points = [s * d for s in np.arange(-100.0, 160.0 + 1e-9, STEP_MM)]
    lines = ["%", "O0001 (THE MATERIAL FOLLOWS THE FIX)",
             f"N10 G21 G90 {'G93' if inverse_time else 'G94'} G17", "N20 G43.5 H1"]
    if e_mode:
        lines += [e_mode, "G92 E0"]
    x, y, _ = points[0]
    lines.append(f"G0 X{x:.3f} Y{y:.3f} Z20.000 I0.000000 J0.000000 K1.000000")
    plunge_feed = f"F{FEED / 20.0:.3f}" if inverse_time else f"F{FEED:.0f}"
    lines.append(f"G1 X{x:.3f} Y{y:.3f} Z0.000 I0.000000 J0.000000 K1.000000 {plunge_feed}")
    e = 0.0
    for p in points[1:]:
        words = f"G1 X{p[0]:.3f} Y{p[1]:.3f} Z0.000" + ("" if sparse else " I0.000000 J0.000000 K1.000000")
        if e_mode:
            e += E_PER_MM * STEP_MM
            words += f" E{(E_PER_MM * STEP_MM if e_mode == 'M83' else e):.5f}"
        if inverse_time:
            words += f" F{FEED / STEP_MM:.3f}"
        lines.append(words)
    lines += ["G0 Z20.000", "M30", "%"]
    return ("\n".join(lines) + "\n").encode()


def _fix(data: bytes, pivot: str = "tip"):
    options = Options(head=str(HEAD), part=[str(WALL)], check=False, device="cpu", bead_radius=0.0,
                      strategy="graph", standoff=STANDOFF, pivot=pivot)
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, options, "follow.nc")
    return out.getvalue(), report


def _moves(data: bytes):
    """Per feed line with X Y Z: (line, P (3,), E text or None, F text or None)."""
    out = []
    for i, raw in enumerate(data.decode().splitlines(), 1):
        m = MOVE.match(raw)
        if m:
            out.append((i, np.array([float(v) for v in m.group(1, 2, 3)]), m.group(4), m.group(5)))
    return out


def _episode(data: bytes, report) -> tuple[int, int]:
    """First and last line of the episode: the re-oriented blocks and the move after the last."""
    tilted = [c["line"] for c in report.changes if c["reason"] in ("collision", "blend")]
    assert tilted, "the wall must make ncfix re-orient blocks"
    after = [line for line, *_ in _moves(data) if line > max(tilted)]
    return min(tilted), after[0] if after else max(tilted)


def _changed_lines(data: bytes, fixed: bytes) -> set[int]:
    a, b = data.splitlines(), fixed.splitlines()
    assert len(a) == len(b)
    return {i for i, (x, y) in enumerate(zip(a, b), 1) if x != y}


@pytest.fixture(scope="module", params=["M82", "M83"])
def e_fix(request):
    data = _program(request.param)
    fixed, report = _fix(data)
    return request.param, data, fixed, report


def test_each_changed_move_keeps_its_programmed_e_per_mm(e_fix):
    mode, data, fixed, report = e_fix
    assert report.exit_code == 0
    before = {line: p for line, p, _, _ in _moves(data)}
    moves = _moves(fixed)
    lengths_changed = 0
    e_prev = Decimal(0)
    for (line, p, e, _), (_, p_prev, _, _) in zip(moves[1:], moves[:-1]):
        e_now = Decimal(e)
        delta = e_now if mode == "M83" else e_now - e_prev
        e_prev = e_now
        length = float(np.linalg.norm(p - p_prev))
        if abs(length - STEP_MM) > 1e-3:
            lengths_changed += 1
        rate = float(delta) / length
        assert rate == pytest.approx(E_PER_MM, rel=0.01), f"line {line}: {rate:.5f} E/mm over {length:.4f} mm"
    assert lengths_changed >= 5, "the fix must move P along the path (else the test proves nothing)"
    assert before  # the programmed moves were read


def test_the_episode_keeps_its_extrusion_and_nothing_outside_it_changes(e_fix):
    mode, data, fixed, report = e_fix
    first, last = _episode(data, report)
    changed = _changed_lines(data, fixed)
    assert changed and min(changed) >= first and max(changed) <= last
    assert changed == {c["line"] for c in report.changes}
    e_in = [Decimal(e) for line, _, e, _ in _moves(data) if first <= line <= last]
    e_out = [Decimal(e) for line, _, e, _ in _moves(fixed) if first <= line <= last]
    if mode == "M82":
        assert e_out[-1] == e_in[-1]
    else:
        assert sum(e_out) == sum(e_in)
    for c in report.changes:
        if c["reason"] == "extrusion rescaled":  # only its E differs from the input
            assert re.sub(r" E\S+", "", c["before"]) == re.sub(r" E\S+", "", c["after"])


def test_new_e_words_keep_the_programs_number_format(e_fix):
    _, data, fixed, _ = e_fix
    for line, _, e, _ in _moves(fixed)[1:]:  # after the plunge
        assert re.fullmatch(r"\d+\.\d{5}", e), f"line {line}: E{e}"


def test_inverse_time_f_keeps_the_programmed_feed_rate():
    data = _program(None, inverse_time=True)
    fixed, report = _fix(data)
    assert report.exit_code == 0
    first, last = _episode(data, report)
    changed = _changed_lines(data, fixed)
    assert changed and min(changed) >= first and max(changed) <= last
    moves = _moves(fixed)
    lengths_changed = 0
    for (line, p, _, f), (_, p_prev, _, _) in zip(moves[2:], moves[1:-1]):
        length = float(np.linalg.norm(p - p_prev))
        if abs(length - STEP_MM) > 1e-3:
            lengths_changed += 1
        assert length * float(f) == pytest.approx(FEED, rel=0.01), f"line {line}: F{f} over {length:.4f} mm"
        assert re.fullmatch(r"\d+\.\d{3}", f)
    assert lengths_changed >= 5


def test_a_program_without_e_or_g93_gets_only_its_tilts():
    data = _program(None)
    fixed, report = _fix(data)
    assert {c["reason"] for c in report.changes} <= {"collision", "blend"}
    for c in report.changes:
        assert " F" not in c["after"] or c["after"].split(" F")[1] == c["before"].split(" F")[1]


def test_with_pivot_point_p_stays_and_no_e_word_changes():
    data = _program("M82")
    fixed, report = _fix(data, pivot="point")
    assert report.summary["changed_blocks"] > 0
    assert [e for *_, e, _ in _moves(fixed)] == [e for *_, e, _ in _moves(data)]
    assert {c["reason"] for c in report.changes} <= {"collision", "blend"}


def test_a_block_both_restated_and_rescaled_is_reported_once():
    """The move after the episode leaves out I J K (restated after the change) and, with
    relative E, gets a new E: one change entry, counted once."""
    data = _program("M83", sparse=True)
    fixed, report = _fix(data)
    lines = [c["line"] for c in report.changes]
    assert len(lines) == len(set(lines)) == report.summary["changed_blocks"]
    assert set(lines) == _changed_lines(data, fixed)
    assert "extrusion rescaled" in {c["reason"] for c in report.changes}
