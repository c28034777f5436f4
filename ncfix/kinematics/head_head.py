"""Head-head machines: both rotary axes carry the tool; the table does not turn.

With TCP off and length compensation active, the programmed point is the tip at zero
orientation: machine XYZ = p + L · (N − e_z), with L the pivot length (tip to head pivot).
"""

from __future__ import annotations

import numpy as np

from ncfix.kinematics.rotary import PositionTransform

EZ = np.array([0.0, 0.0, 1.0])


class HeadHead(PositionTransform):
    def __init__(self, pivot_length_mm: float = 0.0) -> None:
        self.pivot_length_mm = float(pivot_length_mm)

    def _shift(self, r1, r2):
        n = (r1 @ r2)[:, :, 2]
        return self.pivot_length_mm * (n - EZ)

    def to_machine(self, p, r1, r2):
        return p + self._shift(r1, r2)

    def to_workpiece(self, x, r1, r2):
        return x - self._shift(r1, r2)
