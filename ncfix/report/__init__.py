"""What ncfix found and changed: the JSON report (schema 1), the unified diff, and the data the HTML plots."""

from __future__ import annotations

import json
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ncfix.config import OPTION_NAMES
from ncfix.fileio import atomic_output, atomic_write_text
from ncfix.version import __version__

if TYPE_CHECKING:
    import trimesh

    from ncfix.geometry.meshdata import Mesh

    from ncfix.config import Options
    from ncfix.nc.chunk import Chunk

# Bounds that keep a report's memory independent of the program's length (millions of blocks).
TRACE_POINTS = 20_000  # regular trace points kept for the plots; changed blocks (tilt > 0) are kept on top
PREVIEW_FACES = 20_000  # triangles per part preview in the HTML's 3-D picture
CONTEXT_LINES = 3  # program lines kept before and after each changed or colliding line (HTML program text)
CONTEXT_FOCI = 2_000  # changed/colliding lines that get program text; later ones are listed without it

# Columns of a trace row (float64): sequence number along the program, line, point, tilt, step, clearance.
_SEQ, _LINE, _X, _Y, _Z, _TILT, _STEP, _CLEAR = range(8)


class Trace:
    """Per motion block values along the program, decimated to a bounded number of rows.

    Rows arrive in program order. Every ``stride``-th block is kept; when more than ``limit`` are
    kept, every other one is dropped and the stride doubles. Blocks with ``tilt_deg > 0`` (changed)
    are always kept, so no change disappears from the plots.
    """

    def __init__(self, limit: int = TRACE_POINTS):
        self.limit = limit
        self.stride = 1
        self.seen = 0  # motion blocks passed to add()
        self._regular: list[np.ndarray] = []
        self._regular_rows = 0
        self._changed: list[np.ndarray] = []

    def add(self, lines, points, tilt_deg, step_deg, clearance_mm=None) -> None:
        lines = np.asarray(lines, dtype=np.float64).reshape(-1)
        n = len(lines)
        points = np.asarray(points, dtype=np.float64).reshape(n, 3)
        tilt = np.asarray(tilt_deg, dtype=np.float64).reshape(n)
        step = np.asarray(step_deg, dtype=np.float64).reshape(n)
        clear = np.full(n, np.nan) if clearance_mm is None else np.asarray(clearance_mm, dtype=np.float64).reshape(n)
        if n == 0:
            return
        seq = np.arange(self.seen, self.seen + n, dtype=np.float64)
        self.seen += n
        rows = np.column_stack([seq, lines, points, tilt, step, clear])
        changed = tilt > 0
        if changed.any():
            self._changed.append(rows[changed])
        keep = ~changed & (seq.astype(np.int64) % self.stride == 0)
        if keep.any():
            self._regular.append(rows[keep])
            self._regular_rows += int(keep.sum())
        while self._regular_rows > self.limit:
            kept = np.concatenate(self._regular)
            self.stride *= 2
            kept = kept[kept[:, _SEQ].astype(np.int64) % self.stride == 0]
            self._regular, self._regular_rows = [kept], len(kept)

    def rows(self) -> np.ndarray:
        """(m, 8) float64 rows in program order: seq, line, x, y, z (workpiece mm), tilt °, step °, clearance mm."""
        parts = self._regular + self._changed
        if not parts:
            return np.zeros((0, 8))
        rows = np.concatenate(parts)
        return rows[np.argsort(rows[:, _SEQ], kind="stable")]

    def columns(self) -> dict[str, np.ndarray]:
        rows = self.rows()
        return {"line": rows[:, _LINE].astype(np.int64), "points": rows[:, _X:_Z + 1], "tilt_deg": rows[:, _TILT],
                "step_deg": rows[:, _STEP], "clearance_mm": rows[:, _CLEAR]}

    def __len__(self) -> int:
        return self._regular_rows + sum(len(c) for c in self._changed)


