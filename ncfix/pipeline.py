"""The only module that wires the stages: read → modal state → window stages → emit → write."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import BinaryIO, Protocol

import numpy as np

from ncfix.config import Options
from ncfix.errors import ConfigError
from ncfix.fileio import input_size
from ncfix.kinematics.poses import PoseMap, program_poses
from ncfix.nc.chunk import Chunk
from ncfix.nc.modal import COMPILED_AFTER_LINES, Interpreter
from ncfix.nc.orientation import resolve_auto
from ncfix.nc.writer import Writer
from ncfix.profiles import Profile, load_profile
from ncfix.report import Report

AUTO = "auto"  # --machine auto: the profile is chosen from the program (ncfix.nc.orientation)
CHUNK_LINES = 4096  # lines read and interpreted together; memory is bounded by this and the window
# A motion line takes about this many bytes or more: a regular file larger than this many times
# ncfix.nc.modal.COMPILED_AFTER_LINES is read with the compiled reader from its first line.
LINE_BYTES = 40


@dataclass(frozen=True)
class ProgramPoints:
    """Where a program's points are (``program_box``): the box of its programmed points and tips
    (arcs: their whole circle), and the cubes (``collision.grid.cube_cells``) holding its points,
    tips and points along its arcs."""

    box: np.ndarray  # (2, 3) mm
    cubes: np.ndarray  # (k, 3) int64


class Stage(Protocol):
    """A streaming stage: takes chunks in order, gives back the chunks it is done with."""

    def push(self, chunk: Chunk) -> Iterable[Chunk]: ...

    def flush(self) -> Iterable[Chunk]: ...


def read_chunks(stream: BinaryIO, interpreter: Interpreter, lines_per_chunk: int = CHUNK_LINES) -> Iterator[Chunk]:
    """The input as chunks of raw lines (bytes, ends kept), each read by the modal interpreter."""
    take = getattr(stream, "take", None)  # ncfix.fileio.Input reads a chunk's lines in one call
    lineno = 1
    while True:
        lines = take(lines_per_chunk) if take is not None else list(islice(stream, lines_per_chunk))
        if not lines:
            return
        yield interpreter.feed_chunk(lines, lineno)
        lineno += len(lines)


def program_box(stream: BinaryIO, profile: Profile, options: Options, source: str) -> ProgramPoints | None:
    """Where the program's points are, read in a first pass over a seekable file (which is then
    rewound); None for a pipe or a program without a checkable motion block. The part grids are
    cropped to the box and their exact band made where the head can reach (``build_stages``)."""
    from ncfix.collision.grid import REACH_CELL_MM, cube_cells
    from ncfix.collision.path import arc_extent, arc_points

    try:
        if not stream.seekable():
            return None
        start = stream.tell()
    except (AttributeError, OSError, ValueError):
        return None
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    cubes, last = [np.zeros((0, 3), dtype=np.int64)], None
    try:
        chunks = read_chunks(stream, Interpreter(profile, source, options.deposit_codes, compiled_reader=True))
        for chunk, poses in program_poses(chunks, PoseMap(profile)):
            P = poses.P
            tips = [P, P + options.standoff * poses.N]
            pts = list(tips)
            arc = chunk.arc[poses.rows]
            on_arc = np.isfinite(arc[:, 0])
            if on_arc.any():
                radius = np.linalg.norm(P[on_arc] - arc[on_arc, :3], axis=1)[:, None]
                pts += [arc[on_arc, :3] - radius, arc[on_arc, :3] + radius]
            pts = np.concatenate(pts)
            pts = pts[np.isfinite(pts).all(axis=1)]
            if len(pts):
                lo, hi = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
            along = _arc_samples(P, last, arc, on_arc, REACH_CELL_MM, arc_extent, arc_points)
            cubes.append(cube_cells(np.concatenate([*tips, along]), REACH_CELL_MM))
            if sum(len(c) for c in cubes) > 4 * len(cubes[0]) + 65536:  # merged now and then: memory follows the cubes
                cubes = [np.unique(np.concatenate(cubes), axis=0)]
            last = P[-1]
    finally:
        stream.seek(start)
    if not np.isfinite(lo).all():
        return None
    return ProgramPoints(np.array([lo, hi]), np.unique(np.concatenate(cubes), axis=0))


def _arc_samples(P: np.ndarray, last: np.ndarray | None, arc: np.ndarray, on_arc: np.ndarray, spacing_mm: float,
                 arc_extent, arc_points) -> np.ndarray:
    """Points along the arcs of a chunk's poses, at most ``spacing_mm`` apart along each (every
    point of an arc within half of it of one): where the head runs between an arc's ends."""
    rows = np.nonzero(on_arc)[0]
    starts = np.concatenate([last[None] if last is not None else np.full((1, 3), np.nan), P[:-1]])[rows]
    keep = np.isfinite(starts).all(axis=1) & np.isfinite(P[rows]).all(axis=1)
    rows, starts = rows[keep], starts[keep]
    if not len(rows):
        return np.zeros((0, 3))
    _, length = arc_extent(starts, P[rows], arc[rows])
    count = np.ceil(length / spacing_mm).astype(np.int64) + 1
    k = np.repeat(np.arange(len(rows)), count)
    t = (np.arange(len(k)) - np.repeat(np.cumsum(count) - count, count)) / np.repeat(np.maximum(count - 1, 1), count)
    return arc_points(starts[k], P[rows][k], arc[rows][k], t)


