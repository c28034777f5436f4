"""Correction (fix mode): the graph strategy frees the blocks the checker flags, within θ and Θ,
about the tip, proven free by the exact reference, stable under re-runs and window sizes."""

from __future__ import annotations

import io
import re
from dataclasses import replace

import numpy as np
import pytest

from ncfix.config import Options
from ncfix.correct.stage import CorrectStage
from ncfix.geometry.frames import angle_between_deg, minimal_rotation
from ncfix.geometry.mesh import load_head
from ncfix.pipeline import run
from ncfix.reference import ExactReference, bead_centres
from test_checker import HEAD, _wall_lines

pytestmark = pytest.mark.heavy  # each case solves a 60-block episode (10-30 s)

STANDOFF = 6.0
MOVE = re.compile(rb"^N\d+ (G[01]) X(\S+) Y(\S+) Z(\S+) I(\S+) J(\S+) K(\S+)")


def _fix(data: bytes, **kw):
    options = replace(Options(head=str(HEAD), check=False, device="cpu", deposit_codes=("M3", "M5"), strategy="graph"), **kw)
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, options, "wall.nc")
    return out.getvalue(), report


def _moves(data: bytes):
    """(line numbers, G codes, P (n, 3), N (n, 3), depositing (n,)) of the motion lines; the wall
    program writes every word on every motion line; M3/M5 switch deposition."""
    lines, codes, P, N, dep = [], [], [], [], []
    on = False
    for i, raw in enumerate(data.splitlines(), 1):
        if raw.strip() == b"M3":
            on = True
        elif raw.strip() == b"M5":
            on = False
        m = MOVE.match(raw)
        if m:
            lines.append(i)
            codes.append(m.group(1))
            P.append([float(v) for v in m.group(2, 3, 4)])
            n = np.array([float(v) for v in m.group(5, 6, 7)])
            N.append(n / np.linalg.norm(n))
            dep.append(on and m.group(1) == b"G1")
    return np.array(lines), codes, np.array(P), np.array(N), np.array(dep)


def _exact_bead_hits(data: bytes, ref: ExactReference, lines_to_check: set[int]) -> set[int]:
    """The checked moves that collide, exactly: the end pose and sweep samples 0.5 mm apart against
    the beads laid up to each (spheres of 1 mm every 1/8 mm along the deposited moves through P;
    the checker samples at pitch/2 = 1/4 mm)."""
    lines, _, P, N, dep = _moves(data)
    reach = float(np.linalg.norm(ref.head.vertices, axis=1).max()) + 1.0
    beads = np.zeros((0, 3))
    hits = set()
    for k in range(1, len(lines)):
        own = bead_centres(P[k - 1], P[k], 1.0 / 8) if dep[k] else np.zeros((0, 3))
        if int(lines[k]) in lines_to_check and len(beads) + len(own):
            samples = max(1, int(np.ceil(np.linalg.norm(P[k] - P[k - 1]) / 0.5)))
            for t in np.linspace(0.0, 1.0, samples + 1)[1:]:
                n = N[k - 1] * (1 - t) + N[k] * t  # near enough to the great circle for 1-2° steps
                n /= np.linalg.norm(n)
                c = P[k - 1] * (1 - t) + P[k] * t + STANDOFF * n
                seen = np.vstack([beads, own[: int(np.floor(t * (len(own) - 1) + 1e-9)) + 1]]) if len(own) else beads
                seen = seen[np.linalg.norm(seen - c, axis=1) <= reach]
                if len(seen) and ref.bead_collides(c, minimal_rotation(n[None])[0], seen, 1.0):
                    hits.add(int(lines[k]))
                    break
        beads = np.vstack([beads, own])
    return hits


@pytest.fixture(scope="module")
def wall():
    _, _, _, lines, _ = _wall_lines()
    data = "".join(lines).encode()
    fixed, report = _fix(data)
    return data, fixed, report


@pytest.fixture(scope="module")
def reference():
    head = load_head(HEAD).mesh
    return ExactReference(head, {}, tip_allowance_mm=1.0)


