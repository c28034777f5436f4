"""The ``--strategy epa`` correction: offset ramps, and whole runs through the pipeline checked exactly."""

from __future__ import annotations

import io
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix.correct.strategies as strategies
from ncfix.config import EpaOptions, Options
from ncfix.correct.epa_strategy import DEFAULT_VARIANT, EpaStrategy, fill_offsets, keep_chain
from ncfix.errors import ConfigError
from ncfix.geometry.frames import angle_between_deg, rotation_from_z
from ncfix.geometry.mesh import load_head
from ncfix.nc.post import post_program
from ncfix.pipeline import run
from ncfix.profiles import load_profile
from ncfix.reference import ExactReference

REPO = Path(__file__).resolve().parents[1]
HEAD = REPO / "samples" / "deposition_head.stl"
STANDOFF_MM = 6.0  # Options' default: the tip is 6 mm along N from the programmed point
PITCH_MM = 0.5
WORD = re.compile(r"([XYZIJK])(-?\d+(?:\.\d*)?)")


# ---- offsets ---------------------------------------------------------------------------------


def _steps(d: np.ndarray, points: dict[int, np.ndarray], L: int) -> np.ndarray:
    """(L + 1,) change of the offsets into each level and into the row after (anchors included)."""
    chain = np.vstack([points.get(-1, d[0])[None], d, points.get(L, d[-1])[None]])
    return np.linalg.norm(np.diff(chain, axis=0), axis=1)


def test_long_gaps_ramp_down_to_exactly_the_programmed_orientation():
    L = 20
    points = {-1: np.zeros(2), 5: np.array([0.03, 0.0]), 14: np.array([0.0, -0.02]), L: np.zeros(2)}
    budgets = np.full(L + 1, 0.01)
    d, conflict = fill_offsets(points, budgets, L)
    assert conflict is None
    assert np.array_equal(d[5], points[5]) and np.array_equal(d[14], points[14])
    norms = np.linalg.norm(d, axis=1)
    assert np.allclose(norms[2:9], [0.0, 0.01, 0.02, 0.03, 0.02, 0.01, 0.0], atol=1e-15)
    assert not norms[:3].any() and not norms[8:13].any() and not norms[17:].any()  # exact zeros
    assert (_steps(d, points, L) <= budgets + 1e-15).all()


def test_short_gaps_take_a_bent_path_of_full_steps():
    L = 6
    points = {1: np.array([0.05, 0.0]), 4: np.array([0.0, 0.05])}
    budgets = np.full(L + 1, 0.03)  # 0.09 between them: more than the chord 0.0707, less than 0.1
    d, conflict = fill_offsets(points, budgets, L)
    assert conflict is None
    steps = _steps(d, points, L)[2:5]
    # full steps along the path (exactly as long as the steps allow): the chord across the bend is shorter
    assert np.allclose(steps[[0, 2]], 0.03, atol=1e-9) and 0.0 < steps[1] < 0.03
    assert (np.linalg.norm(d, axis=1) <= 0.05 + 1e-15).all()
    # beyond the fixed levels, with nothing to anchor them, ramps down at full steps
    assert np.allclose(np.linalg.norm(d[[0, 5]], axis=1), 0.02)


def test_fixed_offsets_too_far_apart_are_a_conflict():
    points = {2: np.array([0.05, 0.0]), 4: np.array([-0.05, 0.0])}
    d, conflict = fill_offsets(points, np.full(8, 0.04), 7)
    assert conflict == (2, 4) and not d.any()
    assert fill_offsets({}, np.full(8, 0.04), 7) == (pytest.approx(np.zeros((7, 2))), None)


@pytest.mark.parametrize("seed", range(20))
def test_random_fixed_offsets_are_joined_within_the_steps(seed):
    rng = np.random.default_rng(seed)
    L = int(rng.integers(3, 30))
    budgets = rng.uniform(0.0, 0.05, L + 1)
    # fixed offsets on a walk that respects the budgets, so a solution exists
    walk = np.cumsum(rng.normal(size=(L + 2, 2)) * budgets.mean(), axis=0)
    walk -= walk[0]
    for j in range(1, L + 2):
        step = walk[j] - walk[j - 1]
        n = np.linalg.norm(step)
        walk[j] = walk[j - 1] + (step * budgets[j - 1] / n if n > budgets[j - 1] else step)
    keys = sorted(set(rng.choice(np.arange(-1, L + 1), size=int(rng.integers(1, 6)))))
    points = {int(k): walk[k + 1] for k in keys}
    d, conflict = fill_offsets(points, budgets, L)
    assert conflict is None
    for k, v in points.items():
        if 0 <= k < L:
            assert np.array_equal(d[k], v)
    assert (_steps(d, points, L) <= budgets + 1e-9).all()
    assert np.linalg.norm(d, axis=1).max() <= max(np.linalg.norm(v) for v in points.values()) + 1e-12


