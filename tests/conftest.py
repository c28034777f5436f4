"""Shared fixtures: the public corpus beside the checkout (tests skip cleanly without it)."""

from __future__ import annotations

import weakref
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORPUS = REPO.parent / "shared" / "corpus"
_LEFT_OUT = pytest.StashKey[dict]()  # what -m and -k deselected: {"all": n, "heavy": n}
NC_SUFFIXES = {".nc", ".ngc", ".txt", ".gcode", ".mpf", ".h"}


@pytest.fixture(autouse=True, scope="session")
def _fresh_cache(tmp_path_factory, pytestconfig):
    """The suite's own cache folder (``ncfix.cache``): empty when the session starts, so no test
    reads grids or decompositions a developer's earlier runs left in ``~/.cache/ncfix``; tests after
    the first to build something read it back (the cache's hit path runs in the suite too). Under
    pytest-xdist the workers share one folder in the run's temporary folder (the cache writes each
    file under a temporary name and renames it into place): what one worker built, the other reads."""
    root = tmp_path_factory.getbasetemp()  # a worker's is a folder of the run's
    folder = (root.parent if hasattr(pytestconfig, "workerinput") else root) / "ncfix-cache"
    folder.mkdir(exist_ok=True)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("NCFIX_CACHE", str(folder))
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


def pytest_deselected(items):
    """Counts what -m and -k left out, for the summary below (under pytest-xdist each worker
    collects and deselects; the first to finish hands its counts to the controller)."""
    config = items[0].config if items else None
    if config is not None:
        left = config.stash.setdefault(_LEFT_OUT, {"all": 0, "heavy": 0})
        left["all"] += len(items)
        left["heavy"] += sum(1 for item in items if "heavy" in item.keywords)


def pytest_sessionfinish(session):
    workeroutput = getattr(session.config, "workeroutput", None)  # set on a pytest-xdist worker
    if workeroutput is not None:
        workeroutput["left_out"] = session.config.stash.get(_LEFT_OUT, {"all": 0, "heavy": 0})


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """pytest-xdist's controller: a worker's counts of what was left out (every worker collects
    the same tests)."""
    counts = getattr(node, "workeroutput", {}).get("left_out")
    if counts is not None:
        node.config.stash.setdefault(_LEFT_OUT, counts)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """With -rs's list of skips and their reasons: what -m and -k left out, and how to run the heavy cases."""
    left = config.stash.get(_LEFT_OUT, {"all": 0, "heavy": 0})
    if not left["all"]:
        return
    expression = config.getoption("-m") or ""
    heavy = left["heavy"] if "not heavy" in expression else 0
    terminalreporter.section("left out", sep="-")
    if heavy:
        terminalreporter.write_line(f"{heavy} heavy (corpus-wide, end-to-end and full property runs): "
                                    f"pytest -m heavy runs them, as CI's second step does")
    if left["all"] > heavy:
        chosen = " and ".join(f"{flag} {value!r}" for flag, value in (("-m", expression), ("-k", config.getoption("-k")))
                              if value)
        terminalreporter.write_line(f"{left['all'] - heavy} not chosen by {chosen}")


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