def test_every_flagged_block_of_the_wall_workload_is_fixed(wall):
    data, fixed, report = wall
    s = report.summary
    assert s["colliding_blocks_before"] > 20
    assert s["unresolved_blocks"] == 0 and report.exit_code == 0
    assert s["changed_blocks"] >= s["colliding_blocks_before"]
    changed = {c["line"] for c in report.changes}
    assert {c["line"] for c in report.collisions} <= changed
    assert {c["reason"] for c in report.changes} == {"collision", "blend"}
    # lossless outside the changed blocks, and the report's "after" is what was written
    old, new = data.splitlines(keepends=True), fixed.splitlines(keepends=True)
    assert len(old) == len(new)
    assert {i + 1 for i, (a, b) in enumerate(zip(old, new)) if a != b} == changed
    for c in report.changes:
        assert new[c["line"] - 1].rstrip(b"\r\n").decode() == c["after"]
        assert old[c["line"] - 1].rstrip(b"\r\n").decode() == c["before"]


def test_the_exact_reference_finds_no_collision_after_correction(wall, reference):
    data, fixed, report = wall
    flagged = {c["line"] for c in report.collisions}
    assert _exact_bead_hits(data, reference, flagged)  # the workload really collides as programmed
    checked = flagged | {c["line"] for c in report.changes}
    assert _exact_bead_hits(fixed, reference, checked) == set()


def test_steps_stay_within_theta_and_tilts_within_big_theta(wall):
    data, fixed, report = wall
    _, _, _, N0, _ = _moves(data)
    _, _, _, N1, _ = _moves(fixed)
    own = angle_between_deg(N0[1:], N0[:-1])
    step = angle_between_deg(N1[1:], N1[:-1])
    small = own <= 2.0
    assert step[small].max() <= 2.0 + 1e-3  # 6 decimals of I J K
    assert angle_between_deg(N1, N0).max() <= 30.0 + 1e-3
    assert report.summary["max_tilt_deg"] <= 30.0


def test_the_tip_stays_where_it_was_before_formatting(monkeypatch):
    """--pivot tip: C = P + h·N of every rewritten block equals the programmed one to 1e-6 mm."""
    seen = []
    apply = CorrectStage._apply

    def spy(self, first, last, words, collided):
        rows = np.arange(first, last + 1)
        P0, N0, _ = self.path.forward(self.rows.programmed[rows], self.rows.tcp[rows])
        P1, N1, _ = self.path.forward(words, self.rows.tcp[rows])
        seen.append(np.abs((P1 + STANDOFF * N1) - (P0 + STANDOFF * N0)).max())
        return apply(self, first, last, words, collided)

    monkeypatch.setattr(CorrectStage, "_apply", spy)
    _, _, _, lines, _ = _wall_lines()
    _, report = _fix("".join(lines).encode())
    assert report.summary["changed_blocks"] > 0
    assert seen and max(seen) < 1e-6


def test_running_ncfix_on_its_output_changes_nothing(wall):
    _, fixed, _ = wall
    again, report = _fix(fixed)
    assert again == fixed
    assert report.summary["colliding_blocks_before"] == 0 and report.exit_code == 0


@pytest.mark.parametrize("window", [7, 50])
def test_the_output_does_not_depend_on_the_window(wall, window):
    data, fixed, _ = wall
    out, _ = _fix(data, window=window)
    assert out == fixed


def test_with_no_room_to_tilt_the_blocks_stay_and_the_report_says_why(wall):
    data, _, _ = wall
    out, report = _fix(data, max_tilt=1.0)
    assert report.exit_code == 1
    unresolved = {u["line"]: u for u in report.unresolved}
    assert unresolved and set(unresolved) <= {c["line"] for c in report.collisions} | set(unresolved)
    old, new = data.splitlines(), out.splitlines()
    lines = sorted(unresolved)
    for line in lines:
        assert new[line - 1] == old[line - 1]  # left as programmed
        reason = unresolved[line]["reason"]
        # A limit, or the unresolved block before it (a move starting at a colliding pose
        # collides whatever its end); the first block of the run names the limit.
        held = reason == "its move starts at the block before, which is left colliding"
        assert ("--max-tilt" in reason or "--max-step" in reason) or (held and line != lines[0])
    assert "--max-tilt" in unresolved[lines[0]]["reason"] or "--max-step" in unresolved[lines[0]]["reason"]
    assert all(c["tilt_deg"] <= 1.0 + 1e-6 for c in report.changes)
