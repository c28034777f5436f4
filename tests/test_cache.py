"""The on-disk cache of the checker's models (ncfix.cache): a hit gives exactly what a build gives,
every input of a result is in its key (the code that computes it too), and a bad or unwritable
cache costs time, never a wrong answer."""

from __future__ import annotations

import io
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix
from ncfix import cache
from ncfix.collision import depth as depth_module
from ncfix.collision import grid as grid_module
from ncfix.collision import head as head_module
from ncfix.collision import proximity as proximity_module
from ncfix.collision.grid import Reach, build_distance_grid, cached_distance_grid
from ncfix.collision.head import build_head_model, build_sphere_tree, cached_head_model, cached_sphere_tree
from ncfix.collision.near import NearSurface, cached_near_surface

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
GOLDEN = Path(__file__).parent / "golden"
FIX_IJK = GOLDEN / "fix_ijk" / "input.nc"  # a wall beside a straight path (tests/golden/fix_ijk)
FIX_IJK_SETTINGS = {"machine": "ijk", "head": str(SAMPLES / "deposition_head.stl"),
                    "part": [str(GOLDEN / "meshes" / "wall_x.stl")], "bead_radius": 0.0, "strategy": "graph"}


def _l_shape() -> trimesh.Trimesh:
    a = trimesh.creation.box(extents=(20.0, 6.0, 10.0))
    b = trimesh.creation.box(extents=(6.0, 20.0, 10.0))
    b.apply_translation((7.0, 7.0, 0.0))
    return trimesh.util.concatenate([a, b])


def _cone_head() -> trimesh.Trimesh:
    head = trimesh.creation.cone(radius=12.0, height=40.0)
    head.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))  # apex down at the tip
    head.apply_translation((0.0, 0.0, 40.0))
    return head


def _no_build(monkeypatch, module, name):
    def refuse(*args, **kwargs):
        raise AssertionError(f"{name} ran although its result was cached")

    monkeypatch.setattr(module, name, refuse)


def _files(folder: Path, kind: str) -> list[Path]:
    return sorted(folder.glob(f"{kind}-*.npz"))


def _same_grid(a, b) -> None:
    assert a.dist_mm.dtype == b.dist_mm.dtype == np.float32
    assert np.array_equal(a.dist_mm, b.dist_mm)
    assert np.array_equal(a.origin_mm, b.origin_mm) and a.pitch_mm == b.pitch_mm
    assert np.array_equal(a.body_bounds_mm, b.body_bounds_mm) and a.name == b.name


@pytest.mark.parametrize("closed, bounds", [(True, None), (False, None), (True, [[-5, -5, -9], [40, 40, 9]])])
def test_a_cached_grid_is_the_built_grid_bit_for_bit(tmp_path, monkeypatch, closed, bounds):
    mesh = _l_shape()
    bounds = None if bounds is None else np.array(bounds, dtype=np.float64)
    built = build_distance_grid(mesh, 1.0, closed=closed, name="part:l", bounds_mm=bounds)
    first = cached_distance_grid(mesh, 1.0, closed=closed, name="part:l", bounds_mm=bounds, cache_dir=tmp_path)
    assert len(_files(tmp_path, "grid")) == 1
    _no_build(monkeypatch, grid_module, "build_distance_grid")
    again = cached_distance_grid(mesh, 1.0, closed=closed, name="part:l", bounds_mm=bounds, cache_dir=tmp_path)
    _same_grid(first, built)
    _same_grid(again, built)
    points = np.random.default_rng(0).uniform(-30, 50, (500, 3))
    assert np.array_equal(again.lower_bound_np(points), built.lower_bound_np(points))


