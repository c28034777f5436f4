"""The HTML report: one self-contained file (inline CSS, SVG plots, a small canvas script; no network)."""

from __future__ import annotations

import json
import math
from html import escape
from typing import Any

import numpy as np

from ncfix.report import CONTEXT_LINES, Report, rescaled_note
from ncfix.version import __version__

TABLE_ROWS = 2_000  # rows per table; the JSON report lists all
SCROLL_ROWS = 15  # longer tables scroll in a box of about this height
PLOT_WIDTH, PLOT_HEIGHT = 1300, 230
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 64, 24, 30, 40
RED, GREEN, BLUE, GREY, AMBER = "#c62828", "#2e7d32", "#1565c0", "#9e9e9e", "#ef6c00"


def render_html(report: Report) -> str:
    """The whole report as one HTML document (deterministic: no time stamps, no random ids)."""
    title = f"ncfix report: {report.input}"
    body = [
        _header(report),
        _cards(report),
        _unresolved(report),
        _changes(report),
        _collisions(report),
        _plots(report),
        _view(report),
        _program_text(report),
        _settings(report),
    ]
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n"
        + "\n".join(part for part in body if part)
        + f"\n</main>\n<script type=\"application/json\" id=\"ncfix-data\">{_view_data(report)}</script>\n"
        f"<script>{_SCRIPT}</script>\n</body>\n</html>\n"
    )


# -- sections ------------------------------------------------------------------------------------


def _header(report: Report) -> str:
    status = "ok" if report.exit_code == 0 else "bad"
    mode = "check (detect only)" if report.options.check else "fix"
    return (
        f"<header>\n<h1>ncfix report <span class=\"file\">{escape(report.input)}</span></h1>\n"
        f"<p class=\"meta\">machine <b>{escape(report.machine)}</b> · mode <b>{mode}</b> · ncfix {escape(_version())}</p>\n"
        f"<div class=\"verdict {status}\"><div class=\"exit\">exit {report.exit_code}</div>"
        f"<div><p class=\"line\">{escape(report.verdict)}</p>"
        f"<p class=\"means\">{escape(report.exit_meaning())}</p></div></div>\n</header>"
    )


def _cards(report: Report) -> str:
    s, o = report.summary, report.options
    by_reason = report.changed_by_reason()
    cards = [
        ("lines", f"{s['lines']:,}", ""),
        ("motion blocks", f"{s['motion_blocks']:,}", ""),
        ("colliding blocks found", f"{s['colliding_blocks_before']:,}",
         "before any change" if not o.check else "as programmed"),
    ]
    if not o.check:
        cards += [
            ("changed blocks", f"{s['changed_blocks']:,}",
             f"{by_reason.get('collision', 0):,} tilted off a collision, {by_reason.get('blend', 0):,} blended"
             + rescaled_note(by_reason)),
            ("unresolved blocks", f"{s['unresolved_blocks']:,}", "left as programmed"),
            ("max tilt", f"{s['max_tilt_deg']:.2f}°", f"limit {o.max_tilt:g}° (--max-tilt)"),
            ("max step", f"{s['max_step_deg']:.2f}°", f"limit {o.max_step:g}° (--max-step)"),
        ]
    cards.append(("time", f"{s['seconds']:.2f} s", ""))
    bad = {"colliding blocks found": s["colliding_blocks_before"] > 0 and o.check,
           "unresolved blocks": s["unresolved_blocks"] > 0}
    out = ["<section class=\"cards\">"]
    for name, value, note in cards:
        cls = " bad" if bad.get(name) else ""
        out.append(f"<div class=\"card{cls}\"><div class=\"v\">{escape(value)}</div><div class=\"k\">{escape(name)}</div>"
                   f"<div class=\"n\">{escape(note)}</div></div>")
    out.append("</section>")
    if report.warnings:
        out.append(f"<section><h2>Warnings ({len(report.warnings):,})</h2><ul class=\"warnings\">")
        out += [f"<li>{escape(w)}</li>" for w in report.warnings[:TABLE_ROWS]]
        out.append("</ul></section>")
    return "\n".join(out)