def test_opposite_runs_at_a_sharp_turn_keep_whole_runs():
    # Runs of 7 levels tilted 10° one way, then the other, then back, one level apart; steps of
    # 2°: joining +10° and -10° takes 10 steps, so of two neighbouring runs only one can stay.
    deg = np.radians
    values = [(deg(10), 0.0)] * 7 + [(-deg(10), 0.0)] * 7 + [(deg(9), 0.0)] * 7
    levels = list(range(7)) + list(range(8, 15)) + list(range(16, 23))
    keep = keep_chain(values, [deg(2) * k for k in levels], [False] * 21, [1] * 21)
    assert keep.tolist() == [True] * 7 + [False] * 7 + [True] * 7


def test_chains_go_through_the_levels_that_must_stay():
    deg = np.radians
    # anchors at 0 on both ends: the 5° level 2° of steps from the first cannot stay, the 3° one
    # 3° of steps from each can
    values = [(0.0, 0.0), (deg(5), 0.0), (deg(3), 0.0), (0.0, 0.0)]
    at = [0.0, deg(2), deg(3), deg(6)]
    assert keep_chain(values, at, [True, False, False, True], [0, 1, 1, 0]).tolist() == [True, False, True, True]
    # two levels that must stay but cannot be joined: no chain
    assert not keep_chain([(0.0, 0.0), (deg(9), 0.0)], [0.0, deg(2)], [True, True], [0, 0]).any()


def test_options_choose_the_variant():
    assert EpaStrategy(Options()).variant == DEFAULT_VARIANT == "lami"
    assert EpaStrategy(replace(Options(), epa=EpaOptions(variant="fixed"))).variant == "fixed"
    with pytest.raises(ConfigError, match="unknown EPA variant 'best'.*fixed, lami"):
        EpaStrategy(replace(Options(), epa=EpaOptions(variant="best")))
    strategy = EpaStrategy(Options())
    assert strategy.name == "epa" and strategy.model is None  # built on the first solve


# ---- through the pipeline ----------------------------------------------------------------------


@pytest.fixture
def made(monkeypatch, tmp_path):
    """The EpaStrategy objects the pipeline makes (``strategies.make_strategy``), and CoACD's
    cache goes to a fresh folder."""
    monkeypatch.setenv("NCFIX_CACHE", str(tmp_path / "coacd"))
    out: list[EpaStrategy] = []
    original = strategies.make_strategy

    def make_strategy(options):
        if options.strategy != "epa":
            return original(options)
        out.append(EpaStrategy(options))
        return out[-1]

    monkeypatch.setattr(strategies, "make_strategy", make_strategy)
    return out


@pytest.fixture(scope="module")
def head():
    return load_head(HEAD).mesh


def _run(data: bytes, **kw):
    options = replace(Options(head=str(HEAD), strategy="epa", device="cpu"), **kw)
    out = io.BytesIO()
    report = run(io.BytesIO(data), out, options, "test.nc")
    return out.getvalue(), report


