"""Exact point-to-triangle distances and winding numbers, vectorised with numpy."""

from __future__ import annotations

import numpy as np


def closest_points_on_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Closest point of each triangle to its paired point (Ericson, Real-Time Collision Detection 5.1.5).

    points : (n, 3) float64
    triangles : (n, 3, 3) float64, triangle i pairs with point i
    returns : (n, 3) float64
    """
    p = np.asarray(points, dtype=np.float64)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_face = vb / denom
        w_face = vc / denom
        result = a + ab * v_face[:, None] + ac * w_face[:, None]

        # Edge regions, then vertex regions; later assignments win, vertex regions are exclusive.
        on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        result = np.where(on_bc[:, None], b + (c - b) * w_bc[:, None], result)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        w_ac = d2 / (d2 - d6)
        result = np.where(on_ac[:, None], a + ac * w_ac[:, None], result)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        v_ab = d1 / (d1 - d3)
        result = np.where(on_ab[:, None], a + ab * v_ab[:, None], result)
    result = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, result)
    result = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, result)
    result = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, result)
    # A degenerate (zero-area) triangle can leave NaN in the face formula: fall back to its vertices.
    bad = ~np.isfinite(result).all(axis=1)
    if bad.any():
        cand = triangles[bad]
        k = np.argmin(((cand - p[bad][:, None, :]) ** 2).sum(axis=2), axis=1)
        result[bad] = cand[np.arange(len(k)), k]
    return result


def point_mesh_distance(
    points: np.ndarray, triangles: np.ndarray, *, chunk_pairs: int = 2_000_000
) -> np.ndarray:
    """Unsigned distance from each point to the nearest of all triangles (brute force, chunked).

    points : (n, 3) float64
    triangles : (m, 3, 3) float64
    returns : (n,) float64, mm
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    m = len(triangles)
    out = np.full(len(points), np.inf)
    if m == 0:
        return out
    step = max(1, chunk_pairs // m)
    for start in range(0, len(points), step):
        p = points[start : start + step]
        pp = np.repeat(p, m, axis=0)
        tt = np.tile(triangles, (len(p), 1, 1))
        q = closest_points_on_triangles(pp, tt)
        d2 = ((q - pp) ** 2).sum(axis=1).reshape(len(p), m)
        out[start : start + step] = np.sqrt(d2.min(axis=1))
    return out


def winding_numbers(
    points: np.ndarray, triangles: np.ndarray, *, chunk_pairs: int = 2_000_000
) -> np.ndarray:
    """Generalised winding number of each point with respect to a triangle soup.

    About 1 inside and 0 outside a closed, outward-oriented mesh, whatever its quality
    (van Oosterom and Strackee solid angles). Brute force: use it for modest sizes.

    points : (n, 3) float64
    triangles : (m, 3, 3) float64
    returns : (n,) float64
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    m = len(triangles)
    out = np.zeros(len(points))
    if m == 0:
        return out
    step = max(1, chunk_pairs // m)
    for start in range(0, len(points), step):
        p = points[start : start + step]
        a = triangles[None, :, 0, :] - p[:, None, :]
        b = triangles[None, :, 1, :] - p[:, None, :]
        c = triangles[None, :, 2, :] - p[:, None, :]
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("ijk,ijk->ij", a, b) * lc
            + np.einsum("ijk,ijk->ij", b, c) * la
            + np.einsum("ijk,ijk->ij", c, a) * lb
        )
        out[start : start + step] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out