def test_the_depth_field_of_a_cached_grid_is_cached_beside_it(tmp_path, monkeypatch):
    """The report's depth field (``depth.inside_field``) of a grid read from the cache is read from
    the cache too, the same float32 array the distance transform gives; a grid built outside the
    cache has it computed."""
    mesh = _l_shape()
    built = build_distance_grid(mesh, 1.0, name="part:l")
    want = depth_module.distance_transform(built.dist_mm == 0, built.pitch_mm)
    assert not built.cache_key and np.array_equal(depth_module.inside_field(built), want)
    assert not _files(tmp_path, "depth")
    grid = cached_distance_grid(mesh, 1.0, name="part:l", cache_dir=tmp_path)
    first = depth_module.inside_field(grid)
    assert len(_files(tmp_path, "depth")) == 1
    _no_build(monkeypatch, depth_module, "distance_transform")
    again = depth_module.inside_field(cached_distance_grid(mesh, 1.0, name="part:l", cache_dir=tmp_path))
    for field in (first, again):
        assert field.dtype == np.float32 and np.array_equal(field, want)
    assert (want > 0).any()
    other = cached_distance_grid(mesh, 0.5, name="part:l", cache_dir=tmp_path)
    with pytest.raises(AssertionError, match="cached"):  # another grid: another field, built
        depth_module.inside_field(other)


def test_a_program_with_another_reach_does_not_read_a_grid_made_for_the_first(tmp_path, monkeypatch):
    """The exact band is made only where a program can reach (``grid.Reach``): a second program
    reaching elsewhere over the same crop gets its own grid, and the first reads its own back."""
    mesh = _l_shape()
    first = Reach.of_points(np.array([[-9.0, -2.0, 6.0], [-7.0, -2.0, 6.0]]), 5.0)
    second = Reach.of_points(np.array([[2.0, 8.0, 0.0], [2.0, 12.0, 0.0]]), 5.0)  # in the L's inner corner
    kw = dict(name="part:l", bounds_mm=np.array([[-15.0, -10.0, -9.0], [15.0, 20.0, 9.0]]), cache_dir=tmp_path)
    cached_distance_grid(mesh, 0.5, reach=first, **kw)
    got = cached_distance_grid(mesh, 0.5, reach=second, **kw)
    assert len(_files(tmp_path, "grid")) == 2
    built = build_distance_grid(mesh, 0.5, name="part:l", bounds_mm=kw["bounds_mm"], reach=second)
    _same_grid(got, built)
    # the second program's lookups near its path read the whole band's numbers, which the first
    # program's grid does not have there
    whole = build_distance_grid(mesh, 0.5, name="part:l", bounds_mm=kw["bounds_mm"])
    near_second = np.array([[2.0, 10.0, 0.0], [2.5, 9.0, 1.0], [1.5, 11.0, -1.0]])
    assert np.array_equal(got.lower_bound_np(near_second), whole.lower_bound_np(near_second))
    _no_build(monkeypatch, grid_module, "build_distance_grid")
    again = cached_distance_grid(mesh, 0.5, reach=first, **kw)
    assert not np.array_equal(again.lower_bound_np(near_second), whole.lower_bound_np(near_second))


def test_a_hit_takes_the_name_it_is_asked_for(tmp_path):
    mesh = _l_shape()
    cached_distance_grid(mesh, 1.0, name="part:first.stl", cache_dir=tmp_path)
    assert cached_distance_grid(mesh, 1.0, name="part:second.stl", cache_dir=tmp_path).name == "part:second.stl"