def _unresolved(report: Report) -> str:
    if report.options.check or not _checked(report):
        return ""
    rows = report.unresolved
    if not rows:
        return "<section><h2>Unresolved blocks</h2><p>None: every colliding block was fixed.</p></section>"
    head = ("line", "bodies hit", "where", "penetration mm", "why it could not be fixed")
    body = [(_line_link(report, e.get("line")), _bodies(e), escape(str(e.get("where") or "–")),
             _num(e.get("penetration_mm"), 3), escape(str(e.get("reason") or "not corrected")))
            for e in rows[:TABLE_ROWS]]
    reasons: dict[str, int] = {}
    for e in rows:
        reason = str(e.get("reason") or "not corrected")
        reasons[reason] = reasons.get(reason, 0) + 1
    why = "".join(f"<li><b>{n:,}</b> × {escape(r)}</li>" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1]))
    return (f"<section><h2 class=\"bad\">Unresolved blocks ({len(rows):,})</h2>"
            "<p>These blocks still collide: they are left as programmed in the output. Change the toolpath "
            "in the CAM system, or allow more tilt (--max-tilt) or more change per block (--max-step).</p>"
            f"<ul class=\"reasons\">{why}</ul>" + _table(head, body, len(rows), (3,)) + "</section>")


def _changes(report: Report) -> str:
    if report.options.check or not _checked(report):
        return ""
    rows = report.changes
    title = f"<h2>Changed blocks ({len(rows):,})</h2>"
    if not rows:
        return f"<section>{title}<p>No block was changed.</p></section>"
    head = ("line", "reason", "tilt °", "step °", "bodies", "clearance before mm", "clearance after mm")
    body = [(_line_link(report, e.get("line")), escape(str(e.get("reason", ""))), _num(e.get("tilt_deg"), 2),
             _num(e.get("step_deg"), 2), _bodies(e), _num(e.get("clearance_before_mm"), 3),
             _num(e.get("clearance_after_mm"), 3))
            for e in rows[:TABLE_ROWS]]
    return (f"<section>{title}<p><b>collision</b>: the block collided and was tilted; <b>blend</b>: a "
            "neighbouring block tilted so that the orientation changes by at most --max-step per block. "
            "Clearance is the head's distance to the nearest body (negative: penetration). "
            "A line number jumps to the program text.</p>" + _table(head, body, len(rows), (2, 3, 5, 6)) + "</section>")


def _collisions(report: Report) -> str:
    if not _checked(report):
        return ""
    rows = report.collisions
    title = "Colliding blocks" if report.options.check else "Colliding blocks as programmed"
    if not rows:
        return f"<section><h2>{title}</h2><p>No block collides.</p></section>"
    head = ("line", "bodies hit", "where", "penetration mm", "clearance mm")
    if not report.options.check:
        head += ("outcome",)
    body = [(_line_link(report, e.get("line")), _bodies(e), escape(str(e.get("where") or "–")),
             _num(e.get("penetration_mm"), 3), _num(e.get("clearance_mm"), 3))
            + (() if report.options.check else (escape(_outcome(e)),)) for e in rows[:TABLE_ROWS]]
    table = _table(head, body, len(rows), (3, 4))
    where = ("<p><b>where</b>: <b>end</b> = the head collides at the block's end point; <b>sweep</b> = along "
             "the move from the block before, its end point being free. The clearance is at that pose; the "
             "penetration is the deepest the head goes into a body along the move.</p>")
    if report.options.check:
        return f"<section><h2 class=\"bad\">{title} ({len(rows):,})</h2>{where}{table}</section>"
    return (f"<section><details><summary><h2>{title} ({len(rows):,})</h2></summary>"
            "<p>Every block that collided before any change (the fixed ones are in the table above). "
            "<b>outcome</b>: tilted; freed (left as programmed, free once the blocks before it were rewritten); "
            "unresolved.</p>"
            f"{where}{table}</details></section>")


def _outcome(entry: dict[str, Any]) -> str:
    text = str(entry.get("outcome") or "–")
    if entry.get("note"):
        text += f": {entry['note']}"
    if entry.get("detected"):
        text += f" ({entry['detected']})"
    return text


