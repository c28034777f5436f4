"""The conservative, windowed collision checker: a sphere tree of the head against lower-bound
distance fields of the parts and of the beads (compiled loops on the CPU, torch batches on CUDA);
exact tests only where they cannot decide.

The bounds never say "collides": a pose is called free only when it is free, and colliding only
when an exact test says so. Design: docs/collision.md (the pieces, undecided poses, sweeps).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import ctypes.util
import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field

import coal
import numpy as np

from ncfix.collision import descent
from ncfix.collision.deposit import BeadCells, BeadField, BeadShape, BeadStore
from ncfix.collision.depth import DepthProbe
from ncfix.collision.descent import HostTree
from ncfix.collision.exact import ExactParts, cached_clip_head
from ncfix.collision.exact_beads import BeadBuckets, candidates_free, first_bead_hits
from ncfix.collision.grid import DistanceGrid, Reach, cached_distance_grid
from ncfix.collision.head import HeadModel, SphereTree, cached_sphere_tree
from ncfix.collision.near import cached_near_surface
from ncfix.collision.nested import Nested, mesh_bodies
from ncfix.collision.proximity import cached_head_proximity
from ncfix.collision.split import thread_count
from ncfix.errors import ConfigError
from ncfix.geometry.meshdata import Mesh, as_mesh

if TYPE_CHECKING:
    import trimesh

# Octree cell (mm) of the tree's lowest inner level: a few balls each.
LEAF_CELL_MM = 1.0
# The tree is entered at this level (its nodes are ~25 mm spheres): a few more lookups per pose
# than from the root, but two fewer rounds of torch calls per batch.
ENTRY_LEVEL = 2
# A pose with more failing nodes than this on one level is undecided at once (exact test):
# expanding them would cost more than the exact test and could only end in "undecided" anyway.
MAX_PAIRS_PER_POSE = 32
# The same for a group of samples: a group that does not clear quickly is split instead.
GROUP_MAX_PAIRS = 8
# Poses per torch batch.
POSE_BATCH = 8192
# Poses per call of the exact bead test (progress is reported between calls; each call sets up
# work arrays as long as the bucketed beads).
EXACT_POSE_BATCH = 2048
# Sample groups (mm of travel, |ΔC| + ρ·θ summed) certified together, longest first.
GROUP_LEVELS_MM = (24.0, 6.0, 1.5)
# A group level that clears under 5% of its groups is skipped for this many calls.
IDLE_CALLS = 8
# Cells (mm) grouping beads in the exact deposit test of candidates (a cell cleared clears its beads).
BEAD_CELL_MM = 4.0
# deposit_free's beads gathered per tip: kept for this many tips (then dropped), with this much more
# reach than asked for so that a tip asked again (its centre moved by rounding) finds them.
TIP_CACHE_MAX = 64
TIP_CACHE_SLACK_MM = 0.01
# A sample that hits only with its sweep margin is tested again as finer samples, this deep
# (path.Refiner: REFINE_PARTS samples a level): false alarms of the margin go, hits stay. The exact
# test of a sample includes its sweep margin, so a head passing 0.3 mm from a body with 0.5 mm
# between samples would be a false alarm; each finer sample's smaller margin covers its own
# stretch, so the sample collides only when a finer one does (still conservative). What remains
# are false alarms within pitch / 16 of contact.
REFINE_LEVELS = 2
# Sequence number of beads every pose sees (the store's).
ALWAYS_SEEN = np.iinfo(np.int64).min
# Level of the tree whose failing nodes fetch the candidate beads of an undecided pose (the
# sample head's clipped tree: radius about 7 mm there, 3.5 mm a level down). Any level gives the
# same decisions (a failing node's query ball holds its failing children's); on the bathtubs
# this one is the fastest: fewer nodes to reach and to visit outweigh more beads a ball.
CANDIDATE_LEVEL = 4
# The bucketed region of the exact bead test is the box of the failing nodes' query balls widened
# by this (mm): the bead kernel places each ball in its own arithmetic (rounding: ~1e-13 mm).
BOX_SLACK_MM = 1e-9


@contextmanager
def one_thread():
    """Run torch on one CPU thread inside the block: the lookups are memory-bound (a second thread
    gains little), and on a busy machine torch's thread pool waits made them 5-10x slower."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


# Files whose presence means a GPU driver is loaded (Linux): NVIDIA's, WSL's GPU bridge, and AMD's
# (ROCm builds of torch call their GPUs "cuda" too).
GPU_DRIVER_PATHS = ("/proc/driver/nvidia", "/dev/nvidiactl", "/dev/dxg", "/dev/kfd")


def gpu_driver_present() -> bool:
    """Whether torch could see a GPU here, decided without importing torch (about 2.5 s): on
    Linux a loaded GPU driver shows in ``GPU_DRIVER_PATHS``; macOS has no CUDA; elsewhere
    (Windows) NVIDIA's driver library must be on the search path."""
    if sys.platform.startswith("linux"):
        return any(os.path.exists(path) for path in GPU_DRIVER_PATHS)
    if sys.platform == "darwin":
        return False
    return ctypes.util.find_library("nvcuda") is not None


def resolve_device(name: str) -> str:
    """'auto' → 'cuda' when torch sees a GPU, else 'cpu'. torch is imported only when a GPU
    driver is present (``gpu_driver_present``) and torch is installed: the CPU path never needs it.
    'cuda' without torch or without a device is a ConfigError (before any work)."""
    if name.startswith("cuda"):
        try:
            import torch
        except ImportError:
            raise ConfigError("--device cuda needs torch, which is not installed", where="--device",
                              fix="install torch with CUDA support, or use --device cpu") from None
        if not torch.cuda.is_available():
            why = (f"this torch ({torch.__version__}) is built for the CPU only" if torch.version.cuda is None
                   else "torch sees no CUDA device on this machine")
            raise ConfigError(why, where="--device cuda",
                              fix="use --device cpu or auto, or install a CUDA build of torch") from None
        return name
    if name != "auto":
        return name
    if not gpu_driver_present():
        return "cpu"
    try:
        import torch
    except ImportError:
        return "cpu"
    return "cuda" if torch.cuda.is_available() else "cpu"