def test_every_input_of_a_grid_is_in_its_key(tmp_path, monkeypatch):
    mesh = _l_shape()
    vertices = np.array(mesh.vertices)
    vertices[0, 2] = np.nextafter(vertices[0, 2], np.inf)  # one coordinate, one ulp
    moved = trimesh.Trimesh(vertices, mesh.faces, process=False)
    variants = [
        dict(mesh=mesh, pitch_mm=1.0),
        dict(mesh=moved, pitch_mm=1.0),
        dict(mesh=mesh, pitch_mm=0.999),
        dict(mesh=mesh, pitch_mm=1.0, closed=False),
        dict(mesh=mesh, pitch_mm=1.0, bounds_mm=np.array([[-5.0, -5.0, -9.0], [40.0, 40.0, 9.0]])),
        dict(mesh=mesh, pitch_mm=1.0, bounds_mm=np.array([[-5.0, -5.0, -9.0], [40.0, 40.0, 8.0]])),
        dict(mesh=mesh, pitch_mm=1.0, reach=Reach.of_points(np.array([[0.0, 0.0, 6.0]]), 8.0)),
        dict(mesh=mesh, pitch_mm=1.0, reach=Reach.of_points(np.array([[0.0, 0.0, 6.0]]), 8.5)),
        dict(mesh=mesh, pitch_mm=1.0, reach=Reach.of_points(np.array([[0.0, 2.0, 6.0]]), 8.0)),
    ]
    for variant in variants:
        cached_distance_grid(cache_dir=tmp_path, **variant)
    assert len(_files(tmp_path, "grid")) == len(variants)
    # the same inputs again: no new file
    cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    assert len(_files(tmp_path, "grid")) == len(variants)
    # other code computing grids (another fingerprint of its source): another key, a fresh build
    monkeypatch.setattr(cache, "fingerprint", lambda *modules: "edited")
    cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    assert len(_files(tmp_path, "grid")) == len(variants) + 1


def test_the_fingerprint_follows_the_source_files(tmp_path, monkeypatch):
    module = tmp_path / "ncfix_cache_probe.py"
    module.write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cache.fingerprint.cache_clear()
    before = cache.fingerprint("ncfix_cache_probe")
    module.write_text("X = 2\n")
    cache.fingerprint.cache_clear()
    after = cache.fingerprint("ncfix_cache_probe")
    cache.fingerprint.cache_clear()
    sys.modules.pop("ncfix_cache_probe", None)
    assert before != after
    assert cache.fingerprint(*grid_module.GRID_SOURCES) != cache.fingerprint(*head_module.HEAD_SOURCES)


def test_key_parts_are_typed():
    assert cache.make_key("k", np.array([1.0, 2.0])) != cache.make_key("k", np.array([1, 2]))
    assert cache.make_key("k", np.zeros((2, 3))) != cache.make_key("k", np.zeros((3, 2)))
    assert cache.make_key("k", 1.0) != cache.make_key("k", "1.0")
    assert cache.make_key("k", None) != cache.make_key("k", np.zeros(0))
    assert cache.make_key("grid", 1.0) != cache.make_key("head", 1.0)


def test_a_cached_head_model_and_its_trees_are_the_built_ones(tmp_path, monkeypatch):
    head = _cone_head()
    built = build_head_model(head, 1.0)
    first = cached_head_model(head, 1.0, cache_dir=tmp_path)
    tree_built = build_sphere_tree(built.centers_mm, built.radii_mm, 1.0)
    cached_sphere_tree(built.centers_mm, built.radii_mm, 1.0, cache_dir=tmp_path)
    _no_build(monkeypatch, head_module, "build_head_model")
    _no_build(monkeypatch, head_module, "build_sphere_tree")
    model = cached_head_model(head, 1.0, cache_dir=tmp_path)
    tree = cached_sphere_tree(built.centers_mm, built.radii_mm, 1.0, cache_dir=tmp_path)
    for got in (first, model):
        for name in ("centers_mm", "radii_mm", "zone", "interior", "group", "group_centers_mm",
                     "group_radii_mm", "zone_tops_mm"):
            assert getattr(got, name).dtype == getattr(built, name).dtype, name
            assert np.array_equal(getattr(got, name), getattr(built, name)), name
        assert (got.pitch_mm, got.marked_cells) == (built.pitch_mm, built.marked_cells)
        assert got.summary() == built.summary()
    for name in ("center_mm", "radius_mm", "reach_mm", "child_start", "child_count", "level_start"):
        assert np.array_equal(getattr(tree, name), getattr(tree_built, name)), name
    # the model's parameters are in its key
    monkeypatch.undo()
    cached_head_model(head, 1.0, target_spheres=12, cache_dir=tmp_path)
    assert len(_files(tmp_path, "head")) == 2


