"""``--strategy epa``: blocks left colliding are left as programmed (CONTRACT.md), ramps go around them."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh

import ncfix
from ncfix.geometry.frames import angle_between_deg, rotation_from_z
from ncfix.geometry.mesh import load_head
from ncfix.nc.post import post_program
from ncfix.profiles import load_profile
from ncfix.reference import ExactReference
from test_epa_strategy import _poses  # motion blocks of an ijk program

REPO = Path(__file__).resolve().parents[1]
HEAD = REPO / "samples" / "deposition_head.stl"
STANDOFF_MM = 6.0
def test_a_block_no_tilt_frees_stays_programmed_while_its_neighbours_are_fixed(monkeypatch, tmp_path):
    # A pass along x (10 mm apart, tip at z = 8); a wall whose lower edge the head's body (56 mm
    # wide, from 25 mm above the tip) meets 6 mm deep for the blocks from x = -70 to 0 (a tilt of
    # about 12.5° frees them), and a post around the nozzle just above the tip at x = 0: no tilt
    # about the tip frees that block. Its move collides, so the next block (x = 10) collides too.
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "coacd"))
    xs = np.arange(-100.0, 100.0 + 1e-9, 10.0)
    P = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 2.0)])
    data = "".join(post_program(load_profile("ijk"), P, np.tile([0.0, 0.0, 1.0], (len(xs), 1)),
                                title="epa unresolved")).encode()
    bodies = {"wall": trimesh.creation.box(bounds=[[-50.0, 22.0, 30.0], [-20.0, 40.0, 60.0]]),
              "post": trimesh.creation.box(bounds=[[-1.0, -0.3, 8.4], [1.0, 4.0, 13.0]])}
    for name, mesh in bodies.items():
        mesh.export(tmp_path / f"{name}.stl")
    max_tilt, max_step = 20.0, 13.0
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(data), out, head=str(HEAD), part=[str(tmp_path / f"{n}.stl") for n in bodies],
                           bead_radius=0.0, strategy="epa", max_tilt=max_tilt, max_step=max_step, device="cpu")
    before, after = data.decode(), out.getvalue().decode()
    lines, P0, N0 = _poses(before.encode())
    line_of = {round(x): line for x, line in zip(P0[:, 0], lines) if line != lines[0]}  # not the approach

    assert report.exit_code == 1
    unresolved = [u["line"] for u in report.unresolved]
    changed = {c["line"] for c in report.changes}
    # The post's block is unresolved, with why; the block after it (its move starts there) too.
    assert line_of[0] in unresolved and line_of[10] in unresolved
    reasons = {u["line"]: u["reason"] for u in report.unresolved}
    assert "no free orientation within 20° (--max-tilt)" in reasons[line_of[0]]
    # Unresolved blocks are left as programmed: byte for byte, and not among the changes.
    a, b = before.splitlines(), after.splitlines()
    assert len(a) == len(b)
    assert all(a[line - 1] == b[line - 1] for line in unresolved)
    assert not set(unresolved) & changed
    assert {i + 1 for i, (x, y) in enumerate(zip(a, b)) if x != y} == changed
    # ... while the wall's blocks before it are fixed (the ramp ends at the post's block, within θ).
    wall_lines = [line_of[x] for x in range(-70, 0, 10)]
    assert set(wall_lines) <= changed and not set(wall_lines) & set(unresolved)
    assert set(unresolved) == {line_of[0], line_of[10]}

    # The written program: tips stay, tilts within Θ, steps within θ, every block but the
    # unresolved ones free when checked exactly.
    lines1, P1, N1 = _poses(after.encode())
    assert lines1 == lines
    C0, C1 = P0 + STANDOFF_MM * N0, P1 + STANDOFF_MM * N1
    assert np.abs(C1 - C0).max() < 2e-3
    assert angle_between_deg(N1, N0).max() <= max_tilt + 1e-3
    assert angle_between_deg(N1[1:], N1[:-1]).max() <= max_step + 1e-3
    ref = ExactReference(load_head(HEAD).mesh, bodies)
    R1 = rotation_from_z(N1)
    stuck = [line for k, line in enumerate(lines) if line not in unresolved and ref.clearance(C1[k], R1[k])[0] <= -1e-3]
    assert stuck == []
