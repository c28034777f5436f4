"""The golden cases of tests/golden: one folder per case, read, run and (re)written here.

A case folder holds its input program (``input.<ext>``, or ``input =`` a path in case.toml),
``case.toml`` (what it shows, the command line's flags, whether it is heavy) and what ncfix makes of it: ``expected.out`` (the output
program), ``expected.json`` (the JSON report) and ``expected.exit`` (the exit status). A case runs
as a user would run it: ``ncfix input.<ext> FLAGS`` in the case folder (paths in the flags are
relative to it), through the command line's own ``main``. See tests/golden/README.md.
"""

from __future__ import annotations

import contextlib
import json
import os
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ncfix.cli import main as ncfix_main

GOLDEN = Path(__file__).resolve().parent / "golden"
SAMPLES = GOLDEN.parents[1] / "samples"
REPORT_NAME = "expected.json"  # the report's settings.report, as regenerated in the folder


@dataclass(frozen=True)
class Case:
    name: str
    folder: Path
    about: str
    input: Path
    args: tuple[str, ...]
    mark: str | None  # "heavy" or "long" (conftest: only with pytest -m long), or None: a fast case
    sample: str | None  # the bundled sample the folder's input is a copy of (samples/NAME), if any

    @property
    def param(self):
        """A pytest parameter: the case, with its mark."""
        return pytest.param(self, id=self.name, marks=[getattr(pytest.mark, self.mark)] if self.mark else [])


@dataclass(frozen=True)
class Result:
    out: bytes
    report: str
    exit: int


def load(folder: Path) -> Case:
    data = tomllib.loads((folder / "case.toml").read_text(encoding="utf-8"))
    unknown = set(data) - {"about", "input", "args", "heavy", "long", "sample"}
    assert not unknown, f"{folder}/case.toml: unknown keys {sorted(unknown)}"
    if "input" in data:
        program = (folder / data["input"]).resolve()
    else:
        inputs = sorted(folder.glob("input.*"))
        assert len(inputs) == 1, f"{folder}: one input.<ext> file, found {[p.name for p in inputs]}"
        program = inputs[0]
    mark = "long" if data.get("long") else "heavy" if data.get("heavy") else None
    return Case(folder.name, folder, data["about"], program, tuple(data["args"]), mark, data.get("sample"))


def cases(prefix: str = "") -> list[Case]:
    """Every case folder (a folder with a case.toml) whose name starts with ``prefix``."""
    return [load(p.parent) for p in sorted(GOLDEN.glob(f"{prefix}*/case.toml"))]


def params(prefix: str = "") -> list:
    return [case.param for case in cases(prefix)]


@contextlib.contextmanager
def _inside(folder: Path) -> Iterator[None]:
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def normalise_report(text: str) -> str:
    """The report with its one measured value (``summary.seconds``) zeroed and the report's own
    path (``settings.report``) named as in the folder: what a run must match byte for byte."""
    report = json.loads(text)
    report["summary"]["seconds"] = 0.0
    report["settings"]["report"] = REPORT_NAME
    return json.dumps(report, indent=2, ensure_ascii=False) + "\n"


def run(case: Case, scratch: Path, program: Path | None = None) -> Result:
    """``ncfix INPUT FLAGS -o OUT --report REPORT`` in the case folder (OUT, REPORT in ``scratch``);
    INPUT is the case's input, or ``program``."""
    out, report = scratch / "out", scratch / "report.json"
    for path in (out, report):
        path.unlink(missing_ok=True)
    source = program if program is not None else os.path.relpath(case.input, case.folder)
    with _inside(case.folder):
        status = ncfix_main([str(source), *case.args, "-o", str(out), "--report", str(report)])
    # An error (exit 2) writes neither: the case then expects both empty.
    return Result(out.read_bytes() if out.exists() else b"",
                  normalise_report(report.read_text(encoding="utf-8")) if report.exists() else "", status)


def expected(case: Case) -> Result:
    folder = case.folder
    return Result((folder / "expected.out").read_bytes(), (folder / "expected.json").read_text(encoding="utf-8"),
                  int((folder / "expected.exit").read_text()))


def write_expected(case: Case, result: Result) -> None:
    (case.folder / "expected.out").write_bytes(result.out)
    (case.folder / "expected.json").write_text(result.report, encoding="utf-8")
    (case.folder / "expected.exit").write_text(f"{result.exit}\n")