class TreeTensors:
    """A SphereTree in numpy (``host``: the compiled CPU descent) and on a torch device (center,
    radius, reach, child_start, child_count, children (n, 8) int64 padded with -1; made on first
    use, so that the CPU path never imports torch)."""

    def __init__(self, host: HostTree, device: str):
        self.host = host
        self.level_start = host.level_start
        self.device = device
        self._tensors: dict | None = None

    def _on_device(self) -> dict:
        if self._tensors is None:
            import torch

            h = self.host

            def t(a, dt=torch.float64):
                return torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=self.device)

            self._tensors = {"center": t(h.center), "radius": t(h.radius), "reach": t(h.reach),
                             "child_start": t(h.child_start, torch.int64), "child_count": t(h.child_count, torch.int64),
                             "children": t(h.children, torch.int64)}
        return self._tensors

    center = property(lambda self: self._on_device()["center"])
    radius = property(lambda self: self._on_device()["radius"])
    reach = property(lambda self: self._on_device()["reach"])
    child_start = property(lambda self: self._on_device()["child_start"])
    child_count = property(lambda self: self._on_device()["child_count"])
    children = property(lambda self: self._on_device()["children"])


def tree_tensors(tree: SphereTree, device: str) -> TreeTensors:
    width = max(1, int(tree.child_count.max()))
    children = np.full((len(tree.radius_mm), width), -1, dtype=np.int64)
    slot = np.arange(width)
    has = slot[None, :] < tree.child_count[:, None]
    children[has] = (tree.child_start[:, None] + slot[None, :])[has]
    return TreeTensors(HostTree(tree.center_mm, tree.radius_mm, tree.reach_mm, tree.child_start, tree.child_count,
                                children, tree.level_start), device)


@dataclass
class Part:
    name: str  # "part:mold.stl"
    grid: DistanceGrid
    mesh: Mesh


@dataclass
class PoseResult:
    """Per pose: which parts it hits (n, n_parts) bool, whether it hits deposit (n,) bool,
    and the deposit clearance found by the exact test (n,) float64 (+inf when not tested)."""

    part_hit: np.ndarray
    deposit_hit: np.ndarray
    deposit_clearance: np.ndarray


@dataclass
class CheckerStats:
    poses: int = 0
    part_undecided: int = 0
    deposit_undecided: int = 0
    exact_bead_poses: int = 0
    exact_bead_tests: int = 0
    retired_bead_hits: int = 0  # poses called colliding near retired beads (no exact test there)
    seconds: dict = field(default_factory=dict)