def _poses(data: bytes) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Motion blocks of an ijk program: 1-based lines, points (n, 3), unit tool vectors (n, 3)."""
    lines, P, N = [], [], []
    for i, line in enumerate(data.decode().splitlines()):
        words = dict(WORD.findall(line))
        if set("XYZIJK") <= set(words):
            lines.append(i + 1)
            P.append([float(words[k]) for k in "XYZ"])
            N.append([float(words[k]) for k in "IJK"])
    N = np.array(N)
    return lines, np.array(P), N / np.linalg.norm(N, axis=1, keepdims=True)


def _check(data: bytes, out: bytes, report, *, max_tilt: float, max_step: float, free_from: int = 0,
           is_free=None) -> np.ndarray:
    """Every contract of a correction, on the written program: unchanged lines are byte for byte
    the input's (and exactly the lines not in report.changes), tips stay put (--pivot tip),
    tilts within Θ, steps within θ wherever the program's own step was, and the motion blocks from
    index ``free_from`` on free by ``is_free(C, R)``. Returns the tilts (degrees)."""
    before, after = data.decode().splitlines(), out.decode().splitlines()
    assert len(before) == len(after)
    differ = {i + 1 for i, (a, b) in enumerate(zip(before, after)) if a != b}
    assert differ == {c["line"] for c in report.changes}
    lines, P0, N0 = _poses(data)
    lines_out, P1, N1 = _poses(out)
    assert lines == lines_out
    C0, C1 = P0 + STANDOFF_MM * N0, P1 + STANDOFF_MM * N1
    assert np.abs(C1 - C0).max() < 2e-3  # the words' rounding
    tilt = angle_between_deg(N1, N0)
    assert tilt.max() <= max_tilt + 1e-3
    own = angle_between_deg(N0[1:], N0[:-1])
    step = angle_between_deg(N1[1:], N1[:-1])
    assert (step[own <= max_step] <= max_step + 1e-3).all()
    if is_free is not None:
        R = rotation_from_z(N1)
        stuck = [lines[k] for k in range(free_from, len(lines)) if not is_free(C1[k], R[k])]
        assert stuck == []
    return tilt


def _pass_program(vectors=None) -> tuple[bytes, trimesh.Trimesh]:
    """A pass along x at y = 0 (21 blocks, 10 mm apart) and a box wall whose lower edge the head's
    body (56 mm wide, from 25 mm above the tip) meets 6 mm deep over 8 blocks."""
    xs = np.arange(-100.0, 100.0 + 1e-9, 10.0)
    P = np.column_stack([xs, np.zeros_like(xs), np.full_like(xs, 2.0)])
    N = np.tile([0.0, 0.0, 1.0], (len(xs), 1)) if vectors is None else vectors
    data = "".join(post_program(load_profile("ijk"), P, N, title="epa test")).encode()
    return data, trimesh.creation.box(bounds=[[-10.0, 22.0, 30.0], [10.0, 40.0, 60.0]])


def _part_free(head, wall):
    ref = ExactReference(head, {"wall": wall})
    return lambda C, R: ref.clearance(C, R)[0] > -1e-3


def test_a_wall_beside_the_pass_is_avoided_by_both_variants(made, head, tmp_path):
    data, wall = _pass_program()
    wall.export(tmp_path / "wall.stl")
    limits = dict(max_tilt=15.0, max_step=3.0)
    for variant in ("lami", "fixed"):
        out, report = _run(data, part=(str(tmp_path / "wall.stl"),), bead_radius=0.0,
                           epa=EpaOptions(variant=variant), **limits)
        strategy = made[-1]
        assert strategy.variant == variant
        assert report.exit_code == 0 and report.summary["unresolved_blocks"] == 0
        collided = {c["line"] for c in report.collisions}
        assert len(collided) == 8 and all(c["bodies"] == ["part:wall.stl"] for c in report.collisions)
        changed = {c["line"]: c for c in report.changes}
        assert collided <= set(changed) and all(changed[line]["reason"] == "collision" for line in collided)
        tilt = _check(data, out, report, is_free=_part_free(head, wall), **limits)
        assert 5.0 < tilt.max() <= 15.0 + 1e-3
        # the model: built on the first solve, CoACD run once then read from the cache
        assert strategy.model is not None and strategy.pieces_count >= 1
        assert strategy.cached is (variant != "lami")
        # a cold decomposition is told with its time (the summary prints the notes); a cached one is not
        if variant == "lami":
            assert len(report.notes) == 1
            assert re.fullmatch(r"CoACD: part:wall\.stl cut into \d+ convex pieces in \d+\.\d\d s "
                                r"\(not cached before this run\)", report.notes[0])
        else:
            assert report.notes == []
        assert strategy.episodes == 1 and strategy.last["unresolved"] == 0
        print(f"\nepa {variant}: {strategy.last}, decomposition {strategy.decompose_seconds:.3f} s")


def test_steps_stay_within_the_limit_on_a_turning_program(made, head, tmp_path):
    # The program leans 2° more each block (θ = 3°: little room left), then turns by 34° at
    # once (a step above θ: kept, and measured as the program turns).
    lean = np.radians(np.clip(2.0 * (np.arange(21) - 10), -20.0, 20.0))
    N = np.column_stack([np.sin(lean), np.zeros_like(lean), np.cos(lean)])
    N[14:] = [np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))]
    data, wall = _pass_program(N)
    wall.export(tmp_path / "wall.stl")
    limits = dict(max_tilt=15.0, max_step=3.0)
    out, report = _run(data, part=(str(tmp_path / "wall.stl"),), bead_radius=0.0, **limits)
    assert report.exit_code == 0 and report.collisions
    _check(data, out, report, is_free=_part_free(head, wall), **limits)
    print(f"\nepa on a turning program: {made[-1].last}")


def test_no_free_orientation_within_max_tilt_leaves_the_blocks_programmed(made, tmp_path):
    data, wall = _pass_program()
    wall.export(tmp_path / "wall.stl")
    out, report = _run(data, part=(str(tmp_path / "wall.stl"),), bead_radius=0.0, max_tilt=1.0, max_step=0.5)
    assert report.exit_code == 1
    assert out == data and report.changes == []
    assert [u["line"] for u in report.unresolved] == [c["line"] for c in report.collisions]
    reasons = [u["reason"] for u in report.unresolved]
    assert "no free orientation within 1° (--max-tilt)" in reasons[0] and "part:wall.stl" in reasons[0]
    assert all(r and ("--max-tilt" in r or "left colliding" in r) for r in reasons)


def _wall_deposit_program() -> tuple[bytes, np.ndarray, int]:
    """A small wall printed in 6 layers (x from -6 to 6, 2 mm apart, y = 0, 1.5 mm apart; M3 after
    the plunge, M5 after the wall), then a pass beside it at y = 24, low enough for the head's
    body to overhang the wall. Returns the program, the points and the wall's point count."""
    pts = []
    for layer in range(6):
        xs = np.arange(-6.0, 6.0 + 1e-9, 2.0)
        pts += [(x, 0.0, 1.5 * layer) for x in (xs[::-1] if layer % 2 else xs)]
    wall = len(pts)
    pts += [(x, 24.0, -30.0) for x in np.arange(-80.0, 60.0 + 1e-9, 8.0)]
    P = np.array(pts)
    lines = "".join(post_program(load_profile("ijk"), P, np.tile([0.0, 0.0, 1.0], (len(P), 1)),
                                 title="epa deposit test")).splitlines(keepends=True)
    feed = [i for i, line in enumerate(lines) if " X" in line][1:-1]
    lines.insert(feed[wall - 1] + 1, "M5\n")
    lines.insert(feed[0] + 1, "M3\n")
    return "".join(lines).encode(), P, wall


