"""Rotations between the head frame (tip at the origin, axis +Z) and the workpiece frame."""

from __future__ import annotations

import numpy as np


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation taking direction ``a`` to direction ``b`` (Rodrigues).

    a, b : (3,) or (n, 3) float64, any length > 0
    returns : (3, 3) or (n, 3, 3) float64 with ``R @ a_hat == b_hat``. For opposite directions
    the rotation is a half turn about an axis perpendicular to ``a`` (the one nearest +X).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    single = a.ndim == 1 and b.ndim == 1
    a2, b2 = np.broadcast_arrays(np.atleast_2d(a), np.atleast_2d(b))
    a2 = a2 / np.linalg.norm(a2, axis=1, keepdims=True)
    b2 = b2 / np.linalg.norm(b2, axis=1, keepdims=True)
    v = np.cross(a2, b2)
    c = np.einsum("ij,ij->i", a2, b2)
    k = np.zeros((len(a2), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    opposite = c < -1.0 + 1e-12
    scale = np.where(opposite, 0.0, 1.0 / np.where(opposite, 1.0, 1.0 + c))
    r = np.eye(3) + k + (k @ k) * scale[:, None, None]
    if opposite.any():
        # Half turn about the unit axis u perpendicular to a: R = 2 u u^T - I.
        ax = a2[opposite]
        helper = np.where(np.abs(ax[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u = np.cross(ax, helper)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r[opposite] = 2.0 * u[:, :, None] * u[:, None, :] - np.eye(3)
    return r[0] if single else r


def rotation_from_z(n: np.ndarray) -> np.ndarray:
    """The CONTRACT's head rotation for a tool vector: minimal rotation with ``R @ (0,0,1) = N``.

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
    return c[:, None, None] * np.eye(3) + s[:, None, None] * k + (1.0 - c)[:, None, None] * np.outer(u, u)


def minimal_rotation(n: np.ndarray) -> np.ndarray:
    """The smallest rotations taking +Z to each unit vector: n (m, 3) → (m, 3, 3) (CONTRACT spin rule)."""
    n = np.asarray(n, dtype=np.float64).reshape(-1, 3)
    return rotation_between(np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape), n).reshape(-1, 3, 3)


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the rows of ``v`` (..., 3); zero rows stay zero."""
    v = np.asarray(v, dtype=np.float64)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between rows of unit vectors ``a`` and ``b`` (..., 3), robust near 0."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.degrees(np.arctan2(cross, dot))
