"""Draw the README's picture of what ncfix does: `python scripts/make_readme_figure.py [OUT_SVG]`.

Runs ncfix on the golden ijk case (tests/golden/fix_ijk/input.nc: a straight path along X with a wall
on its +Y side, the sample head vertical, the case's settings) and writes
docs/what-ncfix-does.svg (or OUT_SVG): a small, self-contained SVG written directly, no plotting
library. It shows

* a side view (the Y-Z plane, looking along the path) of the wall and of the head's silhouette at
  one block in the middle of the wall: as programmed (red, its body inside the wall) and as ncfix
  wrote it (green, tilted away from the wall about the tip C = P + 6·N, the pivot);
* a close-up of the corner where the body meets the wall;
* the tilt from the programmed orientation at every motion block: ramp in, plateau, ramp out,
  each step within ncfix's 2° per block.

Both programs are read with ncfix's own reader (``ncfix.nc.modal.Interpreter``) and posed with the
ijk profile's kinematics (tool vector N, head spin: the minimal rotation from +Z); the silhouette
is the convex hull of the head mesh's vertices projected on the plane.
"""

from __future__ import annotations

import io
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

import ncfix
from ncfix.geometry.frames import angle_between_deg
from ncfix.geometry.mesh import load_head, load_mesh
from ncfix.nc.modal import Interpreter
from ncfix.profiles import load_profile

REPO = Path(__file__).resolve().parents[1]
PROGRAM = REPO / "tests" / "golden" / "fix_ijk" / "input.nc"
WALL = REPO / "tests" / "golden" / "meshes" / "wall_x.stl"
HEAD = REPO / "samples" / "deposition_head.stl"
OUT = REPO / "docs" / "what-ncfix-does.svg"
STANDOFF_MM = 6.0  # ncfix's default: the tip C is 6 mm from the programmed point P along N
MAX_STEP_DEG = 2.0  # ncfix's default --max-step
TITLE = "ncfix tilts the head about its tip, just enough, and back"

RED, GREEN, INK, MUTED, WALL_FILL = "#c62828", "#2e7d32", "#263238", "#607d8b", "#cfd8dc"
WIDTH, HEIGHT = 1000, 610


@dataclass
class Poses:
    """Per motion block of a program: input line, tip C (n, 3), tool vector N (n, 3), rotation R (n, 3, 3)."""

    lines: np.ndarray
    tip: np.ndarray
    axis: np.ndarray
    rotation: np.ndarray


def fix_program() -> tuple[bytes, bytes, dict[int, float]]:
    """The golden ijk program, what ncfix makes of it (a real run, as tests/test_golden_fix.py does)
    and the head's clearance (mm) after the change, by input line of the changed blocks."""
    source = PROGRAM.read_bytes()
    fixed = io.BytesIO()
    report = ncfix.process(io.BytesIO(source), fixed, machine="ijk", head=str(HEAD), part=[str(WALL)],
                           bead_radius=0.0, strategy="graph")
    if report.exit_code != 0:
        raise SystemExit(f"ncfix did not fix {PROGRAM}: {report.verdict}")
    clearance_after = {change["line"]: change["clearance_after_mm"] for change in report.changes}
    return source, fixed.getvalue(), clearance_after


def read_poses(program: bytes) -> Poses:
    profile = load_profile("ijk")
    chunk = Interpreter(profile).feed_chunk(program.splitlines(keepends=True), 1)
    rows = np.nonzero(chunk.motion >= 0)[0]
    point, axis, rotation = profile.kinematics.forward(chunk.words[rows])  # X Y Z I J K per block
    return Poses(rows + 1, point + STANDOFF_MM * axis, axis, rotation)


def side_view(points: np.ndarray) -> np.ndarray:
    """Project workpiece points (n, 3) on the Y-Z plane (looking along the path, -X): (n, 2)."""
    return points[:, 1:3]


def silhouette(vertices: np.ndarray) -> np.ndarray:
    """The convex outline (k, 2) of vertices (n, 3) in the side view, in order."""
    flat = side_view(vertices)
    return flat[ConvexHull(flat).vertices]


