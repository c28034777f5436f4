"""Bad head and part meshes through the command line: exit 2, the message, and no output file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
PROGRAM = SAMPLES / "bathtub_273.nc"


def ncfix(*args, cwd):
    """-q: the samples' ncfix.toml is read (named on stderr without it); errors still show."""
    return subprocess.run([sys.executable, "-m", "ncfix", "-q", *map(str, args)], capture_output=True, cwd=cwd)


def nan_stl(folder: Path) -> Path:
    path = folder / "nan.stl"
    path.write_text("solid t\nfacet normal 0 0 0\nouter loop\nvertex nan 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
                    "endloop\nendfacet\nendsolid t\n")
    return path


@pytest.mark.parametrize(
    "make, option, message",
    [
        (lambda d: d / "missing.stl", "--head",
         "ncfix: error: {path}: the head mesh file does not exist (check the --head path)"),
        (lambda d: (d / "empty.stl").write_bytes(b"") and d / "empty.stl" or d / "empty.stl", "--head",
         "ncfix: error: {path}: the head mesh file is empty (export the mesh again as STL or OBJ)"),
        (lambda d: d / "missing.stl", "--part",
         "ncfix: error: {path}: the part mesh file does not exist (check the --part path)"),
        (nan_stl, "--head", "ncfix: error: {path}: 1 vertices have NaN or infinite coordinates"),
    ],
)
def test_bad_meshes_exit_2_and_write_nothing(tmp_path, make, option, message):
    mesh = make(tmp_path)
    out = tmp_path / "out.nc"
    args = [PROGRAM, "-o", out, "--check"]
    if option == "--head":
        args += ["--head", mesh, "--part", SAMPLES / "recreated_mold.stl"]
    else:
        args += ["--head", SAMPLES / "deposition_head.stl", "--part", mesh]
    done = ncfix(*args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr.decode().startswith(message.format(path=mesh)), done.stderr.decode()
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.nc")]


def test_a_head_tip_that_is_not_the_lowest_point_is_refused(tmp_path):
    done = ncfix(PROGRAM, "--check", "--head", SAMPLES / "deposition_head.stl", "--head-tip", "0,0,30",
                 "--part", SAMPLES / "recreated_mold.stl", cwd=tmp_path)
    assert done.returncode == 2
    assert "the head reaches 30 mm below the tip (0, 0, 30) along the axis (0, 0, 1)" in done.stderr.decode()


@pytest.mark.heavy  # the whole sample through the command line; test_geometry holds the message fast
def test_a_part_far_from_the_toolpath_is_refused(tmp_path):
    import trimesh

    far = trimesh.load(SAMPLES / "recreated_mold.stl")
    far.apply_translation((0.0, 0.0, 1000.0))  # e.g. exported in another frame
    far_path = tmp_path / "far_mold.stl"
    far.export(far_path)
    out = tmp_path / "out.nc"
    done = ncfix(PROGRAM, "--check", "-o", out, "--head", SAMPLES / "deposition_head.stl", "--part", far_path,
                 cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr.decode().startswith(f"ncfix: error: {far_path}: the part is ")
    assert "mm away from the toolpath" in done.stderr.decode()
    assert not out.exists()
