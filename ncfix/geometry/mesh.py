"""Load and validate head and part meshes (STL, OBJ), and put the head into its frame.

Decisions, so that users and the next stages know what a mesh means:

- Degenerate (zero-area) triangles are dropped with a warning: they carry no geometry.
- Inward-facing meshes (negative volume) and inconsistent winding are repaired with a warning.
- Open meshes: small holes are filled first. A head must then be one closed solid, or loading
  fails: the head model needs its volume. A part that stays open is used as a surface only
  (``LoadedMesh.closed`` is False): ncfix checks the head against its triangles but cannot tell
  its inside from its outside, so a head buried inside it is not seen; a warning says so.
- Warnings are returned as plain sentences in ``LoadedMesh.warnings`` (the CLI prints them).

Reading and repairing use trimesh; the result (the arrays, closedness and warnings) is kept in the
on-disk cache under the file's exact bytes, so that a run whose every model comes from the cache
does not import trimesh at all (``ncfix.geometry.meshdata``).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ncfix import cache
from ncfix.errors import GeometryError
from ncfix.geometry.distance import point_mesh_distance
from ncfix.geometry.frames import rotation_between
from ncfix.geometry.meshdata import Mesh, mesh_arrays
from ncfix.geometry.place import parse
from ncfix.geometry.tolerances import TOLERANCES

if TYPE_CHECKING:
    import trimesh

Role = Literal["head", "part"]

# File suffix -> trimesh file type. Explicit, so an unknown suffix fails listing the known ones.
MESH_FORMATS: dict[str, str] = {".stl": "stl", ".obj": "obj"}

_OPTION = {"head": "--head", "part": "--part", "platform": "--platform"}
# The code a loaded mesh comes from: editing any of these files makes every cached one a miss.
MESH_SOURCES = ("ncfix.geometry.mesh", "ncfix.geometry.meshdata", "ncfix.geometry.tolerances")
_MESH_ARRAYS = ("vertices", "faces", "closed", "warnings")


@dataclass
class LoadedMesh:
    """A validated mesh and what was done to it.

    arrays : the mesh (``Mesh``: vertices (n, 3) float64 in the file's units and frame, faces)
    closed : True when the mesh bounds a volume (watertight, consistently wound)
    warnings : plain sentences, each naming the file
    """

    arrays: Mesh
    name: str
    role: Role
    closed: bool
    warnings: list[str] = field(default_factory=list)

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The mesh as a ``trimesh.Trimesh`` (made on first use: it imports trimesh)."""
        return self.arrays.to_trimesh()


def load_mesh(path: str | Path, role: Role | Literal["platform"], base: np.ndarray | None = None) -> LoadedMesh:
    """Read a head or part mesh from STL (binary or ASCII) or OBJ, validate it and place it.

    path : the file, or the text form ``FILE@translate=X,Y,Z@rotate_deg=RX,RY,RZ``
    (``ncfix.geometry.place``); base : (4, 4) a placement applied before that one (a profile's
    platform). A platform is a part (role "part") that the --platform option named.
    Raises GeometryError when the file is missing, empty, not a mesh, has NaN coordinates,
    or (for a head) is not a closed solid even after filling holes.
    """
    if role not in _OPTION:
        raise ValueError(f"role must be 'head', 'part' or 'platform', not {role!r}")
    option = _OPTION[role]
    if role == "platform":
        role = "part"
    placement = None
    if not isinstance(path, Path):
        placement, problem = parse(str(path))
        if problem:
            raise GeometryError(f"{option} {str(path)!r}: {problem}",
                                fix="write PATH@translate=X,Y,Z@rotate_deg=RX,RY,RZ")
        path = placement.path
    loaded = _load_file(Path(path), role, option)
    matrix = placement.matrix() if placement is not None and not placement.identity else None
    if base is not None:
        matrix = base if matrix is None else matrix @ base
    if matrix is not None:
        loaded.arrays.apply_transform(matrix)  # a rotation and a move: the winding stays outward
    return loaded


def _load_file(path: Path, role: Role, option: str) -> LoadedMesh:
    where = str(path)
    if path.is_dir():
        raise GeometryError(
            f"the {role} mesh path is a folder", where=where, fix=f"give the mesh file's path to {option}"
        )
    if not path.is_file():
        if path.exists():
            raise GeometryError(f"the {role} mesh path is not a regular file", where=where,
                                fix=f"give a mesh file (STL or OBJ) to {option}")
        raise GeometryError(
            f"the {role} mesh file does not exist", where=where, fix=f"check the {option} path"
        )
    if path.stat().st_size == 0:
        raise GeometryError(
            f"the {role} mesh file is empty", where=where, fix="export the mesh again as STL or OBJ"
        )
    suffix = path.suffix.lower()
    if suffix not in MESH_FORMATS:
        known = ", ".join(sorted(MESH_FORMATS))
        raise GeometryError(
            f"cannot read '{path.suffix}' files as a mesh",
            where=where,
            fix=f"export the {role} as one of {known}",
        )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise GeometryError(f"cannot read the {role} mesh: {exc.strerror or exc}", where=where,
                            fix="check the file's permissions") from None
    key = cache.make_key("mesh", np.frombuffer(data, dtype=np.uint8), MESH_FORMATS[suffix], role, where,
                         cache.fingerprint(*MESH_SOURCES),
                         {package: cache.version(package) for package in ("numpy", "trimesh")})

    def build() -> LoadedMesh:
        return _validate(_read_triangles(path, MESH_FORMATS[suffix], role), where, role)

    def to_arrays(loaded: LoadedMesh) -> dict[str, np.ndarray]:
        text = json.dumps(loaded.warnings).encode("utf-8")
        return {"vertices": loaded.arrays.vertices, "faces": loaded.arrays.faces,
                "closed": np.array(loaded.closed), "warnings": np.frombuffer(text, dtype=np.uint8)}

    def from_arrays(a: dict[str, np.ndarray]) -> LoadedMesh | None:
        v, f = a["vertices"], a["faces"]
        if not mesh_arrays(v, f) or a["closed"].dtype != np.bool_:
            return None
        said = json.loads(a["warnings"].tobytes().decode("utf-8"))
        # Copies: a placement moves the vertices in place, never in the cache file.
        return LoadedMesh(Mesh(v.copy(), f.copy()), where, role, bool(a["closed"]), [str(w) for w in said])

    loaded, _ = cache.cached("mesh", key, _MESH_ARRAYS, build, to_arrays, from_arrays)
    return loaded


def _read_triangles(path: Path, file_type: str, role: Role) -> trimesh.Trimesh:
    import trimesh

    not_a_mesh = GeometryError(
        f"no triangles found: the file is not a {file_type.upper()} mesh",
        where=str(path),
        fix=f"export the {role} again as STL or OBJ",
    )
    try:
        # NaN or infinite coordinates make trimesh's normals warn; _validate says it in one line.
        with open(path, "rb") as handle, np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(handle, file_type=file_type, force="mesh", process=False)
    except OSError as exc:
        raise GeometryError(f"cannot read the {role} mesh: {exc.strerror or exc}", where=str(path),
                            fix="check the file's permissions") from None
    except Exception as exc:  # trimesh raises many types for garbage input
        raise not_a_mesh from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise not_a_mesh
    return loaded


def _validate(raw: trimesh.Trimesh, where: str, role: Role) -> LoadedMesh:
    import trimesh

    warnings: list[str] = []
    vertices = np.asarray(raw.vertices, dtype=np.float64)
    faces = np.asarray(raw.faces, dtype=np.int64)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise GeometryError(
            f"{int(bad.sum())} vertices have NaN or infinite coordinates",
            where=where,
            fix="repair the mesh in CAD and export it again",
        )
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.merge_vertices()
    keep = mesh.area_faces > TOLERANCES.degenerate_area_mm2
    # A face with a repeated vertex index has zero area too, but say it once.
    if not keep.all():
        dropped = int((~keep).sum())
        mesh.update_faces(keep)
        mesh.remove_unreferenced_vertices()
        warnings.append(f"{where}: dropped {dropped} degenerate (zero-area) triangles")
    if len(mesh.faces) == 0:
        raise GeometryError(
            "every triangle has zero area", where=where, fix=f"export the {role} again"
        )

    if not mesh.is_watertight:
        open_edges = _open_edge_count(mesh)
        trimesh.repair.fill_holes(mesh)
        if mesh.is_watertight:
            warnings.append(f"{where}: the mesh had {open_edges} open edges; the holes were filled")
        elif role == "head":
            raise GeometryError(
                f"the head mesh is not closed ({_open_edge_count(mesh)} open edges remain "
                "after filling holes)",
                where=where,
                fix="export the head as one closed (watertight) solid",
            )
        else:
            warnings.append(
                f"{where}: the part mesh is not closed ({_open_edge_count(mesh)} open edges); "
                "it is used as a surface, so a head entirely inside it is not detected"
            )
    closed = bool(mesh.is_watertight)

    if closed and not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        warnings.append(f"{where}: the triangle winding was inconsistent and was fixed")
    if closed and mesh.volume < 0:
        mesh.invert()
        warnings.append(f"{where}: the triangles faced inward (negative volume) and were flipped")
    if closed and role == "head":
        bodies = mesh.body_count
        if bodies > 1:
            warnings.append(
                f"{where}: the head has {bodies} separate shells; they are treated as one solid"
            )
    arrays = Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    return LoadedMesh(arrays=arrays, name=where, role=role, closed=closed, warnings=warnings)


def _open_edge_count(mesh: trimesh.Trimesh) -> int:
    edges = mesh.edges_sorted
    if len(edges) == 0:
        return 0
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts != 2).sum())