@pytest.mark.parametrize("garbage", [b"not a zip file", "truncated", "other arrays"])
def test_a_bad_cache_file_is_rebuilt_and_overwritten(tmp_path, garbage):
    mesh = _l_shape()
    built = cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    (path,) = _files(tmp_path, "grid")
    if garbage == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    elif garbage == "other arrays":  # a readable file of the wrong shape (a foreign writer)
        np.savez(path, dist_mm=np.zeros((4, 4), np.float32), origin_mm=np.zeros(3), pitch_mm=np.float64(1.0),
                 body_bounds_mm=np.zeros((2, 3)))
    else:
        path.write_bytes(garbage)
    again = cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    _same_grid(again, built)
    assert cache.read_arrays(path, ["dist_mm"])["dist_mm"].shape == built.dist_mm.shape  # overwritten


def _swap(a: Path, b: Path) -> None:
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)


def _notices(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "ncfix.cache"]


def test_swapped_cache_files_are_rebuilt_with_a_notice(tmp_path, caplog):
    """Two files of one kind swapped: each holds another key than its name says, so each is rebuilt
    (the grids read back are the built ones, not each other's) and says so in one line."""
    mesh, other = _l_shape(), _cone_head()
    built = [build_distance_grid(m, 1.0) for m in (mesh, other)]
    cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    cached_distance_grid(other, 1.0, cache_dir=tmp_path)
    first, second = _files(tmp_path, "grid")
    _swap(first, second)
    with caplog.at_level("WARNING", logger="ncfix.cache"):
        again = [cached_distance_grid(m, 1.0, cache_dir=tmp_path) for m in (mesh, other)]
    for grid, reference in zip(again, built):
        _same_grid(grid, reference)
    assert sorted(_notices(caplog)) == [f"cache: {p.name} does not match its key (rebuilt)" for p in (first, second)]
    caplog.clear()
    with caplog.at_level("WARNING", logger="ncfix.cache"):
        cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)  # rewritten: a plain hit now
    assert _notices(caplog) == []


@pytest.mark.parametrize("damage", ["truncated", "no key", "garbage"])
def test_a_damaged_or_keyless_cache_file_is_rebuilt_with_a_notice(tmp_path, caplog, damage):
    mesh = _l_shape()
    built = cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    (path,) = _files(tmp_path, "grid")
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "no key":  # a file written before files held their key: the same arrays, no key
        arrays = cache.read_arrays(path, grid_module._GRID_ARRAYS)
        cache.write_arrays(path, {name: np.array(arrays[name]) for name in grid_module._GRID_ARRAYS})
    else:
        path.write_bytes(b"PK\x03\x04 not really a zip")
    with caplog.at_level("WARNING", logger="ncfix.cache"):
        _same_grid(cached_distance_grid(mesh, 1.0, cache_dir=tmp_path), built)
    problem = "has no key" if damage == "no key" else "cannot be read"
    assert _notices(caplog) == [f"cache: {path.name} {problem} (rebuilt)"]
    key = cache.read_arrays(path, [cache.KEY_MEMBER])[cache.KEY_MEMBER].tobytes().decode()
    assert path.name == f"grid-{key}.npz"  # rewritten, with its key


