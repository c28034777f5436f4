"""Saying what the wait is: a first run names what it builds before it starts (not with -q), and
the progress callback moves while a program shorter than one chunk is checked or fixed."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import trimesh

import ncfix
from ncfix.cli import main
from ncfix.correct.stage import CorrectStage

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
NOTICE = "ncfix: building the distance grid of blocks.stl (first run for this mesh"


def _program() -> bytes:
    """A pass along x above a plate, dipping the tip into two blocks on it (two episodes)."""
    lines = [b"G21 G90", b"G0 X-200. Y0. Z20.", b"G1 X-200. Y0. Z5. I0. J0. K1. F600."]
    for x in range(-195, 201, 5):
        z = -9.0 if x in (-150, 150) else 5.0  # 60 blocks apart: two episodes
        lines.append(b"G1 X%d. Y0. Z%.1f" % (x, z))
    return b"\n".join(lines + [b"M30", b""])


@pytest.fixture
def scene(tmp_path):
    plate = trimesh.creation.box(extents=(500.0, 100.0, 10.0))
    plate.apply_translation((0.0, 0.0, -15.0))
    blocks = [trimesh.creation.box(extents=(10.0, 10.0, 10.0)) for _ in range(2)]
    blocks[0].apply_translation((-150.0, 0.0, -5.0))
    blocks[1].apply_translation((150.0, 0.0, -5.0))
    part = tmp_path / "blocks.stl"
    trimesh.util.concatenate([plate, *blocks]).export(part)
    src = tmp_path / "in.nc"
    src.write_bytes(_program())
    return src, part


def _args(src: Path, part: Path, out: Path) -> list[str]:
    return [str(src), "--head", str(SAMPLES / "deposition_head.stl"), "--part", str(part), "--pitch", "2",
            "--bead-radius", "0", "--check", "-o", str(out)]


def test_a_first_run_says_what_it_builds_and_a_warm_one_does_not(scene, tmp_path, monkeypatch, capsys):
    src, part = scene
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "cold"))
    import ncfix.collision.grid as grid_module

    seen_before_build = []
    original = grid_module.build_distance_grid

    def building(mesh, pitch_mm, **kw):  # the notice must be out before the work starts
        seen_before_build.append(NOTICE in capsys.readouterr().err)
        return original(mesh, pitch_mm, **kw)

    monkeypatch.setattr(grid_module, "build_distance_grid", building)
    main(_args(src, part, tmp_path / "o.nc"))
    assert seen_before_build[0]  # the part's grid is the first one built
    assert "building the head's proximity lists for blocks.stl" in capsys.readouterr().err
    main(_args(src, part, tmp_path / "o.nc"))  # warm: every array from the cache
    assert "building" not in capsys.readouterr().err
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "cold-quiet"))
    main(_args(src, part, tmp_path / "o.nc") + ["-q"])
    assert capsys.readouterr().err == ""


def test_progress_moves_while_a_single_chunk_program_is_checked(scene):
    src, part = scene
    calls = []
    ncfix.process(src, io.BytesIO(), head=str(SAMPLES / "deposition_head.stl"), part=[str(part)], pitch=2.0,
                  bead_radius=0.0, check=True, progress=lambda done, lines: calls.append((done, lines)))
    size, total = src.stat().st_size, _program().count(b"\n")
    assert calls[-1] == (size, total)
    during = [c for c in calls if c[1] < total]
    assert len(set(during)) >= 3  # the check of the one window reports as it goes, not only at its end
    assert calls == sorted(calls)


def test_progress_moves_between_the_episodes_of_a_fix(scene, monkeypatch):
    src, part = scene
    events: list = []
    original = CorrectStage._solve

    def solving(self, first, last, collided):
        events.append("solve")
        return original(self, first, last, collided)

    monkeypatch.setattr(CorrectStage, "_solve", solving)
    ncfix.process(src, io.BytesIO(), head=str(SAMPLES / "deposition_head.stl"), part=[str(part)], pitch=2.0,
                  bead_radius=0.0, progress=lambda done, lines: events.append(lines))
    solves = [i for i, e in enumerate(events) if e == "solve"]
    assert len(solves) >= 2
    between = [e for e in events[solves[0]:solves[-1]] if e != "solve"]
    assert between and max(between) < _program().count(b"\n")  # it moved while episodes were left to fix
    assert any(e != "solve" for e in events[:solves[0]])  # and during detection, before the first fix


def test_a_first_decomposition_says_so_before_it_starts(tmp_path, monkeypatch, caplog):
    """The epa strategy's CoACD decomposition of a part it has not seen is named on the
    ``ncfix.build`` log (the command line's standard error, piped or not) before CoACD runs;
    read back from the cache, it is not."""
    import ncfix.correct.decompose as decompose_module

    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "cold"))
    notice = "building the CoACD decomposition of block.stl (first run for this mesh)"
    seen_before_run = []
    original = decompose_module._run_coacd

    def running(mesh, threshold):
        seen_before_run.append(notice in caplog.text)
        return original(mesh, threshold)

    monkeypatch.setattr(decompose_module, "_run_coacd", running)
    block = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    with caplog.at_level("WARNING", logger="ncfix.build"):
        first = decompose_module.decompose(block, name="part:block.stl")
        assert seen_before_run == [True] and not first.cached
        caplog.clear()
        assert decompose_module.decompose(block, name="part:block.stl").cached
    assert "building" not in caplog.text
