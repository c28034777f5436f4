"""Arrays derived from the meshes, kept on disk between runs: one ``.npz`` per result.

Building the checker's models (grids, covering balls and trees, cell lists, CoACD pieces) takes
seconds and gives the same arrays for the same inputs every time. A result is stored under
``$NCFIX_CACHE`` (default ``~/.cache/ncfix``) as ``KIND-KEY.npz``, KEY a sha256 of everything it is
computed from, the libraries' versions and ncfix's own source that computes it; a file is used
only when it holds that key. Deleting the folder is always safe. See docs/performance.md#the-cache.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import io
import json
import logging
import os
import struct
import tempfile
import time
import zipfile
import zlib
from pathlib import Path
from collections.abc import Callable, Iterable
from typing import BinaryIO, TypeVar

import numpy as np

T = TypeVar("T")

# The cache folder's ``.npz`` files are kept under this many bytes (least recently used go first).
MAX_BYTES = 2 * 1024**3
# A temporary file this old (seconds) was left by a run that was killed while writing it.
STALE_TEMP_S = 3600.0
# Cached arrays of at least this many bytes are mapped from their file (``read_arrays``), their
# data aligned in it to ALIGN bytes; PAD_FIELD_ID tags the zip extra field that pads them (the id
# Android's zipalign uses for the same purpose).
MAP_BYTES = 1 << 20
ALIGN = 64
PAD_FIELD_ID = 0xD935
# The member that holds a file's own key (its ASCII hex digits as uint8), checked on every read.
KEY_MEMBER = "ncfix_key"

_log = logging.getLogger("ncfix.cache")
# The notice before a first build ("building the distance grid of mold.stl (first run ...)…").
_build_log = logging.getLogger("ncfix.build")


def cache_dir() -> Path:
    """``$NCFIX_CACHE`` when set, else ``~/.cache/ncfix``."""
    env = os.environ.get("NCFIX_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "ncfix"


def version(package: str) -> str:
    """An installed package's version, or "absent" (a fallback path computes the result then)."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


@functools.cache
def fingerprint(*modules: str) -> str:
    """sha256 of the source files of these modules (dotted names), read once per process.

    Part of every key: a changed voxelizer or grid builder never reads a grid the old code made. A
    stale grid could be wrong in the unsafe direction, so the key is never trusted to a version
    number that someone has to remember to bump."""
    digest = hashlib.sha256()
    for name in modules:
        digest.update(name.encode() + b"\0")
        digest.update(Path(importlib.import_module(name).__file__).read_bytes())
    return digest.hexdigest()


def make_key(kind: str, *parts: object) -> str:
    """sha256 naming a result: its kind, then each part, each part tagged with its type.

    Arrays count with their dtype and shape (float64 [1, 2] and int64 [1, 2] differ); anything
    else by its JSON text (floats exactly: JSON writes the shortest repr that reads back the same).
    """
    digest = hashlib.sha256(kind.encode() + b"\0")
    for part in parts:
        if isinstance(part, np.ndarray):
            array = np.ascontiguousarray(part)
            digest.update(f"array {array.dtype.str} {array.shape}\0".encode())
            digest.update(array.tobytes())
        else:
            digest.update(b"json " + json.dumps(part, sort_keys=True).encode() + b"\0")
    return digest.hexdigest()


def fields(obj: object, names: Iterable[str]) -> dict[str, np.ndarray]:
    """The named attributes of ``obj`` as arrays (a ``to_arrays`` for ``cached``)."""
    return {name: np.asarray(getattr(obj, name)) for name in names}


def path_for(kind: str, key: str, folder: str | os.PathLike[str] | None = None) -> Path:
    return (Path(folder) if folder is not None else cache_dir()) / f"{kind}-{key}.npz"