@pytest.mark.heavy  # two end-to-end checks from cold; test_swapped_cache_files_are_rebuilt_with_a_notice is the fast one
def test_a_check_from_swapped_cache_files_is_the_cold_check(tmp_path, monkeypatch, caplog):
    """The issue's case end to end: a warm cache whose two grid files (the part's and the clipped
    head's) were swapped gives the cold run's colliding blocks (trusted by name, the swapped grids
    gave fewer), plus a notice for each."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("NCFIX_CACHE", str(folder))
    settings = {**FIX_IJK_SETTINGS, "bead_radius": 1.0, "check": True}

    def check() -> list:
        return ncfix.process(FIX_IJK, io.BytesIO(), **settings).collisions

    cold = check()
    first, second = _files(folder, "grid")
    _swap(first, second)
    with caplog.at_level("WARNING", logger="ncfix.cache"):
        warm = check()
    assert cold and warm == cold
    assert sorted(_notices(caplog)) == [f"cache: {p.name} does not match its key (rebuilt)" for p in (first, second)]


def test_the_command_line_prints_cache_notices_on_stderr_unless_quiet(tmp_path, capsys):
    from ncfix import cli

    mesh = _l_shape()
    cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
    (path,) = _files(tmp_path, "grid")
    for enabled, expected in ((True, f"ncfix: cache: {path.name} cannot be read (rebuilt)\n"), (False, "")):
        path.write_bytes(b"damaged")
        with cli._notices(enabled=enabled):
            cached_distance_grid(mesh, 1.0, cache_dir=tmp_path)
        assert capsys.readouterr().err == expected


def _large_and_small(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    arrays = {"big": np.arange(60_000, dtype=np.float32).reshape(30, 40, 50), "fortran": np.asfortranarray(
        np.arange(12.0).reshape(3, 4)), "small": np.arange(5, dtype=np.int64), "scalar": np.float64(0.25)}
    path = tmp_path / "kind-key.npz"
    cache.write_arrays(path, arrays)
    return path, arrays


def test_large_cached_arrays_are_mapped_copy_on_write_and_read_back_exactly(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "MAP_BYTES", 64)
    path, arrays = _large_and_small(tmp_path)
    before = path.read_bytes()
    back = cache.read_arrays(path, list(arrays))
    for name, array in arrays.items():
        assert back[name].dtype == array.dtype and back[name].shape == np.shape(array)
        np.testing.assert_array_equal(back[name], array)
    assert type(back["big"]) is np.ndarray and isinstance(back["big"].base, np.memmap)  # mapped, not copied
    assert back["fortran"].flags.f_contiguous and isinstance(back["fortran"].base, np.memmap)
    assert not isinstance(back["small"].base, np.memmap)  # under MAP_BYTES: read into memory of its own
    # Writable like a built array (numba compiles other kernels for read-only ones); a write stays
    # in this process.
    assert back["big"].flags.writeable and back["fortran"].flags.writeable
    back["big"][0, 0, 0] = -1.0
    back["fortran"][:] = 0.0
    del back
    assert path.read_bytes() == before
    np.testing.assert_array_equal(cache.read_arrays(path, ["big"])["big"], arrays["big"])
    with np.load(path) as plain:  # still an .npz any numpy reads
        for name, array in arrays.items():
            np.testing.assert_array_equal(plain[name], array)


def test_cache_files_are_the_same_bytes_for_the_same_arrays(tmp_path):
    first, _ = _large_and_small(tmp_path / "a")
    second, _ = _large_and_small(tmp_path / "b")
    assert first.read_bytes() == second.read_bytes()


def test_cache_members_are_the_bytes_np_save_writes(tmp_path):
    arrays = {"c": np.arange(12.0).reshape(3, 4), "f": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
              "strided": np.arange(9, dtype=np.int32)[::2], "scalar": np.float64(0.5), "empty": np.zeros((0, 3)),
              "flag": np.array(True)}
    path = tmp_path / "kind-key.npz"
    cache.write_arrays(path, arrays)
    with zipfile.ZipFile(path) as archive:
        for name, array in arrays.items():
            expected = io.BytesIO()
            np.save(expected, array)
            assert archive.read(name + ".npy") == expected.getvalue(), name


def test_an_unaligned_cache_file_is_read_not_mapped(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "MAP_BYTES", 64)
    arrays = {"x": np.arange(1000.0)}
    path = tmp_path / "kind-key.npz"
    with zipfile.ZipFile(path, "w") as archive:  # member data 1 byte past an 8-byte boundary
        npy = io.BytesIO()
        np.lib.format.write_array(npy, arrays["x"])
        info = zipfile.ZipInfo("x.npy")
        pad = (-(30 + len("x.npy") + 4)) % 64 + 1
        info.extra = struct.pack("<HH", 0xD935, pad) + bytes(pad)
        archive.writestr(info, npy.getvalue())
    back = cache.read_arrays(path, ["x"])["x"]
    np.testing.assert_array_equal(back, arrays["x"])
    assert back.flags.writeable and back.flags.aligned  # a copy of its own


def test_a_damaged_mapped_array_is_a_miss(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "MAP_BYTES", 64)
    path, arrays = _large_and_small(tmp_path)
    data = bytearray(path.read_bytes())
    at = data.find(np.arange(60_000, dtype=np.float32)[30_000:30_004].tobytes())
    assert at > 0
    data[at] ^= 0x40  # one bit in the middle of "big": the zip's CRC no longer matches
    path.write_bytes(bytes(data))
    assert cache.read_arrays(path, list(arrays)) is None
    assert cache.read_arrays(path, ["small"]) is not None  # the other members are intact


def test_compressed_cache_files_are_read_too(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "MAP_BYTES", 64)
    arrays = {"big": np.arange(60_000, dtype=np.float32), "small": np.arange(3)}
    path = tmp_path / "kind-key.npz"
    np.savez_compressed(path, **arrays)  # an older or foreign writer: members deflated, not mapped
    back = cache.read_arrays(path, list(arrays))
    for name, array in arrays.items():
        np.testing.assert_array_equal(back[name], array)


def test_an_unwritable_cache_folder_only_costs_time(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    mesh = _l_shape()
    grid = cached_distance_grid(mesh, 1.0, cache_dir=blocker / "cache")
    _same_grid(grid, build_distance_grid(mesh, 1.0))


def test_the_default_folder_comes_from_ncfix_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "env"))
    assert cache.cache_dir() == tmp_path / "env"
    cached_distance_grid(_l_shape(), 1.0)
    assert len(_files(tmp_path / "env", "grid")) == 1
    monkeypatch.delenv("NCFIX_CACHE")
    assert cache.cache_dir() == Path.home() / ".cache" / "ncfix"


def _fix_ijk(folder: Path, monkeypatch) -> tuple[bytes, list]:
    monkeypatch.setenv("NCFIX_CACHE", str(folder))
    out = io.BytesIO()
    report = ncfix.process(FIX_IJK, out, **FIX_IJK_SETTINGS)
    return out.getvalue(), report.collisions


def _check_wall(folder: Path, monkeypatch) -> list:
    monkeypatch.setenv("NCFIX_CACHE", str(folder))
    report = ncfix.process(SAMPLES / "deposit_wall.nc", io.BytesIO(), head=str(SAMPLES / "deposition_head.stl"),
                           standoff=6.0, bead_radius=1.0, check=True)
    return report.collisions


@pytest.mark.heavy  # two end-to-end fixes; the deposit check below is the fast end-to-end warm/cold case
def test_a_fix_from_a_warm_cache_is_the_fix_from_a_cold_one(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    cold = _fix_ijk(folder, monkeypatch)
    # The meshes as read, the clipped head, the mold's depth field; no deposit: no near surface
    # of the clipped head.
    assert {p.name.split("-")[0] for p in folder.iterdir()} == {"mesh", "clip", "grid", "depth", "head", "tree",
                                                               "proximity"}
    _no_build(monkeypatch, grid_module, "build_distance_grid")
    _no_build(monkeypatch, head_module, "build_head_model")
    _no_build(monkeypatch, head_module, "build_sphere_tree")
    _no_build(monkeypatch, proximity_module, "build_arrays")
    warm = _fix_ijk(folder, monkeypatch)
    assert warm == cold
    assert cold[0] == (GOLDEN / "fix_ijk" / "expected.out").read_bytes()


def test_a_deposit_check_from_a_warm_cache_is_the_check_from_a_cold_one(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    cold = _check_wall(folder, monkeypatch)
    assert len(_files(folder, "grid")) == 1  # the clipped head's grid (no part)
    assert len(_files(folder, "near")) == 1  # the clipped head's cell lists and sign grid
    _no_build(monkeypatch, grid_module, "build_distance_grid")
    _no_build(monkeypatch, head_module, "build_sphere_tree")
    _no_build(monkeypatch, NearSurface, "__init__")
    assert _check_wall(folder, monkeypatch) == cold
    assert [c["line"] for c in cold] == list(range(497, 521))


def test_the_folder_is_kept_under_its_size_least_recently_used_first(tmp_path, monkeypatch):
    import os

    def box_at(x):  # grids of the same shape: files of the same size
        mesh = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
        mesh.apply_translation((x, 0.0, 0.0))
        return mesh

    files = []
    for i in range(4):
        before = set(_files(tmp_path, "grid"))
        cached_distance_grid(box_at(100.0 * i), 1.0, cache_dir=tmp_path)
        (new,) = set(_files(tmp_path, "grid")) - before
        os.utime(new, (1000.0 * (i + 1),) * 2)  # written in this order, far apart in time
        files.append(new)
    assert len({f.stat().st_size for f in files}) == 1
    cached_distance_grid(box_at(0.0), 1.0, cache_dir=tmp_path)  # a hit: the first grid is the newest now
    assert files[0].stat().st_mtime > 10_000
    stale = tmp_path / "grid-x.tmp"
    stale.write_bytes(b"left by a killed run")
    os.utime(stale, (1.0, 1.0))
    monkeypatch.setattr(cache, "MAX_BYTES", 4 * files[0].stat().st_size)  # room for four grids
    cached_distance_grid(box_at(400.0), 1.0, cache_dir=tmp_path)
    left = set(_files(tmp_path, "grid"))
    assert len(left) == 4 and files[1] not in left  # the least recently used went
    assert {files[0], files[2], files[3]} <= left
    assert not stale.exists()


def test_a_cached_near_surface_has_the_built_ones_array_types(tmp_path):
    """numba compiles a kernel per argument type (read-only arrays apart): a cached NearSurface
    must reach the kernels with the types a built one has, or the first cached run compiles them
    all again."""
    numba = pytest.importorskip("numba")
    triangles = trimesh.creation.icosphere(2, radius=10.0).triangles  # read-only, as trimesh gives it
    built = cached_near_surface(triangles, 1.75, cache_dir=tmp_path)
    cached = cached_near_surface(triangles, 1.75, cache_dir=tmp_path)
    for name in ("triangles", "lo", "dims", "start", "listed", "inside", "sign_lo", "depth"):
        assert numba.typeof(getattr(cached, name)) == numba.typeof(getattr(built, name)), name


def test_a_cached_grid_has_the_built_ones_array_types(tmp_path):
    """As for the NearSurface: the kernels must get the types a built grid has."""
    numba = pytest.importorskip("numba")
    built = cached_distance_grid(_l_shape(), 1.0, cache_dir=tmp_path)
    cached = cached_distance_grid(_l_shape(), 1.0, cache_dir=tmp_path)
    for name in ("dist_mm", "origin_mm", "body_bounds_mm"):
        assert numba.typeof(getattr(cached, name)) == numba.typeof(getattr(built, name)), name


def test_a_cached_near_surface_answers_as_the_built_one(tmp_path, monkeypatch):
    head = _cone_head()
    tris = np.asarray(head.triangles, dtype=np.float64)
    built = NearSurface(tris, 2.0)
    cached_near_surface(tris, 2.0, cache_dir=tmp_path)
    _no_build(monkeypatch, NearSurface, "__init__")
    near = cached_near_surface(tris, 2.0, cache_dir=tmp_path)
    for name in ("triangles", "lo", "dims", "start", "listed", "inside", "sign_lo"):
        assert np.array_equal(getattr(near, name), getattr(built, name)), name
    assert np.array_equal(near.depth, built.depth)
    rng = np.random.default_rng(2)
    pts = rng.uniform(-15, 45, (2000, 3))
    radii = rng.uniform(0.1, 2.0, len(pts))
    group = np.arange(len(pts)) % 50
    for check in (np.ones(len(pts), bool), np.zeros(len(pts), bool)):
        a, b = near.first_touch(pts, radii, check, group, 50), built.first_touch(pts, radii, check, group, 50)
        assert np.array_equal(a[0], b[0]) and a[1] == b[1]
