"""The kinematics contract: machine words ↔ workpiece tip point P, tool vector N and head rotation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class RotaryAxis:
    """One rotary axis of a two-axis chain, as the profile file gives it.

    ``sign`` +1 follows ISO 841 (a positive command turns the tool right-handedly about
    ``direction`` relative to the workpiece); −1 is a reversed axis (LinuxCNC trt, most printer
    beds). ``mode``: ``continuous`` (unwound, never jumps 360°), ``modulo`` (written in
    [0, 360)), or ``limited`` (within ``limits_deg``).
    """

    letter: str
    direction: tuple[float, float, float]
    sign: int
    mode: str
    limits_deg: tuple[float, float]
    on_head: bool  # carried by the head (True) or by the table (False)

    def within(self, value_deg: float) -> bool:
        lo, hi = self.limits_deg
        return lo - 1e-9 <= value_deg <= hi + 1e-9


class Unreachable(Exception):
    """No solution of the inverse kinematics lies within the machine's limits."""


class Kinematics(Protocol):
    """What every kinematic family provides (one module per family, chosen by the profile)."""

    #: the machine words that a motion block carries, in the order of the position arrays
    letters: tuple[str, ...]
    #: the words that carry orientation (rotary axes, or vector components)
    orientation_letters: tuple[str, ...]

    def forward(self, words: np.ndarray, tcp: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """words : (n, len(letters)) float64, mm and degrees → P (n, 3), N (n, 3), R (n, 3, 3).

        P is the tip point in workpiece mm, N the unit tool vector (tip → head) and R the head's
        rotation (R @ e_z = N), both in the workpiece frame.
        """
        ...

    def inverse(self, p: np.ndarray, n: np.ndarray, previous: np.ndarray, tcp: bool = True,
                branch: np.ndarray | None = None) -> np.ndarray:
        """One block: P (3,), N (3,) and the previous block's words → this block's words.

        Rotary families choose the branch closest to ``branch`` (default ``previous``) within the
        limits, unwound next to ``previous``, and raise :class:`Unreachable` when none is.
        """
        ...