def find_tip(mesh: Mesh | trimesh.Trimesh, axis: np.ndarray) -> np.ndarray:
    """The lowest point of a head along ``axis``: the centroid of the vertices within the tip tolerance.

    axis : (3,) float64, tip -> head
    returns : (3,) float64, in the mesh's frame
    """
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    heights = mesh.vertices @ axis
    low = heights <= heights.min() + 1e-6
    return np.asarray(mesh.vertices[low].mean(axis=0))


def orient_head(
    loaded: LoadedMesh, tip: np.ndarray | tuple[float, float, float], axis: np.ndarray | tuple[float, float, float]
) -> LoadedMesh:
    """Apply --head-tip/--head-axis: move the tip to the origin and turn the axis onto +Z.

    tip : (3,) float64, mm in the mesh's frame
    axis : (3,) float64, tip -> head, any length > 0
    Raises GeometryError when the head reaches more than the tip tolerance below the tip along
    the axis (a wrong tip or axis would make ncfix check the wrong place). Warns when the mesh
    starts above the tip or does not touch it.
    """
    where = loaded.name
    tip = np.asarray(tip, dtype=np.float64).reshape(3)
    axis = np.asarray(axis, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(axis))
    if not np.isfinite(norm) or norm == 0.0:
        raise GeometryError(
            f"the head axis {_fmt(axis)} has no direction",
            where=where,
            fix="give --head-axis as a nonzero vector X,Y,Z from the tip toward the head",
        )
    axis = axis / norm
    rotation = rotation_between(axis, np.array([0.0, 0.0, 1.0]))
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = -rotation @ tip
    mesh = loaded.arrays.copy()
    mesh.apply_transform(transform)

    tol = TOLERANCES.head_tip_mm
    warnings = list(loaded.warnings)
    lowest = float(mesh.vertices[:, 2].min())
    if lowest < -tol:
        suggestion = find_tip(loaded.arrays, axis)
        raise GeometryError(
            f"the head reaches {-lowest:.3g} mm below the tip {_fmt(tip)} along the axis {_fmt(axis)}",
            where=where,
            fix=f"check --head-tip and --head-axis; the lowest point along this axis is {_fmt(suggestion)}",
        )
    if lowest > tol:
        warnings.append(
            f"{where}: the head starts {lowest:.3g} mm above the tip {_fmt(tip)} along the axis; "
            "ncfix assumes the nozzle is at the tip"
        )
    else:
        tri = np.asarray(mesh.triangles)
        gap = float(point_mesh_distance(np.zeros((1, 3)), tri)[0])
        if gap > tol:
            warnings.append(
                f"{where}: the tip {_fmt(tip)} is {gap:.3g} mm away from the head mesh; "
                "check --head-tip"
            )
    return LoadedMesh(arrays=mesh, name=where, role=loaded.role, closed=loaded.closed, warnings=warnings)


