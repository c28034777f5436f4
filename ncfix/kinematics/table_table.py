"""Table-table (trunnion) machines: both rotary axes carry the workpiece.

With TCP off, machine XYZ = R_p · (R_s · (p − c_s) + d) + c_p, where R_s and R_p are the
physical rotations of the part-carrying (first in the chain) and the primary table axis,
c_s is the first axis' centre in workpiece coordinates, d the offset between the two axes and
c_p the primary axis' centre in machine coordinates. The MultiAxis_3DP printer is
c_s = 0, d = (0, 0, 40.5), c_p = 0 (measurements.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ncfix.kinematics.rotary import PositionTransform


class TableTable(PositionTransform):
    def __init__(self, centre_first_mm: Sequence[float] = (0.0, 0.0, 0.0), offset_mm: Sequence[float] = (0.0, 0.0, 0.0),
                 centre_primary_mm: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        self.c_s = np.asarray(centre_first_mm, dtype=np.float64)
        self.d = np.asarray(offset_mm, dtype=np.float64)
        self.c_p = np.asarray(centre_primary_mm, dtype=np.float64)

    # r1 = R(u1, s1·θ1) and r2 = R(u2, s2·θ2) turn the tool relative to the part; the
    # physical table rotations are their transposes.
    def to_machine(self, p, r1, r2):
        inner = np.einsum("nji,nj->ni", r1, p - self.c_s) + self.d
        return np.einsum("nji,nj->ni", r2, inner) + self.c_p

    def to_workpiece(self, x, r1, r2):
        inner = np.einsum("nij,nj->ni", r2, x - self.c_p) - self.d
        return np.einsum("nij,nj->ni", r1, inner) + self.c_s
