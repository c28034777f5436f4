"""Head-table machines: the first axis of the chain turns the table, the second tilts the head.

With TCP off: machine XYZ = R_T · (p + o − c) + c + L · (t_m − e_z), where R_T is the physical
table rotation, o the workpiece frame's origin in the table's frame (it turns with the table),
c the table's centre (a point of its axis, in the table's frame), t_m the head's tool axis in
machine coordinates and L the pivot length of the head (tip to pivot). The S3 ring printer is
o = (0, 0, 0.3), c = 0, L = 77.36 (s3-ring-kinematics.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ncfix.kinematics.rotary import PositionTransform

EZ = np.array([0.0, 0.0, 1.0])


class HeadTable(PositionTransform):
    def __init__(self, table_centre_mm: Sequence[float] = (0.0, 0.0, 0.0), pivot_length_mm: float = 0.0,
                 part_origin_mm: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        self.c = np.asarray(table_centre_mm, dtype=np.float64)
        self.pivot_length_mm = float(pivot_length_mm)
        self.o = np.asarray(part_origin_mm, dtype=np.float64)

    def to_machine(self, p, r1, r2):
        t_m = r2[:, :, 2]
        return (np.einsum("nji,nj->ni", r1, p + self.o - self.c) + self.c
                + self.pivot_length_mm * (t_m - EZ))

    def to_workpiece(self, x, r1, r2):
        t_m = r2[:, :, 2]
        return (np.einsum("nij,nj->ni", r1, x - self.c - self.pivot_length_mm * (t_m - EZ))
                + self.c - self.o)
