"""The orientation graph: cheapest smooth path around obstacles, anchored to the programmed orientation."""

from __future__ import annotations

import numpy as np

from ncfix.correct.candidates import cap_pattern, candidates_around
from ncfix.correct.graph import cheapest_path
from ncfix.geometry.frames import angle_between_deg


def test_cap_pattern_covers_the_cap_at_its_resolution():
    pattern = cap_pattern(30.0, 2.0)
    assert np.allclose(np.linalg.norm(pattern, axis=1), 1.0) and np.allclose(pattern[0], [0, 0, 1])
    tilt = np.degrees(np.arccos(pattern[:, 2]))
    assert tilt.max() <= 30.0 + 1e-9
    # every direction of the cap is within 2° of a candidate
    rng = np.random.default_rng(0)
    t = np.radians(rng.uniform(0, 30, 2000))
    a = rng.uniform(0, 2 * np.pi, 2000)
    probe = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    nearest = np.degrees(np.arccos(np.clip(probe @ pattern.T, -1, 1))).min(axis=1)
    assert nearest.max() < 2.0


def test_candidates_are_turned_onto_the_programmed_vectors():
    programmed = np.array([[0, 0, 1.0], [np.sin(0.3), 0, np.cos(0.3)]])
    cands = candidates_around(programmed, cap_pattern(10.0, 5.0))
    assert np.allclose(cands[:, 0], programmed)
    dev = angle_between_deg(cands, programmed[:, None, :])
    assert dev.max() <= 10.0 + 1e-9


def obstacle_case(levels=40, blocked=range(15, 25), need_deg=8.0):
    programmed = np.tile([0.0, 0.0, 1.0], (levels, 1))
    cands = candidates_around(programmed, cap_pattern(30.0, 1.0))
    tilt_x = np.degrees(np.arctan2(cands[..., 0], cands[..., 2]))
    free = np.ones(cands.shape[:2], dtype=bool)
    for level in blocked:
        free[level] = tilt_x[level] > need_deg  # only tilting toward +X by more than need_deg is free
    return programmed, cands, free


def test_path_avoids_the_obstacle_with_small_steps_and_comes_back():
    programmed, cands, free = obstacle_case()
    path = cheapest_path(cands, free, programmed, max_step_deg=2.0)
    assert path is not None
    chosen = cands[np.arange(len(path)), path]
    assert free[np.arange(len(path)), path].all()
    steps = angle_between_deg(chosen[1:], chosen[:-1])
    assert steps.max() <= 2.0 + 1e-9
    assert path[0] == 0 and path[-1] == 0  # anchored at both ends
    dev = angle_between_deg(chosen, programmed)
    assert dev[15:25].min() > 8.0 and dev.max() < 12.0  # just enough
    assert (dev[:5] == 0).all() and (dev[-5:] == 0).all()  # far blocks untouched


def test_no_path_when_the_ramp_is_too_short_for_the_step_limit():
    programmed, cands, free = obstacle_case(levels=8, blocked=range(3, 5), need_deg=8.0)
    assert cheapest_path(cands, free, programmed, max_step_deg=2.0) is None


def test_no_path_when_nothing_is_free():
    programmed, cands, free = obstacle_case()
    free[20] = False
    assert cheapest_path(cands, free, programmed, max_step_deg=2.0) is None
