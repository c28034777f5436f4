"""The golden correction cases, one per built-in machine profile (tests/golden/fix_<profile>, made
by tests/golden/make_fix_cases.py): ncfix frees each colliding input (test_golden.py holds it to
the expected bytes and to idempotence); here, what the output is: the words the fix checked are
the words it wrote, only the reported lines changed, the output is free (exact reference at every
block), every step is within θ, every tilt within Θ, and the tip C stays where it was."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ncfix.geometry.frames import angle_between_deg
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile

import golden_cases

STANDOFF = 6.0
LEVER_MM = 250.0


def _poses(data: bytes, profile):
    """Tip C, tool vector N and rotation R of every motion block with every axis known."""
    from ncfix.kinematics.poses import PoseMap

    chunk = Interpreter(profile).feed_chunk(data.splitlines(keepends=True), 1)
    rows = np.nonzero(chunk.motion >= 0)[0]
    words = chunk.words[rows]
    rows, words = rows[np.isfinite(words).all(axis=1)], words[np.isfinite(words).all(axis=1)]
    poses = PoseMap(profile)
    P, N, R = poses.forward(poses.normalise(words), poses.tcp(chunk, rows))
    return rows, P + STANDOFF * N, N, R


def _flag(case, name: str) -> str:
    """The value of a command-line flag of the case, a path made absolute."""
    value = case.args[case.args.index(name) + 1]
    return str((case.folder / value).resolve()) if name in ("--head", "--part") else value


@pytest.mark.parametrize("case", golden_cases.params("fix_"))
def test_golden_fix(case, tmp_path, monkeypatch):
    from ncfix.correct.stage import CorrectStage

    profile = load_profile(_flag(case, "--machine"))
    expected = golden_cases.expected(case).out
    data = case.input.read_bytes()
    table = {}  # line -> the words the fix checked later rows against (its table, as applied)
    apply = CorrectStage._apply

    def spy(self, first, last, words, collided):
        apply(self, first, last, words, collided)
        for row in range(first, last + 1):
            table[int(self.rows.line[row])] = self.rows.words[row].copy()

    monkeypatch.setattr(CorrectStage, "_apply", spy)
    got = golden_cases.run(case, tmp_path)
    report = json.loads(got.report)
    assert got.out == expected, f"regenerate with `python tests/golden/regen.py {case.name}` and review the diff"
    # The fix checked what it wrote: its table holds the words as the output states them, bit for bit.
    chunk = Interpreter(profile).feed_chunk(expected.splitlines(keepends=True), 1)
    changed = {c["line"] for c in report["changes"]}
    assert changed and changed <= set(table)
    for line in changed:
        assert np.array_equal(table[line], chunk.words[line - 1], equal_nan=True), f"line {line}"
    assert got.exit == 0 and report["summary"]["colliding_blocks_before"] > 0
    before, after = data.splitlines(), expected.splitlines()
    assert len(before) == len(after)
    changed = [i + 1 for i, (a, b) in enumerate(zip(before, after)) if a != b]
    assert changed == sorted(c["line"] for c in report["changes"])

    # The output as a program: free, within θ and Θ, the tip where it was.
    rows0, C0, N0, _ = _poses(data, profile)
    rows1, C1, N1, R1 = _poses(expected, profile)
    assert np.array_equal(rows0, rows1)
    # The tip moves only by the rounding of the printed words: linear words directly, angles through
    # the lever from the rotary axes (a TCP-off machine's machine XYZ: up to LEVER_MM away).
    fmt = profile.number_format
    rounding = 0.5 * 10.0 ** -fmt.linear * np.sqrt(3) + LEVER_MM * np.radians(0.5 * 10.0 ** -fmt.angle) + 2e-6
    assert np.linalg.norm(C1 - C0, axis=1).max() < rounding
    assert angle_between_deg(N1, N0).max() <= 30.0 + 1e-6
    assert angle_between_deg(N1[1:], N1[:-1]).max() <= 2.0 + 0.01
    from ncfix.geometry.mesh import load_head, load_mesh
    from ncfix.reference import ExactReference

    ref = ExactReference(load_head(_flag(case, "--head")).mesh, {"wall": load_mesh(_flag(case, "--part"), "part").mesh})
    assert not any(ref.collides(c, r) for c, r in zip(C1, R1))


def test_every_built_in_profile_has_a_golden_fix_case():
    from ncfix.profiles import builtin_names

    assert sorted(case.name for case in golden_cases.cases("fix_")) == sorted(f"fix_{name}" for name in builtin_names())