def _plots(report: Report) -> str:
    if not _checked(report):
        return ""
    o = report.options
    trace = report.trace.columns() if len(report.trace) else None
    x_max = max(int(report.summary["lines"]), 1)
    changes = report.changes

    def change_dots(key: str) -> list[dict[str, Any]]:
        out = []
        for reason, colour in (("collision", GREEN), ("blend", BLUE)):
            pts = [(e["line"], e[key]) for e in changes if e.get("reason") == reason and _finite(e.get(key))]
            if pts:
                out.append({"kind": "dots", "points": pts, "colour": colour, "label": f"{reason} change",
                            "tip": "line {x}: {y:.2f}°"})
        return out

    charts = []
    if o.check:
        charts.append(("Clearance of the colliding blocks, as programmed (mm; below 0: penetration)",
                       _chart([{"kind": "dots", "points": _pairs(report.collisions, "clearance_mm"), "colour": RED,
                                "label": "colliding block", "tip": "line {x}: {y:.3f} mm"}],
                              x_max, [(0.0, "contact")] + ([(o.clearance, "--clearance")] if o.clearance else []),
                              "mm")))
    else:
        for key, name, limit, flag in (("tilt_deg", "Tilt from the programmed orientation", o.max_tilt, "--max-tilt"),
                                       ("step_deg", "Orientation step from the previous block", o.max_step,
                                        "--max-step")):
            series = []
            if trace is not None:
                series.append({"kind": "line", "xs": trace["line"], "ys": trace[key], "colour": GREY,
                               "label": "every block (sampled)"})
            series += change_dots(key)
            charts.append((f"{name} (°) along the program",
                           _chart(series, x_max, [(limit, f"{flag} {limit:g}°")], "°", "no block was changed")))
        series = []
        if trace is not None and np.isfinite(trace["clearance_mm"]).any():
            series.append({"kind": "line", "xs": trace["line"], "ys": trace["clearance_mm"], "colour": GREY,
                           "label": "every block (sampled)"})
        links = [(e["line"], e["clearance_before_mm"], e["clearance_after_mm"]) for e in changes
                 if _finite(e.get("clearance_before_mm")) and _finite(e.get("clearance_after_mm"))]
        if links:
            series.append({"kind": "links", "links": links, "colour": "#bdbdbd"})
        series.append({"kind": "dots", "points": _pairs(report.collisions, "clearance_mm"), "colour": RED,
                       "label": "before (colliding block)", "tip": "line {x}: {y:.3f} mm before"})
        series.append({"kind": "dots", "points": _pairs(changes, "clearance_after_mm"), "colour": GREEN,
                       "label": "after (changed block)", "tip": "line {x}: {y:.3f} mm after"})
        charts.append(("Clearance before → after (mm; below 0: penetration)",
                       _chart(series, x_max, [(0.0, "contact")] + ([(o.clearance, "--clearance")] if o.clearance else []),
                              "mm")))
    out = ["<section><h2>Along the program</h2><p>Horizontal axis: line number in the input.</p>"]
    for title, svg in charts:
        out.append(f"<figure><figcaption>{escape(title)}</figcaption>{svg}</figure>")
    out.append("</section>")
    return "\n".join(out)


def _view(report: Report) -> str:
    if not _checked(report):
        return ""
    if not report.previews and not _points(report)[0] and not _points(report)[1]:
        return ""
    names = ", ".join(f"{escape(p.name)} ({len(p.faces):,} of {p.source_faces:,} triangles)" for p in report.previews)
    return (
        "<section><h2>Part and blocks in 3-D</h2>"
        f"<p>{names or 'no part mesh'}. Drag to turn, wheel to zoom. "
        f"<span class=\"key\" style=\"background:{RED}\"></span> still colliding "
        f"<span class=\"key\" style=\"background:{GREEN}\"></span> changed "
        f"<span class=\"key line\"></span> toolpath (sampled) "
        "<button type=\"button\" id=\"view-reset\">reset view</button></p>"
        "<canvas id=\"view\" width=\"1300\" height=\"640\"></canvas>"
        "<noscript><p>The 3-D picture needs JavaScript.</p></noscript></section>"
    )


def _program_text(report: Report) -> str:
    if not report.context:
        return ""
    changed = {e["line"] for e in report.changes if isinstance(e.get("line"), int)}
    colliding = {e["line"] for e in (report.unresolved if not report.options.check else report.collisions)
                 if isinstance(e.get("line"), int)}
    out = ["<section><h2>Program text</h2>",
           f"<p>Each changed or colliding line with {_context_lines()} lines around it, as read "
           "(<span class=\"minus\">−</span>) and as written (<span class=\"plus\">+</span>).</p>"]
    if report.context_truncated:
        out.append("<p class=\"note\">Only the first lines of interest are shown here; the JSON report and the "
                   "diff list all.</p>")
    out.append("<div class=\"code\">")
    previous = None
    for line in sorted(report.context):
        if previous is not None and line != previous + 1:
            out.append("<div class=\"gap\">⋯</div>")
        previous = line
        before, after = report.context[line]
        mark = " hit" if line in colliding else ""
        if after is not None or line in changed:
            out.append(f"<div class=\"row minus{mark}\" id=\"L{line}\"><span class=\"ln\">{line}</span>"
                       f"<span class=\"m\">−</span><span class=\"t\">{escape(before)}</span></div>")
            out.append(f"<div class=\"row plus\"><span class=\"ln\"></span><span class=\"m\">+</span>"
                       f"<span class=\"t\">{escape(after if after is not None else before)}</span></div>")
        else:
            tag = "!" if mark else ""
            out.append(f"<div class=\"row{mark}\" id=\"L{line}\"><span class=\"ln\">{line}</span>"
                       f"<span class=\"m\">{tag}</span><span class=\"t\">{escape(before)}</span></div>")
    out.append("</div></section>")
    return "\n".join(out)


