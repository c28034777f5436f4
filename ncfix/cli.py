"""The command line: parse arguments, call the library, map exceptions to exit codes (CONTRACT.md)."""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import stat
import sys
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from ncfix import __version__
from ncfix.config import DEVICES, OPTION_NAMES, PIVOTS, STRATEGIES, Options, build_options, load_config
from ncfix.errors import NcfixError

EXIT_OK, EXIT_COLLISIONS, EXIT_USAGE = 0, 1, 2
EXIT_BROKEN_PIPE = 141  # what a shell reports for a filter whose reader went away (128 + SIGPIPE)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ncfix",
        description="Find and fix deposition-head collisions in 5-axis AM NC programs. "
        "Every line ncfix does not change is written byte for byte.",
        epilog="Every option is also a key of the TOML config (table [ncfix], '_' for '-'); the command line wins. "
        "Exit status: 0 no collision left, 1 collisions remain, 2 usage or input error.",
    )
    p.add_argument("input", nargs="?", default="-", metavar="INPUT", help="NC program; '-' or nothing reads standard input")
    p.add_argument("-o", "--output", metavar="OUTPUT", help="write here (atomically) instead of standard output")
    p.add_argument("-c", "--config", metavar="PATH", help="TOML config (default ./ncfix.toml when it exists)")
    p.add_argument("--machine", metavar="NAME|PATH", help="machine profile: built-in name, profile file, or 'auto' (chosen from the program's "
                   "orientation words) (default ijk)")
    p.add_argument("--head", metavar="PATH", help="deposition-head mesh (STL or OBJ); PATH@translate=X,Y,Z@rotate_deg=RX,RY,RZ places it")
    p.add_argument("--head-tip", metavar="X,Y,Z", help="nozzle tip in the head mesh (default 0,0,0)")
    p.add_argument("--head-axis", metavar="X,Y,Z", help="head axis, tip → head, in the mesh (default 0,0,1)")
    p.add_argument("--part", action="append", metavar="PATH",
                   help="mold/part/fixture mesh in workpiece coordinates; repeatable; "
                   "PATH@translate=X,Y,Z@rotate_deg=RX,RY,RZ places it (turned about X, Y, Z in turn, then moved)")
    p.add_argument("--platform", metavar="PATH", help="the machine's build platform mesh, placed as the --machine profile says")
    p.add_argument("--standoff", metavar="MM", help="h: distance from the path point to the nozzle tip along the tool axis (default 6)")
    p.add_argument("--pivot", choices=PIVOTS, help="rotate about the tip C (default) or about the path point P")
    p.add_argument("--max-step", metavar="DEG", help="largest orientation change ncfix introduces between blocks (default 2)")
    p.add_argument("--max-tilt", metavar="DEG", help="largest deviation from the programmed orientation (default 30)")
    p.add_argument("--pitch", metavar="MM", help="voxel size (default 0.5)")
    p.add_argument("--clearance", metavar="MM", help="extra safety margin around every body (default 0)")
    p.add_argument("--strategy", choices=STRATEGIES, help="correction strategy (default epa)")
    p.add_argument("--resolution", metavar="DEG", help="spacing of the orientations the corrector tries (default 1)")
    p.add_argument("--bead-radius", metavar="MM", help="radius of deposited material; 0 turns the deposit model off (default 1)")
    p.add_argument("--bead-width", metavar="MM", help="a flat bead's width across the tool axis (with --bead-height; overrides the radius)")
    p.add_argument("--bead-height", metavar="MM", help="a flat bead's height along the tool axis, hanging below the nozzle tip")
    p.add_argument("--tip-allowance", metavar="MM", help="bottom of the head not checked against deposit (default 1)")
    p.add_argument("--deposit-codes", metavar="ON,OFF", help="M-codes that switch deposition on and off, e.g. M3,M5")
    p.add_argument("--window", metavar="BLOCKS", help="motion blocks per checking window (default 2000)")
    p.add_argument("--check", action="store_true", default=None, help="detect only: output is the input; exit 1 on collisions")
    p.add_argument("--report", metavar="PATH", help="write the JSON report (schema 1)")
    p.add_argument("--diff", metavar="PATH", help="write a unified diff of the changed blocks")
    p.add_argument("--html", metavar="PATH", help="write a self-contained HTML report")
    p.add_argument("--device", choices=DEVICES, help="where tensors live (default auto)")
    p.add_argument("-q", "--quiet", action="store_true", default=None, help="only errors on standard error")
    p.add_argument("-v", "--verbose", action="store_true", default=None, help="detail and tracebacks")
    p.add_argument("--list-machines", action="store_true", help="list the built-in machine profiles and exit")
    p.add_argument("--version", action="version", version=f"ncfix {__version__}")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    verbose = bool(args.verbose)
    try:
        if args.list_machines:
            return _list_machines()
        options = _options(args)
        with _notices(enabled=not options.quiet):
            return _run(args, options)
    except NcfixError as exc:
        if verbose:
            traceback.print_exc()
        _stderr(f"ncfix: error: {exc}")
        return exc.exit_code
    except BrokenPipeError:
        # The reader went away (`ncfix big.nc | head`): stop quietly, like any filter.
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        _stderr("ncfix: interrupted")
        return 130


