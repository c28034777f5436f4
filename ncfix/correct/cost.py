"""The orientation graph's objective, evaluated on a whole program: the yardstick of a correction.

``path_cost`` evaluates the sum the graph strategy minimises per episode (its steps plus
``DEVIATION_WEIGHT`` times each block's deviation, degrees) on any corrected program, either
strategy's output as written, against the program as posted; a program left as posted costs 0.
It compares what the strategies deliver, not their internal searches (docs/correction.md,
"Choosing between them"; the "cost" column of ``bench/run``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncfix.correct.graph import DEVIATION_WEIGHT
from ncfix.geometry.frames import angle_between_deg, turn_rotations
from ncfix.kinematics.poses import PoseMap, program_poses
from ncfix.nc.modal import Interpreter


@dataclass(frozen=True)
class PathCost:
    added_variation_deg: float  # Σ step(N′) − Σ step(N)
    deviation_deg: float  # Σ angle(N′, N)
    deviation_weight: float = DEVIATION_WEIGHT

    @property
    def total_deg(self) -> float:
        return self.added_variation_deg + self.deviation_weight * self.deviation_deg


def steps_deg(vectors: np.ndarray, programmed: np.ndarray, max_step_deg: float) -> np.ndarray:
    """(n - 1,) the graph's step weight into each block after the first: the plain angle to the
    block before, or, where the programmed vectors turn by more than ``max_step_deg`` (θ), the angle
    to the block before turned as the program turns there (``Episode.turns``: tilt from +Z and
    azimuth about Z)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    programmed = np.asarray(programmed, dtype=np.float64)
    before = vectors[:-1].copy()
    turning = angle_between_deg(programmed[1:], programmed[:-1]) > float(max_step_deg)
    if turning.any():
        turns = turn_rotations(programmed)
        before[turning] = np.einsum("nij,nj->ni", turns[turning], before[turning])
    return angle_between_deg(vectors[1:], before)


def path_cost(programmed: np.ndarray, output: np.ndarray, max_step_deg: float,
              deviation_weight: float = DEVIATION_WEIGHT) -> PathCost:
    """The graph's objective of ``output`` (n, 3) unit tool vectors against ``programmed`` (n, 3),
    the motion blocks of one program in order:

        cost = Σ step(N′) − Σ step(N) + DEVIATION_WEIGHT · Σ angle(N′ᵢ, Nᵢ)        (degrees)

    over consecutive motion blocks, step the graph's edge weight (``steps_deg``; the programmed path
    has no step where the program itself turns by more than θ). The first term is the angular
    variation a correction adds to the program's own (negative where it smooths the program), the
    second how far it leans away from it. On the output as written (after blending, at the printed
    decimals) the graph's path is the least of this sum among its tested candidates on the
    resolution grid (the blocks it must keep colliding aside), so an EPA output that costs less is
    smoother or nearer the program than the graph's grid allowed."""
    programmed = np.asarray(programmed, dtype=np.float64).reshape(-1, 3)
    output = np.asarray(output, dtype=np.float64).reshape(-1, 3)
    if programmed.shape != output.shape:
        raise ValueError(f"{len(output)} output vectors for {len(programmed)} programmed ones")
    if len(programmed) == 0:
        return PathCost(0.0, 0.0, float(deviation_weight))
    added = float(steps_deg(output, programmed, max_step_deg).sum() - steps_deg(programmed, programmed, max_step_deg).sum())
    deviation = float(angle_between_deg(output, programmed).sum())
    return PathCost(added, deviation, float(deviation_weight))


def program_vectors(data: bytes, profile, source: str = "<program>") -> tuple[np.ndarray, np.ndarray]:
    """(lines, N): the 1-based input line and the unit tool vector of every motion block of a
    program whose axes are all known, as ncfix reads it with ``profile`` (a ``Profile``)."""
    # the whole program as one chunk: the compiled reader's memory is the program's, not its words'
    chunk = Interpreter(profile, source, compiled_reader=True).feed_chunk(data.splitlines(keepends=True), 1)
    found = [poses for _, poses in program_poses([chunk], PoseMap(profile))]
    if not found:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    return found[0].lines, found[0].N