def read_arrays(path: Path, names: Iterable[str]) -> dict[str, np.ndarray] | None:
    """The named arrays of an ``.npz``, or None when the file is missing, unreadable or lacks one.

    Arrays of ``MAP_BYTES`` or more are mapped from the file, not copied: a run reads ~100 MB of
    grids and trees and touches a small part of them, and copying them into fresh memory took
    0.1-0.6 s of a run on the 2-core machine (page faults). The mapping is copy-on-write: the
    arrays are writable like built ones (numba compiles other kernels for read-only arrays: 14 s
    more on the first run that read the cache), and a write stays in this process, never reaches
    the file. Each mapped member's CRC is checked as ``np.load`` would (a damaged file is a miss,
    never a wrong grid).
    """
    if not path.is_file():
        return None
    try:
        with zipfile.ZipFile(path) as archive, open(path, "rb") as raw:
            return {name: _member(path, archive, raw, name) for name in names}
    except Exception:  # a truncated or foreign file: any failure means "not cached"
        return None


def _member(path: Path, archive: zipfile.ZipFile, raw: BinaryIO, name: str) -> np.ndarray:
    """One ``.npy`` member of an ``.npz``: mapped when ``_mapped`` can, else read into memory of
    its own (small, compressed or unaligned: an older writer), its CRC checked by zipfile."""
    info = archive.getinfo(name + ".npy")
    mapped = _mapped(path, raw, info) if info.compress_type == zipfile.ZIP_STORED else None
    if mapped is not None:
        return mapped
    with archive.open(info) as member:
        return np.lib.format.read_array(member, allow_pickle=False)


