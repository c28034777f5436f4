"""The bead a program's extrusion implies: E per mm of path, a layer height from the path, and
the bead width they give with ``--filament-diameter`` (docs/deposit.md, "The bead the program
implies"). Reported next to the stated bead; it never changes the deposit model.

- **E per mm**: over the printing moves (depositing G1 moves with an extrusion word whose E grows,
  not plunges or lifts: ``deposit.axial_moves``), E / the programmed length of the move (P's
  straight path), each move weighted by its length: the median and the 95th percentile of the
  deposited path.
- **Layer height**: at the end point P of every QUERY_EVERY-th printing move of the program (the
  same moves whatever the batches they come in: a check and a fix measure alike), the drop along the tool axis N to the nearest path laid before below it: the smallest
  (P − Q)·N over the deposited path points Q (printing moves sampled at most SPACING_MM apart) in
  the cone of half-angle CONE_DEG about −N below P, within SEARCH_MM. A point of the tip's own
  surface (its own line, its neighbours in the layer) lies across the axis, outside the cone; the
  layer below lies under the tip, inside it. A point with nothing below (the first layer, a
  bridge) gives no height. The median of the heights found.
- **Width**: the filament's section π d² / 4 times E per mm is the bead's section (volume
  conservation); at the layer height h the bead is the contract's flat bead, a rectangle with
  round ends, so its section is h·(w − h) + π h² / 4 and w = A / h + (1 − π / 4)·h; a section
  below π h² / 4 is a round strand, w = √(4 A / π).

Memory is bounded: the path points kept for the height are the newest POINTS_MAX (k-d trees in
levels merged like a binary counter, the oldest dropped), the E per mm and heights are counted in
fixed histograms.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ncfix.collision.deposit import axial_moves, bead_samples

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

SPACING_MM = 0.25
CONE_DEG = 60.0
SEARCH_MM = 4.0
# Drops closer than this (mm) are the tip's own surface (its own sample, rounding).
OWN_SURFACE_MM = 1e-3
QUERY_EVERY = 4
POINTS_MAX = 1 << 18
LEVEL_MAX = POINTS_MAX // 4
# E per mm histogram: log-spaced, 0.1% wide bins from 1e-6 to 1e3 (program E units per mm).
RATE_BINS = np.geomspace(1e-6, 1e3, int(math.log(1e9) / math.log(1.001)) + 1)
# Layer heights: 1 µm bins up to SEARCH_MM.
HEIGHT_BINS = np.linspace(0.0, SEARCH_MM, 4001)
# The implied and stated beads "disagree" (a warning) when the implied width of the 95th percentile
# of E per mm is above the stated width by more than NARROWER (the stated bead may not hold the
# material), or the stated width is more than WIDER times it (a bead that wide flags contacts the
# program does not make); the same for the layer height against the stated height.
NARROWER = 1.1
WIDER = 2.0


def implied_width(section_mm2: np.ndarray | float, height_mm: float) -> np.ndarray:
    """The width (mm) of a flat bead of ``section_mm2`` at ``height_mm`` (module doc)."""
    a = np.asarray(section_mm2, dtype=np.float64)
    h = float(height_mm)
    core = 0.25 * math.pi * h * h
    return np.where(a >= core, a / h + (1.0 - 0.25 * math.pi) * h, np.sqrt(a / (0.25 * math.pi)))


def _quantile(counts: np.ndarray, edges: np.ndarray, q: float) -> float | None:
    """The q-quantile of a histogram (the middle of the bin it falls in), None when empty."""
    total = float(counts.sum())
    if total <= 0.0:
        return None
    k = min(int(np.searchsorted(np.cumsum(counts), q * total)), len(counts) - 1)
    return float(0.5 * (edges[k] + edges[k + 1]))


class ImpliedBead:
    """Collects E per mm and layer heights from the programmed moves (``observe``) and reports the
    bead they imply (``summary``, ``warnings``)."""

    def __init__(self, filament_diameter_mm: float, stated_width_mm: float, stated_height_mm: float) -> None:
        self.filament_mm = float(filament_diameter_mm)
        self.stated_width_mm = float(stated_width_mm)
        self.stated_height_mm = float(stated_height_mm)
        self.rates = np.zeros(len(RATE_BINS) - 1)
        self.heights = np.zeros(len(HEIGHT_BINS) - 1, dtype=np.int64)
        self.printing_mm = 0.0
        self.moves = 0  # printing moves seen
        self.below_range = 0.0  # path length of moves whose E per mm is outside RATE_BINS
        self._levels: list[tuple[np.ndarray, cKDTree]] = []
        self._open: list[np.ndarray] = []
        self._open_n = 0
        self._cos = math.cos(math.radians(CONE_DEG))

    # -- collecting ------------------------------------------------------------------------------
    def observe(self, Ps: np.ndarray, Pe: np.ndarray, Ns: np.ndarray, Ne: np.ndarray, e_delta: np.ndarray,
                printing: np.ndarray) -> None:
        """Moves from P ``Ps`` to ``Pe`` (n, 3), tool axis ``Ns``/``Ne`` at their ends, their
        extrusion ``e_delta`` (n,); ``printing`` (n,) bool: depositing straight moves with a known
        start and an extrusion word. Plunges and lifts among them are left out here."""
        length = np.linalg.norm(Pe - Ps, axis=1)
        sel = printing & (length > 0) & np.isfinite(e_delta) & (e_delta > 0)
        sel &= np.isfinite(Ps).all(axis=1) & np.isfinite(Pe).all(axis=1)
        if sel.any():
            sel[sel] = ~axial_moves(Ps[sel], Pe[sel], Ns[sel], Ne[sel])
        if not sel.any():
            return
        ps, pe, ne, lng = Ps[sel], Pe[sel], Ne[sel], length[sel]
        rate = e_delta[sel] / lng
        inside = (rate >= RATE_BINS[0]) & (rate < RATE_BINS[-1])
        self.rates += np.histogram(rate[inside], RATE_BINS, weights=lng[inside])[0]
        self.below_range += float(lng[~inside].sum())
        self.printing_mm += float(lng.sum())
        counts, t = bead_samples(ps, pe, SPACING_MM, length_mm=lng)
        own = np.repeat(np.arange(len(ps)), counts)
        laid = ps[own] + t[:, None] * (pe - ps)[own]
        pick = np.nonzero((self.moves + np.arange(len(pe))) % QUERY_EVERY == 0)[0]
        self.moves += len(pe)
        if len(pick):
            self._heights(pe[pick], ne[pick], laid, own, pick)
        self._add(laid)

    def _add(self, pts: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        self._open.append(pts)
        self._open_n += len(pts)
        if self._open_n < LEVEL_MAX:
            return
        pts = np.concatenate(self._open)
        self._open, self._open_n = [], 0
        while self._levels and len(self._levels[-1][0]) <= len(pts) and len(self._levels[-1][0]) + len(pts) <= LEVEL_MAX:
            pts = np.concatenate([self._levels.pop()[0], pts])
        self._levels.append((pts, cKDTree(pts)))
        while sum(len(level[0]) for level in self._levels) > POINTS_MAX:
            self._levels.pop(0)

    def _heights(self, P: np.ndarray, N: np.ndarray, laid: np.ndarray, laid_by: np.ndarray, move: np.ndarray) -> None:
        """The drop from each tip P (q, 3) along N (q, 3) to the highest path point laid before it
        in its cone: the kept points, and this batch's points ``laid`` (m, 3) by moves ``laid_by``
        (m,) before the tip's own ``move`` (q,)."""
        from scipy.spatial import cKDTree

        groups = [(pts, tree, None) for pts, tree in self._levels]
        if self._open:
            pts = np.concatenate(self._open)
            groups.append((pts, cKDTree(pts), None))
        groups.append((laid, cKDTree(laid), laid_by))
        best = np.full(len(P), np.inf)
        for pts, tree, by in groups:
            found = tree.query_ball_point(P, SEARCH_MM)
            for i, idx in enumerate(found):
                idx = np.asarray(idx, dtype=np.int64)
                if by is not None:
                    idx = idx[by[idx] < move[i]]
                if not len(idx):
                    continue
                d = P[i] - pts[idx]
                drop = d @ N[i]
                dist = np.linalg.norm(d, axis=1)
                ok = (drop > OWN_SURFACE_MM) & (drop >= self._cos * dist)
                if ok.any():
                    best[i] = min(best[i], float(drop[ok].min()))
        found = best[np.isfinite(best)]
        self.heights += np.histogram(found, HEIGHT_BINS)[0]

    # -- reporting -------------------------------------------------------------------------------
    def summary(self) -> dict:
        """The report's ``summary.implied_bead`` (docs/contract.md)."""
        area = 0.25 * math.pi * self.filament_mm ** 2
        median = _quantile(self.rates, RATE_BINS, 0.5)
        p95 = _quantile(self.rates, RATE_BINS, 0.95)
        height = _quantile(self.heights, HEIGHT_BINS, 0.5)
        out = {"filament_diameter_mm": self.filament_mm, "printing_path_mm": round(self.printing_mm, 3),
               "e_per_mm": None if median is None else {"median": round(median, 5), "p95": round(p95, 5)},
               "layer_height_mm": None if height is None else round(height, 4),
               "layer_height_samples": int(self.heights.sum()),
               "width_mm": None,
               "stated": {"width_mm": self.stated_width_mm, "height_mm": self.stated_height_mm}}
        if median is not None and height is not None:
            w = implied_width(np.array([median, p95]) * area, height)
            out["width_mm"] = {"median": round(float(w[0]), 4), "p95": round(float(w[1]), 4)}
        return out

    def line(self) -> str:
        """The summary line on standard error."""
        s = self.summary()
        stated = f"stated {self.stated_width_mm:g} × {self.stated_height_mm:g} mm"
        if s["e_per_mm"] is None:
            return f"implied bead: no printing move with growing E to derive it from ({stated})"
        rate = f"E per mm {s['e_per_mm']['median']:.4g} (95%: {s['e_per_mm']['p95']:.4g})"
        if s["width_mm"] is None:
            return f"implied bead: {rate}, no layer height found in the path (no path below the tips); {stated}"
        w = s["width_mm"]
        return (f"implied bead ({self.filament_mm:g} mm filament): {rate} at a layer height of "
                f"{s['layer_height_mm']:.3f} mm from the path is {w['median']:.3f} (95%: {w['p95']:.3f}) mm wide; "
                f"{stated}")

    def warnings(self) -> list[str]:
        """Where the stated bead and the implied one disagree a lot (module constants)."""
        s = self.summary()
        out = []
        if s["width_mm"] is not None:
            w = s["width_mm"]["p95"]
            if w > NARROWER * self.stated_width_mm:
                out.append(f"the program's E per mm implies beads up to {w:.3f} mm wide (95th percentile, "
                           f"{self.filament_mm:g} mm filament), wider than the stated {self.stated_width_mm:g} mm: "
                           "the deposit model may miss material; check --bead-width and --filament-diameter")
            elif self.stated_width_mm > WIDER * w:
                out.append(f"the stated bead width {self.stated_width_mm:g} mm is more than {WIDER:g} times what "
                           f"the program's E per mm implies ({w:.3f} mm, 95th percentile, {self.filament_mm:g} mm "
                           "filament): expect contacts the print does not make; check --bead-width and "
                           "--filament-diameter")
        h = s["layer_height_mm"]
        if h is not None:
            if h > NARROWER * self.stated_height_mm:
                out.append(f"the path's layer height is {h:.3f} mm (median), more than the stated bead height "
                           f"{self.stated_height_mm:g} mm: check --bead-height")
            elif self.stated_height_mm > WIDER * h:
                out.append(f"the stated bead height {self.stated_height_mm:g} mm is more than {WIDER:g} times the "
                           f"path's layer height {h:.3f} mm (median): check --bead-height")
        return out
