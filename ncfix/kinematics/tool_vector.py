"""Tool-vector machines (Fanuc G43.5 I J K, Siemens A3= B3= C3=, Heidenhain LN TX TY TZ).

The control solves its own inverse kinematics; the program carries the tip point and the
vector. The head's spin about N is the minimal rotation from +Z (docs/contract.md).
"""

from __future__ import annotations

import math

import numpy as np

from ncfix.geometry.frames import minimal_rotation, normalize
from ncfix.kinematics.base import Unreachable


class ToolVector:
    def __init__(self, vector_letters: tuple[str, str, str], max_tilt_deg: float = 180.0) -> None:
        self.letters = ("X", "Y", "Z") + tuple(vector_letters)
        self.orientation_letters = tuple(vector_letters)
        self.max_tilt_deg = float(max_tilt_deg)

    def forward(self, words: np.ndarray, tcp: bool = True):
        words = np.asarray(words, dtype=np.float64).reshape(-1, 6)
        n = normalize(words[:, 3:6])
        return words[:, :3].copy(), n, minimal_rotation(n)

    def inverse(self, p: np.ndarray, n: np.ndarray, previous: np.ndarray, tcp: bool = True,
                branch: np.ndarray | None = None) -> np.ndarray:
        n = np.asarray(n, dtype=np.float64)
        n = n / np.linalg.norm(n)
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(n[2])))))
        if tilt > self.max_tilt_deg + 1e-9:
            raise Unreachable(f"tool vector tilts {tilt:.3f}° from +Z, beyond the machine's {self.max_tilt_deg:g}°")
        return np.concatenate([np.asarray(p, dtype=np.float64).reshape(3), n])
