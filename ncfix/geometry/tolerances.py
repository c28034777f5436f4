"""Geometric tolerances of ncfix in one place, each with the reason for its value."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GeometryTolerances:
    """Tolerances used by mesh loading, head orientation and voxelization (lengths in mm)."""

    # A head tip given by hand is read off a CAD model; half a millimetre is more than rounding
    # and less than any nozzle orifice, so a larger miss means a wrong --head-tip or --head-axis.
    head_tip_mm: float = 0.5
    # Triangles with less area than this carry no geometry (CAD export slivers); they are dropped.
    degenerate_area_mm2: float = 1e-12
    # Ray columns are moved off the cell centres by this fraction of the pitch so that they never
    # pass exactly through a vertex of a mesh whose coordinates sit on the grid.
    ray_jitter_fraction: float = 1e-6
    # Added to covering radii so that rounding in the distance arithmetic cannot uncover a point.
    cover_slack_mm: float = 1e-6
    # How far a part may lie outside the program's bounding box and still be reachable by the head
    # (a generous head size); farther away it is almost surely in the wrong frame or units.
    part_reach_mm: float = 200.0


TOLERANCES = GeometryTolerances()