def _mapped(path: Path, raw: BinaryIO, info: zipfile.ZipInfo) -> np.ndarray | None:
    """A stored member's array mapped copy-on-write from the file, or None when it is smaller than
    ``MAP_BYTES`` or its data is not aligned for its dtype (``write_arrays`` aligns them)."""
    raw.seek(info.header_offset)
    local = raw.read(30)  # the member's local header: signature ... name length, extra length
    if local[:4] != b"PK\x03\x04":
        raise ValueError(f"{path}: bad local header of {info.filename}")
    start = info.header_offset + 30 + sum(struct.unpack("<HH", local[26:30]))
    raw.seek(start)
    version = np.lib.format.read_magic(raw)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read_header(raw)
    offset, nbytes = raw.tell(), int(np.prod(shape)) * dtype.itemsize
    if nbytes < MAP_BYTES or dtype.hasobject or offset % dtype.alignment != 0:
        return None
    if offset + nbytes > start + info.file_size:
        raise ValueError(f"{path}: {info.filename} is shorter than its header says")
    if zlib.crc32(np.memmap(path, dtype=np.uint8, mode="r", offset=start, shape=(info.file_size,))) != info.CRC:
        raise ValueError(f"{path}: {info.filename} fails its CRC")
    mapped = np.memmap(path, dtype=dtype, mode="c", offset=offset, shape=shape, order="F" if fortran_order else "C")
    return mapped.view(np.ndarray)  # a plain array; the mapping lives as long as it does


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """One ``.npz`` (readable by ``np.load``), written under a temporary name and renamed into place.

    Members are stored uncompressed, each array's data at a multiple of ``ALIGN`` bytes in the file
    (the local header's extra field pads it), so that ``read_arrays`` can map it; the members' dates
    are fixed, so the same arrays make the same bytes: a reader never sees half a file, and two
    runs writing the same key write the same bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
            for name, array in arrays.items():
                header, data = _npy(np.asanyarray(array))
                info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o600 << 16
                info.file_size = len(header) + data.nbytes
                # The .npy header is padded to a multiple of 64 bytes: align where the member starts.
                fixed = out.tell() + 30 + len(info.filename.encode()) + 4
                pad = -fixed % ALIGN
                info.extra = struct.pack("<HH", PAD_FIELD_ID, pad) + bytes(pad)
                with archive.open(info, "w") as member:  # the data straight from the array, not copied
                    member.write(header)
                    member.write(data)
        os.replace(temp, path)
    except BaseException:
        os.unlink(temp)
        raise


def _npy(array: np.ndarray) -> tuple[bytes, memoryview]:
    """An array as ``np.save`` writes it: its .npy header and its data (the array's own bytes)."""
    if array.dtype.hasobject:
        raise ValueError("object arrays are not cached")
    header = io.BytesIO()
    meta = np.lib.format.header_data_from_array_1_0(array)
    np.lib.format.write_array_header_1_0(header, meta)
    data = array.T if meta["fortran_order"] else np.ascontiguousarray(array)
    return header.getvalue(), memoryview(data.reshape(-1)).cast("B")


def cached(kind: str, key: str, names: Iterable[str], build: Callable[[], T],
           to_arrays: Callable[[T], dict[str, np.ndarray]], from_arrays: Callable[[dict[str, np.ndarray]], T | None],
           folder: str | os.PathLike[str] | None = None, what: str | None = None) -> tuple[T, bool]:
    """``build()``'s result, read from the cache when this key was built before -> (result, hit).

    The file must hold this key (``KEY_MEMBER``); ``from_arrays`` may return None for arrays that
    do not make a valid result. Either failure is a miss with a notice: a file that was renamed,
    copied over another or left by a writer without keys is never trusted by its name; one whose key
    does not match, that cannot be read, or that holds other arrays than expected is rebuilt and
    written again, with a one-line notice on the ``ncfix`` logger (the command line prints it on
    standard error). A folder that cannot be written is not an error either: the result is only not
    kept. After each write the folder is pruned to ``MAX_BYTES`` (a hit marks its file used); a
    part's grid is cropped to what the program can reach, so each program's box gets its own file
    (tens of MB at a 0.5 mm pitch).
    what : what is built, for the notice logged before a first build ("building WHAT…"; a file
        that is rebuilt has its own notice): a first run waits seconds to minutes here, and the
        user should know why before it starts.
    """
    path = path_for(kind, key, folder)
    names = tuple(names)
    if path.is_file():
        problem = "cannot be read"
        arrays = read_arrays(path, (*names, KEY_MEMBER))
        if arrays is None and read_arrays(path, names) is not None:
            problem = "has no key"  # readable, but written without one: not trusted by its name
        elif arrays is not None:
            stored = arrays.pop(KEY_MEMBER)
            if stored.dtype != np.uint8 or stored.tobytes() != key.encode("ascii"):
                problem = "does not match its key"
            else:
                try:
                    result = from_arrays(arrays)
                except Exception:  # arrays of the wrong shape or type: rebuilt like a foreign file
                    result = None
                if result is not None:
                    _touch(path)
                    return result, True
                problem = "holds other arrays than expected"
        _log.warning("cache: %s %s (rebuilt)", path.name, problem)
    elif what:
        _build_log.warning("building %s…", what)
    result = build()
    try:
        arrays = dict(to_arrays(result))
        arrays[KEY_MEMBER] = np.frombuffer(key.encode("ascii"), dtype=np.uint8)
        write_arrays(path, arrays)
    except OSError:
        return result, False  # an unwritable cache only costs time on the next run; the result is valid
    prune(path.parent, MAX_BYTES, keep=path)
    return result, False


def prune(folder: Path, max_bytes: int, keep: Path | None = None) -> None:
    """Deletes the least recently used ``.npz`` files of ``folder`` (never ``keep``) until the rest
    take at most ``max_bytes``, and temporary files older than ``STALE_TEMP_S``. Files another run
    deletes meanwhile are skipped."""
    entries = []
    now = time.time()
    for path in folder.iterdir():
        try:
            info = path.stat()
        except OSError:
            continue
        if path.suffix == ".tmp" and now - info.st_mtime > STALE_TEMP_S:
            _unlink(path)
        elif path.suffix == ".npz":
            entries.append((info.st_mtime, path.name, info.st_size, path))
    total = sum(size for _, _, size, _ in entries)
    for _, _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        if path != keep and _unlink(path):
            total -= size


def _touch(path: Path) -> None:
    try:
        os.utime(path)
    except OSError:
        pass  # a read-only cache still serves hits; only its eviction order is off


def _unlink(path: Path) -> bool:
    try:
        path.unlink()
        return True
    except OSError:
        return False