@dataclass
class PartPreview:
    """A decimated copy of a part mesh for the HTML's 3-D picture.

    vertices : (v, 3) float32, workpiece mm; faces : (f, 3) int32; source_faces: the mesh's own count.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    source_faces: int


def decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int = PREVIEW_FACES) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering: merge the vertices in each cube of a grid, drop collapsed and repeated faces.

    The cube grows by 1.3× until at most ``max_faces`` remain. Good enough for a picture (it is not
    used for any check); needs nothing beyond numpy.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) <= max_faces or len(vertices) == 0:
        return vertices.astype(np.float32), faces.astype(np.int32)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    extent = float(np.ptp(vertices, axis=0).max()) or 1.0
    cell = max(np.sqrt(2.0 * area / max_faces), extent * 1e-4)
    low = vertices.min(axis=0)
    while True:
        keys = np.floor((vertices - low) / cell).astype(np.int64)
        _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.reshape(-1)
        merged = np.zeros((len(counts), 3))
        np.add.at(merged, cluster, vertices)
        merged /= counts[:, None]
        new = cluster[faces]
        alive = (new[:, 0] != new[:, 1]) & (new[:, 1] != new[:, 2]) & (new[:, 0] != new[:, 2])
        new = new[alive]
        if len(new):
            _, first = np.unique(np.sort(new, axis=1), axis=0, return_index=True)
            new = new[np.sort(first)]
        if len(new) <= max_faces:
            used, remap = np.unique(new.reshape(-1), return_inverse=True)
            return merged[used].astype(np.float32), remap.reshape(-1, 3).astype(np.int32)
        cell *= 1.3


@dataclass
class Report:
    """Everything a run found and changed.

    Filled by the stages (summary counts, ``changes``, ``unresolved``, ``collisions``, warnings,
    trace, part previews) and by ``pipeline.run`` through :meth:`record_emitted` (``diff_lines`` and
    the program text around changed and colliding lines, both taken from the bytes written).
    """

    input: str
    machine: str
    options: "Options"
    summary: dict[str, Any] = field(default_factory=lambda: {
        "lines": 0, "motion_blocks": 0, "colliding_blocks_before": 0, "changed_blocks": 0,
        "unresolved_blocks": 0, "max_tilt_deg": 0.0, "max_step_deg": 0.0, "seconds": 0.0,
    })
    # {"line", "before", "after", "reason": "collision"|"blend", "tilt_deg", "step_deg", "bodies",
    #  "clearance_before_mm", "clearance_after_mm", "point": [x, y, z] (programmed point after)}
    changes: list[dict[str, Any]] = field(default_factory=list)
    # {"line", "bodies", "penetration_mm", "where", "reason": why it could not be fixed}
    unresolved: list[dict[str, Any]] = field(default_factory=list)
    # {"line", "bodies", "penetration_mm", "clearance_mm", "where": "end"|"sweep"}: as found before any
    # change; in fix mode also "outcome": "tilted"|"freed"|"unresolved" ("note" on a freed one) and,
    # on one found only after ncfix rewrote the blocks before it, "detected" (why)
    collisions: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    details: list[str] = field(default_factory=list)  # shown with -v (e.g. the head model's counts)
    notes: list[str] = field(default_factory=list)  # always shown (e.g. the time of a cold CoACD run)
    diff_lines: list[tuple[int, str, str]] = field(default_factory=list)  # (line, before, after), raw text with ends
    trace: Trace = field(default_factory=Trace)
    previews: list[PartPreview] = field(default_factory=list)
    # line → (input text, output text or None when unchanged), line ends stripped; see CONTEXT_LINES
    context: dict[int, tuple[str, str | None]] = field(default_factory=dict)
    context_truncated: bool = False
    _cursors: dict[str, int] = field(default_factory=lambda: {"changes": 0, "collisions": 0, "unresolved": 0},
                                     repr=False)
    _tail: deque = field(default_factory=lambda: deque(maxlen=CONTEXT_LINES), repr=False)
    _pending: list = field(default_factory=list, repr=False)  # (first, last) line ranges still to capture
    _focused: set = field(default_factory=set, repr=False)
    _unfilled: list = field(default_factory=list, repr=False)  # changes whose before/after text is still to come

    def count(self, chunk: "Chunk") -> None:
        self.summary["lines"] += len(chunk)
        self.summary["motion_blocks"] += int((chunk.motion >= 0).sum())

    # -- data for the plots (called by the correction stage) -------------------------------------

    def add_trace(self, lines, points, tilt_deg, step_deg, clearance_mm=None) -> None:
        """Values per motion block, in program order (call per window).

        lines : (n,) int, input line numbers; points : (n, 3) float, programmed points after the
        change (workpiece mm); tilt_deg, step_deg : (n,) float; clearance_mm : (n,) float or None.
        At most ``TRACE_POINTS`` rows are kept, plus every row with ``tilt_deg > 0``.
        """
        self.trace.add(lines, points, tilt_deg, step_deg, clearance_mm)

    def add_part_preview(self, name: str, mesh: Mesh | trimesh.Trimesh) -> None:
        """Keep a copy of a part mesh with at most ``PREVIEW_FACES`` triangles for the 3-D picture."""
        vertices, faces = decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), PREVIEW_FACES)
        self.previews.append(PartPreview(name, vertices, faces, int(len(mesh.faces))))

    # -- what was written (called by pipeline.run for every emitted chunk) -----------------------

    def add_restated(self, line: int) -> None:
        """A block rewritten only to restate words that a changed block before it altered (its
        own move is as programmed): a ``blend`` change without tilt."""
        self.changes.append({"line": int(line), "before": None, "after": None, "reason": "blend", "tilt_deg": 0.0,
                             "step_deg": None, "bodies": [], "clearance_before_mm": None, "clearance_after_mm": None,
                             "note": "restates programmed words that the changed block before it left out"})
        self.summary["changed_blocks"] += 1

    def record_emitted(self, first_lineno: int, lines: list[bytes], rendered: bytes) -> None:
        """Note the changed lines (for the diff) and the text around changed and colliding lines."""
        joined = b"".join(lines)
        out_lines: list[bytes] | None = None
        if rendered != joined:
            out_lines = split_lines(rendered)
            if len(out_lines) != len(lines):  # the writer never adds or removes lines; do not guess
                self.warnings.append(f"lines {first_lineno}-{first_lineno + len(lines) - 1}: the output has "
                                     f"{len(out_lines)} lines for {len(lines)} input lines; no diff for them")
                out_lines = None
        last = first_lineno + len(lines) - 1
        foci: set[int] = set()
        if out_lines is not None:
            for i, (before, after) in enumerate(zip(lines, out_lines)):
                if before != after:
                    line = first_lineno + i
                    self.diff_lines.append((line, before.decode("latin-1"), after.decode("latin-1")))
                    foci.add(line)
        for name in ("changes", "collisions", "unresolved"):
            entries = getattr(self, name)
            for entry in entries[self._cursors[name]:]:
                line = entry.get("line")
                if isinstance(line, int):
                    foci.add(line)
                    if name == "changes" and (entry.get("before") is None or entry.get("after") is None):
                        self._unfilled.append(entry)
            self._cursors[name] = len(entries)
        waiting = []
        for entry in self._unfilled:  # a change's text, from the bytes read and written
            line = entry["line"]
            if line > last:
                waiting.append(entry)
            elif line >= first_lineno:
                i = line - first_lineno
                if entry.get("before") is None:
                    entry["before"] = _strip(lines[i].decode("latin-1"))
                if entry.get("after") is None:
                    after = out_lines[i] if out_lines is not None else lines[i]
                    entry["after"] = _strip(after.decode("latin-1"))
        self._unfilled = waiting
        self._capture(first_lineno, lines, out_lines, foci)

    def _capture(self, first: int, lines: list[bytes], out_lines: list[bytes] | None, foci: set[int]) -> None:
        last = first + len(lines) - 1
        for line in sorted(foci):
            if line in self._focused:
                continue
            if len(self._focused) >= CONTEXT_FOCI:
                self.context_truncated = True
                break
            self._focused.add(line)
            self._pending.append((max(1, line - CONTEXT_LINES), line + CONTEXT_LINES))

        def text(i: int) -> tuple[str, str | None]:
            after = None
            if out_lines is not None and out_lines[i] != lines[i]:
                after = _strip(out_lines[i].decode("latin-1"))
            return _strip(lines[i].decode("latin-1")), after

        still: list[tuple[int, int]] = []
        for lo, hi in self._pending:
            for line, before, after in self._tail:  # context just before this chunk
                if lo <= line <= hi:
                    self.context.setdefault(line, (before, after))
            for line in range(max(lo, first), min(hi, last) + 1):
                if line not in self.context:
                    self.context[line] = text(line - first)
            if hi > last:
                still.append((lo, hi))
        self._pending = still
        for i in range(max(0, len(lines) - CONTEXT_LINES), len(lines)):
            self._tail.append((first + i, *text(i)))

    # -- results ---------------------------------------------------------------------------------

    @property
    def exit_code(self) -> int:
        """0: no collision left; 1: collisions remain (docs/contract.md)."""
        if self.options.check:
            return 1 if self.summary["colliding_blocks_before"] else 0
        return 1 if self.summary["unresolved_blocks"] else 0

    def changed_by_reason(self) -> dict[str, int]:
        counts = {"collision": 0, "blend": 0}
        for change in self.changes:
            reason = str(change.get("reason", "collision"))
            counts[reason] = counts.get(reason, 0) + 1
        return counts

    @property
    def verdict(self) -> str:
        """One line a newcomer understands: what happened and the exit status."""
        s = self.summary
        found = int(s["colliding_blocks_before"])
        if self.options.head is None:
            return "no --head given: the program was read and passed through unchanged: exit 0"
        if self.options.check:
            if not found:
                return "no colliding block found: exit 0"
            return (f"{plural(found, 'colliding block')} found; --check leaves the program as it is "
                    "(run without --check to fix them): exit 1")
        unresolved = int(s["unresolved_blocks"])
        by_reason = self.changed_by_reason()
        tilted, blended = by_reason.get("collision", 0), by_reason.get("blend", 0)
        if unresolved:
            fixed = max(found - unresolved, 0)
            return (f"{plural(unresolved, 'colliding block')} could not be fixed and {_is(unresolved)} left as "
                    f"programmed ({fixed} of {found} fixed): exit 1")
        if not found and not self.changes:
            return "no colliding block: the program is written unchanged: exit 0"
        freed = int(s.get("freed_blocks", 0))
        left = (f", {plural(freed, 'block')} freed by the change of the blocks before {'it' if freed == 1 else 'them'}"
                " (left as programmed)") if freed else ""
        return (f"all {plural(found, 'colliding block')} fixed: {plural(tilted, 'block')} tilted{left}, "
                f"{plural(blended, 'ramp block')} blended; the output has no detected collision: exit 0")

    def exit_meaning(self) -> str:
        """What the exit status means for this run (docs/contract.md), in a sentence."""
        if self.exit_code == 0:
            return "Exit status 0: the output has no detected collision."
        if self.options.check:
            return "Exit status 1: colliding blocks found; --check writes the program unchanged."
        return ("Exit status 1: collisions remain. The output was written; the unresolved blocks are "
                "left as programmed.")

    def to_json(self) -> dict[str, Any]:
        settings = {k: v for k, v in asdict(self.options).items() if k in OPTION_NAMES}  # the user's options
        settings = {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}
        return {
            "schema": 1,
            "ncfix": __version__,
            "input": self.input,
            "machine": self.machine,
            "settings": settings,
            "summary": dict(self.summary),
            "changes": self.changes,
            "unresolved": self.unresolved,
            "collisions": self.collisions,
            "warnings": self.warnings,
        }

    def write_json(self, path: str) -> None:
        atomic_write_text(path, json.dumps(self.to_json(), indent=2, default=_json_default) + "\n")

    def unified_diff(self, source: str, target: str) -> str:
        """A unified diff of the changed lines (one hunk each, no context: lines never move).

        Lines keep their own ends (CRLF stays CRLF), so ``patch`` reproduces the output byte for
        byte; a last line without a newline gets the usual ``\\ No newline at end of file`` marker.
        The text is latin-1 (one character per byte, as the program was read): write it with
        :meth:`write_diff`.
        """
        if not self.diff_lines:
            return ""
        out = [f"--- {source}\n", f"+++ {target}\n"]
        for line, before, after in sorted(self.diff_lines):
            out.append(f"@@ -{line},1 +{line},1 @@\n")
            out.append("-" + _diff_body(before))
            out.append("+" + _diff_body(after))
        return "".join(out)

    def write_diff(self, path: str, source: str, target: str) -> None:
        with atomic_output(path) as handle:
            handle.write(self.unified_diff(source, target).encode("latin-1"))


def split_lines(data: bytes) -> list[bytes]:
    """Split at ``\\n`` only, ends kept (as the reader splits: a lone ``\\r`` is not a line end)."""
    parts = data.split(b"\n")
    out = [p + b"\n" for p in parts[:-1]]
    if parts[-1]:
        out.append(parts[-1])
    return out


def _strip(text: str) -> str:
    return text.rstrip("\r\n")


def _diff_body(text: str) -> str:
    if text.endswith("\n"):
        return text
    return text + "\n\\ No newline at end of file\n"


def plural(count: int, noun: str) -> str:
    """"3 blocks", "1 block"."""
    return f"{count:,} {noun}{'' if count == 1 else 's'}"


def _is(count: int) -> str:
    return "is" if count == 1 else "are"


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} to the JSON report")


def rescaled_note(by_reason: dict) -> str:
    """", N with only E or F rescaled" when a fix rewrote such blocks (ncfix.correct.extrusion)."""
    n = by_reason.get("extrusion rescaled", 0) + by_reason.get("feed rescaled", 0)
    return f", {n:,} with only E or F rescaled" if n else ""