def _settings(report: Report) -> str:
    settings = report.to_json()["settings"]
    rows = [(escape(k.replace("_", "-")), escape(_setting(v))) for k, v in settings.items()
            if k not in ("quiet", "verbose")]
    return ("<section><details><summary><h2>Settings</h2></summary>"
            + _table(("option", "value"), rows, len(rows)) + "</details></section>")


# -- pieces --------------------------------------------------------------------------------------


def _checked(report: Report) -> bool:
    """Whether the run checked anything (a head was given, or a stage reported blocks)."""
    return report.options.head is not None or bool(report.changes or report.collisions or report.unresolved)


def _table(head: tuple[str, ...], rows: list[tuple[str, ...]], total: int, numeric: tuple[int, ...] = ()) -> str:
    """Cells are HTML already (escaped by the caller); ``numeric`` columns are right-aligned."""
    def cls(i: int) -> str:
        return " class=\"n\"" if i in numeric else ""

    out = ["<table><thead><tr>" + "".join(f"<th{cls(i)}>{escape(h)}</th>" for i, h in enumerate(head))
           + "</tr></thead><tbody>"]
    out += ["<tr>" + "".join(f"<td{cls(i)}>{c}</td>" for i, c in enumerate(row)) + "</tr>" for row in rows]
    out.append("</tbody></table>")
    if len(rows) > SCROLL_ROWS:  # long tables scroll in a box, so the plots stay near the top
        out = ["<div class=\"scroll\">"] + out + ["</div>"]
    if total > len(rows):
        out.append(f"<p class=\"note\">… {total - len(rows):,} more rows in the JSON report (--report).</p>")
    return "".join(out)


def _line_link(report: Report, line: Any) -> str:
    if not isinstance(line, int):
        return escape(str(line))
    if line in report.context:
        return f"<a href=\"#L{line}\">{line}</a>"
    return str(line)


def _bodies(entry: dict[str, Any]) -> str:
    return escape(", ".join(str(b) for b in entry.get("bodies") or [])) or "–"


def _num(value: Any, decimals: int) -> str:
    return f"{float(value):.{decimals}f}" if _finite(value) else "–"


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and math.isfinite(value)


def _pairs(entries: list[dict[str, Any]], key: str) -> list[tuple[float, float]]:
    return [(e["line"], e[key]) for e in entries if isinstance(e.get("line"), int) and _finite(e.get(key))]


def _setting(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, (list, tuple)):
        return ", ".join(str(v) for v in value) or "–"
    return str(value)


def _context_lines() -> int:
    return CONTEXT_LINES


def _version() -> str:
    return __version__


# -- SVG charts ----------------------------------------------------------------------------------


def _ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    span = hi - lo
    if span <= 0:
        return [lo]
    raw = span / count
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def _envelope(xs: np.ndarray, ys: np.ndarray, x_of, columns: int) -> list[tuple[float, float]]:
    """Min and max per pixel column, in order: thousands of points drawn as a few, peaks kept."""
    keep = np.isfinite(ys)
    xs, ys = np.asarray(xs, dtype=np.float64)[keep], np.asarray(ys, dtype=np.float64)[keep]
    if len(xs) <= 2 * columns:
        return list(zip(xs.tolist(), ys.tolist()))
    col = np.clip(((x_of(xs) - MARGIN_LEFT)).astype(np.int64), 0, columns - 1)
    out: list[tuple[float, float]] = []
    starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    ends = np.r_[starts[1:], len(col)]
    for a, b in zip(starts.tolist(), ends.tolist()):
        seg = ys[a:b]
        i, j = int(np.argmin(seg)), int(np.argmax(seg))
        for k in sorted({i, j}):
            out.append((float(xs[a + k]), float(seg[k])))
    return out