def load_head(
    path: str | Path,
    tip: tuple[float, float, float] = (0.0, 0.0, 0.0),
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> LoadedMesh:
    """load_mesh(path, 'head') then orient_head(tip, axis): the head in the head frame of docs/contract.md."""
    return orient_head(load_mesh(path, "head"), tip, axis)


def check_part_overlaps(
    part: LoadedMesh, bbox_min_mm: np.ndarray, bbox_max_mm: np.ndarray
) -> list[str]:
    """Check that a part lies where the program works; return warnings.

    bbox_min_mm, bbox_max_mm : (3,) float64, the toolpath's bounding box, workpiece mm
    Raises GeometryError when the part is farther than ``part_reach_mm`` from the toolpath's box
    (the head cannot reach it: wrong units or frame). Warns when the part does not overlap the
    box itself, and when its size is about 25.4 times off (inch/mm mix-up).
    """
    lo = np.asarray(bbox_min_mm, dtype=np.float64)
    hi = np.asarray(bbox_max_mm, dtype=np.float64)
    plo, phi = part.arrays.bounds
    gap = np.maximum(0.0, np.maximum(plo - hi, lo - phi))
    distance = float(np.linalg.norm(gap))
    warnings: list[str] = []
    units_hint = _units_hint(phi - plo, hi - lo, smaller_too=distance > 0.0)
    if distance > TOLERANCES.part_reach_mm:
        raise GeometryError(
            f"the part is {distance:.0f} mm away from the toolpath (part box {_fmt(plo)}..{_fmt(phi)}, "
            f"toolpath box {_fmt(lo)}..{_fmt(hi)})",
            where=part.name,
            fix="export the part in the program's workpiece frame and units" + units_hint,
        )
    if distance > 0.0:
        warnings.append(
            f"{part.name}: the part does not overlap the toolpath's bounding box "
            f"(it is {distance:.3g} mm away); check its frame and units" + units_hint
        )
    elif units_hint:
        warnings.append(f"{part.name}: the part's size does not match the toolpath's" + units_hint)
    return warnings


def _units_hint(part_size: np.ndarray, path_size: np.ndarray, *, smaller_too: bool) -> str:
    # A part much smaller than the toolpath is normal (a fixture); only suspicious when misplaced.
    big_part, big_path = float(np.max(part_size)), float(np.max(path_size))
    if big_part <= 0 or big_path <= 0:
        return ""
    ratio = big_part / big_path
    if 10.0 < ratio < 60.0:
        return " (the part is about 25.4 times larger than the toolpath: inches vs mm?)"
    if smaller_too and 1 / 60.0 < ratio < 1 / 10.0:
        return " (the part is about 25.4 times smaller than the toolpath: inches vs mm?)"
    return ""


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in np.asarray(v).reshape(-1)) + ")"
