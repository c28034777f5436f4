"""The report: bounded trace and previews, the diff (it must apply with patch), verdicts, summary, HTML."""

from __future__ import annotations

import importlib.util
import io
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import trimesh
from rich.console import Console

from ncfix.config import Options
from ncfix.report.html import render_html
from ncfix.report import CONTEXT_LINES, PREVIEW_FACES, TRACE_POINTS, Report, decimate, split_lines
from ncfix.report.summary import print_summary

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
CHROMIUM = Path("/usr/bin/chromium")
FIX = Options(head="head.stl", part=("mold.stl",), deposit_codes=("M3", "M5"))
CHECK = Options(head="head.stl", part=("mold.stl",), check=True)


def make_report(options: Options = FIX, **summary) -> Report:
    report = Report(input="in.nc", machine="ijk", options=options)
    report.summary.update(summary)
    return report


# -- trace ---------------------------------------------------------------------------------------


def test_trace_stays_bounded_on_a_million_blocks_and_keeps_every_changed_block():
    report = make_report()
    rng = np.random.default_rng(1)
    changed_lines = []
    for start in range(0, 1_000_000, 2_000):
        lines = np.arange(start, start + 2_000) + 10
        tilt = np.zeros(2_000)
        if start % 50_000 == 0:
            tilt[[5, 6, 7]] = [1.0, 2.5, 1.0]
            changed_lines += lines[[5, 6, 7]].tolist()
        report.add_trace(lines, rng.normal(size=(2_000, 3)), tilt, np.abs(np.diff(tilt, prepend=0.0)))
    cols = report.trace.columns()
    assert len(cols["line"]) <= TRACE_POINTS + len(changed_lines)
    assert len(cols["line"]) > TRACE_POINTS // 2
    assert set(changed_lines) <= set(cols["line"].tolist())
    assert np.all(np.diff(cols["line"]) > 0)  # program order, no duplicates
    regular = cols["line"][cols["tilt_deg"] == 0]
    assert np.diff(regular).max() <= report.trace.stride  # evenly spread over the whole program
    assert regular[-1] > 1_000_000 - report.trace.stride
    assert np.isnan(cols["clearance_mm"]).all()


def test_trace_keeps_every_block_of_a_short_program_with_its_values():
    report = make_report()
    pts = np.arange(12.0).reshape(4, 3)
    report.add_trace([3, 4], pts[:2], [0.0, 1.5], [0.0, 1.5], [0.2, 0.4])
    report.add_trace(np.array([5, 6]), pts[2:], np.array([0.5, 0.0]), np.array([1.0, 0.5]))
    cols = report.trace.columns()
    assert cols["line"].tolist() == [3, 4, 5, 6]
    assert cols["points"].tolist() == pts.tolist()
    assert cols["tilt_deg"].tolist() == [0.0, 1.5, 0.5, 0.0]
    assert cols["clearance_mm"][:2].tolist() == [0.2, 0.4] and np.isnan(cols["clearance_mm"][2:]).all()


# -- part preview --------------------------------------------------------------------------------


def test_part_preview_is_decimated_to_the_limit_and_keeps_the_shape():
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=40.0)  # 81,920 triangles
    sphere.apply_translation([10, 20, 30])
    report = make_report()
    report.add_part_preview("part:ball.stl", sphere)
    preview = report.previews[0]
    assert preview.source_faces == 81_920
    assert 2_000 < len(preview.faces) <= PREVIEW_FACES
    assert preview.faces.max() < len(preview.vertices) and preview.vertices.dtype == np.float32
    radius = np.linalg.norm(preview.vertices - [10, 20, 30], axis=1)
    assert radius.min() > 37.0 and radius.max() < 40.01


def test_small_meshes_are_kept_as_they_are():
    box = trimesh.creation.box(extents=[1, 2, 3])
    vertices, faces = decimate(box.vertices, box.faces, 100)
    assert np.array_equal(faces, box.faces) and np.allclose(vertices, box.vertices)


# -- diff ----------------------------------------------------------------------------------------