def overlap(subject: np.ndarray, convex: np.ndarray) -> np.ndarray:
    """The part (k, 2) of polygon ``subject`` inside the convex polygon ``convex`` (counter-clockwise,
    as ConvexHull gives it): Sutherland-Hodgman clipping; empty (0, 2) when they do not overlap."""
    out = list(subject)
    for a, b in zip(convex, np.roll(convex, -1, axis=0)):
        edge = b - a
        side = [edge[0] * (p[1] - a[1]) - edge[1] * (p[0] - a[0]) for p in out]  # >= 0: inside
        clipped = []
        for k in range(len(out)):
            p, q, sp, sq = out[k - 1], out[k], side[k - 1], side[k]
            if (sp >= 0) != (sq >= 0):
                clipped.append(p + (q - p) * sp / (sp - sq))
            if sq >= 0:
                clipped.append(q)
        out = clipped
        if not out:
            break
    return np.array(out).reshape(-1, 2)


class Frame:
    """Maps side-view millimetres (y, z) into an SVG box (left, top, width, height), z up, 1:1."""

    def __init__(self, box: tuple[float, float, float, float], y_range: tuple[float, float],
                 z_range: tuple[float, float]):
        self.left, self.top, width, height = box
        self.y0, self.z1 = y_range[0], z_range[1]
        self.scale = min(width / (y_range[1] - y_range[0]), height / (z_range[1] - z_range[0]))

    def xy(self, yz: np.ndarray) -> np.ndarray:
        yz = np.atleast_2d(yz)
        return np.stack([self.left + (yz[:, 0] - self.y0) * self.scale,
                         self.top + (self.z1 - yz[:, 1]) * self.scale], axis=1)


def polygon(points: np.ndarray, **style: str) -> str:
    coords = " ".join(f"{x:.1f},{y:.1f}" for x, y in points)
    return f'<polygon points="{coords}"{attributes(style)}/>'


def polyline(points: np.ndarray, **style: str) -> str:
    coords = " ".join(f"{x:.1f},{y:.1f}" for x, y in points)
    return f'<polyline points="{coords}" fill="none"{attributes(style)}/>'


def line(a, b, **style: str) -> str:
    return f'<line x1="{a[0]:.1f}" y1="{a[1]:.1f}" x2="{b[0]:.1f}" y2="{b[1]:.1f}"{attributes(style)}/>'


def circle(centre, radius: float, **style: str) -> str:
    return f'<circle cx="{centre[0]:.1f}" cy="{centre[1]:.1f}" r="{radius:g}"{attributes(style)}/>'


def text(at, content: str, **style: str) -> str:
    return f'<text x="{at[0]:.1f}" y="{at[1]:.1f}"{attributes(style)}>{content}</text>'


def attributes(style: dict[str, str]) -> str:
    return "".join(f' {key.replace("_", "-")}="{value}"' for key, value in style.items())


def scene(frame: Frame, wall: np.ndarray, before: np.ndarray, after: np.ndarray, clip: str | None = None) -> list[str]:
    """The wall and both head outlines in ``frame`` (optionally clipped to an SVG clipPath id)."""
    group = f'<g clip-path="url(#{clip})">' if clip else "<g>"
    out = [group, polygon(frame.xy(wall), fill=WALL_FILL, stroke=MUTED, stroke_width="1.2")]
    for head, colour in ((before, RED), (after, GREEN)):
        inside = overlap(head, wall)
        if len(inside) >= 3:
            out.append(polygon(frame.xy(inside), fill=colour, fill_opacity="0.55"))
        out.append(polygon(frame.xy(head), fill=colour, fill_opacity="0.10", stroke=colour, stroke_width="2"))
    return out + ["</g>"]


