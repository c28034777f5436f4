"""The conservative, windowed collision checker: head balls vs part distance grids, beads vs head.

Parts (torch, batched, float64 arithmetic on float32 grid values): the head model's covering
balls are tested in a hierarchy (bounding spheres of ~44 groups, then ~4 mm sub-groups, then
the balls) against each part's ``DistanceGrid``. A pose is *free* of a part when every ball is
farther than radius + margin + clearance by the grid's lower bound; otherwise it is *undecided*
and the exact test decides (coal BVH head vs part mesh, plus containment, plus the exact distance
when a margin is asked for). A grid never says "collides" on its own, so it adds no false alarms,
only work; and since the covering balls hold the head and the grid bound is a lower bound, a
pose the grid calls free is free.

Deposit (numpy/scipy): bead centres near the head's group spheres are found in the bead store's
k-d trees; beads laid after the pose (sequence number) and beads wholly below the tip allowance
plane are dropped exactly; the rest are tested against a distance grid of the head above the tip
allowance (head frame); beads the grid cannot clear go to the exact signed distance to the
clipped head (the reference's own function). Same one-sided logic: the grid only clears.

Both take a per-pose margin: the sweeps between motion blocks (``ncfix.collision.path``) check
sampled poses with the distance the head may move between samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import trimesh

from ncfix.collision.deposit import BeadStore
from ncfix.collision.grid import DistanceGrid, build_distance_grid
from ncfix.collision.head import HeadModel
from ncfix.reference import ExactReference

# Sub-group edge (mm) between the head model's ~44 groups and its balls: small enough that a
# sub-group near a body holds a few dozen balls, large enough that there are only ~2,000.
SUBGROUP_EDGE_MM = 4.0
# A pose with more failing sub-groups than this goes straight to the exact test: expanding them
# to balls would cost more than the exact test and could only end in "undecided" anyway.
MAX_FAILING_SUBGROUPS = 48
# Poses per torch batch (memory: ~44 groups x 3 float64 per pose, sub-groups on demand).
POSE_BATCH = 2048
# Poses per deposit batch: beads laid before a batch are committed to the k-d trees, so the
# sequence filter only applies to the batch's own beads.
DEPOSIT_BATCH = 256


def resolve_device(name: str) -> str:
    """'auto' → 'cuda' when torch sees a GPU, else 'cpu'."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


@dataclass
class HeadHierarchy:
    """The head model's balls sorted by (group, sub-group), with CSR ranges, as torch tensors."""

    g_centers: object
    g_radii: object
    g_sub_start: object
    g_sub_count: object
    s_centers: object
    s_radii: object
    s_ball_start: object
    s_ball_count: object
    b_centers: object
    b_radii: object
    n_balls: int
    n_subgroups: int
    n_groups: int


def build_hierarchy(model: HeadModel, device: str) -> HeadHierarchy:
    import torch

    c, r, g = model.centers_mm, model.radii_mm, model.group
    lo = c.min(axis=0)
    cell = np.floor((c - lo) / SUBGROUP_EDGE_MM).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (g * dims[0] + cell[:, 0]) * dims[1] * dims[2] + cell[:, 1] * dims[2] + cell[:, 2]
    order = np.lexsort((key, g))
    c, r, g, key = c[order], r[order], g[order], key[order]
    ukey, b_start, b_count = np.unique(key, return_index=True, return_counts=True)
    sub_of = np.repeat(np.arange(len(ukey)), b_count)
    s_group = g[b_start]
    s_lo = np.full((len(ukey), 3), np.inf)
    s_hi = np.full((len(ukey), 3), -np.inf)
    np.minimum.at(s_lo, sub_of, c - r[:, None])
    np.maximum.at(s_hi, sub_of, c + r[:, None])
    s_c = 0.5 * (s_lo + s_hi)
    s_r = np.zeros(len(ukey))
    np.maximum.at(s_r, sub_of, np.linalg.norm(c - s_c[sub_of], axis=1) + r)
    n_groups = len(model.group_radii_mm)
    g_count = np.bincount(s_group, minlength=n_groups)
    g_start = np.cumsum(g_count) - g_count
    t = lambda a, dt=torch.float64: torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=device)  # noqa: E731
    return HeadHierarchy(
        g_centers=t(model.group_centers_mm), g_radii=t(model.group_radii_mm),
        g_sub_start=t(g_start, torch.int64), g_sub_count=t(g_count, torch.int64),
        s_centers=t(s_c), s_radii=t(s_r), s_ball_start=t(b_start, torch.int64), s_ball_count=t(b_count, torch.int64),
        b_centers=t(c), b_radii=t(r), n_balls=len(r), n_subgroups=len(ukey), n_groups=n_groups,
    )


