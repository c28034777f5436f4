"""The compiled loop of ``ncfix.geometry.frames``' rotations (Rodrigues), in a module of its own so
that loading the profiles and kinematics (which use ``frames``) does not load numba: a run that
computes no rotation, such as a pass-through, never pays for the compiler."""

from __future__ import annotations

import numpy as np
from numba import njit


def _rotations(a, b, out):  # pragma: no cover - compiled
    """out[i] = I + K + K² / (1 + c), K the cross-product matrix of â × b̂ and c = â · b̂; a half
    turn 2uuᵀ − I about u ⊥ â (u from â × x̂, or â × ŷ when â is within 25.8° of x̂) when opposite;
    NaN where either direction is zero or not a number."""
    for i in range(a.shape[0]):
        na = np.sqrt(a[i, 0] * a[i, 0] + a[i, 1] * a[i, 1] + a[i, 2] * a[i, 2])
        nb = np.sqrt(b[i, 0] * b[i, 0] + b[i, 1] * b[i, 1] + b[i, 2] * b[i, 2])
        if not (na > 0.0 and nb > 0.0):  # a zero or NaN direction has no rotation: NaN, never a raise
            out[i, :, :] = np.nan
            continue
        ax, ay, az = a[i, 0] / na, a[i, 1] / na, a[i, 2] / na
        bx, by, bz = b[i, 0] / nb, b[i, 1] / nb, b[i, 2] / nb
        c = ax * bx + ay * by + az * bz
        if c < -1.0 + 1e-12:
            hx, hy = (1.0, 0.0) if abs(ax) < 0.9 else (0.0, 1.0)
            ux, uy, uz = -az * hy, az * hx, ax * hy - ay * hx
            nu = np.sqrt(ux * ux + uy * uy + uz * uz)
            u = (ux / nu, uy / nu, uz / nu)
            for r in range(3):
                for s in range(3):
                    out[i, r, s] = 2.0 * u[r] * u[s] - (1.0 if r == s else 0.0)
            continue
        vx, vy, vz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        scale = 1.0 / (1.0 + c)
        k = ((0.0, -vz, vy), (vz, 0.0, -vx), (-vy, vx, 0.0))
        for r in range(3):
            for s in range(3):
                kk = k[r][0] * k[0][s] + k[r][1] * k[1][s] + k[r][2] * k[2][s]
                out[i, r, s] = (1.0 if r == s else 0.0) + k[r][s] + kk * scale


rotations = njit(cache=True, nogil=True)(_rotations)


def _about_axis(c, s, eye, k, uu, out):  # pragma: no cover - compiled
    """out[i] = c[i]·I + s[i]·K + (1 − c[i])·uuᵀ (``frames.axis_rotation``), each entry summed in
    that order, as the broadcast numpy expression does: the same numbers, in one pass."""
    for i in range(c.shape[0]):
        ci, si = c[i], s[i]
        oc = 1.0 - ci
        for r in range(3):
            for q in range(3):
                out[i, r, q] = (ci * eye[r, q] + si * k[r, q]) + oc * uu[r, q]


about_axis = njit(cache=True, nogil=True)(_about_axis)