def tilt_panel(box: tuple[float, float, float, float], tilt: np.ndarray, step: np.ndarray, shown: int) -> list[str]:
    """Tilt (°) per motion block, and the largest orientation step (°) between blocks; ``shown``:
    the block of the side view (1-based)."""
    left, top, width, height = box
    top_deg = np.ceil(tilt.max() / 2.0) * 2.0 + 2.0  # room for a line of text above the plateau
    blocks = np.arange(1, len(tilt) + 1)

    def xy(block, deg):
        return np.stack([left + (np.asarray(block) - 1) / (len(tilt) - 1) * width,
                         top + height - np.asarray(deg) / top_deg * height], axis=-1)

    out = [text((left, top - 14), "Tilt from the programmed orientation, per block", font_weight="600")]
    for deg in np.arange(0.0, top_deg + 1e-9, 2.0):
        a, b = xy(1, deg), xy(len(tilt), deg)
        out.append(line(a, b, stroke="#eceff1"))
        out.append(text((a[0] - 8, a[1] + 4), f"{deg:g}°", text_anchor="end", font_size="11", fill=MUTED))
    for block in range(10, len(tilt) + 1, 10):
        a = xy(block, 0)
        out.append(line(a, (a[0], a[1] + 4), stroke=MUTED))
        out.append(text((a[0], a[1] + 17), str(block), text_anchor="middle", font_size="11", fill=MUTED))
    out.append(line(xy(1, 0), xy(len(tilt), 0), stroke=MUTED))
    out.append(text((left + width / 2, top + height + 34), "motion block (program order)", text_anchor="middle",
                    font_size="12", fill=MUTED))
    marker = xy(shown, 0), xy(shown, top_deg)
    out.append(line(*marker, stroke=MUTED, stroke_dasharray="3 3"))
    out.append(text((marker[0][0] + 4, marker[0][1] - 6), "side view", font_size="11", fill=MUTED))
    out.append(polyline(xy(blocks, tilt), stroke=GREEN, stroke_width="2"))
    changed = tilt > 1e-6
    out.extend(circle(p, 2.6, fill=GREEN) for p in xy(blocks[changed], tilt[changed]))

    moving = np.nonzero(changed)[0]
    first, last = moving[0] + 1, moving[-1] + 1
    plateau = float(np.median(tilt[changed]))
    ramp_in, ramp_out = xy(first, plateau / 2), xy(last, plateau / 2)
    out.append(text((ramp_in[0] - 8, ramp_in[1]), "ramp in", text_anchor="end", font_size="12"))
    out.append(text((ramp_out[0] + 8, ramp_out[1]), "ramp out", font_size="12"))
    at = xy((shown + last) / 2, plateau)
    out.append(text((at[0], at[1] + 18), f"plateau {plateau:.1f}°", text_anchor="middle", font_size="12"))
    out.append(text((left + 6, top + 12), f"largest step {step.max():.2f}° ≤ {MAX_STEP_DEG:g}° per block",
                    font_size="12"))
    return out


def legend(at: tuple[float, float]) -> list[str]:
    x, y = at
    rows = [(RED, 0.15, RED, "as programmed: hits the wall"),
            (GREEN, 0.15, GREEN, "as ncfix wrote it: just clear"),
            (WALL_FILL, 1.0, MUTED, "the wall (the part)")]
    out = []
    for k, (fill, opacity, stroke, label) in enumerate(rows):
        row_y = y + 24 * k
        out.append(f'<rect x="{x}" y="{row_y - 10}" width="18" height="12" fill="{fill}" fill-opacity="{opacity}" '
                   f'stroke="{stroke}" stroke-width="2"/>')
        out.append(text((x + 26, row_y), label))
    row_y = y + 24 * len(rows)
    out.append(circle((x + 9, row_y - 4), 4.5, fill="#fff", stroke=INK, stroke_width="2"))
    out.append(text((x + 26, row_y), "tip C = P + 6·N, the pivot"))
    out.append(text((x + 26, row_y + 18), "(it stays where it was)", font_size="12", fill=MUTED))
    return out


