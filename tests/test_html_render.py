"""The HTML report of a real correction run renders in headless chromium and its script runs cleanly.

Opt-in by what is installed: marked ``browser`` (``pytest -m browser`` runs only these) and
skipped when /usr/bin/chromium is absent (Debian: ``apt-get install chromium``). The program is
the golden ijk case of tests/golden/fix_ijk (a wall beside a straight path; ncfix tilts 41 blocks).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

import ncfix

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
GOLDEN = REPO / "tests" / "golden"

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed")]


def load_render_script():
    spec = importlib.util.spec_from_file_location("render_html", REPO / "scripts" / "render_html.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_report_of_the_golden_ijk_case_runs_its_script_without_errors(tmp_path):
    page = tmp_path / "report.html"
    report = ncfix.process(GOLDEN / "fix_ijk" / "input.nc", tmp_path / "out.nc", machine="ijk",
                           head=str(REPO / "samples" / "deposition_head.stl"), part=[str(GOLDEN / "meshes" / "wall_x.stl")],
                           bead_radius=0.0, strategy="graph", html=str(page))
    assert report.exit_code == 0 and report.changes
    html = page.read_text(encoding="utf-8")
    assert f"Changed blocks ({len(report.changes)})" in html and "<canvas" in html

    dom, console = load_render_script().dump_dom_and_console(page)
    body = re.search(r"<body[^>]*>", dom).group(0)  # the script marks <body> when it has run to its end
    assert 'data-ok="1"' in body and "data-error" not in body, body
    errors = [line for line in console.splitlines() if "Uncaught" in line]
    assert not errors, "\n".join(errors)