def _chart(series: list[dict[str, Any]], x_max: int, hlines: list[tuple[float, str]], unit: str,
           empty: str = "nothing to plot") -> str:
    width, height = PLOT_WIDTH, PLOT_HEIGHT
    inner_w = width - MARGIN_LEFT - MARGIN_RIGHT
    inner_h = height - MARGIN_TOP - MARGIN_BOTTOM
    values: list[float] = [v for v, _ in hlines]
    for s in series:
        if s["kind"] == "line":
            ys = np.asarray(s["ys"], dtype=np.float64)
            values += [float(np.nanmin(ys)), float(np.nanmax(ys))] if np.isfinite(ys).any() else []
        elif s["kind"] == "dots":
            values += [y for _, y in s["points"]]
        elif s["kind"] == "links":
            values += [v for _, a, b in s["links"] for v in (a, b)]
    has_data = any((s["kind"] == "line" and len(s["xs"])) or s.get("points") or s.get("links") for s in series)
    lo, hi = (min(values), max(values)) if values else (0.0, 1.0)
    if unit == "°":
        lo = min(lo, 0.0)
    pad = (hi - lo) * 0.06 or 1.0
    lo, hi = lo - pad, hi + pad

    def x_of(x):
        return MARGIN_LEFT + (np.asarray(x, dtype=np.float64) - 1.0) / max(x_max - 1, 1) * inner_w

    def y_of(y):
        return MARGIN_TOP + (hi - np.asarray(y, dtype=np.float64)) / (hi - lo) * inner_h

    out = [f"<svg class=\"chart\" viewBox=\"0 0 {width} {height}\" width=\"{width}\" height=\"{height}\" "
           "xmlns=\"http://www.w3.org/2000/svg\" role=\"img\">"]
    out.append(f"<rect x=\"{MARGIN_LEFT}\" y=\"{MARGIN_TOP}\" width=\"{inner_w}\" height=\"{inner_h}\" class=\"frame\"/>")
    for t in _ticks(lo, hi, 5):
        y = float(y_of(t))
        out.append(f"<line x1=\"{MARGIN_LEFT}\" x2=\"{MARGIN_LEFT + inner_w}\" y1=\"{y:.1f}\" y2=\"{y:.1f}\" class=\"grid\"/>"
                   f"<text x=\"{MARGIN_LEFT - 6}\" y=\"{y + 4:.1f}\" class=\"ty\">{t:g}</text>")
    for t in _ticks(1, x_max, 10):
        x = float(x_of(t))
        out.append(f"<line x1=\"{x:.1f}\" x2=\"{x:.1f}\" y1=\"{MARGIN_TOP}\" y2=\"{MARGIN_TOP + inner_h}\" class=\"grid\"/>"
                   f"<text x=\"{x:.1f}\" y=\"{MARGIN_TOP + inner_h + 16}\" class=\"tx\">{int(t):,}</text>")
    out.append(f"<text x=\"{MARGIN_LEFT + inner_w / 2:.0f}\" y=\"{height - 4}\" class=\"tx\">line</text>"
               f"<text x=\"14\" y=\"{MARGIN_TOP + inner_h / 2:.0f}\" class=\"tx\" "
               f"transform=\"rotate(-90 14 {MARGIN_TOP + inner_h / 2:.0f})\">{escape(unit)}</text>")
    for value, label in hlines:
        y = float(y_of(value))
        out.append(f"<line x1=\"{MARGIN_LEFT}\" x2=\"{MARGIN_LEFT + inner_w}\" y1=\"{y:.1f}\" y2=\"{y:.1f}\" class=\"limit\"/>"
                   f"<text x=\"{MARGIN_LEFT + inner_w - 4}\" y=\"{y - 4:.1f}\" class=\"tl\">{escape(label)}</text>")
    legend = []
    for s in series:
        colour = s["colour"]
        if s["kind"] == "line":
            pts = _envelope(np.asarray(s["xs"]), np.asarray(s["ys"]), x_of, inner_w)
            if pts:
                xy = " ".join(f"{float(x_of(x)):.1f},{float(y_of(y)):.1f}" for x, y in pts)
                out.append(f"<polyline points=\"{xy}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.2\"/>")
        elif s["kind"] == "links":
            for x, a, b in s["links"]:
                px = float(x_of(x))
                out.append(f"<line x1=\"{px:.1f}\" x2=\"{px:.1f}\" y1=\"{float(y_of(a)):.1f}\" "
                           f"y2=\"{float(y_of(b)):.1f}\" stroke=\"{colour}\" stroke-width=\"1\"/>")
        else:
            for x, y in s["points"]:
                tip = escape(s["tip"].format(x=x, y=float(y)))
                out.append(f"<circle cx=\"{float(x_of(x)):.1f}\" cy=\"{float(y_of(y)):.1f}\" r=\"3\" fill=\"{colour}\">"
                           f"<title>{tip}</title></circle>")
        if s.get("label") and (s.get("points") or (s["kind"] == "line" and len(s["xs"]))):
            legend.append((s["label"], colour))
    for i, (label, colour) in enumerate(legend):
        x = MARGIN_LEFT + i * 220
        out.append(f"<rect x=\"{x}\" y=\"8\" width=\"10\" height=\"10\" fill=\"{colour}\"/>"
                   f"<text x=\"{x + 15}\" y=\"17\" class=\"lg\">{escape(label)}</text>")
    if not has_data:
        out.append(f"<text x=\"{MARGIN_LEFT + inner_w / 2:.0f}\" y=\"{MARGIN_TOP + inner_h / 2:.0f}\" class=\"tx\">"
                   f"{escape(empty)}</text>")
    out.append("</svg>")
    return "".join(out)


