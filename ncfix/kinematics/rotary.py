"""Two rotary axes in a chain: orientation, inverse kinematics, branch choice, unwinding, limits.

The chain lists the axes from the workpiece to the tool. With ISO signs the tool vector is
``N = R(u1, s1·θ1) · R(u2, s2·θ2) · e_z`` whether an axis sits on the table or on the head
(reference: nc-dialects-and-kinematics.md §3.1), so one solver serves every topology; the
topology modules (table_table, head_head, head_table) add only where machine XYZ goes when TCP
is off.
"""

from __future__ import annotations

import math

import numpy as np

from ncfix.geometry.frames import axis_rotation
from ncfix.kinematics.base import RotaryAxis, Unreachable

# Below this |sin(tilt)| the first axis cannot change N (the pole): keep its previous value.
POLE_SIN = 1e-9


class PositionTransform:
    """Machine XYZ ↔ workpiece tip point for one topology (identity when TCP is on)."""

    def to_machine(self, p: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def to_workpiece(self, x: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
        raise NotImplementedError


class TwoAxisChain:
    """Kinematics of a machine with linear X, Y, Z and two rotary axes (see module docstring)."""

    def __init__(self, axes: tuple[RotaryAxis, RotaryAxis], transform: PositionTransform) -> None:
        self.axes = axes
        self.transform = transform
        self.letters = ("X", "Y", "Z", axes[0].letter, axes[1].letter)
        self.orientation_letters = (axes[0].letter, axes[1].letter)
        self._u = [np.asarray(a.direction, dtype=np.float64) for a in axes]
        self._s = [float(a.sign) for a in axes]
        self._u1 = tuple(float(v) for v in axes[0].direction)
        self._u2 = tuple(float(v) for v in axes[1].direction)
        u1, u2 = self._u
        # u1 · R(u2, φ2) · e_z = a·cos φ2 + b·sin φ2 + c (Rodrigues, projected on u1)
        self._abc = (float(u1[2] - u2[2] * (u1 @ u2)), float(u1 @ np.cross(u2, [0.0, 0.0, 1.0])),
                     float(u2[2] * (u1 @ u2)))

    # -- forward ---------------------------------------------------------------------------
    def rotations(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 5) words → R(u1, s1·θ1) and R(u2, s2·θ2), each (n, 3, 3)."""
        phi1 = np.radians(words[:, 3]) * self._s[0]
        phi2 = np.radians(words[:, 4]) * self._s[1]
        return axis_rotation(self._u[0], phi1), axis_rotation(self._u[1], phi2)

    def vertical(self, words: np.ndarray) -> np.ndarray:
        """The machine's +Z (up) seen in the part frame at the words (n, 5): (n, 3) unit vectors
        (the tables turn the part under it; the head's rotations do not change it)."""
        words = np.asarray(words, dtype=np.float64).reshape(-1, 5)
        r1, r2 = self.rotations(words)
        zero = np.zeros((len(words), 3))
        up = self.transform.to_workpiece(zero + [0.0, 0.0, 1.0], r1, r2) - self.transform.to_workpiece(zero, r1, r2)
        return up / np.linalg.norm(up, axis=1, keepdims=True)

    def forward(self, words: np.ndarray, tcp: bool = True):
        words = np.asarray(words, dtype=np.float64).reshape(-1, 5)
        r1, r2 = self.rotations(words)
        rot = r1 @ r2
        n = rot[:, :, 2].copy()
        xyz = words[:, :3]
        p = xyz.copy() if tcp else self.transform.to_workpiece(xyz, r1, r2)
        return p, n, rot

    # -- inverse ---------------------------------------------------------------------------
    def solutions(self, n: np.ndarray) -> list[tuple[float | None, float]]:
        """Both (φ1, φ2) solutions in radians for unit vector ``n``; φ1 None at the pole.

        φ2 from the component of N along the first axis (it does not change when that axis
        turns), then φ1 as the turn about the first axis that takes R(u2, φ2)·e_z onto N.
        """
        u1, u2 = self._u1, self._u2
        a, b, c = self._abc
        r = math.hypot(a, b)
        if r < 1e-12:
            raise Unreachable("the second rotary axis cannot tilt the tool in this chain")
        nx, ny, nz = float(n[0]), float(n[1]), float(n[2])
        d = u1[0] * nx + u1[1] * ny + u1[2] * nz
        x = (d - c) / r
        if abs(x) > 1.0 + 1e-9:
            raise Unreachable("orientation is outside the cone this chain can reach")
        base = math.atan2(b, a)
        spread = math.acos(max(-1.0, min(1.0, x)))
        n_perp = _sub(n, d, u1)
        out: list[tuple[float | None, float]] = []
        for phi2 in (base + spread, base - spread):
            v = _rotate_z(u2, phi2)
            v_perp = _sub(v, v[0] * u1[0] + v[1] * u1[1] + v[2] * u1[2], u1)
            if _norm(v_perp) < POLE_SIN or _norm(n_perp) < POLE_SIN:
                out.append((None, phi2))
                continue
            cx = v_perp[1] * n_perp[2] - v_perp[2] * n_perp[1]
            cy = v_perp[2] * n_perp[0] - v_perp[0] * n_perp[2]
            cz = v_perp[0] * n_perp[1] - v_perp[1] * n_perp[0]
            sin_part = u1[0] * cx + u1[1] * cy + u1[2] * cz
            cos_part = v_perp[0] * n_perp[0] + v_perp[1] * n_perp[1] + v_perp[2] * n_perp[2]
            out.append((math.atan2(sin_part, cos_part), phi2))
        return out

    def _place(self, axis: RotaryAxis, value_deg: float, previous_deg: float) -> float | None:
        """The word value for an axis angle: unwound, modulo or within limits; None if out."""
        if axis.mode == "continuous":
            value = previous_deg + _wrap(value_deg - previous_deg)
            return value if axis.within(value) else None
        if axis.mode == "modulo":
            value = value_deg % 360.0
            return 0.0 if value >= 360.0 - 1e-9 else value
        best = None
        for turns in (-2, -1, 0, 1, 2):
            value = value_deg + 360.0 * turns
            if axis.within(value) and (best is None or abs(value - previous_deg) < abs(best - previous_deg)):
                best = value
        return best

    def orientation_words(self, n: np.ndarray, previous: tuple[float, float],
                          branch: tuple[float, float] | None = None) -> tuple[float, float]:
        """Rotary words for unit vector ``n``: the solution nearest ``branch`` (default
        ``previous``) within the limits, its values placed (unwound) next to ``previous``.

        Both solutions give the same N but spin the head 180° apart about it (``(a, c)`` and
        ``(-a, c + 180°)`` on an A/C table), so the branch decides the pose. The corrector tests a
        candidate orientation with the branch nearest its block's programmed words and writes it
        with the same branch (``branch``): a block ends in the pose its test found free, whatever
        the blocks before it were given."""
        n = np.asarray(n, dtype=np.float64)
        n = n / np.linalg.norm(n)
        ref = previous if branch is None else branch
        best, best_cost = None, math.inf
        for phi1, phi2 in self.solutions(n):
            theta2 = math.degrees(phi2) / self._s[1]
            theta1 = ref[0] if phi1 is None else math.degrees(phi1) / self._s[0]
            w1 = self._place(self.axes[0], theta1, previous[0])
            w2 = self._place(self.axes[1], theta2, previous[1])
            if w1 is None or w2 is None:
                continue
            cost = abs(_wrap(w1 - ref[0])) + abs(_wrap(w2 - ref[1]))
            if cost < best_cost - 1e-12:
                best, best_cost = (w1, w2), cost
        if best is None:
            raise Unreachable(
                f"no {self.axes[0].letter}/{self.axes[1].letter} solution within the axis limits "
                f"for tool vector ({n[0]:.4f}, {n[1]:.4f}, {n[2]:.4f})"
            )
        return best

    def inverse(self, p: np.ndarray, n: np.ndarray, previous: np.ndarray, tcp: bool = True,
                branch: np.ndarray | None = None) -> np.ndarray:
        ref = None if branch is None else (float(branch[3]), float(branch[4]))
        w1, w2 = self.orientation_words(n, (float(previous[3]), float(previous[4])), ref)
        p = np.asarray(p, dtype=np.float64).reshape(1, 3)
        if tcp:
            xyz = p[0]
        else:
            r1, r2 = self.rotations(np.array([[0.0, 0.0, 0.0, w1, w2]]))
            xyz = self.transform.to_machine(p, r1, r2)[0]
        return np.array([xyz[0], xyz[1], xyz[2], w1, w2])


def _rotate_z(u: tuple[float, float, float], angle: float) -> tuple[float, float, float]:
    """R(u, angle) · e_z by Rodrigues, in plain floats (this runs once per rewritten block)."""
    c, s = math.cos(angle), math.sin(angle)
    k = u[2] * (1.0 - c)
    return (u[1] * s + u[0] * k, -u[0] * s + u[1] * k, c + u[2] * k)


def _sub(v, scale: float, u) -> tuple[float, float, float]:
    return (v[0] - scale * u[0], v[1] - scale * u[1], v[2] - scale * u[2])


def _norm(v) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0
