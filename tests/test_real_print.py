"""The real print (corpus model_1_Gcode.txt with samples/model_1.toml) still shows real faults.

The recipe's settings are physical (README "The real print"); these tests plant faults a printer
would suffer in the first eight layers of the program and check that ncfix flags them at their
lines, and only there: the platform raised 1.5 mm into the first layer, a travel move through the
printed part at mid-height, a stretch of blocks with the tool axis tilted 60° from the programmed
one (past the nozzle cone's 45° half-angle: the cone dips into the layers below). The corpus is
read at run time; the tests skip without it.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

import ncfix
from conftest import REPO, corpus_path
from ncfix.pipeline import load_parts
from ncfix.profiles import load_profile

RECIPE = REPO / "samples" / "model_1.toml"
LAYER_9 = 13721  # the line of the plunge that opens layer 9: the part below it is 5-6 mm tall
STRETCH = range(5600, 5620)  # 20 blocks of layer 5 (lines 5077-6985)
PLATFORM = "part:printingPlatform_converted.stl"


def _program() -> list[bytes]:
    """Layers 1-8 of model_1, ending the program there."""
    lines = corpus_path("multiaxis_3dp_motionplanning", "model_1_Gcode.txt").read_bytes().splitlines(keepends=True)
    return lines[:LAYER_9 - 1] + [b"G0 Z93.300 F4750\n", b"M30\n"]


def _check(lines: list[bytes], **options) -> dict[int, list[str]]:
    corpus_path("multiaxis_3dp_motionplanning", "extruderHead_converted.stl")
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(b"".join(lines)), out, config=RECIPE, check=True, quiet=True, **options)
    assert out.getvalue() == b"".join(lines)  # --check: the program as it came
    return {c["line"]: c["bodies"] for c in report.collisions}


def _words(line: bytes) -> dict[str, float]:
    return {w[0]: float(w[1:]) for w in line.decode().split() if w[0] in "XYZBCE"}


def _block(words: np.ndarray, letters, e: float | None) -> bytes:
    order = {letter: value for letter, value in zip(letters, words)}
    text = "G1 " + " ".join(f"{a}{order[a]:.3f}" for a in "XYZBC")
    return (text + (f" E{e:.3f}" if e is not None else "") + "\n").encode()


@pytest.fixture(scope="module")
def baseline():
    return _check(_program())


@pytest.mark.heavy
def test_the_platform_raised_into_the_first_layer_is_hit_where_the_nozzle_goes_below_its_top():
    lines = _program()
    profile = load_profile("multiaxis-3dp-bc")
    kin = profile.kinematics
    platform = str(corpus_path("multiaxis_3dp_motionplanning", "printingPlatform_converted.stl"))
    hits = _check(lines, platform=platform + "@translate=0,0,1.5")
    top = -0.5 + 1.5  # the profile puts the platform's top at z = -0.5; raised 1.5 mm
    solid = load_parts(ncfix.config.Options(platform=platform + "@translate=0,0,1.5"), profile)[0].mesh
    below, above, tips = set(), set(), {}
    state: dict[str, float] = {}
    prev_z = prev_words = None
    for number, line in enumerate(lines, start=1):
        if not line.startswith((b"G0", b"G1")) or number < 11:
            if line.startswith(b"G0"):
                state.update(_words(line))
            continue
        state.update(_words(line))
        if not any(a in _words(line) for a in "XYZBC"):
            continue  # an extruder move only
        words = np.array([[state[a] for a in kin.letters]])
        P, _, _ = kin.forward(words, tcp=False)
        z = float(P[0, 2])
        tips[number] = P[0]
        if prev_z is not None and min(prev_z, z) > top + 0.5 and number < 1801:
            # layers 1-2: a move whose ends are a pitch or more above the top, not a C flip
            # (whose machine-interpolated loop runs far from its chord)
            t = np.linspace(0.0, 1.0, 41)[:, None]
            path, _, _ = kin.forward(prev_words + t * (words[0] - prev_words), tcp=False)
            length = np.linalg.norm(np.diff(path, axis=0), axis=1).sum()
            if length < 2 * np.linalg.norm(path[-1] - path[0]) + 1.0:
                above.add(number)
        prev_z, prev_words = z, words[0]
    # the tip inside the raised platform (its top face has a hole of 2 mm radius at the centre)
    numbers = sorted(tips)
    inside = solid.contains(np.array([tips[n] for n in numbers]))
    below = {n for n, k in zip(numbers, inside) if k}
    flagged = {line for line, bodies in hits.items() if PLATFORM in bodies}
    assert below and below <= flagged  # the tip inside the platform: every such block
    # blocks a pitch above the raised top at both ends are not hit by it (the head is above its tip)
    assert above and not flagged & above, sorted(flagged & above)[:20]


@pytest.mark.heavy
def test_a_travel_through_the_printed_part_and_a_tilted_stretch_are_flagged_at_their_lines(baseline):
    lines = _program()
    profile = load_profile("multiaxis-3dp-bc")
    kin = profile.kinematics
    letters = kin.letters
    # The stretch: each block keeps its point P, its tool axis turned 60° toward the part's axis.
    state: dict[str, float] = {}
    previous = None
    for number, line in enumerate(lines, start=1):
        if not line.startswith((b"G0", b"G1")):
            continue
        state.update(_words(line))
        if number in STRETCH:
            words = np.array([[state[a] for a in letters]])
            P, N, _ = kin.forward(words, tcp=False)
            P, N = P[0], N[0]
            inward = -np.array([P[0], P[1], 0.0])
            inward -= (inward @ N) * N
            inward /= np.linalg.norm(inward)
            tilted = math.cos(math.radians(60)) * N + math.sin(math.radians(60)) * inward
            new = kin.inverse(P, tilted, previous if previous is not None else words[0], tcp=False)
            e = _words(line).get("E")
            lines[number - 1] = _block(new, letters, e)
            previous = new
        else:
            previous = np.array([state[a] for a in letters]) if all(a in state for a in letters) else previous
    # The travel: from beside the part at mid-height straight through it (B = C = 0).
    mid = 2.8
    travel = [kin.inverse(np.array([x, 0.0, mid]), np.array([0.0, 0.0, 1.0]), np.zeros(5), tcp=False)
              for x in (-70.0, 70.0)]
    end = len(lines) - 2
    lines[end:end] = [b"G0 Z93.300 F4750\n",
                      f"G0 X{travel[0][0]:.3f} Y{travel[0][1]:.3f} B0 C0 F5250\n".encode(),
                      f"G0 Z{travel[0][2]:.3f} F4750\n".encode(),
                      f"G0 X{travel[1][0]:.3f} Y{travel[1][1]:.3f} Z{travel[1][2]:.3f} F5250\n".encode()]
    through = end + 4
    hits = _check(lines)
    new = {line for line in hits if line not in baseline}
    assert set(STRETCH) <= set(hits)  # every tilted block
    assert through in new and "deposit" in hits[through]  # the travel through the part
    assert end + 3 not in hits  # its descent beside the part is free
    # nothing else newly flagged: the tilted stretch, the block that turns back from it, the travel
    assert new <= set(STRETCH) | {STRETCH[-1] + 1, through}


@pytest.mark.heavy
@pytest.mark.parametrize("head", ["extruderHead_converted.stl", "extruderHead_original_converted.stl"])
def test_the_whole_program_flags_nothing_with_either_head(head):
    """The program printed: the recipe flags none of its blocks, with either of its heads."""
    lines = corpus_path("multiaxis_3dp_motionplanning", "model_1_Gcode.txt").read_bytes().splitlines(keepends=True)
    hits = _check(lines, head=str(corpus_path("multiaxis_3dp_motionplanning", head)))
    assert not hits, sorted(hits)[:20]