def test_unified_diff_applies_with_patch_byte_for_byte(tmp_path):
    if shutil.which("patch") is None:
        pytest.skip("patch is not installed")
    before = [b"%\n", b"G1 X1 Y1 Z1 I0 J0 K1 (\xe9)\r\n", b"G1 X2\n", b"G1 X3 I0 J0 K1\n", b"M30\n", b"G1 X4 K1"]
    after = list(before)
    after[1] = b"G1 X1 Y1 Z1 I0.1 J0 K0.994987 (\xe9)\r\n"  # CRLF and a latin-1 byte stay as they are
    after[3] = b"G1 X3 I0.05 J0 K0.99875\n"
    after[5] = b"G1 X4 I0 J0 K1"  # last line without a newline
    report = make_report()
    report.record_emitted(1, before, b"".join(after))
    assert [line for line, _, _ in report.diff_lines] == [2, 4, 6]
    src, diff = tmp_path / "prog.nc", tmp_path / "prog.diff"
    src.write_bytes(b"".join(before))
    report.write_diff(str(diff), "prog.nc", "out.nc")
    text = diff.read_bytes()
    assert text.startswith(b"--- prog.nc\n+++ out.nc\n@@ -2,1 +2,1 @@\n-G1 X1 Y1 Z1 I0 J0 K1 (\xe9)\r\n")
    assert text.endswith(b"+G1 X4 I0 J0 K1\n\\ No newline at end of file\n")
    done = subprocess.run(["patch", "-s", str(src), str(diff)], capture_output=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert src.read_bytes() == b"".join(after)


def test_no_change_gives_an_empty_diff():
    report = make_report()
    lines = [b"G1 X1\n", b"G1 X2\n"]
    report.record_emitted(1, lines, b"".join(lines))
    assert report.diff_lines == [] and report.unified_diff("a", "b") == ""


def test_split_lines_splits_at_newline_only():
    assert split_lines(b"a\r\nb\rc\nd") == [b"a\r\n", b"b\rc\n", b"d"]
    assert split_lines(b"a\n") == [b"a\n"] and split_lines(b"") == []


# -- program text around changed and colliding lines ----------------------------------------------


def test_context_is_captured_around_changed_and_colliding_lines_across_chunks():
    lines = [f"N{n} G1 X{n}\n".encode() for n in range(1, 101)]
    out = list(lines)
    out[49] = b"N50 G1 X50 I0.1 K0.99\n"  # line 50 changed
    report = make_report()
    report.changes.append({"line": 50, "before": None, "after": None, "reason": "collision"})
    report.collisions.append({"line": 61, "bodies": ["deposit"], "penetration_mm": 0.1, "clearance_mm": -0.1})
    report.collisions.append({"line": 2, "bodies": ["deposit"], "penetration_mm": 0.1, "clearance_mm": -0.1})
    # chunks of 30 lines: 50 and 61 are known before their chunks are written, 99 only with its own chunk
    for first in (1, 31, 61, 91):
        if first == 91:
            report.collisions.append({"line": 99, "bodies": [], "penetration_mm": 0.0, "clearance_mm": 0.1})
        report.record_emitted(first, lines[first - 1:first + 29], b"".join(out[first - 1:first + 29]))
    expect = set(range(1, 6)) | set(range(47, 54)) | set(range(58, 65)) | set(range(96, 101))
    assert set(report.context) == expect
    assert report.context[50] == ("N50 G1 X50", "N50 G1 X50 I0.1 K0.99")
    assert report.context[58] == ("N58 G1 X58", None)
    assert report.changes[0]["before"] == "N50 G1 X50" and report.changes[0]["after"] == "N50 G1 X50 I0.1 K0.99"
    assert CONTEXT_LINES == 3


# -- verdicts and summary ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "options, summary, changes, verdict, code",
    [
        (Options(), {}, [], "no --head given: the program was read and passed through unchanged: exit 0", 0),
        (CHECK, {}, [], "no colliding block found: exit 0", 0),
        (CHECK, {"colliding_blocks_before": 3}, [],
         "3 colliding blocks found; --check leaves the program as it is (run without --check to fix them): exit 1", 1),
        (FIX, {}, [], "no colliding block: the program is written unchanged: exit 0", 0),
        (FIX, {"colliding_blocks_before": 75, "changed_blocks": 105}, ["collision"] * 75 + ["blend"] * 30,
         "all 75 colliding blocks fixed: 75 blocks tilted, 30 ramp blocks blended; "
         "the output has no detected collision: exit 0", 0),
        (FIX, {"colliding_blocks_before": 75, "unresolved_blocks": 1}, ["collision"] * 74,
         "1 colliding block could not be fixed and is left as programmed (74 of 75 fixed): exit 1", 1),
    ],
)
def test_verdict_says_what_happened_and_the_exit_status(options, summary, changes, verdict, code):
    report = make_report(options, **summary)
    report.changes = [{"line": i + 1, "reason": r} for i, r in enumerate(changes)]
    assert report.verdict == verdict
    assert report.exit_code == code


