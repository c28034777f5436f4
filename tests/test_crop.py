"""The part grids are cropped to what the head can reach from the program's points (a first pass
over a seekable input); a pipe gets the whole part. The decisions are the same either way."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh

import ncfix
import ncfix.collision.checker as checker_module

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
# A short path near one corner of a big plate, dipping into a block on it at the end.
PROGRAM = b"G21 G90\nG0 X-380. Y-380. Z20.\nG1 X-380. Y-380. Z0. I0. J0. K1. F600.\nG1 X-340. Y-380. Z0.\nG1 X-300. Y-380. Z-8.\nM30\n"


class _Pipe(io.BytesIO):
    def seekable(self) -> bool:
        return False


def test_grids_are_cropped_to_the_heads_reach_with_the_same_decisions(tmp_path, monkeypatch):
    plate = trimesh.creation.box(extents=(800.0, 800.0, 10.0))
    plate.apply_translation((0.0, 0.0, -15.0))  # top at z = -10: 16 mm under the tip
    block = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    block.apply_translation((-300.0, -380.0, -5.0))  # top at z = 0: the last move dips the tip into it
    part = tmp_path / "plate.stl"
    trimesh.util.concatenate([plate, block]).export(part)
    shapes = []
    original = checker_module.cached_distance_grid

    def recording(mesh, pitch_mm, **kw):
        grid = original(mesh, pitch_mm, **kw)
        if kw.get("name", "").startswith("part:"):
            shapes.append(grid.shape)
        return grid

    monkeypatch.setattr(checker_module, "cached_distance_grid", recording)
    src = tmp_path / "in.nc"
    src.write_bytes(PROGRAM)
    options = dict(head=str(SAMPLES / "deposition_head.stl"), part=[str(part)], check=True, bead_radius=0.0, pitch=2.0)
    cropped = ncfix.process(src, io.BytesIO(), **options)
    whole = ncfix.process(_Pipe(PROGRAM), io.BytesIO(), **options)
    assert [c["line"] for c in cropped.collisions] == [c["line"] for c in whole.collisions] == [5]
    cropped_cells, whole_cells = (int(np.prod(s)) for s in shapes)
    assert cropped_cells < 0.2 * whole_cells  # the head reaches ~140 mm around an 80 mm path


def test_the_reach_of_a_program_follows_its_arcs():
    """The exact band is made near the program's points and along its arcs (``grid.Reach``): the
    cubes of an arc's far side are in the reach, though no programmed point lies there."""
    from ncfix.collision.grid import REACH_CELL_MM
    from ncfix.config import Options
    from ncfix.pipeline import program_box
    from ncfix.profiles import load_profile

    program = b"G21 G90 G17\nG0 X10. Y0. Z5.\nG1 X10. Y0. Z0. I0. J0. K1. F600.\nG3 X-10. Y0. I-10. J0.\nM30\n"
    profile = load_profile("ijk")
    where = program_box(io.BytesIO(program), profile, Options(head="head.stl", part=["part.stl"]), "arc.nc")
    cubes = {tuple(c) for c in where.cubes}
    for angle in np.linspace(0.0, np.pi, 50):  # the half circle the tip runs, ccw from (10, 0) to (-10, 0)
        point = np.array([10.0 * np.cos(angle), 10.0 * np.sin(angle), 0.0])
        cube = np.floor(point / REACH_CELL_MM).astype(np.int64)
        assert any(np.abs(np.array(c) - cube).max() <= 1 for c in cubes), point
    assert tuple(np.floor(np.array([0.0, 10.0, 0.0]) / REACH_CELL_MM).astype(np.int64)) in cubes
    # no point of the other half circle: the reach follows the arc, not its circle
    assert not any(c[1] < -1 for c in cubes)