def _expand(pair_pose, pair_item, start, count):
    """CSR expansion: each (pose, item) pair → (pose, child) for the item's children."""
    import torch

    n = count[pair_item]
    pose = torch.repeat_interleave(pair_pose, n)
    first = torch.repeat_interleave(start[pair_item], n)
    offset = torch.arange(int(n.sum()), device=pose.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
    return pose, first + offset


@dataclass
class Part:
    name: str  # "part:mold.stl"
    grid: DistanceGrid
    mesh: trimesh.Trimesh


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
    exact_bead_tests: int = 0
    seconds: dict = field(default_factory=dict)


class Checker:
    """Array-level checker: head pose batches against parts and beads (see module doc).

    head : closed trimesh in the head frame (tip at the origin, axis +Z)
    parts : (name, mesh, closed) in workpiece mm; names as the report shows them
    """

    def __init__(self, head: trimesh.Trimesh, model: HeadModel, parts: list[tuple[str, trimesh.Trimesh, bool]], *,
                 pitch_mm: float, clearance_mm: float = 0.0, bead_radius_mm: float = 1.0,
                 tip_allowance_mm: float = 1.0, device: str = "cpu", part_bounds_mm: np.ndarray | None = None):
        import torch

        self.device = resolve_device(device)
        self.torch = torch
        self.pitch_mm = float(pitch_mm)
        self.clearance_mm = float(clearance_mm)
        self.bead_radius_mm = float(bead_radius_mm)
        self.tip_allowance_mm = float(tip_allowance_mm)
        self.model = model
        self.head = head
        self.rho_mm = float(np.linalg.norm(head.vertices, axis=1).max())
        self.hier = build_hierarchy(model, self.device)
        self.parts = [Part(name, build_distance_grid(mesh, pitch_mm, closed=closed, name=name, bounds_mm=part_bounds_mm),
                           mesh) for name, mesh, closed in parts]
        self.reference = ExactReference(head, {p.name: p.mesh for p in self.parts},
                                        tip_allowance_mm=self.tip_allowance_mm)
        self.stats = CheckerStats()
        if self.bead_radius_mm > 0:
            clipped = self.reference._bead_head
            # The head above the allowance, in the head frame, at the pitch.
            self.head_grid = build_distance_grid(clipped, self.pitch_mm, closed=True, name="head")
            # Only balls reaching above the allowance plane can meet a bead (same groups).
            above = model.centers_mm[:, 2] + model.radii_mm > self.tip_allowance_mm
            dep_model = replace(model, centers_mm=model.centers_mm[above], radii_mm=model.radii_mm[above],
                                zone=model.zone[above], interior=model.interior[above], group=model.group[above])
            h = build_hierarchy(dep_model, "cpu")
            self.dep_hier = {k: (v.numpy() if hasattr(v, "numpy") else v) for k, v in vars(h).items()}

    # -- parts -------------------------------------------------------------------------------
    def _part_undecided(self, grid: DistanceGrid, C, R, margin) -> np.ndarray:
        """Indices of poses (torch batch) the grid cannot clear of this part."""
        torch = self.torch
        h = self.hier
        n = C.shape[0]
        pos = C[:, None, :] + torch.einsum("nij,gj->ngi", R, h.g_centers)
        lb = grid.lower_bound(pos.reshape(-1, 3)).reshape(n, -1)
        fail = lb <= h.g_radii[None, :] + margin[:, None] + self.clearance_mm
        pose, grp = fail.nonzero(as_tuple=True)
        if len(pose) == 0:
            return np.zeros(0, dtype=np.int64)
        pose, sub = _expand(pose, grp, h.g_sub_start, h.g_sub_count)
        pos = C[pose] + torch.einsum("nij,nj->ni", R[pose], h.s_centers[sub])
        fail = grid.lower_bound(pos) <= h.s_radii[sub] + margin[pose] + self.clearance_mm
        pose, sub = pose[fail], sub[fail]
        if len(pose) == 0:
            return np.zeros(0, dtype=np.int64)
        per_pose = torch.bincount(pose, minlength=n)
        crowded = per_pose > MAX_FAILING_SUBGROUPS
        keep = ~crowded[pose]
        pose, sub = pose[keep], sub[keep]
        undecided = crowded.clone()
        if len(pose):
            pose, ball = _expand(pose, sub, h.s_ball_start, h.s_ball_count)
            pos = C[pose] + torch.einsum("nij,nj->ni", R[pose], h.b_centers[ball])
            fail = grid.lower_bound(pos) <= h.b_radii[ball] + margin[pose] + self.clearance_mm
            undecided[pose[fail]] = True
        return undecided.nonzero().reshape(-1).cpu().numpy()

    def _exact_part(self, k: int, c: np.ndarray, r: np.ndarray, margin: float) -> bool:
        import coal

        ref = self.reference
        part = ref.parts[k]
        tf = coal.Transform3s(r, c)
        cres = coal.CollisionResult()
        if coal.collide(ref._head_bvh, tf, part.bvh, coal.Transform3s(), ref._creq, cres) > 0:
            return True
        if ref._nested(part, c, r):
            return True
        need = margin + self.clearance_mm
        if need > 0:
            dres = coal.DistanceResult()
            d = coal.distance(ref._head_bvh, tf, part.bvh, coal.Transform3s(), ref._dreq, dres)
            return bool(d < need)
        return False

    def check_parts(self, C: np.ndarray, R: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """(n, n_parts) bool: which parts each pose (tip C (n, 3), rotation R (n, 3, 3)) hits."""
        torch = self.torch
        n = len(C)
        out = np.zeros((n, len(self.parts)), dtype=bool)
        for a in range(0, n, POSE_BATCH):
            b = min(n, a + POSE_BATCH)
            Ct = torch.as_tensor(C[a:b], dtype=torch.float64, device=self.device)
            Rt = torch.as_tensor(R[a:b], dtype=torch.float64, device=self.device)
            Mt = torch.as_tensor(margin[a:b], dtype=torch.float64, device=self.device)
            for k, part in enumerate(self.parts):
                for i in self._part_undecided(part.grid, Ct, Rt, Mt):
                    j = a + int(i)
                    self.stats.part_undecided += 1
                    out[j, k] = self._exact_part(k, C[j], R[j], float(margin[j]))
        return out

    def free_poses(self, C: np.ndarray, R: np.ndarray, seq: np.ndarray, store: BeadStore,
                   pending: np.ndarray, pending_seq: np.ndarray) -> np.ndarray:
        """(n,) bool: poses (no sweep) free of every part and of the beads they see: for testing
        candidate orientations in batch. ``pending`` beads are seen by poses with seq >= theirs."""
        zero = np.zeros(len(C))
        free = ~self.check_parts(C, R, zero).any(axis=1)
        if self.bead_radius_mm > 0 and free.any() and (store.count or len(pending)):
            idx = np.nonzero(free)[0]
            hit, _ = self.check_deposit(C[idx], R[idx], zero[idx], seq[idx], store, pending, pending_seq)
            free[idx[hit]] = False
        return free

    # -- deposit -----------------------------------------------------------------------------
    def _deposit_pairs(self, C, R, extra, near):
        """(pose, sub-group) pairs whose sphere may come within its radius + extra of a bead (numpy).

        Beads are then fetched per sub-group (not per ball): fewer queries and duplicates, and the
        head grid prunes the few extra candidates exactly as well."""
        h = self.dep_hier
        n = len(C)
        pos = C[:, None, :] + np.einsum("nij,gj->ngi", R, h["g_centers"])
        reach = h["g_radii"][None, :] + extra[:, None]
        fail = near(pos.reshape(-1, 3), reach.reshape(-1)).reshape(n, -1)
        pose, item = np.nonzero(fail)
        for level in ("s",):
            if len(pose) == 0:
                break
            parent = "g" if level == "s" else "s"
            start = h[f"{parent}_sub_start"] if level == "s" else h["s_ball_start"]
            count = h[f"{parent}_sub_count"] if level == "s" else h["s_ball_count"]
            cnt = count[item]
            pose = np.repeat(pose, cnt)
            item = np.repeat(start[item], cnt) + (np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt))
            centers = h["s_centers"] if level == "s" else h["b_centers"]
            radii = h["s_radii"] if level == "s" else h["b_radii"]
            pos = C[pose] + np.einsum("nij,nj->ni", R[pose], centers[item])
            ok = near(pos, radii[item] + extra[pose])
            pose, item = pose[ok], item[ok]
        return pose, item

    def check_deposit(self, C: np.ndarray, R: np.ndarray, margin: np.ndarray, seq: np.ndarray,
                      store: BeadStore, pending: np.ndarray, pending_seq: np.ndarray,
                      step_mm: np.ndarray | None = None, turn_rad: np.ndarray | None = None,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Deposit hits (n,) bool and exact clearances (n,) (+inf where the grid cleared).

        store : beads laid before every pose of the batch; pending (m, 3) / pending_seq (m,):
        beads of the current window, seen by poses with seq >= their pending_seq.
        margin : (n,) sweep margin, |ΔC| + ρ·θ; with step_mm = |ΔC| (n,) and turn_rad = θ (n,)
        the margin near a bead is tightened to |ΔC| + θ·(reach of the head points that can
        touch it): a head point at distance r from the tip moves at most |ΔC| + r·θ.
        """
        from scipy.spatial import cKDTree

        from ncfix.collision.deposit import query_pairs

        n = len(C)
        hit = np.zeros(n, dtype=bool)
        clearance = np.full(n, np.inf)
        if self.bead_radius_mm <= 0 or n == 0 or (store.count == 0 and len(pending) == 0):
            return hit, clearance
        bead_r = self.bead_radius_mm
        ta = self.tip_allowance_mm
        extra = bead_r + margin + self.clearance_mm
        pend_tree = cKDTree(pending) if len(pending) else None

        def near(points, reach):
            upper = float(reach.max()) if len(reach) else 0.0
            d = store.nearest(points, upper) if store.count else np.full(len(points), np.inf)
            if pend_tree is not None:
                d = np.minimum(d, pend_tree.query(points, k=1, distance_upper_bound=upper)[0])
            return d <= reach

        pose, sub = self._deposit_pairs(C, R, extra, near)
        if len(pose) == 0:
            return hit, clearance
        h = self.dep_hier
        centers = C[pose] + np.einsum("nij,nj->ni", R[pose], h["s_centers"][sub])
        radii = h["s_radii"][sub] + extra[pose]
        poses, ids, pts, fresh = [], [], [], []
        if store.count:
            q, gid, p = store.within(centers, radii)
            poses.append(pose[q]), ids.append(gid), pts.append(p), fresh.append(np.zeros(len(q), dtype=bool))
        if pend_tree is not None:
            q, idx = query_pairs(pend_tree, centers, radii)
            seen = pending_seq[idx] <= seq[pose[q]]
            poses.append(pose[q][seen]), ids.append(idx[seen] + store.count), pts.append(pending[idx[seen]])
            fresh.append(pending_seq[idx[seen]] == seq[pose[q][seen]])
        pose = np.concatenate(poses)
        if len(pose) == 0:
            return hit, clearance
        gid, pts, fresh = np.concatenate(ids), np.concatenate(pts), np.concatenate(fresh)
        # One test per (pose, bead): a bead is found through several balls.
        _, first = np.unique(pose * (store.count + len(pending) + 1) + gid, return_index=True)
        pose, pts, fresh = pose[first], pts[first], fresh[first]
        local = np.einsum("nji,nj->ni", R[pose], pts - C[pose])  # R^T (b - C): head frame
        # A bead laid in this very step exists only once the head reaches this sample: the poses
        # swept since the previous sample never see it, so it gets no sweep margin.
        swept = margin[pose]
        if step_mm is not None and turn_rad is not None:
            reach = np.linalg.norm(local, axis=1) + bead_r + self.clearance_mm + swept
            swept = np.minimum(swept, step_mm[pose] + turn_rad[pose] * reach)
        need = bead_r + self.clearance_mm + np.where(fresh, 0.0, swept)
        # Beads wholly below the allowance plane cannot reach the checked head (exact).
        keep = local[:, 2] + need > ta
        # The head grid clears the rest where it can (a lower bound on the distance to the head).
        lb = np.full(len(pose), -np.inf)
        lb[keep] = self.head_grid.lower_bound_np(local[keep])
        keep &= lb <= need
        pose, local, need, lb = pose[keep], local[keep], need[keep], lb[keep]
        if len(pose) == 0:
            return hit, clearance
        self.stats.deposit_undecided += len(np.unique(pose))
        # Exact test in rounds, most suspect beads first; a pose stops at its first hit.
        order = np.lexsort((lb, pose))
        pose, local, need = pose[order], local[order], need[order]
        starts = np.searchsorted(pose, pose, side="left")
        rank = np.arange(len(pose)) - starts
        lo, width = 0, 1
        while True:
            sel = (rank >= lo) & (rank < lo + width) & ~hit[pose]
            if not sel.any():
                if lo > rank.max():
                    break
                lo, width = lo + width, width * 2
                continue
            idx = np.nonzero(sel)[0]
            self.stats.exact_bead_tests += len(idx)
            signed = self.reference.signed_distance_to_clipped_head(local[idx]) - bead_r
            np.minimum.at(clearance, pose[idx], signed)
            hit[pose[idx][signed < need[idx] - bead_r]] = True
            lo, width = lo + width, width * 2
        return hit, clearance


def rotation_angle(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation between (n, 3, 3) pairs; robust near 0 (from the Frobenius norm)."""
    fro = np.linalg.norm((ra - rb).reshape(len(ra), -1), axis=1)
    return 2.0 * np.arcsin(np.clip(fro / (2.0 * np.sqrt(2.0)), 0.0, 1.0))