def test_the_head_is_tilted_away_from_what_it_printed(made, head):
    data, P, wall = _wall_deposit_program()
    limits = dict(max_tilt=20.0, max_step=4.0)
    out, report = _run(data, deposit_codes=("M3", "M5"), **limits)
    assert report.collisions and all(c["bodies"] == ["deposit"] for c in report.collisions)
    assert report.exit_code == 0
    # Reference: the wall's beads, sampled densely along its deposit moves.
    beads = np.concatenate([a + np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(b - a) / (PITCH_MM / 8))) + 1)[:, None]
                            * (b - a) for a, b in zip(P[:wall - 1], P[1:wall])])
    ref = ExactReference(head, {}, tip_allowance_mm=1.0)
    first_pass = 1 + wall  # motion blocks: the approach, the wall, then the pass
    _check(data, out, report, free_from=first_pass, is_free=lambda C, R: not ref.bead_collides(C, R, beads, 1.0),
           **limits)
    print(f"\nepa deposit: {made[-1].last}")


def _wall_deposit_solver(monkeypatch):
    """The first episode solver of a fix of ``_wall_deposit_program`` (after it ran)."""
    from ncfix.correct import epa_strategy

    solvers = []
    run = epa_strategy._EpisodeSolver.run
    monkeypatch.setattr(epa_strategy._EpisodeSolver, "run", lambda self: solvers.append(self) or run(self))
    data, _, _ = _wall_deposit_program()
    _run(data, deposit_codes=("M3", "M5"), max_tilt=20.0, max_step=4.0)
    return solvers[0]


