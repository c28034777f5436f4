"""The graph's objective on a whole program (``ncfix.correct.cost``): the bench's yardstick."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from ncfix.correct.cost import path_cost, program_vectors, steps_deg
from ncfix.correct.graph import DEVIATION_WEIGHT, LIMIT_SLACK, LayeredGraph
from ncfix.geometry.frames import angle_between_deg, turn_rotations
from ncfix.profiles import load_profile


def _vec(tilt_deg, azimuth_deg):
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    return np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])


def test_a_program_left_as_posted_costs_nothing():
    rng = np.random.default_rng(3)
    programmed = np.array([_vec(t, a) for t, a in zip(rng.uniform(0, 40, 30), rng.uniform(0, 360, 30))])
    cost = path_cost(programmed, programmed, 5.0)
    assert cost.added_variation_deg == pytest.approx(0.0, abs=1e-9)
    assert cost.deviation_deg == 0.0 and cost.total_deg == pytest.approx(0.0, abs=1e-9)
    assert path_cost(programmed[:0], programmed[:0], 5.0).total_deg == 0.0


def test_one_tilted_block_costs_its_steps_in_and_out_and_its_weighted_tilt():
    programmed = np.tile([0.0, 0.0, 1.0], (5, 1))
    output = programmed.copy()
    output[2] = _vec(5.0, 30.0)
    cost = path_cost(programmed, output, 2.0)
    assert cost.added_variation_deg == pytest.approx(10.0)
    assert cost.deviation_deg == pytest.approx(5.0)
    assert cost.total_deg == pytest.approx(10.0 + DEVIATION_WEIGHT * 5.0)


def test_where_the_program_turns_a_correction_kept_around_the_corner_adds_no_step():
    """The program turns 28° a block (over θ = 5°); the output leans 5° further from +Z at every
    block, turning as the program turns: the graph's turned steps are 0, only the lean costs."""
    programmed = np.array([_vec(20.0, a) for a in (0.0, 90.0, 180.0)])
    output = np.array([_vec(25.0, a) for a in (0.0, 90.0, 180.0)])
    assert angle_between_deg(programmed[1:], programmed[:-1]).min() > 5.0
    cost = path_cost(programmed, output, 5.0)
    assert cost.added_variation_deg == pytest.approx(0.0, abs=1e-9)
    assert cost.deviation_deg == pytest.approx(15.0)
    # Measured plainly (θ above the program's turns) the same lean changes the steps.
    assert abs(path_cost(programmed, output, 60.0).added_variation_deg) > 1.0


def test_mismatched_programs_are_refused():
    with pytest.raises(ValueError, match="2 output vectors for 3"):
        path_cost(np.tile([0.0, 0.0, 1.0], (3, 1)), np.tile([0.0, 0.0, 1.0], (2, 1)), 2.0)


def _brute_force(cands, programmed, theta, weight=DEVIATION_WEIGHT):
    """(least path_cost, its middle vertices) over every path of candidates 1.. at the middle
    levels and the programmed orientation at both ends, each step within θ."""
    levels, k = cands.shape[:2]
    best, arg = np.inf, None
    for middle in itertools.product(range(1, k), repeat=levels - 2):
        chosen = cands[np.arange(levels), [0, *middle, 0]]
        if (steps_deg(chosen, programmed, theta) <= theta * LIMIT_SLACK).all():
            total = path_cost(programmed, chosen, theta, weight).total_deg
            if total < best:
                best, arg = total, middle
    return best, arg


@pytest.mark.parametrize("turning", [False, True])
def test_the_graphs_cheapest_path_is_the_least_cost_path(turning):
    """The yardstick is the graph's own objective: among every path within the step limits, the
    one ``LayeredGraph.cheapest`` picks has the least ``path_cost`` (brute force over 6³ paths)."""
    rng = np.random.default_rng(11)
    theta = 6.0
    azimuths = (0.0, 50.0, 100.0, 150.0, 200.0) if turning else (0.0,) * 5
    tilt = 15.0 if turning else 0.0
    programmed = np.array([_vec(tilt, a) for a in azimuths])
    levels, k = len(programmed), 6
    cands = np.zeros((levels, k, 3))
    for level in range(levels):
        cands[level, 0] = programmed[level]
        for j in range(1, k):
            cands[level, j] = _vec(tilt + rng.uniform(-6, 6), azimuths[level] + rng.uniform(-12, 12))
    if not turning:
        # Two ways round, one smooth and far (4° three times), one near and jumpy (2° with a 4°
        # swing): which is cheaper depends on the deviation weight; the others lean 5-6°.
        cands[1:4, 3:] = [[_vec(rng.uniform(5, 6), rng.uniform(0, 360)) for _ in range(3)] for _ in range(3)]
        cands[1:4, 1] = _vec(4.0, 0.0)
        cands[1:4, 2] = [_vec(2.0, 0.0), _vec(2.0, 180.0), _vec(2.0, 0.0)]
    valid = np.ones((levels, k), dtype=bool)
    valid[[0, -1], 1:] = False  # both ends anchored to the programmed orientation
    allowed = valid.copy()
    allowed[1:-1, 0] = False  # as programmed, the middle blocks collide
    turns = None
    if turning:
        turns = np.concatenate([np.eye(3)[None], turn_rotations(programmed)])
        assert (angle_between_deg(programmed[1:], programmed[:-1]) > theta).all()
    path = LayeredGraph(cands, valid, programmed, theta, turns=turns).cheapest(allowed)
    assert path is not None
    best, arg = _brute_force(cands, programmed, theta)
    assert np.isfinite(best)
    assert path_cost(programmed, cands[np.arange(levels), path], theta).total_deg == pytest.approx(best, abs=1e-9)
    assert tuple(path[1:-1]) == arg
    if not turning:  # the weight decides between the ways here (a weight of 5 picks another)
        assert _brute_force(cands, programmed, theta, 5.0)[1] != arg


def test_program_vectors_reads_motion_blocks_as_ncfix_does():
    ijk = b"%\nG90 G43.5 H1\nG1 X0 Y0 Z5 I0 J0 K1 F600\n(a comment)\nG1 X1 I0.6 K0.8\nG1 X2\nM30\n"
    lines, n = program_vectors(ijk, load_profile("ijk"))
    assert lines.tolist() == [3, 5, 6]
    assert np.allclose(n, [[0, 0, 1], [0.6, 0, 0.8], [0.6, 0, 0.8]])
    table = b"G1 X0 Y0 Z5 A0 C0 F600\nG1 A30 C90\n"
    lines, n = program_vectors(table, load_profile("table-ac"))
    assert lines.tolist() == [1, 2]
    s = np.sin(np.radians(30.0))  # N = (sin A sin C, -sin A cos C, cos A)
    assert np.allclose(n[1], [s, 0.0, np.cos(np.radians(30.0))], atol=1e-12)
