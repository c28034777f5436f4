"""The bundled samples: made by samples/make_samples.py, and labelled as samples/README.md says."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def make_samples():
    spec = importlib.util.spec_from_file_location("make_samples", SAMPLES / "make_samples.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def readme_labels() -> tuple[dict[str, tuple[int, int, int]], dict[str, list[int]]]:
    text = (SAMPLES / "README.md").read_text()
    counts = {m[0]: (int(m[1]), int(m[2]), int(m[3]))
              for m in re.findall(r"^\| `([^`]+)` \| `[^`]+` \| (\d+) \| (\d+) \| (\d+) \|$", text, re.M)}
    lines = {m[0]: [int(x) for x in m[1].split(", ") if x]
             for m in re.findall(r"^- `([^`]+)`: ([\d, ]*)$", text, re.M)}
    return counts, lines


def test_programs_are_made_deterministically(tmp_path):
    module = make_samples()
    module.write_programs((273,), out=tmp_path)
    module.write_deposit_program(out=tmp_path)
    for path in tmp_path.iterdir():
        assert path.read_bytes() == (SAMPLES / path.name).read_bytes(), path.name


def sample_cases():
    return [pytest.param(*case, id=case[0]) for case in make_samples().SAMPLES]


@pytest.mark.heavy  # the exact reference at every block of a sample: 15-45 s each on the small ones
@pytest.mark.parametrize("name, machine, parts, codes", sample_cases())
def test_reference_labels_match_the_samples_readme(name, machine, parts, codes):
    module = make_samples()
    counts, lines = readme_labels()
    labels = module.reference_labels(name, machine, parts, codes)
    assert module.label_counts(labels) == counts[name]
    if name in lines:
        assert [line for line, _ in labels] == lines[name]


def test_bathtub_collides_on_10_to_30_percent_of_its_blocks():
    counts, _ = readme_labels()
    for name in ("bathtub_273.nc", "bathtub_5000.nc"):
        assert 0.10 * int(name.split("_")[1].split(".")[0]) <= counts[name][0] <= 0.30 * int(name.split("_")[1].split(".")[0])


def test_deposit_sample_collides_only_with_deposit():
    counts, _ = readme_labels()
    total, parts, deposit_only = counts["deposit_wall.nc"]
    assert total > 0 and parts == 0 and deposit_only == total


@pytest.mark.heavy
def test_every_colliding_block_of_bathtub_273_is_fixable_within_30_degrees():
    """Tilting about the tip within Θ = 30° frees every colliding block, mold and beads alike."""
    module = make_samples()
    counts, _ = readme_labels()
    colliding, unfixable = module.unfixable_blocks("bathtub_273.nc", "ijk", ("recreated_mold.stl",), ("M3", "M5"))
    assert colliding == counts["bathtub_273.nc"][0]
    assert unfixable == []
