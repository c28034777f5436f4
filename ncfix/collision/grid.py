"""Distance grids of meshes at the pitch: a lower bound on the distance to a body (looked up by
compiled loops on the CPU, ``descent``; in torch on CUDA; the same arithmetic in each).

The bound is valid anywhere in space and every approximation lies inside it, so a ball it clears
is free; anything else is *undecided* and goes to the exact test, never straight to "collides".
The proof is on ``DistanceGrid``, the exact band near the body on ``tighten_near_body``
(docs/collision.md, "The pieces").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ncfix import cache
from ncfix.collision.near import surface_distances
from ncfix.collision.voxelize import EDT_SLACK_MM, distance_transform, grid_frame, surface_cells, voxelize
from ncfix.geometry.tolerances import TOLERANCES
from ncfix.memory import ensure_fits, grid_cells

if TYPE_CHECKING:
    import trimesh

# Empty cells around the body: near it, lookups then stay inside the grid (tighter bounds).
GRID_PAD_CELLS = 6
# Peak bytes per cell while a grid is built (masks, the voxelizer's column sums, the EDT's float32
# output): 29-35 measured on the sample mold at 1 and 0.5 mm; what ``ensure_fits`` checks.
GRID_BUILD_BYTES_PER_CELL = 40
# Cells outside the body with D below this (mm) store their exact distance (``tighten_near_body``).
EXACT_BAND_MM = 4.0
# A surface cell's centre nearer the surface than this (mm) keeps D: the voxelizer's jittered ray
# (TOLERANCES.ray_jitter_fraction of a cell) may have passed on the other side of the surface.
JITTER_SAFE_MM = 1e-3
# The code a grid comes from: editing any of these files makes every cached grid a miss.
GRID_SOURCES = ("ncfix.collision.grid", "ncfix.collision.voxelize", "ncfix.collision.near", "ncfix.geometry.tolerances")
_GRID_ARRAYS = ("dist_mm", "origin_mm", "pitch_mm", "body_bounds_mm")
# The program's points are gathered in cubes of this edge (mm) for the exact band's region (``Reach``).
REACH_CELL_MM = 2.0


@dataclass(frozen=True)
class Reach:
    """Where a program can look a part grid up: within ``radius_mm`` of one of its points (its
    programmed points, tips and points along its arcs), the points given by the cubes of edge
    ``cell_mm`` they lie in (cube (i, j, k) spans [i, i + 1)·cell_mm on x, and so on).

    cells : (k, 3) int64, sorted, unique
    """

    cells: np.ndarray
    cell_mm: float
    radius_mm: float

    @classmethod
    def of_points(cls, points: np.ndarray, radius_mm: float, cell_mm: float = REACH_CELL_MM) -> "Reach":
        """The reach of points (n, 3) mm (non-finite rows left out)."""
        return cls(cube_cells(points, cell_mm), float(cell_mm), float(radius_mm))

    def mask(self, origin_mm: np.ndarray, shape: tuple[int, int, int], pitch_mm: float, slack_mm: float) -> np.ndarray:
        """(shape) bool: True at least at every cell centre of the grid within ``radius_mm +
        slack_mm`` of a point of the reach (a superset: a centre c in cube Q is within s·√3/2 of
        Q's centre, and so is a point in cube q of q's, so |c - p| <= r gives |Q - q| <= r + s·√3
        between cube centres, which an EDT over the cubes measures)."""
        s = self.cell_mm
        within = self.radius_mm + slack_mm + s * np.sqrt(3.0) + 1e-3  # 1e-3: the EDT's float32
        axes = [np.floor((origin_mm[a] + np.arange(shape[a]) * pitch_mm) / s).astype(np.int64) for a in range(3)]
        pad = int(np.ceil(within / s)) + 1
        lo = np.array([axis[0] for axis in axes]) - pad
        hi = np.array([axis[-1] for axis in axes]) + pad
        cubes = np.asarray(self.cells, dtype=np.int64).reshape(-1, 3)
        cubes = cubes[((cubes >= lo) & (cubes <= hi)).all(axis=1)]
        if not len(cubes):
            return np.zeros(shape, dtype=bool)
        free = np.ones(tuple(hi - lo + 1), dtype=bool)
        free[tuple((cubes - lo).T)] = False
        near = distance_transform(free, s) <= within
        return near[np.ix_(axes[0] - lo[0], axes[1] - lo[1], axes[2] - lo[2])]


def cube_cells(points: np.ndarray, cell_mm: float) -> np.ndarray:
    """The cubes of edge ``cell_mm`` holding points (n, 3) mm: (k, 3) int64, sorted, unique."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return np.unique(np.floor(pts / cell_mm).astype(np.int64), axis=0).reshape(-1, 3)