def _stderr(text: str) -> None:
    with contextlib.suppress(OSError):
        print(text, file=sys.stderr)


@contextlib.contextmanager
def _notices(enabled: bool) -> Iterator[None]:
    """The library's notices (the "ncfix" logger, e.g. a cache file rebuilt) as lines on standard
    error while the command runs; none with -q."""
    if not enabled:
        yield
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("ncfix: %(message)s"))
    logger = logging.getLogger("ncfix")
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


def _list_machines() -> int:
    from ncfix.profiles import builtin_names, load_profile

    for name in builtin_names():
        profile = load_profile(name)
        print(f"{name:22} {profile.description}")
    return EXIT_OK


def _config_path(args: argparse.Namespace) -> Path:
    """-c PATH; else ./ncfix.toml; else ncfix.toml beside the input file (so a folder of programs
    can carry its own settings: `ncfix samples/bathtub_273.nc`)."""
    if args.config is not None:
        return Path(args.config)
    here = Path("ncfix.toml")
    if here.exists() or args.input == "-":
        return here
    beside = Path(args.input).parent / "ncfix.toml"
    return beside if beside.exists() else here


def _options(args: argparse.Namespace) -> Options:
    explicit = args.config is not None
    path = _config_path(args)
    config = load_config(path, explicit)
    cli = {name: getattr(args, name, None) for name in OPTION_NAMES}  # None: not given on the command line
    return build_options(config, cli, where=str(path))


def _run(args: argparse.Namespace, options: Options) -> int:
    from ncfix.api import process_options

    src = sys.stdin.buffer if args.input == "-" else args.input
    dst = args.output if args.output else sys.stdout.buffer
    with _progress(src, enabled=not options.quiet) as progress:
        report = process_options(src, dst, options, progress=progress)
    if not options.quiet:
        from ncfix.summary import print_summary

        print_summary(report, verbose=options.verbose)
    return report.exit_code


@contextlib.contextmanager
def _progress(src: str | BinaryIO, enabled: bool) -> Iterator[Callable[[int, int], None] | None]:
    """A rich progress bar on standard error while the program streams: by bytes when the input's
    size is known, else a line count. Only when standard error is a terminal, never with -q."""
    if not enabled or not _stderr_is_terminal():
        yield None
        return
    from rich.console import Console
    from rich.progress import (BarColumn, DownloadColumn, Progress, SpinnerColumn, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    total = _input_size(src)
    console = Console(stderr=True)
    lines = TextColumn("{task.fields[lines]:,} lines")
    if total:
        columns = (TextColumn("ncfix"), BarColumn(), DownloadColumn(), lines, TimeElapsedColumn(),
                   TimeRemainingColumn())
    else:
        columns = (SpinnerColumn(), TextColumn("ncfix"), lines, TimeElapsedColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task("ncfix", total=total or None, lines=0)

        def update(bytes_done: int, lines_done: int) -> None:
            bar.update(task, completed=bytes_done, lines=lines_done)

        yield update


def _stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _input_size(src: str | BinaryIO) -> int | None:
    """Bytes to read, when the input is a regular file (a path, or standard input redirected from one)."""
    try:
        info = os.stat(src) if isinstance(src, str) else os.fstat(src.fileno())
    except (OSError, AttributeError, ValueError, io.UnsupportedOperation):
        return None
    return info.st_size if stat.S_ISREG(info.st_mode) and info.st_size > 0 else None