def summary_text(report: Report, verbose: bool = False) -> str:
    buffer = io.StringIO()
    print_summary(report, verbose=verbose, console=Console(file=buffer, width=200, highlight=False))
    return buffer.getvalue()


def test_fix_summary_lists_changes_unresolved_blocks_with_reasons_and_the_verdict():
    report = make_report(lines=288, motion_blocks=275, colliding_blocks_before=3, changed_blocks=4,
                         unresolved_blocks=1, max_tilt_deg=12.5, max_step_deg=2.0, seconds=1.5)
    report.changes = [{"line": n, "reason": r} for n, r in ((10, "collision"), (11, "collision"), (9, "blend"),
                                                            (12, "blend"))]
    report.unresolved = [{"line": 40, "bodies": ["part:mold.stl"], "penetration_mm": 0.8,
                          "reason": "no free orientation within --max-tilt 30°"}]
    text = summary_text(report)
    assert "3 colliding blocks found" in text
    assert "4 blocks changed: 2 tilted off a collision, 2 blended into ramps (max tilt 12.50°, max step 2.00°" in text
    assert re.search(r"40\s+part:mold.stl\s+–\s+0.800\s+no free orientation within --max-tilt 30°", text)
    assert text.rstrip().endswith(
        "1 colliding block could not be fixed and is left as programmed (2 of 3 fixed): exit 1")


def test_notes_are_shown_without_verbose_details_only_with():
    report = make_report(FIX, colliding_blocks_before=1, changed_blocks=1)
    report.details.append("head model at 0.5 mm: 78332 balls")
    report.notes.append("CoACD: part:mold.stl cut into 28 convex pieces in 5.34 s (not cached before this run)")
    quiet, verbose = summary_text(report), summary_text(report, verbose=True)
    for text in (quiet, verbose):
        assert "\n  CoACD: part:mold.stl cut into 28 convex pieces in 5.34 s (not cached before this run)\n" in text
    assert "head model" not in quiet and "head model at 0.5 mm" in verbose


def test_check_summary_keeps_the_collision_table():
    report = make_report(CHECK, colliding_blocks_before=25)
    report.collisions = [{"line": n, "bodies": ["deposit"], "penetration_mm": 0.5, "clearance_mm": -0.5,
                          "where": "end"} for n in range(100, 125)]
    text = summary_text(report)
    assert re.search(r"line\s+bodies\s+where\s+penetration mm\s+clearance mm", text)
    assert re.search(r"119\s+deposit\s+end\s+0.500\s+-0.500", text) and "120  deposit" not in text
    assert "… 5 more colliding blocks (-v or --report lists all)" in text
    assert re.search(r"124\s+deposit", summary_text(report, verbose=True))


# -- HTML ----------------------------------------------------------------------------------------


