"""The set S of candidate orientations: a spherical cap of directions around each programmed vector."""

from __future__ import annotations

import math

import numpy as np

from ncfix.geometry.frames import rotation_from_z


def cap_pattern(max_tilt_deg: float, resolution_deg: float) -> np.ndarray:
    """Unit directions (K, 3) around +Z: rings every ``resolution_deg`` up to ``max_tilt_deg``,
    each ring with points about ``resolution_deg`` apart. Row 0 is +Z itself.
    """
    rings = int(math.floor(max_tilt_deg / resolution_deg + 1e-9))
    out = [np.array([0.0, 0.0, 1.0])]
    for k in range(1, rings + 1):
        tilt = math.radians(k * resolution_deg)
        count = max(6, int(math.ceil(2 * math.pi * math.sin(tilt) / math.radians(resolution_deg))))
        phase = 0.5 * (k % 2) * 2 * math.pi / count  # stagger rings
        azimuth = phase + 2 * math.pi * np.arange(count) / count
        out.append(np.stack([math.sin(tilt) * np.cos(azimuth), math.sin(tilt) * np.sin(azimuth),
                             np.full(count, math.cos(tilt))], axis=1))
    return np.vstack([np.atleast_2d(o) for o in out])


def candidates_around(programmed: np.ndarray, pattern: np.ndarray) -> np.ndarray:
    """The cap pattern turned onto each programmed vector: (m, 3) → (m, K, 3); [:, 0] is programmed."""
    rot = np.asarray(rotation_from_z(np.asarray(programmed, dtype=np.float64).reshape(-1, 3))).reshape(-1, 3, 3)
    return np.einsum("mij,kj->mki", rot, pattern)
