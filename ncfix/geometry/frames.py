"""Rotations between the head frame (tip at the origin, axis +Z) and the workpiece frame."""

from __future__ import annotations

import numpy as np


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation taking direction ``a`` to direction ``b`` (Rodrigues).

    a, b : (3,) or (n, 3) float64, any length > 0
    returns : (3, 3) or (n, 3, 3) float64 with ``R @ a_hat == b_hat``. For opposite directions
    the rotation is a half turn about an axis perpendicular to ``a`` (the one nearest +X).
    One compiled loop: the correction's walks ask for one rotation at a time, tens of thousands
    of times, where numpy's per-call overhead was 40 µs.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    single = a.ndim == 1 and b.ndim == 1
    a2, b2 = np.broadcast_arrays(np.atleast_2d(a), np.atleast_2d(b))
    r = np.empty((len(a2), 3, 3))
    from ncfix.geometry import rodrigues  # compiled: numba loads with the first rotation, not with the profiles

    rodrigues.rotations(np.ascontiguousarray(a2), np.ascontiguousarray(b2), r)
    return r[0] if single else r


def rotation_from_z(n: np.ndarray) -> np.ndarray:
    """The head rotation of docs/contract.md for a tool vector: minimal rotation with ``R @ (0,0,1) = N``.

    n : (3,) or (n, 3) float64, tool vectors (normalised here)
    returns : (3, 3) or (n, 3, 3) float64
    """
    return rotation_between(np.array([0.0, 0.0, 1.0]), n)


def axis_rotation(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Right-handed rotation matrices about a fixed unit ``axis``.

    axis : (3,) float64 unit vector; angle_rad : (n,) float64 → (n, 3, 3) float64.
    """
    u = np.asarray(axis, dtype=np.float64)
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    out = np.empty((len(c), 3, 3))
    from ncfix.geometry import rodrigues  # compiled (see rotation_between)

    # c·I + s·K + (1 − c)·uuᵀ per angle, in one compiled pass: the poses ask for it thousands of
    # times a run, where the broadcast expression's temporaries cost more than the sums.
    rodrigues.about_axis(np.ascontiguousarray(c), np.ascontiguousarray(s), np.eye(3), k, np.outer(u, u), out)
    return out


def minimal_rotation(n: np.ndarray) -> np.ndarray:
    """The smallest rotations taking +Z to each unit vector: n (m, 3) → (m, 3, 3) (the spin rule of docs/contract.md)."""
    n = np.ascontiguousarray(n, dtype=np.float64).reshape(-1, 3)
    z = np.zeros_like(n)
    z[:, 2] = 1.0
    r = np.empty((len(n), 3, 3))
    from ncfix.geometry import rodrigues

    rodrigues.rotations(z, n, r)
    return r


def half_turn_direction(a: np.ndarray) -> np.ndarray:
    """Where a 180° turn of the tool vector away from ``a`` passes at its middle: +X made
    perpendicular to ``a``, or +Y where ``a`` is within ~26° of ±X.

    A vector and its opposite have no unique shortest turn between them (every great circle
    through both is one); ncfix takes this one, the plane ``rotation_between`` turns in for
    opposite vectors and ``correct.blend.slerp`` for antipodal pairs, so it is repeatable.
    a : (n, 3) float64 unit vectors → (n, 3) float64 unit vectors perpendicular to them.
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    helper = np.where((np.abs(a[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = helper - np.sum(helper * a, axis=1)[:, None] * a
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the rows of ``v`` (..., 3); zero rows stay zero, NaN rows NaN."""
    v = np.asarray(v, dtype=np.float64)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    out = np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)
    return np.where(np.isnan(norm), np.nan, out)


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between rows of unit vectors ``a`` and ``b`` (..., 3), robust near 0.

    Written out by component: the same sums in the same order as ``np.cross``, ``np.linalg.norm``
    and ``np.sum`` (the same bits) at a third of their call overhead on a few rows."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    cross = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    dot = a0 * b0 + a1 * b1 + a2 * b2
    return np.degrees(np.arctan2(cross, dot))


def tilt_azimuth_frames(n: np.ndarray) -> np.ndarray:
    """(m, 3, 3) frames Rz(φ)·Ry(θ) of unit vectors n (m, 3) by tilt θ from +Z and azimuth φ about
    Z; at the pole the azimuth of the vector before is kept (it is undefined there)."""
    tilt = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(n[:, 1], n[:, 0])
    pole = np.hypot(n[:, 0], n[:, 1]) < 1e-9
    for i in range(len(n)):
        if pole[i]:
            azimuth[i] = azimuth[i - 1] if i else 0.0
    ct, st, cp, sp = np.cos(tilt), np.sin(tilt), np.cos(azimuth), np.sin(azimuth)
    out = np.zeros((len(n), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = cp * ct, -sp, cp * st
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = sp * ct, cp, sp * st
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = -st, 0.0, ct
    return out


def turn_rotations(n: np.ndarray) -> np.ndarray:
    """(m - 1, 3, 3) the rotations F_l · F_{l-1}^T taking each unit vector's tilt/azimuth frame
    (``tilt_azimuth_frames``) to the next one's: how a sequence of vectors n (m, 3) turns."""
    frames = tilt_azimuth_frames(n)
    return np.einsum("nij,nkj->nik", frames[1:], frames[:-1])