def load_parts(options: Options, profile: Profile) -> list:
    """The --part meshes, placed, then the --platform mesh placed by the profile's [platform]
    (``ncfix.geometry.place``; a profile without one leaves it where its file has it)."""
    from ncfix.geometry.mesh import load_mesh
    from ncfix.geometry.place import transform

    out = [load_mesh(path, "part") for path in options.part]
    if options.platform is not None:
        base = transform(*profile.platform) if profile.platform is not None else None
        out.append(load_mesh(options.platform, "platform", base=base))
    return out


class Tracker:
    """Turns "the work has reached line L" into ``progress(bytes_done, lines_done)`` calls.

    The pipeline reports each chunk it writes; a stage that works long on lines it holds (a
    window, or a whole program shorter than one chunk) reports the line its work has reached
    through its ``progress`` attribute (``reached``), so a bar moves while it works. Calls only
    go forward: a report behind the last one is dropped."""

    def __init__(self, progress: Callable[[int, int], None]):
        self.progress = progress
        self.held: list[tuple[int, int, np.ndarray]] = []  # (first line, bytes before it, end of each line)
        self.bytes_read = 0
        self.bytes_done = self.lines_done = 0

    def read(self, chunk: Chunk) -> None:
        ends = np.cumsum([len(line) for line in chunk.lines], dtype=np.int64)
        self.held.append((chunk.first_lineno, self.bytes_read, ends))
        self.bytes_read += int(ends[-1]) if len(ends) else 0

    def reached(self, line: float) -> None:
        """Every line before ``line`` (1-based, may be fractional) is done."""
        done = int(line) - 1  # lines done
        for first, before, ends in self.held:
            if done < first - 1 + len(ends):
                k = done - (first - 1)
                self._report(before + (int(ends[k - 1]) if k > 0 else 0), done)
                return
        if self.held:
            first, before, ends = self.held[-1]
            self._report(before + int(ends[-1]) if len(ends) else before, first - 1 + len(ends))

    def wrote(self, chunk: Chunk) -> None:
        self.reached(chunk.first_lineno + len(chunk.lines))
        while self.held and self.held[0][0] + len(self.held[0][2]) <= chunk.first_lineno + len(chunk.lines):
            self.held.pop(0)

    def _report(self, bytes_done: int, lines_done: int) -> None:
        if bytes_done > self.bytes_done or lines_done > self.lines_done:
            self.bytes_done, self.lines_done = max(bytes_done, self.bytes_done), max(lines_done, self.lines_done)
            self.progress(self.bytes_done, self.lines_done)


