"""Shared fixtures: the public corpus beside the checkout (tests skip cleanly without it)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORPUS = REPO.parent / "shared" / "corpus"
NC_SUFFIXES = {".nc", ".ngc", ".txt", ".gcode", ".mpf", ".h"}


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
