"""The Python API (`ncfix.process`), for CAM export hooks and scripts; the command line runs the same code."""

from __future__ import annotations

import difflib
import io
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, BinaryIO, Union

from ncfix.config import OPTION_NAMES, Options, build_options, load_config
from ncfix.errors import ConfigError, InternalError, NcfixError
from ncfix.fileio import Input, Output, atomic_output, atomic_write_text

if TYPE_CHECKING:
    from ncfix.report import Report

Source = Union[str, "os.PathLike[str]", BinaryIO, IO[bytes]]
Progress = Callable[[int, int], None]


def process(src: Source, dst: Source, *, config: str | os.PathLike[str] | None = None,
            progress: Progress | None = None, **options: Any) -> "Report":
    """Read the NC program ``src``, write the checked (or fixed) program to ``dst``; return the report.

    ``src``, ``dst``: a path (``dst`` is written atomically: nothing exists there after an error)
    or an open binary stream. ``options``: the names of :class:`ncfix.config.Options`, i.e. the
    command line's long options with ``_`` for ``-`` (``head="head.stl"``,
    ``part=["mold.stl@translate=0,0,-5"]``, ``platform=``, ``standoff=6.0``, ``deposit_codes="M3,M5"``, ``check=True``, ``report="r.json"``, ``diff=``,
    ``html=``); checked as the command line checks them, with the same messages. ``config``: a
    TOML file read as ``-c`` reads it (keywords win); no config file is read without it.
    ``progress(bytes_done, lines_done)`` is called after each chunk of 4,096 lines.

    Raises an :class:`ncfix.NcfixError` subclass where the command line exits 2, also for a
    failure ncfix did not foresee (:class:`ncfix.errors.InternalError`, the original exception
    as its ``__cause__``); a path ``dst`` is then not written. Nothing is printed; ``report.exit_code`` is the command line's status (0: no collision left, 1:
    collisions remain) and ``report.verdict`` says it in a line.
    """
    for key in options:
        if key not in OPTION_NAMES:
            close = difflib.get_close_matches(key, OPTION_NAMES, n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"known options: {', '.join(OPTION_NAMES)}"
            raise ConfigError(f"ncfix.process() got an unknown option '{key}'", fix=hint)
    table: dict[str, Any] = {}
    where = "ncfix.process()"
    with internal_errors():
        if config is not None:
            path = Path(os.fspath(config))
            table = load_config(path, explicit=True)
            where = str(path)
        values = {key: _plain(value) for key, value in options.items()}
        built = build_options(table, values, where=where)
    return process_options(src, dst, built, progress=progress)


def process_options(src: Source, dst: Source, options: Options, *, progress: Progress | None = None) -> "Report":
    """:func:`process` with options already checked (the command line comes in here).

    Any failure is an :class:`NcfixError`: an unexpected exception becomes an
    :class:`InternalError` (its ``__cause__`` the original), running out of memory an error
    naming the settings to change; ``BrokenPipeError`` (the reader of ``dst`` went away) and
    ``KeyboardInterrupt`` pass as they are. A path ``dst`` is never left partly written."""
    with internal_errors():
        return _process_options(src, dst, options, progress)


@contextmanager
def internal_errors() -> Iterator[None]:
    """Turn exceptions that are not ncfix's own into :class:`NcfixError` (``process_options``)."""
    try:
        yield
    except (NcfixError, BrokenPipeError):
        raise
    except MemoryError:
        raise NcfixError("out of memory", fix="use a coarser --pitch, a smaller --window or smaller meshes") from None
    except Exception as exc:
        raise InternalError.wrap(exc) from exc


def _process_options(src: Source, dst: Source, options: Options, progress: Progress | None) -> "Report":
    from ncfix.pipeline import run

    for path in (dst if _is_path(dst) else None, options.report, options.diff, options.html):
        if path is not None:
            _check_writable(os.fspath(path))  # fail before reading: no output without its report
    with _input(src) as (stream, source):
        if _is_path(dst):
            target = os.fspath(dst)
            with atomic_output(target) as out:
                report = run(stream, out, options, source, progress)
                out.flush()  # a full disk says so here, before any report is written
                _write_extras(report, options, source, target)  # the program appears only if these worked
        else:
            raw = _binary(dst, "dst")
            name = _name(raw, "<stream>")
            out = Output(raw, "standard output" if name == "<stdout>" else name)
            report = run(stream, out, options, source, progress)
            out.flush()
            _write_extras(report, options, source, name)
    return report


def _write_extras(report: "Report", options: Options, source: str, target: str) -> None:
    if options.report:
        report.write_json(options.report)
    if options.diff:
        if options.check:  # --check never changes the program: its diff is empty by definition
            atomic_write_text(options.diff, "")
        else:
            report.write_diff(options.diff, source, target)
    if options.html:
        from ncfix.report.html import render_html

        _add_part_previews(report, options)
        atomic_write_text(options.html, render_html(report))


def _add_part_previews(report: "Report", options: Options) -> None:
    """The HTML's 3-D picture needs the parts: load them here when no stage handed them over."""
    if report.previews or options.head is None:
        return
    from ncfix.pipeline import load_parts
    from ncfix.profiles import load_profile

    try:
        loaded_parts = load_parts(options, load_profile(options.machine))
    except NcfixError as exc:  # the stages read them already; a picture is not worth failing for
        report.warnings.append(f"no 3-D picture of the parts: {exc}")
        return
    for loaded in loaded_parts:
        report.add_part_preview(f"part:{Path(loaded.name).name}", loaded.arrays)


@contextmanager
def _input(src: Source) -> Iterator[tuple[BinaryIO, str]]:
    if not _is_path(src):
        stream = _binary(src, "src")
        name = _name(stream, "<stream>")
        yield Input(stream, "standard input" if name == "<stdin>" else name), name
        return
    path = os.fspath(src)
    p = Path(path)
    if p.is_dir():
        raise NcfixError(f"cannot read '{path}': it is a folder", fix="give the NC program's file path")
    try:
        handle = open(p, "rb")
    except FileNotFoundError:
        raise NcfixError(f"cannot read '{path}': no such file", fix="check the path") from None
    except OSError as exc:
        raise NcfixError(f"cannot read '{path}': {exc.strerror}", fix="check the file's permissions") from None
    with handle:
        yield Input(handle, path), path


def _check_writable(path: str) -> None:
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise NcfixError(f"cannot write '{path}': it is a folder", fix="give a file path")
    if not folder.is_dir():
        raise NcfixError(f"cannot write '{path}': folder '{folder}' does not exist",
                         fix="create the folder or choose another path")


def _is_path(value: Any) -> bool:
    return isinstance(value, (str, os.PathLike))


def _binary(stream: Any, what: str) -> Any:
    if isinstance(stream, io.TextIOBase):
        raise ConfigError(f"{what} is a text stream", fix="open the file in binary mode ('rb'/'wb') or pass its path")
    if not hasattr(stream, "read" if what == "src" else "write"):
        raise ConfigError(f"{what} must be a path or a binary stream, not {type(stream).__name__}")
    return stream


def _name(stream: Any, default: str) -> str:
    name = getattr(stream, "name", None)
    return name if isinstance(name, str) else default


def _plain(value: Any) -> Any:
    """Paths as strings, so keywords accept pathlib.Path like the command line accepts text."""
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple)):
        return type(value)(os.fspath(v) if isinstance(v, os.PathLike) else v for v in value)
    return value