# -- 3-D view data -------------------------------------------------------------------------------


def _points(report: Report) -> tuple[list[list[float]], list[list[float]]]:
    """(red, green): points of blocks still colliding, and of changed blocks (workpiece mm)."""
    where: dict[int, list[float]] = {}
    if len(report.trace):
        cols = report.trace.columns()
        for line, p in zip(cols["line"].tolist(), cols["points"].tolist()):
            where[line] = p
    green = [list(map(float, e["point"])) for e in report.changes if e.get("point") is not None]
    still = report.collisions if report.options.check else report.unresolved
    red = []
    for e in still:
        p = e.get("point") if e.get("point") is not None else where.get(e.get("line"))
        if p is not None:
            red.append([float(v) for v in p])
    return red, green


def _winding(vertices: np.ndarray, faces: np.ndarray) -> int:
    """+1 (-1): the faces form a closed shell wound outward (inward), so the picture can skip the
    faces turned away from the viewer, which painting in depth order would draw over near ones;
    0: an open or inconsistently wound mesh (every face is drawn)."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return 0
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    directed = np.unique(edges[:, 0] * n + edges[:, 1])
    # closed and consistently wound: every edge once in each direction
    if len(directed) != len(edges) or not np.isin(edges[:, 1] * n + edges[:, 0], directed).all():
        return 0
    tri = np.asarray(vertices, dtype=np.float64)[f]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    return int(np.sign(volume))


def _view_data(report: Report) -> str:
    red, green = _points(report)
    path: list[float] = []
    if len(report.trace):
        path = np.round(report.trace.columns()["points"], 2).reshape(-1).tolist()
    data = {
        "meshes": [{"name": p.name, "v": np.round(p.vertices.astype(np.float64), 2).reshape(-1).tolist(),
                    "f": p.faces.reshape(-1).tolist(), "cull": _winding(p.vertices, p.faces)}
                   for p in report.previews],
        "path": path,
        "red": [round(v, 2) for p in red for v in p],
        "green": [round(v, 2) for p in green for v in p],
    }
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return text.replace("&", "\\u0026").replace("<", "\\u003c").replace(">", "\\u003e")


_CSS = """
:root{--red:#c62828;--green:#2e7d32;--ink:#1f2328;--mute:#59636e;--line:#d8dee4}
*{box-sizing:border-box}
body{margin:0;font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,sans-serif;color:var(--ink);background:#f6f8fa}
main{max-width:1360px;margin:0 auto;padding:20px 24px 60px}
h1{font-size:22px;margin:0 0 4px}h1 .file{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-weight:500}
h2{font-size:17px;margin:0 0 8px;display:inline-block}h2.bad{color:var(--red)}
section{background:#fff;border:1px solid var(--line);border-radius:8px;padding:14px 18px;margin:14px 0}
header{margin-bottom:6px}.meta{color:var(--mute);margin:0 0 10px}
.verdict{display:flex;gap:16px;align-items:center;border-radius:8px;padding:12px 16px;color:#fff}
.verdict.ok{background:var(--green)}.verdict.bad{background:var(--red)}
.verdict .exit{font:700 20px ui-monospace,Menlo,Consolas,monospace;white-space:nowrap;border:2px solid #fff;border-radius:6px;padding:4px 10px}
.verdict p{margin:0}.verdict .line{font-size:16px;font-weight:600}.verdict .means{opacity:.92}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(150px,1fr));gap:10px;background:none;border:0;padding:0}
.card{background:#fff;border:1px solid var(--line);border-radius:8px;padding:10px 12px}
.card .v{font-size:22px;font-weight:700}.card .k{color:var(--ink)}.card .n{color:var(--mute);font-size:12px}
.card.bad{border-color:var(--red)}.card.bad .v{color:var(--red)}
table{border-collapse:collapse;width:100%;font-variant-numeric:tabular-nums}
th,td{padding:4px 10px;border-bottom:1px solid var(--line);text-align:left;vertical-align:top}
th{background:#f6f8fa;font-weight:600}tbody tr:nth-child(even){background:#fafbfc}
th.n,td.n{text-align:right}
a{color:#0b57d0}.note{color:var(--mute)}
ul.warnings{margin:0;padding-left:20px}
details>summary{cursor:pointer;list-style:revert}
figure{margin:10px 0 16px}figcaption{font-weight:600;margin-bottom:4px}
svg.chart{width:100%;height:auto;background:#fff}
svg .frame{fill:none;stroke:#bbb}svg .grid{stroke:#eee}svg .limit{stroke:#ef6c00;stroke-dasharray:6 4}
svg text{font:11px system-ui,Arial,sans-serif;fill:#555}svg .ty{text-anchor:end}svg .tx{text-anchor:middle}
svg .tl{text-anchor:end;fill:#ef6c00}svg .lg{fill:#333}
canvas#view{width:100%;height:auto;border:1px solid var(--line);border-radius:6px;background:#fbfcfd;cursor:grab;touch-action:none}
.key{display:inline-block;width:11px;height:11px;border-radius:50%;margin:0 3px 0 10px;vertical-align:middle}
.key.line{border-radius:0;height:2px;width:18px;background:#607d8b}
button{margin-left:12px;font:inherit;padding:2px 10px}
.code{font:12.5px/1.5 ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;border:1px solid var(--line);border-radius:6px;overflow-x:auto}
.code .row{display:flex;white-space:pre}.code .ln{flex:0 0 70px;text-align:right;color:#8c959f;padding-right:10px;background:#f6f8fa;user-select:none}
.code .m{flex:0 0 18px;text-align:center}.code .t{padding-right:12px}
.code .minus{background:#ffebe9}.code .plus{background:#dafbe1}.code .hit{background:#fff1e5}.code .hit .m{color:var(--red);font-weight:700}
.code .gap{color:#8c959f;padding-left:80px;background:#f6f8fa}
.scroll{max-height:440px;overflow-y:auto;border:1px solid var(--line);border-radius:6px}
.scroll th{position:sticky;top:0;z-index:1}
ul.reasons{margin:4px 0 10px;padding-left:20px}
.code .row:target{outline:2px solid #0b57d0;outline-offset:-2px}
span.minus{color:var(--red);font-weight:700}span.plus{color:var(--green);font-weight:700}
"""

# The 3-D picture: orthographic view, painter's algorithm, flat shading; drag turns, wheel zooms.
# Sets data-ok on <body> when it has run to the end (tests read it with chromium --dump-dom).
_SCRIPT = r"""
window.addEventListener('error', function (e) { document.body.setAttribute('data-error', String(e.message)); });
(function () {
  var data = JSON.parse(document.getElementById('ncfix-data').textContent);
  var canvas = document.getElementById('view');
  if (!canvas) { document.body.setAttribute('data-ok', '1'); return; }
  var ctx = canvas.getContext('2d');
  var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  function grow(a) { for (var i = 0; i + 2 < a.length; i += 3) for (var k = 0; k < 3; k++) {
    if (a[i + k] < lo[k]) lo[k] = a[i + k]; if (a[i + k] > hi[k]) hi[k] = a[i + k]; } }
  data.meshes.forEach(function (m) { grow(m.v); }); grow(data.path); grow(data.red); grow(data.green);
  if (!isFinite(lo[0])) { lo = [0, 0, 0]; hi = [1, 1, 1]; }
  var centre = [0, 1, 2].map(function (k) { return (lo[k] + hi[k]) / 2; });
  var radius = Math.max(1e-6, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
  var yaw0 = -0.55, elev0 = 0.62, yaw = yaw0, elev = elev0, zoom = 1;
  function project(a) {
    var out = new Float32Array(a.length), cy = Math.cos(yaw), sy = Math.sin(yaw), ce = Math.cos(elev), se = Math.sin(elev);
    var s = zoom * 0.6 * Math.min(canvas.width, canvas.height) / radius;
    for (var i = 0; i + 2 < a.length; i += 3) {
      var x = a[i] - centre[0], y = a[i + 1] - centre[1], z = a[i + 2] - centre[2];
      var x1 = x * cy - y * sy, y1 = x * sy + y * cy;
      out[i] = canvas.width / 2 + x1 * s;
      out[i + 1] = canvas.height / 2 - (y1 * se + z * ce) * s;
      out[i + 2] = y1 * ce - z * se;  // depth: larger is farther
    }
    return out;
  }
  function draw() {
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    var ce = Math.cos(elev), se = Math.sin(elev);
    var vwx = -Math.sin(yaw) * ce, vwy = -Math.cos(yaw) * ce, vwz = se;  // towards the viewer, world frame
    data.meshes.forEach(function (m) {
      var p = project(m.v), f = m.f, n = f.length / 3, depth = new Float32Array(n), shade = new Float32Array(n);
      var order = new Uint32Array(n), hidden = new Uint8Array(n);
      for (var t = 0; t < n; t++) {
        var a = 3 * f[3 * t], b = 3 * f[3 * t + 1], c = 3 * f[3 * t + 2];
        depth[t] = p[a + 2] + p[b + 2] + p[c + 2];
        // normal in the world frame, then against the direction towards the viewer
        var ux = m.v[b] - m.v[a], uy = m.v[b + 1] - m.v[a + 1], uz = m.v[b + 2] - m.v[a + 2];
        var vx = m.v[c] - m.v[a], vy = m.v[c + 1] - m.v[a + 1], vz = m.v[c + 2] - m.v[a + 2];
        var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
        var len = Math.hypot(nx, ny, nz) || 1;
        var facing = (nx * vwx + ny * vwy + nz * vwz) / len;
        shade[t] = Math.abs(facing);
        hidden[t] = m.cull * facing < 0 ? 1 : 0;  // the back of a closed shell (m.cull: its winding)
        order[t] = t;
      }
      order.sort(function (i, j) { return depth[j] - depth[i]; });
      for (var k = 0; k < n; k++) {
        var t2 = order[k], a2 = 3 * f[3 * t2], b2 = 3 * f[3 * t2 + 1], c2 = 3 * f[3 * t2 + 2];
        if (hidden[t2]) continue;
        var g = 0.35 + 0.65 * shade[t2];
        var col = 'rgb(' + Math.round(150 * g) + ',' + Math.round(165 * g) + ',' + Math.round(185 * g) + ')';
        ctx.fillStyle = col; ctx.strokeStyle = col; ctx.lineWidth = 0.6;
        ctx.beginPath(); ctx.moveTo(p[a2], p[a2 + 1]); ctx.lineTo(p[b2], p[b2 + 1]); ctx.lineTo(p[c2], p[c2 + 1]);
        ctx.closePath(); ctx.fill(); ctx.stroke();
      }
    });
    if (data.path.length >= 6) {
      var q = project(data.path);
      ctx.strokeStyle = 'rgba(55,71,79,0.75)'; ctx.lineWidth = 1.2; ctx.beginPath();
      ctx.moveTo(q[0], q[1]);
      for (var i = 3; i + 2 < q.length; i += 3) ctx.lineTo(q[i], q[i + 1]);
      ctx.stroke();
    }
    [[data.green, '#2e7d32'], [data.red, '#c62828']].forEach(function (pair) {
      var r = project(pair[0]);
      ctx.fillStyle = pair[1]; ctx.strokeStyle = '#fff'; ctx.lineWidth = 1;
      for (var i = 0; i + 2 < r.length; i += 3) {
        ctx.beginPath(); ctx.arc(r[i], r[i + 1], 4, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      }
    });
  }
  var pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(function () { pending = false; draw(); }); } }
  var drag = null;
  canvas.addEventListener('pointerdown', function (e) { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener('pointermove', function (e) {
    if (!drag) return;
    yaw -= (e.clientX - drag[0]) * 0.01;
    elev = Math.max(-1.5, Math.min(1.5, elev + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY]; redraw();
  });
  canvas.addEventListener('pointerup', function () { drag = null; });
  canvas.addEventListener('wheel', function (e) {
    e.preventDefault(); zoom = Math.max(0.2, Math.min(20, zoom * Math.exp(-e.deltaY * 0.001))); redraw();
  }, { passive: false });
  var reset = document.getElementById('view-reset');
  if (reset) reset.addEventListener('click', function () { yaw = yaw0; elev = elev0; zoom = 1; redraw(); });
  draw();
  document.body.setAttribute('data-ok', '1');
})();
"""
