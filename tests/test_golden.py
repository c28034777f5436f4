"""The golden cases (tests/golden: one folder per case, its README says how to add or regenerate
one): ncfix run as a user runs it makes exactly the expected output, report and exit status, and
its output is a fixed point (run on it, ncfix writes it back byte for byte and changes nothing)."""

from __future__ import annotations

import json

import pytest

import golden_cases


@pytest.mark.parametrize("case", golden_cases.params())
def test_golden_case(case, tmp_path):
    got, want = golden_cases.run(case, tmp_path), golden_cases.expected(case)
    again = f"regenerate with `python tests/golden/regen.py {case.name}` and review the git diff"
    assert got.out == want.out, f"the output differs: {again}"
    assert got.report == want.report, f"the report differs: {again}"
    assert got.exit == want.exit, f"the exit status differs: {again}"

    rerun = golden_cases.run(case, tmp_path, program=case.folder / "expected.out")
    assert rerun.out == want.out
    summary = json.loads(rerun.report)["summary"]
    assert summary["changed_blocks"] == 0
    if want.exit == 0:  # a clean output: nothing left for ncfix to find
        assert summary["colliding_blocks_before"] == 0 and rerun.exit == 0


def test_every_case_says_what_it_shows_and_has_its_expected_files():
    for case in golden_cases.cases():
        assert case.about.strip() and case.args, case.name
        assert case.input.is_file(), case.name
        for name in ("expected.out", "expected.json", "expected.exit"):
            assert (case.folder / name).is_file(), f"{case.name}/{name}: run tests/golden/regen.py {case.name}"


def test_copied_inputs_are_the_bundled_samples():
    copies = [case for case in golden_cases.cases() if case.sample]
    assert copies
    for case in copies:
        assert case.input.read_bytes() == (golden_cases.SAMPLES / case.sample).read_bytes(), (
            f"{case.name}: samples/{case.sample} changed; run tests/golden/regen.py {case.name}")


def test_every_bundled_sample_is_a_golden_case_with_each_strategy():
    from ncfix.config import STRATEGIES

    # The 5,000-point samples take 5-15 minutes a run: tests/test_sample_fixes.py checks them (pytest -m long).
    programs = sorted(p.name for p in golden_cases.SAMPLES.iterdir() if p.suffix in (".nc", ".mpf") and "5000" not in p.name)
    for name in programs:
        for strategy in STRATEGIES:
            case = golden_cases.load(golden_cases.GOLDEN / f"sample_{name.rsplit('.', 1)[0]}_{strategy}")
            assert case.input == golden_cases.SAMPLES / name or case.sample == name, case.name
            assert case.args[-2:] == ("--strategy", strategy), case.name