def bathtub_report() -> Report:
    """A fix-mode report like the corrector's on the 273-point sample: trace, preview, changes, one unresolved."""
    raw = (SAMPLES / "bathtub_273.nc").read_bytes()
    lines = split_lines(raw)
    lines[20] = b"N150 G1 X7.530 Y38.763 Z56.701 (<script>alert(1)</script> & co)\n"  # must come out escaped
    motion = [i for i, line in enumerate(lines) if re.match(rb"N\d+ G1 X", line)]
    xyz = np.array([[float(v) for v in re.findall(rb"[XYZ](-?[\d.]+)", lines[i])[:3]] for i in motion])
    line_numbers = np.array(motion) + 1
    tilt = np.zeros(len(motion))
    changed = {115: "collision", 116: "collision", 129: "collision", 130: "collision", 114: "blend", 117: "blend",
               128: "blend", 131: "blend"}
    for line in changed:
        tilt[np.searchsorted(line_numbers, line)] = 4.0 if changed[line] == "collision" else 2.0
    step = np.abs(np.diff(tilt, prepend=0.0))
    report = make_report(lines=len(lines), motion_blocks=len(motion), colliding_blocks_before=5, changed_blocks=8,
                         unresolved_blocks=1, max_tilt_deg=4.0, max_step_deg=2.0, seconds=3.2)
    report.add_trace(line_numbers, xyz, tilt, step, clearance_mm=np.linspace(3.0, 0.5, len(motion)))
    report.add_part_preview("part:recreated_mold.stl", trimesh.load(SAMPLES / "recreated_mold.stl"))
    out = list(lines)
    for line, reason in sorted(changed.items()):
        i = line - 1
        out[i] = lines[i].replace(b" K0.866025", b" K0.9")
        k = int(np.searchsorted(line_numbers, line))
        collided = reason == "collision"
        report.changes.append({
            "line": line, "before": None, "after": None, "reason": reason, "tilt_deg": float(tilt[k]),
            "step_deg": float(step[k]), "bodies": ["part:recreated_mold.stl"] if collided else [],
            "clearance_before_mm": -0.8 if collided else 0.6, "clearance_after_mm": 0.3 if collided else 0.5,
            "point": xyz[k].tolist()})
        if collided:
            report.collisions.append({"line": line, "bodies": ["part:recreated_mold.stl"], "penetration_mm": 0.8,
                                      "clearance_mm": -0.8})
    report.collisions.append({"line": 21, "bodies": ["part:recreated_mold.stl", "deposit"], "penetration_mm": 1.2,
                              "clearance_mm": -1.2})
    report.unresolved.append({"line": 21, "bodies": ["part:recreated_mold.stl", "deposit"], "penetration_mm": 1.2,
                              "reason": "no free orientation within --max-tilt 30° <of the head>"})
    report.warnings.append("3 blocks have an unknown axis <G28>: not checked")
    report.record_emitted(1, lines, b"".join(out))
    return report