class Checker:
    """Array-level checker: head pose batches against parts and beads.

    Bodies: each part is a ``DistanceGrid`` and the beads are the store's rolling ``BeadField``,
    each a lower bound on the distance to its material anywhere in space. The head is a
    ``SphereTree`` over its covering balls (octree levels, 1 mm cells at the bottom); the deposit
    uses the tree of the balls that reach above the tip allowance.

    Test of a pose (tip C, rotation R) with a sweep margin (lin, ang): breadth first, a node with
    centre c and radius r is *clear* when ``lb(C + R c) > r + lin + ang·reach + clearance`` (reach =
    |c| + r: no point of the node is farther from the tip, so none moves more than lin + ang·reach
    when the tip moves lin and the head turns ang); a clear node clears its subtree. A pose is
    *free* when every path from the root ends in a clear node, else *undecided* (a ball fails, or
    more than MAX_PAIRS_PER_POSE nodes fail on one level). An undecided pose goes to the exact
    test, which decides: triangle pairs (``proximity``) and a body of the part or of the head
    wholly inside the other (``nested``) for parts; the exact signed distance from the bead
    centres to the clipped head (``exact_beads``) for beads.

    head : closed mesh in the head frame (tip at the origin, axis +Z): a ``Mesh`` or a trimesh
    parts : (name, mesh, closed) in workpiece mm; names as the report shows them
    part_bounds_mm, part_reach : the box the part grids are cropped to, and where the program
        can look them up (their exact band is made there: ``grid.build_distance_grid``)

    The grids, sphere trees and the clipped head's NearSurface come from the on-disk cache
    (``ncfix.cache``) when they were built before.
    """

    def __init__(self, head: Mesh | trimesh.Trimesh, model: HeadModel, parts: list[tuple[str, Mesh | trimesh.Trimesh, bool]], *,
                 pitch_mm: float, clearance_mm: float = 0.0, bead_radius_mm: float = 1.0,
                 tip_allowance_mm: float = 1.0, device: str = "cpu", part_bounds_mm: np.ndarray | None = None,
                 part_reach: Reach | None = None, bead_drop_mm: float = 0.0, bead_shape: BeadShape | None = None) -> None:
        self.device = resolve_device(device)
        # The sphere-tree descent: compiled loops on the CPU (``descent``), torch batches elsewhere.
        self.compiled = self.device == "cpu"
        thread_count()  # a bad $NCFIX_THREADS is an error here, before any work
        self.pitch_mm = float(pitch_mm)
        self.clearance_mm = float(clearance_mm)
        self.bead_radius_mm = float(bead_radius_mm)  # the sphere each bead is held as (deposit.BeadShape)
        self.bead_drop_mm = float(bead_drop_mm)  # bead centres lie this far below P along the tool axis
        # The stated bead (deposit.BeadShape; None: round, of the bead radius): sizes the thinner
        # strand of a looping tip (PathChecker).
        self.bead_shape = bead_shape if bead_shape is not None else \
            BeadShape(2.0 * self.bead_radius_mm, 2.0 * self.bead_radius_mm, self.bead_drop_mm)
        self.tip_allowance_mm = float(tip_allowance_mm)
        self.model = model
        head = as_mesh(head)
        parts = [(name, as_mesh(mesh), closed) for name, mesh, closed in parts]
        self.head = head
        self.rho_mm = float(np.linalg.norm(head.vertices, axis=1).max())
        self.tree = tree_tensors(cached_sphere_tree(model.centers_mm, model.radii_mm, LEAF_CELL_MM), self.device)
        self.parts = [Part(name, cached_distance_grid(mesh, pitch_mm, closed=closed, name=name, bounds_mm=part_bounds_mm,
                                                reach=part_reach),
                           mesh) for name, mesh, closed in parts]
        # A point where a part's grid bounds the distance above zero is outside it: the depth of a
        # colliding pose tests the others only.
        self.exact = ExactParts(head, {p.name: p.mesh for p in self.parts},
                                open_parts={name for name, _, closed in parts if not closed},
                                maybe_inside={p.name: _maybe_inside(p.grid) for p in self.parts})
        # The head above the tip allowance: all that beads are tested against.
        self.clipped_head = cached_clip_head(head, self.tip_allowance_mm)
        # One body inside the other (``nested``): every connected body of the head and of each part.
        head_bodies = mesh_bodies(head)
        self._nested = [Nested(head_bodies, mesh_bodies(mesh), closed) for _, mesh, closed in parts]
        self._margin_request = coal.CollisionRequest()  # ``_exact_part``'s, its margin set per test
        self._proximity = [cached_head_proximity(head, p.mesh, p.grid, name=p.name.split(":", 1)[-1]) for p in self.parts]
        self.stats = CheckerStats()
        self._idle_levels: dict = {}
        self._store_beads = None  # (store state, its kept beads concatenated)
        self._tip_cache = None  # (store state, pending, pending_seq, {tip key: (centre, radius, cells)})
        if self.bead_radius_mm > 0:
            clipped = self.clipped_head
            # The head above the allowance, in the head frame, at the pitch (filters candidate beads).
            self.head_grid = cached_distance_grid(clipped, self.pitch_mm, closed=True, name="head")
            # Only balls reaching above the allowance plane can meet a bead.
            above = model.centers_mm[:, 2] + model.radii_mm > self.tip_allowance_mm
            self.dep_tree = tree_tensors(cached_sphere_tree(model.centers_mm[above], model.radii_mm[above],
                                                            LEAF_CELL_MM), self.device)
            self._head_triangles_clipped = np.asarray(clipped.triangles, dtype=np.float64)
            # Exact bead tests: a bead's ball (radius + clearance + sweep margin, <= a pitch) against
            # the clipped head's triangles near it.
            self.near_head = cached_near_surface(self._head_triangles_clipped,
                                                 self.bead_radius_mm + self.clearance_mm + 1.5 * self.pitch_mm)

    def depth_probe(self):
        """The report's penetration estimates (``depth.DepthProbe``), made on first use."""
        if getattr(self, "_depth_probe", None) is None:
            self._depth_probe = DepthProbe(self.head, [p.grid for p in self.parts], max(2.0 * self.pitch_mm, 2.0))
        return self._depth_probe

    # -- the sphere-tree test ----------------------------------------------------------------
    @property
    def torch(self):
        """The torch module, imported on first use (the torch descent: CUDA, and the tests)."""
        import torch

        return torch

    def _tensor(self, a, dtype=None):
        return self.torch.as_tensor(np.ascontiguousarray(a), dtype=dtype or self.torch.float64, device=self.device)

    def _undecided(self, tree: TreeTensors, lower_bound, C, R, lin, ang, cap: int = MAX_PAIRS_PER_POSE) -> np.ndarray:
        """(n,) bool: poses (torch C (n, 3), R (n, 3, 3), margins lin, ang (n,)) the bound cannot clear."""
        torch = self.torch
        n = C.shape[0]
        dev = C.device
        entry = min(ENTRY_LEVEL, len(tree.level_start) - 2)
        first, last = int(tree.level_start[entry]), int(tree.level_start[entry + 1])
        width = last - first
        pose = torch.arange(n, device=dev).repeat_interleave(width)
        node = torch.arange(first, last, device=dev).repeat(n)
        undecided = torch.zeros(n, dtype=torch.bool, device=dev)
        extra = self.clearance_mm
        while pose.numel():
            pos = C[pose] + torch.bmm(R[pose], tree.center[node].unsqueeze(-1)).squeeze(-1)
            need = tree.radius[node] + lin[pose] + ang[pose] * tree.reach[node] + extra
            fail = lower_bound(pos) <= need
            pose, node = pose[fail], node[fail]
            child = tree.children[node]
            leaf = child[:, 0] < 0
            if bool(leaf.any()):
                undecided[pose[leaf]] = True
            keep = ~undecided[pose]
            pose, child = pose[keep], child[keep]
            if not pose.numel():
                break
            crowded = torch.bincount(pose, minlength=n) > cap
            if bool(crowded.any()):
                undecided |= crowded
                keep = ~crowded[pose]
                pose, child = pose[keep], child[keep]
            valid = child >= 0
            pose = pose.unsqueeze(1).expand_as(child)[valid]
            node = child[valid]
        return undecided.cpu().numpy()

    def _failing_nodes(self, tree: TreeTensors, lower_bound, C, R, lin, ang, level: int):
        """(pose, node) pairs (numpy) of the nodes at ``level`` whose sphere the bound cannot clear."""
        torch = self.torch
        n = C.shape[0]
        dev = C.device
        level = min(level, len(tree.level_start) - 2)
        pose = torch.arange(n, device=dev)
        node = torch.zeros(n, dtype=torch.int64, device=dev)
        for lev in range(level + 1):
            pos = C[pose] + torch.bmm(R[pose], tree.center[node].unsqueeze(-1)).squeeze(-1)
            need = tree.radius[node] + lin[pose] + ang[pose] * tree.reach[node] + self.clearance_mm
            fail = lower_bound(pos) <= need
            pose, node = pose[fail], node[fail]
            if lev < level:
                pose, node = _expand(pose, tree.child_start[node], tree.child_count[node])
        return pose.cpu().numpy(), node.cpu().numpy()

    def _undecided_batched(self, tree, lower_bound, C, R, lin, ang, cap: int = MAX_PAIRS_PER_POSE) -> np.ndarray:
        if self.compiled:
            return descent.undecided(tree.host, lower_bound, C, R, lin, ang, self.clearance_mm, ENTRY_LEVEL, cap)
        out = np.zeros(len(C), dtype=bool)
        with one_thread():
            for a in range(0, len(C), POSE_BATCH):
                b = min(len(C), a + POSE_BATCH)
                out[a:b] = self._undecided(tree, lower_bound, self._tensor(C[a:b]), self._tensor(R[a:b]),
                                           self._tensor(lin[a:b]), self._tensor(ang[a:b]), cap)
        return out

    def deposit_balls_near(self, lower_bound, C: np.ndarray, R: np.ndarray, reach_mm: np.ndarray) -> np.ndarray:
        """(n,) bool: poses (tips C (n, 3), rotations R (n, 3, 3)) at which the deposit tree's balls
        (the head above the tip allowance) are not cleared from a body by more than ``reach_mm``
        (n,) plus the clearance, the body given by its ``lower_bound`` (a bead field's): the
        conservative sphere-tree test, no exact test."""
        return self._undecided_batched(self.dep_tree, lower_bound, C, R, reach_mm, np.zeros(len(C)))

    def _grouped_undecided(self, tree, lower_bound, C, R, lin, ang, cum_lin, cum_ang) -> np.ndarray:
        """(n,) bool: samples not cleared, coarse to fine. cum_lin / cum_ang (n,): summed
        tip steps and turns from the first sample (|ΔC| and θ between consecutive samples).

        Any sample k of a group lies within (|cumL_k - cumL_m|, |cumA_k - cumA_m|) of the group's
        middle sample m (the summed steps and turns between them), so m tested with margins
        max_k(lin_k + |ΔcumL|) and max_k(ang_k + |ΔcumA|) clears every sample of the group with its
        own margin. Groups of GROUP_LEVELS_MM of travel are tried, longest first; only the samples
        no group could clear are tested one by one."""
        n = len(C)
        todo = np.arange(n)
        travel = cum_lin + self.rho_mm * cum_ang
        for level, length in enumerate(GROUP_LEVELS_MM):
            if len(todo) < 2:
                break
            # A level that cleared almost nothing last time for this tree is skipped for a while
            # (speed only: the finer levels and the samples decide anyway).
            skip_key = (id(tree), id(getattr(lower_bound, "__self__", lower_bound)), level)
            idle = self._idle_levels.get(skip_key, 0)
            if idle > 0:
                self._idle_levels[skip_key] = idle - 1
                continue
            key = np.floor(travel[todo] / length).astype(np.int64)
            start = np.concatenate([[0], np.nonzero(key[1:] != key[:-1])[0] + 1])
            size = np.diff(np.concatenate([start, [len(todo)]]))
            if (size >= 2).sum() == 0:
                continue
            gid = np.repeat(np.arange(len(start)), size)
            rep = todo[start + size // 2]
            member_rep = rep[gid]
            glin = np.maximum.reduceat(lin[todo] + np.abs(cum_lin[todo] - cum_lin[member_rep]), start)
            gang = np.maximum.reduceat(ang[todo] + np.abs(cum_ang[todo] - cum_ang[member_rep]), start)
            multi = np.nonzero(size >= 2)[0]
            undecided = self._undecided_batched(tree, lower_bound, C[rep[multi]], R[rep[multi]], glin[multi],
                                                gang[multi], GROUP_MAX_PAIRS)
            cleared = np.zeros(len(start), dtype=bool)
            cleared[multi[~undecided]] = True
            if (~undecided).sum() < 0.05 * len(multi):
                self._idle_levels[skip_key] = IDLE_CALLS
            todo = todo[~cleared[gid]]
        out = np.zeros(n, dtype=bool)
        if len(todo):
            out[todo] = self._undecided_batched(tree, lower_bound, C[todo], R[todo], lin[todo], ang[todo])
        return out

    # -- parts -------------------------------------------------------------------------------
    def _exact_part(self, k: int, c: np.ndarray, r: np.ndarray, margin: float) -> bool:
        """Whether the head at (c, r) comes within ``margin`` + the clearance of part k, exactly:
        some triangle pair within that distance, or a body of one inside the other (``nested``,
        each connected body of the head and of the part on its own). The triangle pairs go to the
        compiled test of ``proximity`` (about half the time of coal's) while the distance is
        within its cap, else to coal's mesh-mesh collision test with the distance as its security
        margin (the triangle pairs closer than it collide)."""
        exact = self.exact
        need = margin + self.clearance_mm
        near = self._proximity[k]
        if need <= near.cap_mm:
            return near.within(c, r, need) or self._nested[k](c, r)
        request = exact.collision_request
        if need > 0:
            request = self._margin_request
            request.security_margin = need
        if coal.collide(exact.head_bvh, coal.Transform3s(r, c), exact.parts[k].bvh, coal.Transform3s(), request,
                        coal.CollisionResult()) > 0:
            return True
        return self._nested[k](c, r)

    def sweep_parts(self, C: np.ndarray, R: np.ndarray, lin: np.ndarray, ang: np.ndarray,
                    cum_lin: np.ndarray | None = None, cum_ang: np.ndarray | None = None, *,
                    exact: bool = True, move_of: np.ndarray | None = None, refine=None, progress=None) -> np.ndarray:
        """(n, n_parts) bool: which parts each pose hits, with sweep margins lin (mm) and ang (rad)
        per pose (a head point at distance d from the tip is checked with lin + ang·d). With
        cum_lin / cum_ang (consecutive samples) groups are certified first. Without ``exact``
        an undecided pose counts as hitting (conservative). With ``move_of`` (n,) (ascending move
        of each sample) only the last hitting sample of each move is found: the exact tests go
        from a move's last sample backwards and stop at its first hit (earlier ones stay False).
        With ``refine`` (a ``path.Refiner`` of the samples) a sample that hits only with its sweep
        margin is tested again as finer samples (REFINE_LEVELS)."""
        n = len(C)
        out = np.zeros((n, len(self.parts)), dtype=bool)
        for k, part in enumerate(self.parts):
            if cum_lin is None:
                undecided = self._undecided_batched(self.tree, part.grid.lower_bound, C, R, lin, ang)
            else:
                undecided = self._grouped_undecided(self.tree, part.grid.lower_bound, C, R, lin, ang, cum_lin, cum_ang)
            idx = np.nonzero(undecided)[0]
            self.stats.part_undecided += len(idx)
            if not exact:
                out[idx, k] = True
                continue
            if move_of is not None:
                idx = idx[np.lexsort((-idx, move_of[idx]))]
            hit_move = -1
            for done, j in enumerate(idx):
                if progress is not None:
                    progress((k + (done + 1) / len(idx)) / len(self.parts))
                if move_of is not None and move_of[j] == hit_move:
                    continue
                margin = float(lin[j] + self.rho_mm * ang[j])
                out[j, k] = self._exact_part(k, C[j], R[j], margin)
                if out[j, k] and refine is not None and margin > 0 and not self._exact_part(k, C[j], R[j], 0.0):
                    out[j, k] = self._refined_part(k, refine, j, REFINE_LEVELS)
                if out[j, k] and move_of is not None:
                    hit_move = move_of[j]
        return out

    def _refined_part(self, k: int, refine, j: int, levels: int) -> bool:
        """Whether part k is hit by any finer sample of sample j (``levels`` more levels)."""
        C, R, lin, ang, _, sub = refine.split(np.array([j]))
        for i in range(len(C) - 1, -1, -1):
            margin = float(lin[i] + self.rho_mm * ang[i])
            hit = self._exact_part(k, C[i], R[i], margin)
            if hit and margin > 0 and levels > 1:
                hit = self._refined_part(k, sub, i, levels - 1)
            if hit:
                return True
        return False

    def check_parts(self, C: np.ndarray, R: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """(n, n_parts) bool: which parts each pose (tip C (n, 3), rotation R (n, 3, 3)) hits, every
        head point checked with ``margin`` (n,) mm."""
        C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        return self.sweep_parts(C, R, np.asarray(margin, dtype=np.float64).reshape(-1), np.zeros(len(C)))

    def free_poses(self, C: np.ndarray, R: np.ndarray, seq: np.ndarray, store: BeadStore,
                   pending: np.ndarray, pending_seq: np.ndarray) -> np.ndarray:
        """(n,) bool: poses (no sweep) *certainly* free of every part and of the beads: for testing
        candidate orientations in batch. Fast: no exact test; a pose the bounds cannot clear is
        not free (errs toward "collides"; near contact a free pose may be refused). Every pending
        bead counts for every pose (a superset of what each sees)."""
        C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        zero = np.zeros(len(C))
        free = ~self.sweep_parts(C, R, zero, zero, exact=False).any(axis=1)
        if self.bead_radius_mm > 0 and free.any() and (store.count or len(pending)):
            idx = np.nonzero(free)[0]
            bead_field = store.field(self.pitch_mm)
            with bead_field.overlay(pending):
                undecided = self._undecided_batched(self.dep_tree, bead_field.lower_bound, C[idx], R[idx],
                                                    zero[idx], zero[idx])
            free[idx[undecided]] = False
        return free

    def poses_free(self, C: np.ndarray, R: np.ndarray, seq: np.ndarray, store: BeadStore,
                   pending: np.ndarray, pending_seq: np.ndarray) -> np.ndarray:
        """(n,) bool: end poses (no sweep) free of every part and of the beads each sees (the store,
        and the pending beads with pending_seq <= its seq). The bounds decide first; an undecided
        pose goes to the exact test, so the answer is exact (up to the clearance)."""
        C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        zero = np.zeros(len(C))
        free = ~self.sweep_parts(C, R, zero, zero).any(axis=1)
        if self.bead_radius_mm > 0 and free.any() and (store.count or len(pending)):
            idx = np.nonzero(free)[0]
            free[idx] = self.deposit_free(C[idx], R[idx], np.asarray(seq)[idx], store, pending, pending_seq)
        return free

    def deposit_free(self, C: np.ndarray, R: np.ndarray, seq: np.ndarray, store: BeadStore,
                     pending: np.ndarray, pending_seq: np.ndarray) -> np.ndarray:
        """(n,) bool: end poses free of the beads each sees, exactly; made for many orientations
        about a few tips (candidate batches). Per tip, the beads within the clipped head's reach
        are gathered once and grouped in BEAD_CELL_MM cells; the head grid's lower bound on the
        distance to the clipped head clears whole cells, then single beads, and the beads it
        cannot clear go to the exact test (``NearSurface``), a pose stopping at its first hit."""
        C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        seq = np.asarray(seq, dtype=np.int64).reshape(-1)
        n = len(C)
        free = np.ones(n, dtype=bool)
        need = self.bead_radius_mm + self.clearance_mm
        reach = float(np.linalg.norm(self.clipped_head.vertices, axis=1).max()) + need
        ta = self.tip_allowance_mm
        if store.old is not None:  # retired beads: only their field decides (``_exact_deposit``)
            zero = np.zeros(n)
            free &= ~self._undecided_batched(self.dep_tree, store.old.lower_bound, C, R, zero, zero)
        # Poses of one level share their tip (tip pivot) or stay within h of it (point pivot).
        keys = np.round(C / 1e-3).astype(np.int64)
        for key in np.unique(np.column_stack([seq, keys])[free], axis=0):
            sel = np.flatnonzero((seq == key[0]) & (keys == key[1:]).all(axis=1) & free)
            centre = C[sel].mean(axis=0)
            radius = reach + float(np.linalg.norm(C[sel] - centre, axis=1).max())
            cells = self._tip_cells(store, pending, pending_seq, tuple(int(v) for v in key), centre, radius)
            if cells is None:
                continue
            ok, tested = candidates_free(C[sel], R[sel], cells, self.head_grid, self.near_head, need=need,
                                         allowance=ta, clearance=self.clearance_mm)
            self.stats.exact_bead_tests += tested
            free[sel] &= ok
        return free

    def _tip_cells(self, store: BeadStore, pending: np.ndarray, pending_seq: np.ndarray, key: tuple,
                   centre: np.ndarray, radius: float):
        """The beads a pose at ``key`` (seq, tip in µm) sees within ``radius`` of ``centre``, in cells
        (``deposit_free``): (beads, members, counts, starts, cell centres, cell radii), or None when
        there are none. The store's beads come in the cells of its levels (``BeadStore.cells``,
        built once per level: whole cells that may reach the ball, so a superset of its beads,
        which every later filter, a bound, and the last test, exact, answer the same); the pending
        ones it sees are grouped here. A correction's walk asks at one tip many times: the
        gathering is kept per tip for one store state and one set of pending beads, and reused
        while the ball asked for lies inside the ball gathered."""
        state = (id(store), store.count, store.retired)
        memo = self._tip_cache
        if memo is None or memo[0] != state or memo[1] is not pending or memo[2] is not pending_seq:
            memo = self._tip_cache = (state, pending, pending_seq, {})
        tips = memo[3]
        got = tips.get(key)
        if got is not None and float(np.linalg.norm(centre - got[0])) + radius <= got[1]:
            return got[2]
        radius = radius + TIP_CACHE_SLACK_MM
        groups = [level.gather(centre, radius, radii=True) for level in
                  (store.cells(BEAD_CELL_MM) if store.count else [])]
        if len(pending):
            seen = pending[pending_seq <= key[0]]
            groups.append(BeadCells(seen[np.linalg.norm(seen - centre, axis=1) <= radius], BEAD_CELL_MM).take(radii=True))
        groups = [g for g in groups if len(g[0])]
        cells = None
        if groups:
            B = np.concatenate([g[0] for g in groups])
            counts = np.concatenate([g[1] for g in groups])
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            # each bead's own radius (the stated one where none was given: the pending beads')
            r = self.bead_radius_mm
            own = np.concatenate([np.full(len(g[0]), r) if g[4] is None else g[4] for g in groups])
            cells = (B, np.arange(len(B)), counts, starts, np.concatenate([g[2] for g in groups]),
                     np.concatenate([g[3] for g in groups]), own)
        if len(tips) >= TIP_CACHE_MAX:
            tips.clear()
        tips[key] = (centre.copy(), radius, cells)
        return cells

    # -- deposit -----------------------------------------------------------------------------
    def check_deposit(self, C: np.ndarray, R: np.ndarray, margin: np.ndarray, seq: np.ndarray,
                      store: BeadStore, pending: np.ndarray, pending_seq: np.ndarray,
                      step_mm: np.ndarray | None = None, turn_rad: np.ndarray | None = None,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Deposit hits (n,) bool and exact clearances (n,) (+inf where the field cleared).

        store : beads laid before every pose of the batch; pending (m, 3) / pending_seq (m,):
        beads of the current window, seen by poses with seq >= their pending_seq.
        margin : (n,) sweep margin, |ΔC| + ρ·θ; with step_mm = |ΔC| (n,) and turn_rad = θ (n,)
        the margin of a head point at distance d from the tip is |ΔC| + θ·d.
        """
        C = np.asarray(C, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        n = len(C)
        if step_mm is None or turn_rad is None:
            step_mm, turn_rad = np.asarray(margin, dtype=np.float64), np.zeros(n)
        return self.sweep_deposit(C, R, step_mm, turn_rad, None, None, seq, store, pending, pending_seq)

    def sweep_deposit(self, C, R, lin, ang, cum_lin, cum_ang, seq, store: BeadStore, pending, pending_seq, *,
                      stamped: bool = False, move_of: np.ndarray | None = None,
                      refine=None, clearances: bool = True, progress=None,
                      pending_r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Deposit hits (n,) and exact clearances (n,) with sweep margins (lin, ang) per pose and,
        given cum_lin / cum_ang, groups certified first. ``stamped``: the pending beads are in the
        store's field already (else they are overlaid for the call). ``move_of``: as in
        ``sweep_parts`` (the last undecided sample of each move first, the rest of a move only
        when that one is free); ``refine``: as in ``sweep_parts``. Without ``clearances`` the
        hits are the same and the kept beads' clearances not computed (-inf): such a hit with a
        sweep margin is then tested again without it before refining (with them, a hit whose own
        clearance is below the clearance is known to collide without that test). ``progress``: as in
        ``sweep_parts``. ``pending_r``: the radius each pending bead is held as in the exact test
        (None: the bead radius).

        A group of samples sees every bead of the window (a superset of what each of its poses
        sees: conservative); the exact test keeps the exact sequence (a pose sees the beads laid up
        to its own sample; the beads laid at its own sample get no sweep margin)."""
        n = len(C)
        hit = np.zeros(n, dtype=bool)
        clearance = np.full(n, np.inf)
        if self.bead_radius_mm <= 0 or n == 0 or (store.count == 0 and len(pending) == 0):
            return hit, clearance
        bead_field = store.field(self.pitch_mm)
        with bead_field.overlay(np.zeros((0, 3)) if stamped else pending):
            if cum_lin is None:
                undecided = self._undecided_batched(self.dep_tree, bead_field.lower_bound, C, R, lin, ang)
            else:
                undecided = self._grouped_undecided(self.dep_tree, bead_field.lower_bound, C, R, lin, ang,
                                                    cum_lin, cum_ang)
            idx = np.nonzero(undecided)[0]
            self.stats.deposit_undecided += len(idx)
            passes = [idx]
            if move_of is not None and len(idx):
                last = np.ones(len(idx), dtype=bool)
                last[:-1] = move_of[idx[1:]] != move_of[idx[:-1]]
                passes = [idx[last], idx[~last]]
            for k, sel in enumerate(passes):
                if k and move_of is not None:
                    hit_moves = np.unique(move_of[hit])
                    sel = sel[~np.isin(move_of[sel], hit_moves)]
                if len(sel):
                    tick = None if progress is None else (
                        lambda f, k=k: progress((k + f) / len(passes)))
                    hit[sel], clearance[sel] = self._exact_deposit(C[sel], R[sel], lin[sel], ang[sel], seq[sel],
                                                                   store, pending, pending_seq, bead_field, clearances,
                                                                   progress=tick, pending_r=pending_r)
                    # A pose whose own clearance is below the clearance collides whatever the sweep does
                    # (-inf: not computed, ``clearances`` False).
                    cl = clearance[sel]
                    doubt = hit[sel] & (lin[sel] + ang[sel] > 0) & ((cl >= self.clearance_mm) | (cl == -np.inf))
                    again = sel[doubt] if refine is not None else sel[:0]
                    if len(again):  # ... and so does one that hits without its sweep margin
                        zero = np.zeros(len(again))
                        own, _ = self._exact_deposit(C[again], R[again], zero, zero, seq[again], store, pending,
                                                     pending_seq, bead_field, clearances=False, pending_r=pending_r)
                        again = again[~own]
                    if len(again):
                        hit[again] = self._refined_deposit(refine, again, seq, store, pending, pending_seq,
                                                           bead_field, REFINE_LEVELS, pending_r)
                        clearance[again[~hit[again]]] = np.inf
        return hit, clearance

    def _refined_deposit(self, refine, idx, seq, store, pending, pending_seq, bead_field, levels: int,
                         pending_r=None):
        """Deposit hits of samples idx from their finer samples (``levels`` deep); a finer sample
        sees the beads its sample sees (a superset of its own: conservative)."""
        C, R, lin, ang, parent, sub = refine.split(idx)
        sseq = np.asarray(seq)[idx][parent]
        h, _ = self._exact_deposit(C, R, lin, ang, sseq, store, pending, pending_seq, bead_field, clearances=False,
                                   pending_r=pending_r)
        again = np.nonzero(h & (lin + ang > 0))[0]
        if levels > 1 and len(again):
            h[again] = self._refined_deposit(sub, again, sseq, store, pending, pending_seq, bead_field, levels - 1,
                                             pending_r)
        hit = np.zeros(len(idx), dtype=bool)
        np.logical_or.at(hit, parent, h)
        return hit

    def _exact_deposit(self, C, R, lin, ang, seq, store: BeadStore, pending, pending_seq, bead_field: BeadField,
                       clearances: bool = True, progress=None, pending_r=None):
        """The exact deposit test of undecided poses (``_exact_kept``). Beads the store retired
        (BeadStore: only a field of them is left) cannot be tested exactly: a pose that their
        field cannot clear counts as a hit, with clearance 0 (errs toward "collides")."""
        n = len(C)
        hit = np.zeros(n, dtype=bool)
        clearance = np.full(n, np.inf)
        if store.old is not None:
            hit = self._undecided_batched(self.dep_tree, store.old.lower_bound, C, R, lin, ang)
            self.stats.retired_bead_hits += int(hit.sum())
            clearance[hit] = 0.0
        rest = np.nonzero(~hit)[0]
        if len(rest):
            hit[rest], clearance[rest] = self._exact_kept(C[rest], R[rest], lin[rest], ang[rest], seq[rest], store,
                                                          pending, pending_seq, bead_field, clearances, pending_r,
                                                          progress)
        return hit, clearance

    def _exact_kept(self, C, R, lin, ang, seq, store: BeadStore, pending, pending_seq, bead_field: BeadField,
                    clearances: bool = True, pending_r=None, progress=None):
        """The exact test against the kept beads (``exact_beads``): candidate beads near the failing
        nodes (``CANDIDATE_LEVEL``), the sequence filter, the allowance plane, the head grid, then the exact test;
        the clearance of each hit pose is that of its deepest bead (unless not ``clearances``).
        The beads are bucketed once for all the poses, which are tested in batches."""
        n = len(C)
        hit = np.zeros(n, dtype=bool)
        clearance = np.full(n, np.inf)
        pad = self.bead_radius_mm
        if self.compiled:
            pose, node, box = descent.failing_nodes(self.dep_tree.host, bead_field.lower_bound, C, R, lin, ang,
                                                    self.clearance_mm, CANDIDATE_LEVEL, pad)
        else:
            pose, node = [], []
            for a in range(0, n, POSE_BATCH):
                b = min(n, a + POSE_BATCH)
                with one_thread():
                    p, q = self._failing_nodes(self.dep_tree, bead_field.lower_bound, self._tensor(C[a:b]),
                                               self._tensor(R[a:b]), self._tensor(lin[a:b]),
                                               self._tensor(ang[a:b]), CANDIDATE_LEVEL)
                pose.append(p + a)
                node.append(q)
            pose, node = np.concatenate(pose), np.concatenate(node)
            box = _balls_box(self.dep_tree.host, C, R, lin, ang, pose, node, pad + self.clearance_mm)
        if len(pose) == 0:
            return hit, clearance
        order = np.argsort(pose, kind="stable")
        pose, node = pose[order], node[order]
        host = self.dep_tree.host
        node_c, radii, reach = host.center[node], host.radius[node], host.reach[node]
        beads, bseq, brad = self._bead_arrays(store, pending, pending_seq, pending_r)
        # Only the beads in the region the failing nodes' query balls cover are bucketed (with a
        # slack: the bead kernel places the balls in arithmetic of its own).
        buckets = BeadBuckets(beads, bseq, box[0] - BOX_SLACK_MM, box[1] + BOX_SLACK_MM, brad)
        bounds = np.searchsorted(pose, np.arange(0, n + EXACT_POSE_BATCH, EXACT_POSE_BATCH).clip(max=n))
        for a, (first, end) in zip(range(0, n, EXACT_POSE_BATCH), zip(bounds[:-1], bounds[1:])):
            b = min(n, a + EXACT_POSE_BATCH)
            h, depth, candidates, tested = first_bead_hits(
                C[a:b], R[a:b], lin[a:b], ang[a:b], seq[a:b], pose[first:end] - a, node_c[first:end], radii[first:end],
                reach[first:end], buckets, self.head_grid, self.near_head, bead_r=self.bead_radius_mm,
                clearance=self.clearance_mm, allowance=self.tip_allowance_mm, rho=self.rho_mm, deepest=clearances)
            hit[a:b] = h
            clearance[a:b][h] = depth[h] if clearances else -np.inf
            self.stats.exact_bead_poses += int((candidates > 0).sum())
            self.stats.exact_bead_tests += tested
            if progress is not None:
                progress(b / n)
        return hit, clearance

    def _bead_arrays(self, store: BeadStore, pending: np.ndarray, pending_seq: np.ndarray,
                     pending_r: np.ndarray | None = None):
        """Every exact bead a pose may see (the store's kept beads, then the pending ones), the
        sequence number from which each is seen (the store's: always) and the radius each is held
        as (``BeadStore.add``; pending_r None: the bead radius)."""
        key = (id(store), store.count, store.retired)
        if self._store_beads is None or self._store_beads[0] != key:
            kept, radii = store.exact() if store.count else (np.zeros((0, 3)), None)
            self._store_beads = (key, kept, radii)
        _, kept, radii = self._store_beads
        r = self.bead_radius_mm
        if len(pending) == 0:
            return kept, np.full(len(kept), ALWAYS_SEEN, dtype=np.int64), (r if radii is None else radii)
        if radii is None and pending_r is None:
            brad = r
        else:
            brad = np.concatenate([np.full(len(kept), r) if radii is None else radii,
                                   np.full(len(pending), r) if pending_r is None else
                                   np.minimum(np.asarray(pending_r, dtype=np.float64), r)])
        return (np.concatenate([kept, pending]),
                np.concatenate([np.full(len(kept), ALWAYS_SEEN, dtype=np.int64), np.asarray(pending_seq, np.int64)]),
                brad)


def _maybe_inside(grid: DistanceGrid):
    """points (n, 3) -> (n,) bool: False where the grid's lower bound on the distance to its body
    is above zero (the point is outside the body)."""
    return lambda points: ~(grid.lower_bound_np(points) > 0.0)


def _balls_box(host, C, R, lin, ang, pose, node, pad: float) -> np.ndarray:
    """(2, 3): the box of the balls of (pose, node) pairs, centre C + R c, radius
    r + lin + ang·reach + pad (``descent.failing_nodes``'s box, in numpy)."""
    if len(pose) == 0:
        return descent.empty_box()
    centers = C[pose] + np.einsum("nij,nj->ni", R[pose], host.center[node])
    ball = (host.radius[node] + lin[pose] + ang[pose] * host.reach[node] + pad)[:, None]
    return np.array([(centers - ball).min(axis=0), (centers + ball).max(axis=0)])


def _expand(pose, start, count):
    """CSR expansion: each (pose, node) pair → (pose, child) for the node's ``count`` children from ``start``."""
    import torch

    pose = torch.repeat_interleave(pose, count)
    first = torch.repeat_interleave(start, count)
    total = first.numel()
    offset = torch.arange(total, device=pose.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    return pose, first + offset


def rotation_angle(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation between (n, 3, 3) pairs; robust near 0 (from the Frobenius norm)."""
    fro = np.linalg.norm((ra - rb).reshape(len(ra), -1), axis=1)
    return 2.0 * np.arcsin(np.clip(fro / (2.0 * np.sqrt(2.0)), 0.0, 1.0))