def angle_arc(frame: Frame, centre: np.ndarray, radius: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Points (k, 2) of the arc of ``radius`` mm about ``centre`` from direction a to b (side view)."""
    start, stop = np.arctan2(a[1], a[0]), np.arctan2(b[1], b[0])
    angles = np.linspace(start, stop, 24)
    return frame.xy(centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1))


def draw(source: Poses, fixed: Poses, clearance_after: dict[int, float], head_vertices: np.ndarray,
         wall_vertices: np.ndarray) -> str:
    tilt = angle_between_deg(fixed.axis, source.axis)
    changed = np.nonzero(tilt > 1e-6)[0]
    shown = int(changed[len(changed) // 2])  # mid-wall, on the plateau
    tip = source.tip[shown]
    before = silhouette(tip + head_vertices @ source.rotation[shown].T)
    after = silhouette(fixed.tip[shown] + head_vertices @ fixed.rotation[shown].T)
    wall = silhouette(wall_vertices)
    tip_yz = side_view(tip[None])[0]
    axis_before, axis_after = side_view(source.axis[shown][None])[0], side_view(fixed.axis[shown][None])[0]

    out = [(f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" '
            f'font-family="DejaVu Sans, Helvetica, Arial, sans-serif" font-size="13" fill="{INK}">'),
           f'<rect width="{WIDTH}" height="{HEIGHT}" fill="#ffffff"/>',
           text((24, 34), TITLE, font_size="21", font_weight="700"),
           text((24, 56), f"{PROGRAM.relative_to(REPO)}: a path along X beside a wall, the head vertical; "
                          f"ncfix changed {len(changed)} of its {len(tilt)} motion blocks", fill=MUTED)]

    # Side view: the whole head and the wall.
    view = Frame((40, 100, 360, 470), (-75.0, 45.0), (-16.0, 133.0))
    out.append(text((40, 86), f"Side view at line {source.lines[shown]}, looking along the path (−X)",
                    font_weight="600"))
    out += scene(view, wall, before, after)
    for axis, colour in ((axis_before, RED), (axis_after, GREEN)):
        out.append(line(view.xy(tip_yz)[0], view.xy(tip_yz + 118.0 * axis)[0], stroke=colour, stroke_width="1.2",
                        stroke_dasharray="5 4"))
    arc = angle_arc(view, tip_yz, 100.0, axis_before, axis_after)
    out.append(polyline(arc, stroke=INK, stroke_width="1.2"))
    out.append(text(arc[-1] + (-6, -6), f"{tilt[shown]:.1f}°", text_anchor="end", font_size="12", font_weight="600"))
    path_at = view.xy(side_view((source.tip[shown] - STANDOFF_MM * source.axis[shown])[None]))[0]
    out.append(circle(path_at, 3, fill=INK))
    out.append(text(path_at + (-8, 16), "P: the path (runs along X)", text_anchor="end", font_size="12"))
    out.append(circle(view.xy(tip_yz)[0], 4.5, fill="#fff", stroke=INK, stroke_width="2"))
    out.append(text(view.xy(tip_yz)[0] + (10, 5), "C", font_weight="700"))
    out.append(text(view.xy((32.5, -15.0))[0], "wall", text_anchor="middle", font_size="12", fill=MUTED))
    out.append(text(view.xy((-74.0, -15.0))[0], "← −Y", font_size="12", fill=MUTED))
    out.append(text(view.xy((44.0, -15.0))[0] + (0, 16), "+Y →", text_anchor="end", font_size="12", fill=MUTED))

    # Close-up of the corner of the body and the wall.
    corner_y, corner_z = (18.0, 34.0), (24.0, 42.0)
    zoom = Frame((450, 100, 240, 270), corner_y, corner_z)
    box = np.array([[corner_y[0], corner_z[1]], [corner_y[1], corner_z[0]]])
    (x0, y0), (x1, y1) = zoom.xy(box)
    out.append(f'<clipPath id="closeup"><rect x="{x0:.1f}" y="{y0:.1f}" width="{x1 - x0:.1f}" '
               f'height="{y1 - y0:.1f}"/></clipPath>')
    out.append(text((x0, 86), "Close-up: the body's corner at the wall", font_weight="600"))
    out += scene(zoom, wall, before, after, clip="closeup")
    for frame in (zoom, view):
        (a0, b0), (a1, b1) = frame.xy(box)
        dash = "none" if frame is zoom else "3 2"
        out.append(f'<rect x="{a0:.1f}" y="{b0:.1f}" width="{a1 - a0:.1f}" height="{b1 - b0:.1f}" fill="none" '
                   f'stroke="{MUTED}" stroke-dasharray="{dash}"/>')
    depth = np.ptp(overlap(before, wall)[:, 0])
    out.append(text((x0, y1 + 18), f"red: the body {depth:.0f} mm inside the wall", font_size="12", fill=RED,
                    font_weight="600"))
    out.append(text((x0, y1 + 34), f"green: {clearance_after[int(source.lines[shown])]:.2f} mm clear of it",
                    font_size="12", fill=GREEN, font_weight="600"))
    bar = zoom.xy(np.array([[corner_y[0] + 1.0, corner_z[1] - 1.5], [corner_y[0] + 6.0, corner_z[1] - 1.5]]))
    out.append(line(bar[0], bar[1], stroke=INK, stroke_width="2"))
    out.append(text(bar[0] + (0, -6), "5 mm", font_size="11", fill=MUTED))

    out += legend((720, 130))
    step = angle_between_deg(fixed.axis[1:], fixed.axis[:-1])
    out += tilt_panel((500, 450, 470, 100), tilt, step, shown + 1)
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) > 1:
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    out = Path(argv[0]) if argv else OUT
    source, fixed, clearance_after = fix_program()
    head = load_head(str(HEAD)).mesh.vertices
    wall = load_mesh(str(WALL), "part").mesh.vertices
    out.parent.mkdir(parents=True, exist_ok=True)
    picture = draw(read_poses(source), read_poses(fixed), clearance_after, np.asarray(head), np.asarray(wall))
    out.write_text(picture, encoding="utf-8")
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