def test_walks_run_in_step_get_the_answers_they_get_alone(made, monkeypatch):
    # The required tilts' walks run in step (one Episode.free call per round for all of them):
    # each must ask for and get exactly what it gets alone, in one ball or none, found or not.
    from ncfix.correct import epa_strategy

    solver = _wall_deposit_solver(monkeypatch)
    levels = [int(l) for l in np.nonzero(solver.ep.is_colliding)[0]]
    assert len(levels) >= 4
    asks = ([(l, None, None) for l in levels] + [(l, np.array([0.0, 0.05]), None) for l in levels]
            + [(l, None, [(np.zeros(2), 1e-4)]) for l in levels])  # a ball too small to leave N0
    monkeypatch.setattr(epa_strategy, "TILTS_IN_STEP", 5)  # groups of walks, and a short last one
    tests = solver.ep.tests
    together = solver._searches(asks)
    tests, tests_together = solver.ep.tests, solver.ep.tests - tests
    alone = [solver._search(*ask) for ask in asks]
    assert solver.ep.tests - tests == tests_together > len(asks)
    assert len(together) == len(alone) == len(asks)
    for (found, bodies), (found_alone, bodies_alone) in zip(together, alone):
        assert bodies == bodies_alone
        assert (found is None) == (found_alone is None)
        assert found is None or np.array_equal(found, found_alone)
    kinds = [found is None for found, _ in together]
    assert any(kinds) and not all(kinds)


def test_the_walk_gets_the_rotations_orient_gives(made, monkeypatch):
    # The walk asks for rotations alone (``Episode.rotations``): on a vector machine it skips the
    # words, and must give exactly ``orient``'s rotations, unnormalised vectors included.
    ep = _wall_deposit_solver(monkeypatch).ep
    rng = np.random.default_rng(2)
    levels = rng.integers(0, len(ep.N0), 64)
    N = ep.N0[levels] + rng.normal(0.0, 0.3, (64, 3))
    N *= rng.uniform(0.5, 3.0, (64, 1))
    assert ep.is_vector and np.array_equal(ep.rotations(levels, N), ep.orient(levels, N)[1])


def test_blocks_the_walk_leaves_colliding_are_searched_by_the_graph(made, head, tmp_path, monkeypatch):
    # The walk is greedy: here it is made to find nothing (every tilt search comes back empty),
    # so it leaves the wall's 8 blocks as programmed; the orientation graph then searches the
    # episode, frees them all, and its answer is kept. With the fallback off they stay.
    from ncfix.correct import epa

    def no_tilt(self, C, N0, rotation_of, *, max_tilt_deg, **kw):
        return epa.TiltResult(None, max_tilt_deg, 0, ["part:wall.stl"])
        yield  # a walk that asks nothing

    monkeypatch.setattr(epa.EpaModel, "tilt_steps", no_tilt)
    data, wall = _pass_program()
    wall.export(tmp_path / "wall.stl")
    limits = dict(max_tilt=15.0, max_step=3.0)
    part = (str(tmp_path / "wall.stl"),)

    out, report = _run(data, part=part, bead_radius=0.0, epa=EpaOptions(graph_fallback=False), **limits)
    assert report.exit_code == 1 and len(report.unresolved) == 8 and out == data
    assert made[-1].graph is None and made[-1].last["left_by_epa"] == 8

    out, report = _run(data, part=part, bead_radius=0.0, **limits)
    strategy = made[-1]
    assert strategy.last["left_by_epa"] == 8 and strategy.last["by_graph"] is True
    assert strategy.graph_episodes == strategy.graph_kept == 1
    assert report.exit_code == 0 and report.summary["unresolved_blocks"] == 0
    assert {c["line"] for c in report.collisions} <= {c["line"] for c in report.changes}
    _check(data, out, report, is_free=_part_free(head, wall), **limits)


def test_the_graph_fallback_takes_true_or_false():
    with pytest.raises(ConfigError, match="graph_fallback"):
        EpaStrategy(replace(Options(), epa=EpaOptions(graph_fallback="yes")))


def test_the_graph_leaves_the_blocks_programmed_where_max_tilt_is_below_its_coarse_spacing(tmp_path):
    # Θ = 1° holds no point of the graph's coarse grid (4 resolutions apart): its first tests
    # are empty (this crashed), and no orientation within 1° frees the wall's blocks.
    data, wall = _pass_program()
    wall.export(tmp_path / "wall.stl")
    out, report = _run(data, part=(str(tmp_path / "wall.stl"),), bead_radius=0.0, strategy="graph",
                       max_tilt=1.0, max_step=0.5)
    assert report.exit_code == 1 and out == data and report.changes == []
    assert [u["line"] for u in report.unresolved] == [c["line"] for c in report.collisions]
    assert "--max-tilt" in report.unresolved[0]["reason"]