class Collect(HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.hrefs, self.srcs, self.tags, self.scripts = set(), [], [], [], []
        self._in_script = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        self.tags.append(tag)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        if "href" in attrs:
            self.hrefs.append(attrs["href"])
        if "src" in attrs:
            self.srcs.append(attrs["src"])
        self._in_script = tag == "script"


def test_html_is_self_contained_escaped_and_every_line_link_has_its_anchor():
    report = bathtub_report()
    page = render_html(report)
    parsed = Collect()
    parsed.feed(page)
    assert parsed.srcs == []  # no external script, image or font
    assert not re.search(r"(?:href|src)=\"(?:https?:)?//", page) and "@import" not in page and "url(" not in page
    assert all(h.startswith("#L") for h in parsed.hrefs) and parsed.hrefs
    assert {h[1:] for h in parsed.hrefs} <= parsed.ids  # each line number jumps to its program text
    for line in (21, 114, 115, 131):
        assert f'href="#L{line}"' in page
    assert "<script>alert(1)</script>" not in page
    assert "(&lt;script&gt;alert(1)&lt;/script&gt; &amp; co)" in page
    assert "no free orientation within --max-tilt 30° &lt;of the head&gt;" in page
    assert "3 blocks have an unknown axis &lt;G28&gt;: not checked" in page
    assert report.verdict in page and "exit 1" in page
    assert page.count("<svg") == 3 and parsed.tags.count("canvas") == 1
    # the JSON data for the 3-D picture: the preview, the sampled path, 1 red and 8 green points
    data = re.search(r'<script type="application/json" id="ncfix-data">(.*?)</script>', page, re.S).group(1)
    import json

    view = json.loads(data)
    assert len(view["meshes"]) == 1 and len(view["meshes"][0]["f"]) == 3 * len(report.previews[0].faces)
    assert len(view["red"]) == 3 and len(view["green"]) == 24 and len(view["path"]) == 3 * len(report.trace)


def test_html_of_a_check_run_and_of_a_pass_through_render():
    report = make_report(CHECK, lines=10, motion_blocks=5, colliding_blocks_before=1)
    report.collisions.append({"line": 4, "bodies": ["deposit"], "penetration_mm": 0.3, "clearance_mm": -0.3})
    report.record_emitted(1, [b"G1 X%d\n" % i for i in range(10)], b"".join(b"G1 X%d\n" % i for i in range(10)))
    page = render_html(report)
    assert "Colliding blocks (1)" in page and 'href="#L4"' in page and 'id="L4"' in page
    assert "Changed blocks" not in page and "exit 1" in page
    plain = render_html(make_report(Options()))
    assert "passed through unchanged" in plain and "<svg" not in plain and "<canvas" not in plain


def test_the_3d_picture_skips_the_back_of_closed_shells_only():
    from ncfix.report.html import _winding

    box = trimesh.creation.box(extents=(20.0, 15.0, 50.0))
    assert _winding(box.vertices, box.faces) == 1  # wound outward: back faces are not drawn
    assert _winding(box.vertices, box.faces[:, ::-1]) == -1
    assert _winding(box.vertices, box.faces[1:]) == 0  # open: every face is drawn, as before
    flipped = box.faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert _winding(box.vertices, flipped) == 0


def load_script():
    spec = importlib.util.spec_from_file_location("render_html", REPO / "scripts" / "render_html.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed")
def test_html_renders_in_chromium_without_script_errors(tmp_path):
    page = tmp_path / "report.html"
    page.write_text(render_html(bathtub_report()), encoding="utf-8")
    script = load_script()
    dom = script.dump_dom(page)
    body = re.search(r"<body[^>]*>", dom).group(0)  # the script marks <body> when it has run to its end
    assert 'data-ok="1"' in body and "data-error" not in body, body
    png = tmp_path / "report.png"
    script.screenshot(page, png, size="1400,900")
    image = read_png(png).astype(np.float64)
    assert image.shape == (900, 1400, 3)
    assert image.std() > 20  # not blank: the banner, tables and plots are drawn
    red = (image[..., 0] > 180) & (image[..., 1] < 80) & (image[..., 2] < 80)
    assert red[:200].sum() > 5_000  # the exit-1 banner at the top


def read_png(path: Path) -> np.ndarray:
    """(h, w, channels) uint8 of an 8-bit, non-interlaced PNG (what chromium writes; no PIL here)."""
    import struct
    import zlib

    data, pos, idat = path.read_bytes(), 8, []
    while pos < len(data):
        size, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[pos + 8:pos + 21])
            assert depth == 8 and interlace == 0 and colour in (2, 6)
        elif kind == b"IDAT":
            idat.append(data[pos + 8:pos + 8 + size])
        pos += 12 + size
    bpp = 3 if colour == 2 else 4
    raw = zlib.decompress(b"".join(idat))
    stride = width * bpp
    out = np.zeros((height, stride), dtype=np.uint8)
    previous = np.zeros(stride, dtype=np.int64)
    for y in range(height):
        kind, row = raw[y * (stride + 1)], np.frombuffer(raw, np.uint8, stride, y * (stride + 1) + 1).astype(np.int64)
        if kind == 0:
            line = row
        elif kind == 1:  # Sub: a running sum per channel
            line = np.cumsum(row.reshape(-1, bpp), axis=0).reshape(-1) % 256
        elif kind == 2:  # Up
            line = (row + previous) % 256
        else:  # Average, Paeth: sequential along the row
            line, up = row.tolist(), previous.tolist()
            for x in range(stride):
                a = line[x - bpp] if x >= bpp else 0
                b = up[x]
                if kind == 3:
                    line[x] = (line[x] + (a + b) // 2) % 256
                else:
                    c = up[x - bpp] if x >= bpp else 0
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) % 256
            line = np.array(line, dtype=np.int64)
        out[y] = line
        previous = line
    return out.reshape(height, width, bpp)[..., :3]