@dataclass
class DistanceGrid:
    """Distance from each cell centre to the nearest marked cell centre.

    *Marked* cells: cells whose centre is inside the closed mesh (exact, by the column-parity
    voxelizer) plus cells the surface may pass through (centre within half a cell diagonal of a
    triangle, ``surface_cells``). Every point of the body lies in the closed cube of a marked cell,
    so within ``h = pitch·√3/2`` of a marked cell centre. The Euclidean distance transform ``D``
    gives, at each cell centre ``c``, the distance to the nearest marked centre. For any point
    ``x`` and its nearest grid cell ``c`` (clamped to the grid), distance is 1-Lipschitz, so

        dist(x, body) >= D(c) - |x - c| - h        (``lower_bound``)

    with no assumption on where ``x`` lies. Far outside the grid that bound is loose, so the larger
    of it and the distance from ``x`` to the body's bounding box (which holds all of the body) is
    used. Every approximation (cell size, nearest-cell lookup, float32 EDT values) is inside that
    bound, so a ball of radius r at x is certainly free when ``lower_bound(x) > r + clearance``.
    An open mesh has no inside: its surface is the body.

    dist_mm : (nx, ny, nz) float32, mm (0 on marked cells)
    origin_mm : (3,) float64, centre of cell (0, 0, 0), in the frame of the mesh
    pitch_mm : cell edge
    name : the body, as the report names it (``part:mold.stl``)
    """

    dist_mm: np.ndarray
    origin_mm: np.ndarray
    pitch_mm: float
    name: str = ""
    body_bounds_mm: np.ndarray | None = None  # (2, 3) box holding the whole body
    # The on-disk cache's key and folder of this grid (key "" when it was built outside the
    # cache): what is derived from the grid alone (``depth.DepthProbe``'s field) is cached by it.
    cache_key: str = ""
    cache_dir: str | None = None
    _tensors: dict | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.dist_mm.shape)  # type: ignore[return-value]

    @property
    def margin_mm(self) -> float:
        """What the lookup may be off by at a cell centre: half a cell diagonal plus float slack."""
        return 0.5 * np.sqrt(3.0) * self.pitch_mm + EDT_SLACK_MM + TOLERANCES.cover_slack_mm

    @property
    def nbytes(self) -> int:
        return int(self.dist_mm.nbytes)

    def tensors(self, device):
        """The grid as torch tensors (distances float32, widened to float64 on lookup) on ``device`` (cached per device)."""
        import torch

        key = str(device)
        if self._tensors is None:
            self._tensors = {}
        if key not in self._tensors:
            dist = torch.as_tensor(self.dist_mm, device=device).reshape(-1)  # float32; gathered values widen exactly
            origin = torch.as_tensor(self.origin_mm, dtype=torch.float64, device=device)
            shape = torch.as_tensor(self.shape, dtype=torch.int64, device=device)
            box = torch.as_tensor(np.array(self._box()), dtype=torch.float64, device=device)
            self._tensors[key] = (dist, origin, shape, box)
        return self._tensors[key]

    def lower_bound(self, points):
        """Lower bound (mm) on the distance from points (m, 3) float64 tensor to the body -> (m,).

        Negative values mean "may be inside"; the bound is valid anywhere in space.
        """
        import torch

        dist, origin, shape, box = self.tensors(points.device)
        rel = (points - origin) / self.pitch_mm
        idx = torch.round(rel).to(torch.int64)
        idx = torch.minimum(torch.maximum(idx, torch.zeros_like(idx)), shape - 1)
        centre = origin + idx.to(torch.float64) * self.pitch_mm
        flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
        # Sums of squares spelled out: the order of the compiled CPU lookup (``descent._grid_lb``).
        d = points - centre
        off = torch.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        gap = torch.clamp(torch.maximum(box[0] - points, points - box[1]), min=0.0)
        outside = torch.sqrt(gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] + gap[:, 2] * gap[:, 2])
        return torch.maximum(dist[flat].to(torch.float64) - off - self.margin_mm, outside)

    def _box(self) -> np.ndarray:
        if self.body_bounds_mm is None:
            return np.array([[-np.inf] * 3, [np.inf] * 3])
        return np.asarray(self.body_bounds_mm, dtype=np.float64)

    def lower_bound_np(self, points: np.ndarray) -> np.ndarray:
        """The same bound in numpy (points (m, 3) float64 mm) -> (m,) float64, in the same order."""
        points = np.asarray(points, dtype=np.float64)
        rel = (points - self.origin_mm) / self.pitch_mm
        idx = np.clip(np.round(rel).astype(np.int64), 0, np.array(self.shape) - 1)
        centre = self.origin_mm + idx * self.pitch_mm
        d = points - centre
        off = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        box = self._box()
        gap = np.maximum(np.maximum(box[0] - points, points - box[1]), 0.0)
        outside = np.sqrt(gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] + gap[:, 2] * gap[:, 2])
        grid = self.dist_mm[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.float64) - off - self.margin_mm
        return np.maximum(grid, outside)


