"""The command line: parse arguments, call the library, map exceptions to exit codes (docs/contract.md)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

from ncfix.api import process_options
from ncfix.config import (DEVICES, OPTION_NAMES, PIVOTS, STRATEGIES, Options, build_options, confine_outputs,
                          load_config)
from ncfix.errors import InternalError, NcfixError
from ncfix.fileio import Output, input_size, remove_temporary_files
from ncfix.version import __version__

EXIT_OK, EXIT_COLLISIONS, EXIT_USAGE = 0, 1, 2
EXIT_BROKEN_PIPE = 141  # what a shell reports for a filter whose reader went away (128 + SIGPIPE)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ncfix",
        description="Find and fix deposition-head collisions in 5-axis AM NC programs. "
        "Every line ncfix does not change is written byte for byte.",
        epilog="Every option is also a key of the TOML config (table [ncfix], '_' for '-'); the command line wins. "
        "Exit status: 0 no collision left, 1 collisions remain (output written), 2 usage, input, "
        "system or internal error (nothing written to -o), 141 the reader of the output went away, "
        "143/129 ended by SIGTERM/SIGHUP.",
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
    p.add_argument("--filament-diameter", metavar="MM", help="diameter of the filament the E words feed: the report "
                   "gives the bead width the program's E per mm implies (never used as the bead)")
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
    with _signals_end_the_run():
        try:
            if args.list_machines:
                return _list_machines()
            options = _options(args)
            with _notices(enabled=not options.quiet):
                return _run(args, options)
        except InternalError as exc:
            return _internal_error(exc, exc.__cause__ or exc, verbose)
        except NcfixError as exc:
            if verbose:
                _traceback(exc)
            _stderr(f"ncfix: error: {exc}")
            return exc.exit_code
        except BrokenPipeError:
            # The reader went away (`ncfix big.nc | head`): stop quietly, like any filter.
            with contextlib.suppress(OSError, AttributeError, ValueError):
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
            return EXIT_BROKEN_PIPE
        except KeyboardInterrupt:
            _stderr("ncfix: interrupted")
            return 128 + signal.SIGINT
        except Terminated as exc:
            return 128 + exc.signum
        except MemoryError:
            _stderr("ncfix: error: out of memory (use a coarser --pitch, a smaller --window or smaller meshes)")
            return EXIT_USAGE
        except Exception as exc:  # a bug: exit 2 (never 1, which says "output written"), one line
            return _internal_error(InternalError.wrap(exc), exc, verbose)


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


def _internal_error(error: InternalError, cause: BaseException, verbose: bool) -> int:
    if verbose:
        _traceback(cause)
        _stderr(f"ncfix: {error.message}")
    else:
        _stderr(f"ncfix: {error.message}; run with -v for the traceback")
    return EXIT_USAGE


def _traceback(exc: BaseException) -> None:
    if sys.stderr is not None:
        with contextlib.suppress(OSError, ValueError):
            traceback.print_exception(exc, file=sys.stderr)


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwind (temporary files are removed on the way) and exit 128 + N."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def _signals_end_the_run() -> Iterator[None]:
    """SIGTERM and SIGHUP end the run as an exception, so no temporary file of ``-o``,
    ``--report`` … is left behind; the exit status is then the shell's 128 + N (143, 129).
    Only in the main thread (Python allows handlers nowhere else); the old handlers come back."""
    previous: dict[int, Any] = {}

    def handler(signum: int, frame: Any) -> None:
        for number in previous:  # a second signal must not cut the clean-up short
            signal.signal(number, signal.SIG_IGN)
        remove_temporary_files()
        raise Terminated(signum)

    try:
        for number in (signal.SIGTERM, signal.SIGHUP):
            previous[number] = signal.signal(number, handler)
    except ValueError:  # not the main thread
        pass
    try:
        yield
    finally:
        for number, old in previous.items():
            with contextlib.suppress(ValueError, TypeError):
                signal.signal(number, old)


def _stderr(text: str) -> None:
    if sys.stderr is None:  # closed (2>&-): print(file=None) would write to standard output
        return
    with contextlib.suppress(OSError, ValueError):
        print(text, file=sys.stderr, flush=True)


def _list_machines() -> int:
    from ncfix.profiles import builtin_names, load_profile

    out = Output(_stdout(), "standard output")
    for name in builtin_names():
        profile = load_profile(name)
        out.write(f"{name:22} {profile.description}\n".encode())
    out.flush()
    return EXIT_OK


def _stdin() -> BinaryIO:
    if sys.stdin is None:
        raise NcfixError("cannot read standard input: it is closed", fix="give the NC program's path or redirect standard input")
    return sys.stdin.buffer


def _stdout() -> BinaryIO:
    if sys.stdout is None:
        raise NcfixError("cannot write standard output: it is closed", fix="give -o OUTPUT or redirect standard output")
    return sys.stdout.buffer


def _config_path(args: argparse.Namespace) -> tuple[Path, bool]:
    """-c PATH; else ./ncfix.toml; else ncfix.toml beside the input file (so a folder of programs
    can carry its own settings: `ncfix samples/bathtub_273.nc`). The flag: found beside the input."""
    if args.config is not None:
        return Path(args.config), False
    here = Path("ncfix.toml")
    if here.exists() or args.input == "-":
        return here, False
    beside = Path(args.input).parent / "ncfix.toml"
    return (beside, True) if beside.exists() else (here, False)


def _options(args: argparse.Namespace) -> Options:
    explicit = args.config is not None
    path, beside = _config_path(args)
    config = load_config(path, explicit)
    cli = {name: getattr(args, name, None) for name in OPTION_NAMES}  # None: not given on the command line
    if beside:
        confine_outputs(config, path, cli)  # someone else's file, maybe: it writes only in its folder
    options = build_options(config, cli, where=str(path))
    args.config_read = path if path.is_file() else None  # named with the summary, after the run
    return options


def _run(args: argparse.Namespace, options: Options) -> int:
    src = _stdin() if args.input == "-" else args.input
    dst = args.output if args.output else _stdout()
    with _progress(src, enabled=not options.quiet) as progress:
        report = process_options(src, dst, options, progress=progress)
    if not options.quiet and sys.stderr is not None:
        from ncfix.report.summary import print_summary

        # Which settings were used, said once the run has succeeded: an error stays one line (and an
        # error in the config names the file itself).
        if getattr(args, "config_read", None) is not None:
            _stderr(f"ncfix: using config {args.config_read}")
        try:
            print_summary(report, verbose=options.verbose)
        except (OSError, ValueError):  # standard error is gone or full: the output is written, its status stands
            pass
        except Exception as exc:  # a bug in the summary must not turn a written output into exit 2
            _stderr(f"ncfix: internal error printing the summary: {type(exc).__name__}: {exc}")
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

    total = input_size(src)
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
