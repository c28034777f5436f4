"""Output files and streams: atomic where the target is a regular file, every byte written or an error.

A regular file (or a symlink to one, followed) is written as a temporary file in its folder and
renamed into place on success, so after a failure no partial file exists. A device node or FIFO
(``-o /dev/null``, a named pipe) is written through, since renaming over it would replace the
device with a plain file. Write errors (a full disk, a closed stream) become one-line
:class:`NcfixError` messages naming the file; a reader that went away stays a ``BrokenPipeError``
(the command line exits 141 for it, as a filter does).
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Iterator
from itertools import islice
from pathlib import Path
from typing import Any, BinaryIO

from ncfix.errors import NcfixError

# Temporary files of atomic outputs still open, removed by ``remove_temporary_files`` when a
# signal ends the process before their ``with`` block could clean up (cli.py).
_PENDING: set[str] = set()


def _quoted(name: str) -> str:
    return name if name.startswith("standard ") else f"'{name}'"


def write_error(name: str, exc: OSError) -> NcfixError:
    """The one-line message for a failed write to ``name`` (a path, or "standard output")."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        fix = "free some space on that disk or write elsewhere"
    elif exc.errno in (errno.EBADF, errno.EINVAL):
        fix = "give -o OUTPUT or redirect the output to a file"
    else:
        fix = "check the path and its permissions"
    return NcfixError(f"cannot write {_quoted(name)}: {reason}", fix=fix)


def read_error(name: str, exc: OSError) -> NcfixError:
    reason = exc.strerror or str(exc) or type(exc).__name__
    return NcfixError(f"cannot read {_quoted(name)}: {reason}", fix="check the input file or stream")


class Output:
    """A binary stream that writes every byte it is given (looping over short writes, which a
    buffered writer returns when the OS fails part way and only reports on the next call) and
    turns OS errors into :class:`NcfixError` naming ``name``; ``BrokenPipeError`` passes."""

    def __init__(self, raw: Any, name: str):
        self.raw = raw
        self.name = name

    def write(self, data: bytes) -> int:
        view = memoryview(data).cast("B")
        done = 0
        try:
            while done < len(view):
                n = self.raw.write(view[done:])
                if n is None:  # a non-blocking stream that would block: the rest is not taken
                    raise OSError(errno.EAGAIN, "the stream would block")
                if n <= 0:
                    raise OSError(errno.EIO, "the stream took no bytes")
                done += n
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise write_error(self.name, exc) from None
        return done

    def flush(self) -> None:
        try:
            self.raw.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise write_error(self.name, exc) from None

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.raw, attr)


class Input:
    """A binary input stream read line by line, OS errors as :class:`NcfixError` naming ``name``
    (``< /`` gives EISDIR on the first read, a failing disk EIO); the rest is the stream's."""

    def __init__(self, raw: Any, name: str):
        self.raw = raw
        self.name = name
        self._lines: Iterator[bytes] | None = None

    def __iter__(self) -> "Input":
        return self

    def __next__(self) -> bytes:
        try:
            if self._lines is None:
                self._lines = iter(self.raw)
            return next(self._lines)
        except OSError as exc:
            raise read_error(self.name, exc) from None

    def take(self, count: int) -> list[bytes]:
        """The next ``count`` lines (fewer at the end) in one call: a chunk without a Python call
        per line (``ncfix.pipeline.read_chunks``)."""
        try:
            if self._lines is None:
                self._lines = iter(self.raw)
            return list(islice(self._lines, count))
        except OSError as exc:
            raise read_error(self.name, exc) from None

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.raw, attr)


def input_size(src: str | BinaryIO) -> int | None:
    """Bytes to read, when the input is a regular file (a path, or a stream such as standard
    input redirected from one); None for a pipe, a device or an empty file."""
    try:
        info = os.stat(src) if isinstance(src, str) else os.fstat(src.fileno())
    except (OSError, AttributeError, ValueError):  # io.UnsupportedOperation is both
        return None
    return info.st_size if stat.S_ISREG(info.st_mode) and info.st_size > 0 else None


def _is_regular_target(path: str) -> tuple[bool, Path]:
    """(True, the file to replace: symlinks followed) for a regular file or a new name; (False,
    the path) for anything else that exists (device node, FIFO, socket, ``/dev/stdout``: stat
    follows /proc's links to pipes, which realpath cannot name)."""
    try:
        info = os.stat(path)
    except OSError:  # a new name (or a dangling symlink): created, and errors said, when written
        info = None
    if info is not None and not stat.S_ISREG(info.st_mode):
        return False, Path(path)
    return True, Path(os.path.realpath(path))


@contextlib.contextmanager
def atomic_output(path: str) -> Iterator[BinaryIO]:
    """Yield a binary file that becomes ``path`` only if the block finishes without error.

    A symlink is followed (its target is replaced, the link stays); a target that exists and is
    not a regular file is opened and written through (module doc)."""
    regular, target = _is_regular_target(path)
    if not regular:
        try:
            handle = open(target, "wb")
        except OSError as exc:
            raise write_error(path, exc) from None
        out = Output(handle, path)
        try:
            yield out  # type: ignore[misc]
            out.flush()
        finally:
            with contextlib.suppress(OSError):
                handle.close()
        return
    folder = target.parent
    if not folder.is_dir():
        raise NcfixError(f"cannot write '{path}': folder '{folder}' does not exist", fix="create the folder or choose another path")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise NcfixError(f"cannot write '{path}': {exc.strerror}", fix="check the folder's permissions") from None
    _PENDING.add(tmp)
    try:
        handle = os.fdopen(fd, "wb")
        try:
            out = Output(handle, path)
            yield out  # type: ignore[misc]
            out.flush()
            try:
                os.fsync(handle.fileno())  # a full disk may only say so here
            except OSError as exc:
                if exc.errno not in (errno.EINVAL, errno.ENOTSUP):  # file systems without fsync
                    raise write_error(path, exc) from None
        except BaseException:
            # Closing flushes what the failed write left in the buffer, and fails the same way:
            # the first error is the one to report.
            with contextlib.suppress(OSError):
                handle.close()
            raise
        try:
            handle.close()
            os.chmod(tmp, _mode_for(target))
            os.replace(tmp, target)
        except OSError as exc:
            raise write_error(path, exc) from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        _PENDING.discard(tmp)


def remove_temporary_files() -> None:
    """Remove the temporary files of atomic outputs still being written (a signal ends the run)."""
    for tmp in list(_PENDING):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        _PENDING.discard(tmp)


def _mode_for(target: Path) -> int:
    """The mode the file would get from a plain ``open(path, "w")``: the existing file's, else
    0666 less the umask (mkstemp makes 0600, which would hide reports from the rest of a team)."""
    try:
        return target.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def atomic_write_text(path: str, text: str) -> None:
    with atomic_output(path) as handle:
        handle.write(text.encode("utf-8"))