def marked_cells(mesh: trimesh.Trimesh, closed: bool, pitch_mm: float, origin_mm: np.ndarray,
                 shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Cells (nx, ny, nz) bool whose closed cube may hold a point of the body (``DistanceGrid``),
    and the cells whose centre the voxelizer finds inside (all False for an open mesh).

    An open (surface-only) mesh marks only the cells its triangles may pass through.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    half_diagonal = 0.5 * np.sqrt(3.0) * pitch_mm
    marked = surface_cells(v, f, origin_mm, shape, pitch_mm, half_diagonal + TOLERANCES.cover_slack_mm)
    if not closed:
        return marked, np.zeros_like(marked)
    inside = voxelize(v, f, pitch_mm, origin_mm=origin_mm, shape=shape).occupancy
    return marked | inside, inside


def tighten_near_body(dist: np.ndarray, inside: np.ndarray, mesh: trimesh.Trimesh, origin_mm: np.ndarray,
                      pitch_mm: float, region: np.ndarray | None = None) -> None:
    """Raises ``dist`` (the EDT, float32, in place) to ``d(c) + h`` at the cells within
    ``EXACT_BAND_MM`` whose centre is known to lie outside the body (and, given ``region``, (nx,
    ny, nz) bool, lies in it: the cells a program can look up; the others keep ``D``, a looser
    bound that is just as valid).

    Near the body ``D(c)`` can be up to ``2h`` below the true distance ``d(c)`` (``D`` measures to
    marked centres, each up to ``h`` from the body). Storing ``max(D(c), d(c) + h)``, with ``d(c)``
    the exact distance to the mesh's surface (``near.surface_distances``), keeps the lookup and its
    proof (``d(c) + h - |x - c| - h <= d(x)``) and makes the bound up to ``2h`` tighter there. A
    centre is known outside when it is unmarked (farther than ``h`` from the surface and not
    inside), or marked only for the surface with the voxelizer calling it outside and farther from
    the surface than the voxelizer's ray jitter (``JITTER_SAFE_MM``: the jittered ray saw the same
    side)."""
    h = 0.5 * np.sqrt(3.0) * pitch_mm
    band = (dist.ravel() <= EXACT_BAND_MM) & ~inside.ravel()
    if region is not None:
        band &= region.ravel()
    cells = np.flatnonzero(band)
    if not len(cells):
        return
    centres = np.asarray(origin_mm, dtype=np.float64) + np.stack(np.unravel_index(cells, dist.shape), axis=1) * pitch_mm
    exact = surface_distances(np.asarray(mesh.triangles, dtype=np.float64), centres, EXACT_BAND_MM + 2.0 * h)
    # A marked cell (D = 0) that is not inside is marked for the surface: known outside only
    # beyond the ray jitter. An unmarked one (D > 0) is farther than h from the surface.
    known = (dist.ravel()[cells] > 0) | (exact > JITTER_SAFE_MM)
    cells, raised = cells[known], (exact[known] + h).astype(np.float32)
    flat = dist.reshape(-1)
    flat[cells] = np.maximum(flat[cells], raised)


def build_distance_grid(mesh: trimesh.Trimesh, pitch_mm: float, *, closed: bool = True, name: str = "",
                        bounds_mm: np.ndarray | None = None, reach: Reach | None = None) -> DistanceGrid:
    """Distance grid of a mesh at ``pitch_mm``.

    bounds_mm : (2, 3) region to cover (default: the mesh's bounds); it is intersected with the
        mesh's bounds (no body outside them) and padded by two cells. Lookups outside the grid
        stay valid lower bounds, only looser.
    reach : where the program looks the grid up (default: anywhere); the exact band is computed
        only for the cells a lookup there can read (its nearest cell centre, within half a cell
        diagonal), the others keep the distance transform's bound.
    """
    bounds = np.asarray(mesh.bounds, dtype=np.float64)
    cropped = False
    if bounds_mm is not None:
        crop = np.asarray(bounds_mm, dtype=np.float64)
        lo, hi = np.maximum(bounds[0], crop[0]), np.minimum(bounds[1], crop[1])
        if (lo <= hi).all() and ((lo > bounds[0]) | (hi < bounds[1])).any():
            bounds, cropped = np.array([lo, hi]), True
    label = name.split(":", 1)[1] if name.startswith("part:") else f"the {name or 'mesh'}"
    ensure_fits(f"the distance grid of {label}", grid_cells(bounds, pitch_mm, GRID_PAD_CELLS),
                GRID_BUILD_BYTES_PER_CELL, pitch_mm=pitch_mm, extent_mm=float(np.ptp(bounds, axis=0).max()))
    origin, shape = grid_frame(bounds, pitch_mm, pad_cells=GRID_PAD_CELLS)
    marked, inside = marked_cells(mesh, closed, pitch_mm, origin, shape)
    if cropped:
        # The body goes on beyond the grid: the outer layer stands for it (any path from inside
        # the grid to that material crosses the layer), so the bound stays a lower bound.
        for axis in range(3):
            marked[(slice(None),) * axis + (0,)] = True
            marked[(slice(None),) * axis + (-1,)] = True
    dist = distance_transform(~marked, pitch_mm)
    region = None if reach is None else reach.mask(origin, shape, pitch_mm, 0.5 * np.sqrt(3.0) * pitch_mm)
    tighten_near_body(dist, inside, mesh, origin, pitch_mm, region)
    # The bounds copied: trimesh's are read-only, the cached ones writable (numba types them apart).
    return DistanceGrid(dist, origin, float(pitch_mm), name, np.array(mesh.bounds, dtype=np.float64))


def cached_distance_grid(mesh: trimesh.Trimesh, pitch_mm: float, *, closed: bool = True, name: str = "",
                         bounds_mm: np.ndarray | None = None, reach: Reach | None = None,
                         cache_dir: str | None = None) -> DistanceGrid:
    """``build_distance_grid``'s grid, read from the on-disk cache (``ncfix.cache``) when the same
    mesh was gridded before with the same pitch, closedness, crop, reach, code and libraries."""
    key = cache.make_key(
        "grid",
        np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64),
        float(pitch_mm), bool(closed), None if bounds_mm is None else np.asarray(bounds_mm, dtype=np.float64),
        None if reach is None else np.asarray(reach.cells, dtype=np.int64),
        None if reach is None else [float(reach.cell_mm), float(reach.radius_mm)],
        cache.fingerprint(*GRID_SOURCES),
        {package: cache.version(package) for package in ("numpy", "edt", "scipy")},
    )

    def to_arrays(grid: DistanceGrid) -> dict[str, np.ndarray]:
        return {"dist_mm": grid.dist_mm, "origin_mm": grid.origin_mm, "pitch_mm": np.float64(grid.pitch_mm),
                "body_bounds_mm": grid.body_bounds_mm}

    def from_arrays(a: dict[str, np.ndarray]) -> DistanceGrid | None:
        dist, origin, bounds = a["dist_mm"], a["origin_mm"], a["body_bounds_mm"]
        if dist.dtype != np.float32 or dist.ndim != 3 or origin.shape != (3,) or bounds.shape != (2, 3):
            return None
        return DistanceGrid(dist, origin.astype(np.float64), float(a["pitch_mm"]), name, bounds.astype(np.float64))

    body = "the head" if name == "head" else name.split(":", 1)[-1] or "a mesh"
    what = (f"the distance grid of {body} (first run for this mesh"
            + (" and this program's reach)" if bounds_mm is not None or reach is not None else ")"))
    grid, _ = cache.cached("grid", key, _GRID_ARRAYS,
                           lambda: build_distance_grid(mesh, pitch_mm, closed=closed, name=name, bounds_mm=bounds_mm,
                                                       reach=reach),
                           to_arrays, from_arrays, cache_dir, what=what)
    grid.cache_key, grid.cache_dir = key, cache_dir
    return grid
