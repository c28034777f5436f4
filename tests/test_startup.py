"""What a run imports and compiles: the CPU path never imports torch (about 2.5 s of start-up), and
its numpy / compiled lookups give the numbers of the torch lookups CUDA runs."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"


def _run_python(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter (the test process may have imported torch already)."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300)


def test_importing_the_command_line_does_not_import_torch(tmp_path):
    done = _run_python("""
        import sys
        import ncfix.cli
        assert "torch" not in sys.modules, "importing ncfix.cli imported torch"
        """, tmp_path)
    assert done.returncode == 0, done.stderr


def test_a_pass_through_imports_no_numba_or_scipy(tmp_path):
    """A run without --head needs no compiled kernel: it reads the program with the numpy reader
    and computes no rotation, so numba and the scipy its compiler loads (about 0.5 s of start-up
    together) are never imported; each kind of profile (tool vectors, rotary words, a dialect
    chosen by --machine auto). The output is the input, byte for byte."""
    (tmp_path / "ncfix.toml").write_text("[ncfix]\n")  # not samples/ncfix.toml (which names a head)
    runs = [("bathtub_273.nc", "ijk"), ("bathtub_273_table_ac.nc", "table-ac"), ("bathtub_273_sinumerik.mpf", "auto")]
    done = _run_python(f"""
        import sys
        from ncfix.cli import main
        for name, machine in {runs!r}:
            assert main([{str(SAMPLES)!r} + "/" + name, "--machine", machine, "-o", name]) == 0
        loaded = sorted(m for m in sys.modules if m.partition(".")[0] in ("numba", "scipy", "llvmlite"))
        assert not loaded, f"a pass-through imported {{loaded[:5]}}"
        """, tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    for name, _ in runs:
        assert (tmp_path / name).read_bytes() == (SAMPLES / name).read_bytes()


def test_a_file_longer_than_the_numpy_reader_reads_loads_the_compiled_one_at_once(tmp_path):
    """A regular file larger than ``COMPILED_AFTER_LINES`` lines of ``LINE_BYTES`` is read with the
    compiled reader from its first line (numba paid once, not after the numpy reader's share):
    here every file counts as long. The output is still the input."""
    (tmp_path / "ncfix.toml").write_text("[ncfix]\n")
    done = _run_python(f"""
        import sys
        import ncfix.pipeline
        from ncfix.cli import main
        ncfix.pipeline.LINE_BYTES = 0
        assert main([{str(SAMPLES / "bathtub_273.nc")!r}, "--machine", "ijk", "-q", "-o", "out.nc"]) == 0
        assert "numba" in sys.modules, "a long file was not read with the compiled reader"
        """, tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (tmp_path / "out.nc").read_bytes() == (SAMPLES / "bathtub_273.nc").read_bytes()


def _no_torch_run(tmp_path: Path, runs: str) -> None:
    """``runs`` (lines calling ``main(common + [...])``) in a fresh interpreter on deposit_wall.nc
    with the sample head and a part below the wall (gridded and looked up, never hit)."""
    import trimesh

    box = trimesh.creation.box(extents=(20.0, 20.0, 4.0))
    box.apply_translation((60.0, 0.0, -10.0))  # the tip stays above z = 6.5
    box.export(tmp_path / "block.stl")
    (tmp_path / "ncfix.toml").write_text("[ncfix]\n")  # not samples/ncfix.toml beside the input
    done = _run_python(textwrap.dedent(f"""
        import sys
        import ncfix.cli
        from ncfix.collision.checker import gpu_driver_present
        main = ncfix.cli.main
        common = [{str(SAMPLES / "deposit_wall.nc")!r}, "--machine", "ijk",
                  "--head", {str(SAMPLES / "deposition_head.stl")!r}, "--part", "block.stl",
                  "--standoff", "6", "--bead-radius", "1", "--pitch", "0.5", "-q"]
        """) + textwrap.dedent(runs), tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_cpu_check_never_imports_torch(tmp_path):
    """A check on the CPU (head, part and deposit model: grids, bead field, the compiled
    sphere-tree descent, exact tests) runs without torch in ``sys.modules``; so does
    ``--device auto`` on a machine with no GPU driver."""
    _no_torch_run(tmp_path, """
        assert main(common + ["--check", "--device", "cpu", "-o", "checked.nc"]) == 1
        assert "torch" not in sys.modules, "a CPU check imported torch"
        if not gpu_driver_present():
            assert main(common + ["--check", "-o", "auto.nc"]) == 1
            assert "torch" not in sys.modules, "--device auto imported torch on a machine without a GPU driver"
        """)
    assert (tmp_path / "checked.nc").read_bytes() == (SAMPLES / "deposit_wall.nc").read_bytes()


@pytest.mark.heavy
def test_a_cpu_fix_never_imports_torch(tmp_path):
    """The same for a fix (the epa strategy, its candidate tests and re-checks)."""
    _no_torch_run(tmp_path, """
        assert main(common + ["--device", "cpu", "-o", "fixed.nc"]) == 0
        assert "torch" not in sys.modules, "a CPU fix imported torch"
        """)
    assert (tmp_path / "fixed.nc").read_bytes() != (SAMPLES / "deposit_wall.nc").read_bytes()


# Imported by a cold run (reading a mesh, building a model), never by a warm-cache check: trimesh
# and what it pulls in (about a second), scipy's k-d trees, torch. scipy itself is loaded by numba
# (its compiler target looks for scipy's BLAS), so only these of its modules are looked for.
HEAVY = ("trimesh", "networkx", "torch", "scipy.spatial", "scipy.sparse", "scipy.optimize")


def _warm_check(tmp_path: Path, runs: str, heavy_modules: tuple[str, ...] = HEAVY) -> None:
    """``runs`` (``main([...])`` calls) twice, each time in a fresh interpreter with one cache
    folder: the first fills it, the second must import none of ``heavy_modules``."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "NCFIX_CACHE": str(tmp_path / "cache")}
    code = "import sys\nfrom ncfix.cli import main\n" + textwrap.dedent(runs) + textwrap.dedent(f"""
        heavy = sorted(m for m in sys.modules
                       if m in {heavy_modules!r} or m.startswith(tuple(h + "." for h in {heavy_modules!r})))
        print("HEAVY", heavy)
        """)
    for warm in (False, True):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env,
                              timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
        heavy = done.stdout.splitlines()[-1]
        if warm:
            assert heavy == "HEAVY []", f"a warm-cache check imported {heavy}"
        else:
            assert "'trimesh'" in heavy, heavy  # the cold run reads the meshes with it: the test sees it


def test_a_warm_cache_check_imports_no_trimesh_scipy_spatial_or_torch(tmp_path):
    """A check whose meshes, grids, trees and cell lists all come from the cache reads its meshes
    as arrays: no trimesh (nor the scipy and networkx modules it pulls in), no torch. Part
    collisions reported with their depth (a wall across the path) and beads (the deposit wall)."""
    (tmp_path / "ncfix.toml").write_text("[ncfix]\n")
    _warm_check(tmp_path, f"""
        head = {str(SAMPLES / "deposition_head.stl")!r}
        assert main([{str(REPO / "tests" / "golden" / "fix_ijk" / "input.nc")!r}, "--machine", "ijk", "--head", head,
                     "--part", {str(REPO / "tests" / "golden" / "meshes" / "wall_x.stl")!r}, "--bead-radius", "0",
                     "--check", "-q", "-o", "wall.nc"]) == 1
        assert main([{str(SAMPLES / "deposit_wall.nc")!r}, "--machine", "ijk", "--head", head, "--standoff", "6",
                     "--bead-radius", "1", "--pitch", "0.5", "--check", "-q", "-o", "beads.nc"]) in (0, 1)
        """)


def test_a_warm_cache_fix_imports_no_trimesh_or_torch(tmp_path):
    """A fix (the EPA strategy: the head's hulls and the part's CoACD pieces from the cache) of a
    wall across the path: no trimesh (nor networkx), no torch. scipy's k-d trees are allowed: the
    graph fallback that frees this wall searches with them."""
    (tmp_path / "ncfix.toml").write_text("[ncfix]\n")
    _warm_check(tmp_path, f"""
        assert main([{str(REPO / "tests" / "golden" / "fix_ijk" / "input.nc")!r}, "--machine", "ijk",
                     "--head", {str(SAMPLES / "deposition_head.stl")!r},
                     "--part", {str(REPO / "tests" / "golden" / "meshes" / "wall_x.stl")!r}, "--bead-radius", "0",
                     "-q", "-o", "fixed.nc"]) == 0
        """, heavy_modules=("trimesh", "networkx", "torch"))


@pytest.mark.heavy
def test_a_warm_cache_check_of_the_bathtub_sample_imports_no_trimesh(tmp_path):
    """The same for ``ncfix samples/bathtub_273.nc --check`` (the start-up row of bench/run)."""
    _warm_check(tmp_path, f"""
        assert main([{str(SAMPLES / "bathtub_273.nc")!r}, "--check", "-q", "-o", "checked.nc"]) == 1
        """)


def test_auto_picks_the_cpu_without_importing_torch_when_no_driver_is_present(tmp_path):
    done = _run_python("""
        import sys
        import ncfix.collision.checker as checker

        checker.GPU_DRIVER_PATHS = ("/nonexistent/nvidia",)
        if sys.platform.startswith("linux"):
            assert not checker.gpu_driver_present()
            assert checker.resolve_device("auto") == "cpu"
            assert "torch" not in sys.modules
        assert checker.resolve_device("cpu") == "cpu" and "torch" not in sys.modules
        """, tmp_path)
    assert done.returncode == 0, done.stderr


def _sample_bounds(seed: int):
    """A part's distance grid, a bead field whose retired beads lie in a second field below it,
    and random points near and far from each (mm)."""
    import trimesh

    from ncfix.collision.deposit import BeadStore
    from ncfix.collision.grid import build_distance_grid

    rng = np.random.default_rng(seed)
    mold = trimesh.creation.cylinder(radius=12.0, height=8.0, sections=40)
    grid = build_distance_grid(mold, 0.5)
    near = rng.choice([0.3, 3.0, 30.0], (20000, 1))
    grid_points = mold.vertices[rng.integers(0, len(mold.vertices), 20000)] + rng.normal(0, 1, (20000, 3)) * near
    t = np.linspace(0.0, 40.0, 3000)
    beads = np.stack([t, 3.0 * np.sin(t), np.floor(t / 4.0)], axis=1)
    store = BeadStore(1.0, exact_max=512)
    store.field(0.5)
    for part in np.array_split(beads, 20):
        store.add(part)
    field = store.field(0.5)
    assert field.below is not None and field.below.count
    field_points = beads[rng.integers(0, len(beads), 20000)] + rng.normal(0, 1, (20000, 3)) * near
    return [(grid, grid_points), (field, field_points)]


def test_numpy_and_compiled_lookups_are_bit_identical():
    """The CPU's two formulations of each lower bound (numpy ``lower_bound_np``, the compiled
    ``descent`` loop) give the same float64 values, bit for bit."""
    from ncfix.collision import descent

    for body, points in _sample_bounds(5):
        np_values = body.lower_bound_np(points)
        assert np.isfinite(np_values).all()
        assert np.array_equal(np_values.view(np.int64), descent.lower_bounds(body.lower_bound, points).view(np.int64))


def test_cpu_lookups_are_bit_identical_to_the_torch_lookups(monkeypatch):
    """The torch lookups (the CUDA path) and the CPU's give the same numbers bit for bit: the same
    float32 → float64 widening, rounding, clamping and order of operations. torch's vectorised
    CPU square root is not correctly rounded (CUDA's and numpy's are), so it is compared here with
    an IEEE square root in its place, and without that within an ulp of the values."""
    torch = pytest.importorskip("torch")
    from ncfix.collision import descent

    cases = _sample_bounds(6)
    for body, points in cases:
        own = body.lower_bound(torch.as_tensor(points)).numpy()
        assert np.allclose(own, body.lower_bound_np(points), rtol=0, atol=1e-12)

    def ieee_sqrt(x):
        return torch.from_numpy(np.sqrt(x.numpy()))

    monkeypatch.setattr(torch, "sqrt", ieee_sqrt)
    for body, points in cases:
        want = body.lower_bound(torch.as_tensor(points)).numpy()
        assert np.array_equal(body.lower_bound_np(points).view(np.int64), want.view(np.int64))
        assert np.array_equal(descent.lower_bounds(body.lower_bound, points).view(np.int64), want.view(np.int64))


def test_auto_runs_the_torch_path_on_a_gpu():
    """Where a GPU exists, ``--device auto`` picks it and the checker runs torch batches there
    (the decisions are compared with the CPU's in test_checker)."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device on this machine")
    from ncfix.collision.checker import gpu_driver_present, resolve_device

    assert gpu_driver_present()
    assert resolve_device("auto") == "cuda"


def test_cuda_without_a_device_is_a_usage_error():
    """``--device cuda`` on a machine where torch sees no GPU (or without torch) fails at once
    with one line naming the option, before any grid is built."""
    from ncfix.collision.checker import resolve_device
    from ncfix.errors import ConfigError

    try:
        import torch
    except ImportError:
        torch = None
    if torch is not None and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(ConfigError, match="--device"):
        resolve_device("cuda")
