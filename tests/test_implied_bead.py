"""The bead a program's extrusion implies (--filament-diameter; docs/deposit.md "The bead the program
implies"): E per mm of path, the layer height from the path, the width they give by volume
conservation, reported next to the stated bead, never used as it.

Synthetic programs with a known E per mm, layer height and width: flat layers of parallel lines
(with plunges and travels between them, which do not count), the same layers tilted 30° with
the tool axis normal to them (the height is measured along the axis), relative and absolute E.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest

import ncfix
from ncfix.collision.implied import implied_width
from ncfix.errors import ConfigError

HEAD = Path(__file__).resolve().parents[1] / "samples" / "deposition_head.stl"
FILAMENT = 1.75


def section(width: float, height: float) -> float:
    """A flat bead's section: a rectangle with round ends (the contract's bead)."""
    return height * (width - height) + math.pi * height * height / 4.0


def layers(width: float, height: float, *, tilt_deg: float = 0.0, relative: bool = True, count: int = 6) -> str:
    """``count`` layers ``height`` apart of 10 lines ``width`` apart, each 20 mm long, extruding
    the E per mm of a ``width`` × ``height`` bead from 1.75 mm filament; each layer opens with a
    plunge that extrudes (priming: not a printing move). With ``tilt_deg`` the layers lie in
    planes turned about X and the tool vector is their normal."""
    rate = section(width, height) / (math.pi * FILAMENT ** 2 / 4.0)
    a = math.radians(tilt_deg)
    normal = np.array([0.0, -math.sin(a), math.cos(a)])
    across = np.array([0.0, math.cos(a), math.sin(a)])
    i, j, k = normal
    out = ["G90 G21", "M83" if relative else "M82"]
    e = 0.0

    def at(x: float, y: float, z: float) -> str:
        p = np.array([x, 0.0, 0.0]) + y * across + z * normal
        return f"X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f} I{i:.6f} J{j:.6f} K{k:.6f}"

    for layer in range(count):
        z = height * (layer + 1)
        out.append(f"G0 {at(0.0, 0.0, z + 3.0)}")
        e += 0.5
        out.append(f"G1 {at(0.0, 0.0, z)} E{0.5 if relative else e:.5f} F600")  # a plunge that primes
        for line in range(10):
            y = width * line
            out.append(f"G0 {at(0.0, y, z)}")
            e += 20.0 * rate
            out.append(f"G1 {at(20.0, y, z)} E{20.0 * rate if relative else e:.5f}")
    out.append("M30")
    return "\n".join(out) + "\n"


def run(text: str, **options):
    options = {"head": str(HEAD), "check": True, "quiet": True, "standoff": 0.0, **options}
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(text.encode()), out, **options)
    assert out.getvalue() == text.encode()
    return report


@pytest.mark.parametrize("width, height", [(0.5, 0.3), (1.0, 0.64), (0.45, 0.2)])
def test_flat_layers_give_back_their_width_and_height(width, height):
    report = run(layers(width, height), bead_width=width, bead_height=height, filament_diameter=FILAMENT)
    implied = report.summary["implied_bead"]
    rate = section(width, height) / (math.pi * FILAMENT ** 2 / 4.0)
    assert implied["e_per_mm"]["median"] == pytest.approx(rate, rel=2e-3)
    assert implied["e_per_mm"]["p95"] == pytest.approx(rate, rel=2e-3)
    assert implied["layer_height_mm"] == pytest.approx(height, abs=1e-3)
    assert implied["layer_height_samples"] >= 50 // 4  # every fourth line end above the first layer
    assert implied["width_mm"]["median"] == pytest.approx(width, rel=5e-3)
    assert implied["printing_path_mm"] == pytest.approx(6 * 10 * 20.0)  # the plunges are not printing
    assert implied["stated"] == {"width_mm": width, "height_mm": height}
    assert any(note.startswith("implied bead (1.75 mm filament)") and f"{implied['width_mm']['median']:.3f} (95%" in note
               for note in report.notes)
    assert not report.warnings


def test_the_height_is_measured_along_the_tool_axis_on_tilted_layers():
    report = run(layers(0.6, 0.4, tilt_deg=30.0), bead_width=0.6, bead_height=0.4, filament_diameter=FILAMENT)
    implied = report.summary["implied_bead"]
    assert implied["layer_height_mm"] == pytest.approx(0.4, abs=1e-3)
    assert implied["width_mm"]["median"] == pytest.approx(0.6, rel=5e-3)


def test_a_fix_run_measures_as_a_check_does():
    text = layers(0.6, 0.4, tilt_deg=30.0, count=8)
    check = run(text, filament_diameter=FILAMENT, window=16).summary["implied_bead"]
    out = io.BytesIO()
    fix = ncfix.process(io.BytesIO(text.encode()), out, head=str(HEAD), quiet=True, standoff=0.0,
                        filament_diameter=FILAMENT).summary["implied_bead"]
    assert fix == check


def test_absolute_and_relative_extrusion_give_the_same_answer():
    a = run(layers(0.5, 0.3, relative=True), filament_diameter=FILAMENT).summary["implied_bead"]
    b = run(layers(0.5, 0.3, relative=False), filament_diameter=FILAMENT).summary["implied_bead"]
    assert a["width_mm"] == pytest.approx(b["width_mm"], rel=2e-3)
    assert a["layer_height_mm"] == b["layer_height_mm"]


def test_disagreement_is_a_warning_and_never_changes_the_bead_model():
    text = layers(1.0, 0.64)
    narrow = run(text, bead_width=0.6, bead_height=0.64, filament_diameter=FILAMENT)
    assert any("wider than the stated 0.6 mm" in w for w in narrow.warnings), narrow.warnings
    wide = run(text, bead_width=2.5, bead_height=0.64, filament_diameter=FILAMENT)
    assert any("more than 2 times" in w and "bead width 2.5" in w for w in wide.warnings), wide.warnings
    low = run(text, bead_width=1.0, bead_height=0.3, filament_diameter=FILAMENT)
    assert any("more than the stated bead height 0.3" in w for w in low.warnings), low.warnings
    # the model is the stated bead whatever the derivation says: the same collisions either way
    # (with no tip allowance the nozzle's tip meets the beads it lays on, so there are some)
    for options in ({"bead_width": 0.6, "bead_height": 0.64}, {"bead_width": 2.5, "bead_height": 0.64}):
        with_d = run(text, tip_allowance=0.0, filament_diameter=FILAMENT, **options)
        without = run(text, tip_allowance=0.0, **options)
        assert without.collisions and with_d.collisions == without.collisions
        assert "implied_bead" not in without.summary
        assert not any("implied" in note for note in without.notes)


def test_no_extrusion_words_and_no_layer_below_are_said_so():
    flat = "G90\nG0 X0 Y0 Z1 I0 J0 K1\nG1 X20 Y0 Z1 F600\nG1 X20 Y5 Z1\nM30\n"
    report = run(flat, filament_diameter=FILAMENT)
    assert report.summary["implied_bead"]["e_per_mm"] is None
    assert any("no printing move with growing E" in note for note in report.notes)
    one = run(layers(0.5, 0.3, count=1), filament_diameter=FILAMENT)
    implied = one.summary["implied_bead"]
    assert implied["e_per_mm"] is not None and implied["layer_height_mm"] is None and implied["width_mm"] is None
    assert any("no layer height found" in note for note in one.notes)


def test_the_width_formula_is_the_flat_bead_and_a_round_strand_below_it():
    h = 0.4
    for w in (0.4, 0.6, 1.5):
        assert implied_width(section(w, h), h) == pytest.approx(w)
    thin = math.pi * 0.15 ** 2  # a round strand 0.3 mm across: less than the round of the height
    assert implied_width(thin, h) == pytest.approx(0.3)


def test_the_option_is_checked_and_read_from_the_config(tmp_path):
    text = layers(0.5, 0.3, count=2)  # two layers: a layer height and a width to read back
    with pytest.raises(ConfigError, match="filament-diameter"):
        run(text, filament_diameter=0)
    config = tmp_path / "ncfix.toml"
    config.write_text("[ncfix]\nfilament_diameter = 1.75\nbead_width = 0.5\nbead_height = 0.3\n")
    report = run(text, config=config)
    assert report.summary["implied_bead"]["filament_diameter_mm"] == 1.75
    assert report.summary["implied_bead"]["width_mm"]["median"] == pytest.approx(0.5, rel=5e-3)
    # with a part (read once before the run for its box), measured once: the same figures
    mold = str(HEAD.parent / "recreated_mold.stl")
    with_part = run(text, config=config, part=[mold]).summary["implied_bead"]
    assert with_part == report.summary["implied_bead"]
