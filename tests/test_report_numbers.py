"""Reports that add up: where a block collides (its end point or along its move), how deep a pass
goes, what became of every colliding block in a fix, and a fix's collisions agreeing with
``--check``'s."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import trimesh
from rich.console import Console

import ncfix
from ncfix.report.summary import print_summary

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "bathtub_273.nc"


def _text(report) -> str:
    buffer = io.StringIO()
    print_summary(report, console=Console(file=buffer, width=200, highlight=False, soft_wrap=True))
    return buffer.getvalue()


@pytest.fixture(scope="module")
def through_wall(tmp_path_factory):
    """A cylinder head (r 5 mm, 40 mm tall), a wall 10 mm thick across X (x -5..5, 30 mm high),
    and a program: a pass through the wall whose both ends are 20 mm clear of it, then a move
    that ends inside it, checked without beads."""
    folder = tmp_path_factory.mktemp("wall")
    head = trimesh.creation.cylinder(radius=5.0, height=40.0, sections=48)
    head.apply_translation((0.0, 0.0, 20.0))
    head.export(folder / "head.stl")
    trimesh.creation.box(bounds=[(-5.0, -50.0, 0.0), (5.0, 50.0, 30.0)]).export(folder / "wall.stl")
    program = folder / "pass.nc"
    program.write_bytes(b"G21 G90\nG0 X-30 Y0 Z10 I0 J0 K1\nG1 X30 Y0 Z10 F1000\nG1 X0 Y0 Z10\n")
    report = ncfix.process(program, io.BytesIO(), head=str(folder / "head.stl"), part=[str(folder / "wall.stl")],
                           check=True, bead_radius=0.0, standoff=2.0, device="cpu")
    return report


def test_a_pass_through_a_wall_is_a_sweep_hit_with_its_depth(through_wall):
    """The pass (line 3) collides along its move only: its end pose is 20 mm clear, and the head
    goes about half the wall's thickness (5 mm) deep into it on the way; the move that ends in
    the wall (line 4) collides at its end point."""
    by_line = {e["line"]: e for e in through_wall.collisions}
    assert sorted(by_line) == [3, 4]
    passing, ending = by_line[3], by_line[4]
    assert passing["where"] == "sweep" and passing["clearance_mm"] > 0
    assert 3.5 <= passing["penetration_mm"] <= 6.0
    assert ending["where"] == "end" and ending["clearance_mm"] < 0
    assert 3.5 <= ending["penetration_mm"] <= 6.0


def test_the_check_table_says_where(through_wall):
    text = _text(through_wall)
    assert "where" in text and "sweep" in text and "'sweep' = along the move" in text


def _lines(report, **keep) -> set[int]:
    return {e["line"] for e in report.collisions if all(e.get(k) == v for k, v in keep.items())}


@pytest.fixture(scope="module")
def checked():
    return ncfix.process(SAMPLE, io.BytesIO(), config=REPO / "samples" / "ncfix.toml", check=True, device="cpu")


@pytest.mark.heavy
@pytest.mark.parametrize("strategy", ["epa", "graph"])
def test_a_fix_accounts_for_every_colliding_block(strategy, checked):
    """Every colliding block of a fix is tilted, freed (left as programmed: the blocks before it
    were rewritten; a note says how) or unresolved, and the counts add up in the summary, the
    JSON and the verdict. The collisions found as programmed are exactly those ``--check`` finds;
    a block found only after ncfix rewrote the blocks before it says so (``detected``)."""
    report = ncfix.process(SAMPLE, io.BytesIO(), config=REPO / "samples" / "ncfix.toml", strategy=strategy,
                           device="cpu")
    s = report.summary
    outcomes = [e["outcome"] for e in report.collisions]
    assert len(outcomes) == s["colliding_blocks_before"]
    tilted, freed = outcomes.count("tilted"), outcomes.count("freed")
    assert tilted == report.changed_by_reason()["collision"]
    assert freed == s["freed_blocks"] and outcomes.count("unresolved") == s["unresolved_blocks"]
    assert tilted + freed + s["unresolved_blocks"] == s["colliding_blocks_before"]
    assert all(e.get("note") for e in report.collisions if e["outcome"] == "freed")
    if freed and not s["unresolved_blocks"]:
        assert f"{freed} block{'s' if freed > 1 else ''} freed by the change of the blocks before" in report.verdict
    after = {e["line"] for e in report.collisions if e.get("detected")}
    assert len(after) == s["found_after_changes"]
    found = {e["line"] for e in report.collisions}
    assert found - after <= {e["line"] for e in checked.collisions} <= found
    print(f"{strategy}: {s['colliding_blocks_before']} colliding, {tilted} tilted, {freed} freed, "
          f"{s['unresolved_blocks']} unresolved; found after changes: {sorted(after)}")
