"""``--strategy epa``: blocks left colliding are left as programmed (docs/contract.md), ramps go around them."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
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
def _pass_and_post(tmp_path, x_last: float, wall_x_max: float):
    """A pass along x from -100 to ``x_last`` (10 mm apart, tip at z = 8); a wall whose lower edge
    the head's body (56 mm wide, from 25 mm above the tip) meets 6 mm deep for the blocks from
    x = -70 to ``wall_x_max`` + 20 (a tilt of about 12.5° frees them), and a post around the nozzle
    just above the tip at x = 0: no tilt about the tip frees that block. Fixed with epa (Θ 20°,
    θ 13°); the program, the bodies, the report, the output and each x's line."""
    xs = np.arange(-100.0, x_last + 1e-9, 10.0)
    P = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 2.0)])
    data = "".join(post_program(load_profile("ijk"), P, np.tile([0.0, 0.0, 1.0], (len(xs), 1)),
                                title="epa unresolved")).encode()
    bodies = {"wall": trimesh.creation.box(bounds=[[-50.0, 22.0, 30.0], [wall_x_max, 40.0, 60.0]]),
              "post": trimesh.creation.box(bounds=[[-1.0, -0.3, 8.4], [1.0, 4.0, 13.0]])}
    for name, mesh in bodies.items():
        mesh.export(tmp_path / f"{name}.stl")
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(data), out, head=str(HEAD), part=[str(tmp_path / f"{n}.stl") for n in bodies],
                           bead_radius=0.0, strategy="epa", max_tilt=20.0, max_step=13.0, device="cpu")
    lines, P0, _ = _poses(data)
    line_of = {round(x): line for x, line in zip(P0[:, 0], lines) if line != lines[0]}  # not the approach
    return data, bodies, report, out.getvalue(), line_of


def test_a_block_no_tilt_frees_stays_programmed_while_its_neighbours_are_fixed(monkeypatch, tmp_path):
    # The wall meets the blocks from x = -70 to 0; the post's move collides, so the next block
    # (x = 10) collides too.
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "coacd"))
    data, bodies, report, out, line_of = _pass_and_post(tmp_path, 100.0, -20.0)
    max_tilt, max_step = 20.0, 13.0
    before, after = data.decode(), out.decode()
    lines, P0, N0 = _poses(data)

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


@pytest.mark.heavy  # an end-to-end fix; the test above is this module's fast one
def test_the_blocks_held_by_one_left_colliding_are_left_with_it_and_the_rest_fixed(monkeypatch, tmp_path):
    # The pass and post of the test above, with the wall from x = -70 to 120: no tilt frees the
    # post's block (x = 0), so the wall's blocks after it, colliding as programmed, each start
    # where the one before is left colliding: they are left with it (one round, not one round
    # each: the rounds ran out before, and the whole episode, the wall's blocks before the post
    # too, was left as programmed).
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "coacd"))
    data, _, report, out, line_of = _pass_and_post(tmp_path, 200.0, 95.0)
    before, after = data.decode(), out.decode()
    reasons = {u["line"]: u["reason"] for u in report.unresolved}
    changed = {c["line"] for c in report.changes}
    held = [line_of[x] for x in range(10, 140, 10)]  # the wall's, and x = 130 (free, starts at 120)
    assert report.exit_code == 1
    assert "no free orientation within 20° (--max-tilt)" in reasons[line_of[0]]
    assert all(reasons[line] == "its move starts at the block before, which is left colliding" for line in held)
    assert set(reasons) == {line_of[0], *held}
    wall_lines = [line_of[x] for x in range(-70, 0, 10)]
    assert set(wall_lines) <= changed  # fixed, not left as programmed with the post
    a, b = before.splitlines(), after.splitlines()
    assert all(a[line - 1] == b[line - 1] for line in reasons)
