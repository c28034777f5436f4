"""Shared fixtures: the public corpus beside the checkout (tests skip cleanly without it)."""

from __future__ import annotations

import weakref
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORPUS = REPO.parent / "shared" / "corpus"
NC_SUFFIXES = {".nc", ".ngc", ".txt", ".gcode", ".mpf", ".h"}


@pytest.fixture(autouse=True, scope="session")
def _fresh_cache(tmp_path_factory):
    """The suite's own cache folder (``ncfix.cache``): empty when the session starts, so no test
    reads grids or decompositions a developer's earlier runs left in ``~/.cache/ncfix``; tests after
    the first to build something read it back (the cache's hit path runs in the suite too)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("NCFIX_CACHE", str(tmp_path_factory.mktemp("ncfix-cache")))
        yield


def corpus_path(*parts: str) -> Path:
    path = CORPUS.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"corpus file {path} is absent")
    return path


def corpus_programs() -> list[Path]:
    """Every NC program of the corpus (waypoint lists and licences are not programs)."""
    if not CORPUS.is_dir():
        return []
    out = []
    for path in sorted(CORPUS.rglob("*")):
        if not path.is_file() or path.suffix.lower() not in NC_SUFFIXES:
            continue
        if "waypoint" in path.parts or path.name.upper().startswith(("LICENSE", "README", "COPYING")):
            continue
        out.append(path)
    return out


def pytest_collection_modifyitems(config, items):
    """Cases marked ``long`` (the 5,000-point samples fixed and verified: most of an hour) run only
    when asked for by name of the marker (``pytest -m long``), not in the default suite or CI."""
    if "long" in (config.getoption("-m") or ""):
        return
    skip = pytest.mark.skip(reason="long: run with pytest -m long")
    for item in items:
        if "long" in item.keywords:
            item.add_marker(skip)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """With -rs's list of skips and their reasons: what -m and -k left out, and how to run the heavy cases."""
    left_out = terminalreporter.stats.get("deselected", [])
    if not left_out:
        return
    expression = config.getoption("-m") or ""
    heavy = sum(1 for item in left_out if "heavy" in item.keywords) if "not heavy" in expression else 0
    terminalreporter.section("left out", sep="-")
    if heavy:
        terminalreporter.write_line(f"{heavy} heavy (corpus-wide, end-to-end and full property runs): "
                                    f"pytest -m heavy runs them, as CI's second step does")
    if len(left_out) > heavy:
        chosen = " and ".join(f"{flag} {value!r}" for flag, value in (("-m", expression), ("-k", config.getoption("-k")))
                              if value)
        terminalreporter.write_line(f"{len(left_out) - heavy} not chosen by {chosen}")


_ORACLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def oracle(checker):
    """The tests' exact reference (``ncfix.reference.ExactReference``) for a checker's head, parts
    and tip allowance, made once per checker (imported here: most tests never need it)."""
    from ncfix.reference import ExactReference

    if checker not in _ORACLES:
        _ORACLES[checker] = ExactReference(checker.head, {p.name: p.mesh for p in checker.exact.parts},
                                           tip_allowance_mm=checker.tip_allowance_mm,
                                           open_parts={p.name for p in checker.exact.parts if not p.closed})
    return _ORACLES[checker]
