"""The head model for checking: balls that provably cover the head, densest near the nozzle.

Every ball is the circumscribed ball of a cube of voxel cells and every cell that may hold a point
of the head lies in such a cube, so the union of balls covers the head: when every ball is farther
than its radius (plus the clearance) from every body, the head is free. The balls are grouped into
bounding spheres (``SphereTree``) for a coarse first test. How they are built: ``build_head_model``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ncfix import cache
from ncfix.collision.voxelize import grid_frame, surface_cells, voxelize
from ncfix.geometry.tolerances import TOLERANCES
from ncfix.memory import ensure_fits, grid_cells

if TYPE_CHECKING:
    import trimesh

ZONE_NAMES = ("lower", "middle", "upper")
# Peak bytes per cell of the head's voxel grid while the model is built (38-42 measured on the
# sample head at 1 and 0.5 mm); what ``ensure_fits`` checks.
HEAD_BUILD_BYTES_PER_CELL = 48
# The code a head model and a sphere tree come from: editing any of these files makes every
# cached model and tree a miss.
HEAD_SOURCES = ("ncfix.collision.head", "ncfix.collision.voxelize", "ncfix.geometry.tolerances")
_MODEL_ARRAYS = ("centers_mm", "radii_mm", "zone", "interior", "group", "group_centers_mm", "group_radii_mm",
                 "pitch_mm", "zone_tops_mm", "marked_cells")
_TREE_ARRAYS = ("center_mm", "radius_mm", "reach_mm", "child_start", "child_count", "level_start")


@dataclass(frozen=True)
class RiskZones:
    """Where the head's lower/middle/upper sections end, and how coarse each one is sampled.

    tops_fraction : top of the lower and middle section, as fractions of the head's height
    levels : cube edge of the covering balls in each section, as log2 of cells (0 = one cell)
    """

    tops_fraction: tuple[float, float] = (0.3, 0.7)
    levels: tuple[int, int, int] = (0, 1, 2)


@dataclass(frozen=True)
class HeadModel:
    """Covering balls of a head in its frame (tip at the origin, axis +Z).

    centers_mm : (n, 3) float64, ball centres, head frame
    radii_mm : (n,) float64
    zone : (n,) int8, 0 lower, 1 middle, 2 upper (by the ball centre's height)
    interior : (n,) bool, True for the coarse balls deep inside the head
    group : (n,) int64, index into the bounding spheres
    group_centers_mm : (k, 3) float64; group_radii_mm : (k,) float64; each bounding sphere
        contains all balls of its group
    pitch_mm : the voxel pitch the model was built at
    zone_tops_mm : (2,) float64, heights where the lower and the middle zone end
    marked_cells : number of voxels (inside or on the surface) the balls cover
    """

    centers_mm: np.ndarray
    radii_mm: np.ndarray
    zone: np.ndarray
    interior: np.ndarray
    group: np.ndarray
    group_centers_mm: np.ndarray
    group_radii_mm: np.ndarray
    pitch_mm: float
    zone_tops_mm: np.ndarray
    marked_cells: int

    def counts(self) -> dict[str, int]:
        """Ball counts for ``-v``: per zone (surface samples), interior balls, bounding spheres."""
        samples = ~self.interior
        out = {name: int((samples & (self.zone == k)).sum()) for k, name in enumerate(ZONE_NAMES)}
        out["interior"] = int(self.interior.sum())
        out["total"] = int(len(self.radii_mm))
        out["spheres"] = int(len(self.group_radii_mm))
        return out

    def zone_fractions(self) -> tuple[float, float, float]:
        """Share of the surface samples in the lower, middle and upper zone."""
        c = self.counts()
        total = max(1, c["lower"] + c["middle"] + c["upper"])
        return (c["lower"] / total, c["middle"] / total, c["upper"] / total)

    def summary(self) -> str:
        """One line for ``-v``."""
        c = self.counts()
        f = self.zone_fractions()
        return (
            f"head model at {self.pitch_mm:g} mm: {c['total']} balls "
            f"({c['lower'] + c['middle'] + c['upper']} samples: lower {c['lower']} ({f[0]:.0%}), "
            f"middle {c['middle']} ({f[1]:.0%}), upper {c['upper']} ({f[2]:.0%}); "
            f"{c['interior']} interior), {c['spheres']} bounding spheres"
        )

    def covers(self, points_mm: np.ndarray) -> np.ndarray:
        """Whether each head-frame point (n, 3) lies in some ball -> (n,) bool."""
        from scipy.spatial import cKDTree

        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        tree = cKDTree(self.centers_mm)
        out = np.zeros(len(pts), dtype=bool)
        for i, near in enumerate(tree.query_ball_point(pts, float(self.radii_mm.max()))):
            if near:
                d = np.linalg.norm(self.centers_mm[near] - pts[i], axis=1)
                out[i] = bool((d <= self.radii_mm[near]).any())
        return out


def build_head_model(
    head: trimesh.Trimesh,
    pitch_mm: float = 0.5,
    *,
    zones: RiskZones = RiskZones(),
    max_level: int = 4,
    target_spheres: int = 24,
) -> HeadModel:
    """Build the covering-ball model of a closed head mesh given in the head frame (tip at the
    origin, axis +Z), from a voxel grid of the head at the pitch:

    1. *marked* cells: cells whose centre is inside the head (exact, column winding counts) plus
       cells the surface may pass through (centre within half a cell diagonal of a triangle).
       Every point of the head lies in a marked cell: a cell the surface does not cross is wholly
       inside or wholly outside, and then its centre says which.
    2. *interior balls*: cubes of 2^L cells (L = max_level .. 1) whose circumscribed ball lies
       within marked cells, coarsest first; they replace the many cells deep inside the head.
    3. *risk zones* (the seed's lower/middle/upper sections along the axis): the remaining marked
       cells are covered by the circumscribed balls of cubes of 1, 2 and 4 cells in the lower,
       middle and upper zone. Fine balls where collisions happen, coarse ones high up: the coarse
       balls only make the model more conservative, never less.
    """
    pitch = float(pitch_mm)
    v = np.asarray(head.vertices, dtype=np.float64)
    f = np.asarray(head.faces, dtype=np.int64)
    bounds = np.array([v.min(axis=0), v.max(axis=0)])
    align = 2**max_level
    ensure_fits("the head model", grid_cells(bounds, pitch, 1 + align), HEAD_BUILD_BYTES_PER_CELL, pitch_mm=pitch,
                extent_mm=float(np.ptp(bounds, axis=0).max()))
    origin, shape = grid_frame(bounds, pitch, pad_cells=1, align_cells=align)
    inside = voxelize(v, f, pitch, origin_mm=origin, shape=shape).occupancy
    half_diagonal = 0.5 * np.sqrt(3.0) * pitch
    band = surface_cells(v, f, origin, shape, pitch, half_diagonal + TOLERANCES.cover_slack_mm)
    marked = inside | band

    height = bounds[1, 2] - bounds[0, 2]
    # Zone boundaries on block edges of the coarsest zone level, so no cube straddles two zones.
    zone_block = 2 ** max(zones.levels) * pitch
    edge0 = origin[2] - 0.5 * pitch
    tops = np.array(
        [edge0 + np.round((bounds[0, 2] + t * height - edge0) / zone_block) * zone_block for t in zones.tops_fraction]
    )
    cell_z = origin[2] + np.arange(shape[2]) * pitch
    cell_zone = np.searchsorted(tops, cell_z, side="right")
    # An interior ball may reach past the marked cells by as much as a sample ball of its zone
    # can (the cube of that zone's level, less one cell): no looser than the zone already is.
    zone_slack = np.array([2**level - 1 for level in zones.levels])

    covered = np.zeros(shape, dtype=bool)
    centers: list[np.ndarray] = []
    radii: list[np.ndarray] = []
    interior: list[np.ndarray] = []

    # Summed-volume table of unmarked cells: a window is fully marked when its sum is zero.
    unmarked = np.zeros(tuple(s + 1 for s in shape), dtype=np.int32)
    unmarked[1:, 1:, 1:] = (~marked).astype(np.int32).cumsum(0).cumsum(1).cumsum(2)
    dims = np.array(shape)
    for level in range(max_level, 0, -1):
        b = 2**level
        starts = np.argwhere(np.ones(tuple(dims // b), dtype=bool)) * b
        # The ball around a cube of edge b reaches (sqrt(3) - 1) / 2 * b beyond its faces.
        reach = int(np.ceil((np.sqrt(3.0) - 1.0) / 2.0 * b))
        block_zone = cell_zone[np.minimum(starts[:, 2] + b // 2, shape[2] - 1)]
        margin = np.maximum(reach - zone_slack[block_zone], 0)[:, None]
        lo, hi = starts - margin, starts + b + margin
        ok = (lo >= 0).all(axis=1) & (hi <= dims).all(axis=1)
        lo, hi, starts = lo[ok], hi[ok], starts[ok]
        solid = _window_sum(unmarked, lo, hi) == 0
        starts = starts[solid]
        # Skip cubes already inside a coarser accepted cube.
        starts = starts[~covered[starts[:, 0], starts[:, 1], starts[:, 2]]]
        accepted = np.zeros(tuple(dims // b), dtype=bool)
        accepted[tuple((starts // b).T)] = True
        covered |= accepted.repeat(b, 0).repeat(b, 1).repeat(b, 2)
        centers.append(origin + (starts + 0.5 * (b - 1)) * pitch)
        radii.append(np.full(len(starts), 0.5 * np.sqrt(3.0) * b * pitch))
        interior.append(np.ones(len(starts), dtype=bool))

    remaining = marked & ~covered
    for zone, level in enumerate(zones.levels):
        b = 2**level
        mask = remaining & (cell_zone == zone)[None, None, :]
        blocks = mask.reshape(dims[0] // b, b, dims[1] // b, b, dims[2] // b, b).any(axis=(1, 3, 5))
        starts = np.argwhere(blocks) * b
        centers.append(origin + (starts + 0.5 * (b - 1)) * pitch)
        radii.append(np.full(len(starts), 0.5 * np.sqrt(3.0) * b * pitch))
        interior.append(np.zeros(len(starts), dtype=bool))

    c = np.concatenate(centers)
    r = np.concatenate(radii) + TOLERANCES.cover_slack_mm
    inner = np.concatenate(interior)
    zone_of = np.searchsorted(tops, c[:, 2], side="right").astype(np.int8)
    group, g_centers, g_radii = _group(c, r, bounds, target_spheres)
    return HeadModel(
        centers_mm=c,
        radii_mm=r,
        zone=zone_of,
        interior=inner,
        group=group,
        group_centers_mm=g_centers,
        group_radii_mm=g_radii,
        pitch_mm=pitch,
        zone_tops_mm=tops,
        marked_cells=int(marked.sum()),
    )


def _window_sum(table: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sums over boxes [lo, hi) (n, 3) from a summed-volume table with a zero border."""
    x0, y0, z0 = lo.T
    x1, y1, z1 = hi.T
    return (
        table[x1, y1, z1]
        - table[x0, y1, z1]
        - table[x1, y0, z1]
        - table[x1, y1, z0]
        + table[x0, y0, z1]
        + table[x0, y1, z0]
        + table[x1, y0, z0]
        - table[x0, y0, z0]
    )


def _group(
    centers: np.ndarray, radii: np.ndarray, bounds: np.ndarray, target: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin balls into cubes sized for about ``target`` bins; a bounding sphere per bin."""
    size = bounds[1] - bounds[0]
    edge = max(float(np.prod(size) / target) ** (1.0 / 3.0), 1e-9)
    key = np.maximum(np.floor((centers - bounds[0]) / edge).astype(np.int64) + 1, 0)
    flat = np.ravel_multi_index(tuple(key.T), tuple(key.max(axis=0) + 1))
    _, group = np.unique(flat, return_inverse=True)
    group = group.reshape(-1)
    k = int(group.max()) + 1
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    np.minimum.at(lo, group, centers - radii[:, None])
    np.maximum.at(hi, group, centers + radii[:, None])
    g_centers = 0.5 * (lo + hi)
    reach = np.linalg.norm(centers - g_centers[group], axis=1) + radii
    g_radii = np.zeros(k)
    np.maximum.at(g_radii, group, reach)
    return group, g_centers, g_radii


@dataclass(frozen=True)
class SphereTree:
    """A bounding-sphere tree over a set of covering balls (head frame), for breadth-first tests.

    Nodes are numbered level by level, root first; the balls are the leaves (every leaf is at
    the last level). Node i holds the balls of its subtree inside the sphere (center[i], radius[i]);
    its children are child_start[i] .. child_start[i] + child_count[i] - 1 (none for a leaf).
    reach[i] = |center[i]| + radius[i]: no point of the node is farther from the tip (for the
    sweep margin of a rotation: such a point moves at most reach·θ).

    center_mm : (n, 3) float64; radius_mm, reach_mm : (n,) float64; child_start, child_count :
    (n,) int64; level_start : (levels + 1,) int64, the first node of each level.
    """

    center_mm: np.ndarray
    radius_mm: np.ndarray
    reach_mm: np.ndarray
    child_start: np.ndarray
    child_count: np.ndarray
    level_start: np.ndarray

    @property
    def n_balls(self) -> int:
        return int(self.level_start[-1] - self.level_start[-2])


def _octree_order(c: np.ndarray, leaf_cell_mm: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """The order of the ball centres c (n, 3) in ``build_sphere_tree``'s leaves (sorted by their
    octree cells at every level, root first, so each node's balls are contiguous; a stable sort),
    and each level's (n, 3) cell keys, root first."""
    lo = c.min(axis=0) - 1e-9
    extent = float((c.max(axis=0) - lo).max())
    levels = max(1, int(np.ceil(np.log2(max(extent / leaf_cell_mm, 1.0)))) + 1)
    keys = [np.floor((c - lo) / (leaf_cell_mm * 2.0 ** (levels - 1 - lev))).astype(np.int64) for lev in range(levels)]
    return np.lexsort(tuple(k[:, d] for k in reversed(keys) for d in (2, 1, 0))), keys


def leaf_order(centers_mm: np.ndarray, leaf_cell_mm: float) -> np.ndarray:
    """The order in which ``build_sphere_tree`` puts these balls in its last level: balls given
    in this order stay in it (the leaf of node ``level_start[-2] + i`` is ball i)."""
    return _octree_order(np.asarray(centers_mm, dtype=np.float64), leaf_cell_mm)[0]


def build_sphere_tree(centers_mm: np.ndarray, radii_mm: np.ndarray, leaf_cell_mm: float) -> SphereTree:
    """Octree levels over ball centres: cells of leaf_cell_mm·2^k, up to one root; each node's
    sphere is the tightest about its balls' box centre that holds all of them."""
    c = np.asarray(centers_mm, dtype=np.float64)
    r = np.asarray(radii_mm, dtype=np.float64)
    order, keys = _octree_order(c, leaf_cell_mm)
    c, r = c[order], r[order]
    keys = [k[order] for k in keys]
    node_of = []  # per level: (n_balls,) node id within the level
    for k in keys:
        change = np.ones(len(c), dtype=bool)
        change[1:] = (k[1:] != k[:-1]).any(axis=1)
        node_of.append(np.cumsum(change) - 1)
    node_of[0][:] = 0  # one root, whatever the top cell split says
    node_of.append(np.arange(len(c)))  # the balls themselves
    counts = [int(n.max()) + 1 for n in node_of]
    level_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n_total = int(level_start[-1])
    center = np.zeros((n_total, 3))
    radius = np.zeros(n_total)
    child_start = np.zeros(n_total, dtype=np.int64)
    child_count = np.zeros(n_total, dtype=np.int64)
    for lev, ids in enumerate(node_of):
        n = counts[lev]
        blo = np.full((n, 3), np.inf)
        bhi = np.full((n, 3), -np.inf)
        np.minimum.at(blo, ids, c - r[:, None])
        np.maximum.at(bhi, ids, c + r[:, None])
        mid = 0.5 * (blo + bhi)
        rad = np.zeros(n)
        np.maximum.at(rad, ids, np.linalg.norm(c - mid[ids], axis=1) + r)
        if lev == len(node_of) - 1:
            mid, rad = c, r
        base = level_start[lev]
        center[base:base + n] = mid
        radius[base:base + n] = rad + TOLERANCES.cover_slack_mm
        if lev + 1 < len(node_of):
            child = node_of[lev + 1]
            # first child of each node: the child node of its first ball (children are contiguous)
            first_ball = np.searchsorted(ids, np.arange(n), side="left")
            last_ball = np.searchsorted(ids, np.arange(n), side="right") - 1
            child_start[base:base + n] = level_start[lev + 1] + child[first_ball]
            child_count[base:base + n] = child[last_ball] - child[first_ball] + 1
    reach = np.linalg.norm(center, axis=1) + radius
    return SphereTree(center, radius, reach, child_start, child_count, level_start)


def cached_head_model(head: trimesh.Trimesh, pitch_mm: float = 0.5, *, zones: RiskZones = RiskZones(),
                      max_level: int = 4, target_spheres: int = 24, cache_dir: str | None = None,
                      name: str = "the head") -> HeadModel:
    """``build_head_model``'s model, read from the on-disk cache (``ncfix.cache``) when the same
    head was modelled before with the same parameters, code and libraries (``name``: the head's
    file, for the notice of a build)."""
    key = cache.make_key(
        "head",
        np.asarray(head.vertices, dtype=np.float64), np.asarray(head.faces, dtype=np.int64), float(pitch_mm),
        {"tops_fraction": list(zones.tops_fraction), "levels": list(zones.levels), "max_level": int(max_level),
         "target_spheres": int(target_spheres)},
        cache.fingerprint(*HEAD_SOURCES), {"numpy": cache.version("numpy")},
    )

    def from_arrays(a: dict[str, np.ndarray]) -> HeadModel | None:
        n = len(a["radii_mm"])
        if a["centers_mm"].shape != (n, 3) or any(len(a[k]) != n for k in ("zone", "interior", "group")):
            return None
        return HeadModel(
            centers_mm=a["centers_mm"], radii_mm=a["radii_mm"], zone=a["zone"], interior=a["interior"],
            group=a["group"], group_centers_mm=a["group_centers_mm"], group_radii_mm=a["group_radii_mm"],
            pitch_mm=float(a["pitch_mm"]), zone_tops_mm=a["zone_tops_mm"], marked_cells=int(a["marked_cells"]),
        )

    model, _ = cache.cached("head", key, _MODEL_ARRAYS,
                            lambda: build_head_model(head, pitch_mm, zones=zones, max_level=max_level,
                                                     target_spheres=target_spheres),
                            lambda model: cache.fields(model, _MODEL_ARRAYS), from_arrays, cache_dir,
                            what=f"the ball model of {name} (first run for this head)")
    return model


def cached_sphere_tree(centers_mm: np.ndarray, radii_mm: np.ndarray, leaf_cell_mm: float,
                       cache_dir: str | None = None) -> SphereTree:
    """``build_sphere_tree``'s tree, read from the on-disk cache (``ncfix.cache``) when it was
    built before from the same balls, leaf cell, code and libraries."""
    key = cache.make_key(
        "tree",
        np.asarray(centers_mm, dtype=np.float64), np.asarray(radii_mm, dtype=np.float64), float(leaf_cell_mm),
        cache.fingerprint(*HEAD_SOURCES), {"numpy": cache.version("numpy")},
    )

    def from_arrays(a: dict[str, np.ndarray]) -> SphereTree | None:
        n = len(a["radius_mm"])
        if a["center_mm"].shape != (n, 3) or a["level_start"][-1] != n:
            return None
        return SphereTree(**{name: a[name] for name in _TREE_ARRAYS})

    tree, _ = cache.cached("tree", key, _TREE_ARRAYS, lambda: build_sphere_tree(centers_mm, radii_mm, leaf_cell_mm),
                           lambda tree: cache.fields(tree, _TREE_ARRAYS), from_arrays, cache_dir)
    return tree
