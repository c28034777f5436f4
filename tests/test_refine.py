"""Sweep margins: a sample hit only because of its margin is tested again as finer samples (down
to 1/16 of the pitch), so a head gliding 0.1 mm over a part is free, and one that dips into it
still collides."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix

SAMPLES = Path(__file__).resolve().parents[1] / "samples"
PROGRAM = b"G21 G90\nG0 X-10. Y0. Z0.\nG1 X10. Y0. Z0. I0. J0. K1. F600.\nG1 X10. Y10. Z0.\nM30\n"


@pytest.mark.parametrize("top, collides", [(5.7, False), (5.9, False), (6.05, True)])
def test_a_head_gliding_over_a_part_is_free_and_one_dipping_in_collides(tmp_path, top, collides):
    mesh = trimesh.creation.box(extents=(40.0, 8.0, 10.0))
    mesh.apply_translation((0.0, -4.0, top - 5.0))  # the tip runs at z = 6 (standoff 6)
    path = tmp_path / "slab.stl"
    mesh.export(path)
    report = ncfix.process(io.BytesIO(PROGRAM), io.BytesIO(), head=str(SAMPLES / "deposition_head.stl"),
                           part=[str(path)], check=True, bead_radius=0.0, pitch=1.0)
    assert bool(report.collisions) == collides
    if not collides:  # the exact reference agrees all along the move (0.05 mm apart)
        from ncfix.geometry.mesh import load_head
        from ncfix.reference import ExactReference

        ref = ExactReference(load_head(SAMPLES / "deposition_head.stl").mesh, {"slab": mesh})
        for x in np.linspace(-10, 10, 401):
            assert ref.clearance(np.array([x, 0.0, 6.0]), np.eye(3))[0] > 0


@pytest.mark.parametrize("bead_z, collides", [(4.5, False), (5.2, True)])
def test_a_bead_passed_within_the_margin_is_free(bead_z, collides):
    """The deposit test refines too: a later pass glides over a bead (top at bead_z + 1, the tip
    at z = 6) with a 1 mm sweep margin."""
    program = (f"G21 G90\nG0 X-10. Y20. Z{bead_z}\nM3\nG1 X10. Y20. I0. J0. K1. F600.\nM5\n"
               "G0 X10. Y0. Z0.\nG1 X-10. Y0. Z0.\nG1 X-10. Y20. Z0.\nG1 X10. Y20. Z0.\nM30\n").encode()
    report = ncfix.process(io.BytesIO(program), io.BytesIO(), head=str(SAMPLES / "deposition_head.stl"),
                           check=True, bead_radius=1.0, deposit_codes="M3,M5", pitch=1.0, tip_allowance=0.0)
    # line 8 runs into the bead's end, line 9 along the bead
    assert [c["line"] for c in report.collisions] == ([8, 9] if collides else [])