def build_stages(options: Options, profile: Profile, report: Report, where: ProgramPoints | None = None) -> list[Stage]:
    """The window stages for these options: none without --head, else the collision checker.
    ``where``: where the program's points are (``program_box``), to crop the part grids to what
    the head can reach from them."""
    if options.head is None:
        return []
    from ncfix.collision.checker import Checker, resolve_device
    from ncfix.collision.deposit import BeadShape
    from ncfix.collision.grid import REACH_CELL_MM, Reach
    from ncfix.collision.head import cached_head_model
    from ncfix.collision.stage import CheckStage
    from ncfix.geometry.mesh import load_head

    resolve_device(options.device)  # a missing GPU is said before the meshes are read
    head = load_head(options.head, options.head_tip, options.head_axis)
    report.warnings.extend(head.warnings)
    height = float(head.arrays.vertices[:, 2].max())  # head frame: the tip at 0, the axis +Z
    if options.bead_radius > 0 and options.tip_allowance >= height:
        raise ConfigError(f"--tip-allowance {options.tip_allowance:g} mm is not below the top of the head "
                          f"({height:.4g} mm above its tip): no part of it would be checked against deposited "
                          "material", fix="use a smaller --tip-allowance, or check the head mesh and --head-tip")
    parts, loaded_parts = [], []
    for loaded in load_parts(options, profile):
        report.warnings.extend(loaded.warnings)
        parts.append((f"part:{Path(loaded.name).name}", loaded.arrays, loaded.closed))
        loaded_parts.append(loaded)
    model = cached_head_model(head.arrays, options.pitch, name=Path(options.head).name)
    report.details.append(model.summary())
    reach_box = part_reach = None
    if where is not None:
        # The head lies within rho of its tip; with --pivot point a tilted tip stays within h of P.
        rho = float(np.linalg.norm(head.arrays.vertices, axis=1).max())
        reach = rho + options.standoff + options.clearance + 2 * options.pitch
        reach_box = np.array([where.box[0] - reach, where.box[1] + reach])
        # Points along arcs lie within half a cube of one sampled.
        part_reach = Reach(where.cubes, REACH_CELL_MM, reach + 0.5 * REACH_CELL_MM)
    bead = BeadShape.stated(options.bead_radius, options.bead_width, options.bead_height, options.standoff)
    checker = Checker(head.arrays, model, parts, pitch_mm=options.pitch, clearance_mm=options.clearance,
                      bead_radius_mm=bead.radius_mm, tip_allowance_mm=options.tip_allowance,
                      device=options.device, part_bounds_mm=reach_box, part_reach=part_reach, bead_drop_mm=bead.drop_mm,
                      bead_shape=bead)
    box = where.box if where is not None else None
    if options.check:
        return [CheckStage(checker, profile, options, report, placed_parts=loaded_parts, program_box=box)]
    from ncfix.correct import strategies
    from ncfix.correct.stage import CorrectStage

    return [CorrectStage(checker, profile, options, report, strategies.make_strategy(options),
                         placed_parts=loaded_parts, program_box=box)]


def run(src: BinaryIO, dst: BinaryIO, options: Options, source: str = "<stdin>",
        progress: Callable[[int, int], None] | None = None) -> Report:
    """Stream ``src`` to ``dst`` through the stages; returns the report (also for --check).

    ``progress(bytes_done, lines_done)`` is called after each chunk written and while the stages
    work on the lines they hold (``Tracker``); bytes: the sum of the raw lines' lengths, so it
    matches the input file's size at the end.
    """
    started = time.perf_counter()
    note = None
    if options.machine == AUTO:
        choice, src = resolve_auto(src, source)
        profile, note = choice.profile, choice.note
    else:
        profile = load_profile(options.machine)
    report = Report(input=source, machine=profile.name, options=options)
    if note is not None:
        report.notes.append(note)
    # A check loads numba for its kernels anyway, and a long file pays for it: the compiled
    # reader from the start. Otherwise (a pipe too) the interpreter decides as it reads.
    compiled = options.head is not None or (input_size(src) or 0) > COMPILED_AFTER_LINES * LINE_BYTES
    interpreter = Interpreter(profile, source, options.deposit_codes, compiled_reader=compiled)
    where = program_box(src, profile, options, source) if options.head is not None and (options.part or options.platform) \
        else None
    stages = build_stages(options, profile, report, where)
    writer = Writer(profile)
    tracker = Tracker(progress) if progress is not None else None
    for stage in stages:
        if tracker is not None and hasattr(stage, "progress"):
            stage.progress = tracker.reached

    def emit(chunks: Iterable[Chunk]) -> None:
        for chunk in chunks:
            report.count(chunk)
            rendered = writer.render(chunk)
            for i in writer.restored:  # restates words a change before it altered (Writer doc)
                report.add_restated(chunk.first_lineno + i)
            report.record_emitted(chunk.first_lineno, chunk.lines, rendered)
            dst.write(rendered)
            if tracker is not None:
                tracker.wrote(chunk)

    for chunk in read_chunks(src, interpreter):
        if tracker is not None:
            tracker.read(chunk)
        chunks: Iterable[Chunk] = (chunk,)
        for stage in stages:
            chunks = [out for c in chunks for out in stage.push(c)]
        emit(chunks)
    tail: list[Chunk] = []
    for stage in stages:
        tail = [out for c in tail for out in stage.push(c)] + list(stage.flush())
    emit(tail)
    report.summary["seconds"] = round(time.perf_counter() - started, 3)
    return report
