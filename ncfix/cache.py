"""Arrays derived from the meshes, kept on disk between runs: one ``.npz`` per result.

Building the checker's models from the head and part meshes (voxelizing, the distance transform,
the covering balls and their trees, the clipped head's cell lists and sign grid, the head's
triangle tree and each part's cell lists for the exact part test, the CoACD pieces) takes
seconds and gives the same arrays for the same meshes and settings every time. They are stored under ``$NCFIX_CACHE`` (default
``~/.cache/ncfix``) in files named ``KIND-KEY.npz``, where KEY is a sha256 of

- everything the result is computed from: the mesh's exact vertex and face arrays, the pitch and
  the other parameters;
- the versions of the libraries that compute it;
- the bytes of the source files of ncfix that compute it (``fingerprint``): a changed voxelizer
  or grid builder never reads a grid the old code made. A stale grid could be wrong in the unsafe
  direction, so the key is never trusted to a version number that someone has to remember to bump.

A file that cannot be read, or holds other arrays than expected, is a miss: the result is built
and the file written again. A folder that cannot be written is not an error either: the result is
only not kept. Files are written under a temporary name and renamed, so a reader never sees half
a file, and two runs writing the same key write the same bytes. Deleting the folder is always safe.

A part's grid is cropped to what the program can reach, so each program's box gets its own grid
(tens of MB at a 0.5 mm pitch). After each write the folder is kept under ``MAX_BYTES``: the files
used least recently go first (a hit marks its file used).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterable, TypeVar

import numpy as np

T = TypeVar("T")

# The cache folder's ``.npz`` files are kept under this many bytes (least recently used go first).
MAX_BYTES = 2 * 1024**3
# A temporary file this old (seconds) was left by a run that was killed while writing it.
STALE_TEMP_S = 3600.0


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


@functools.lru_cache(maxsize=None)
def fingerprint(*modules: str) -> str:
    """sha256 of the source files of these modules (dotted names), read once per process."""
    import importlib

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
    """The named arrays of an ``.npz``, or None when the file is missing, unreadable or lacks one."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in names}  # each read into an array of its own
    except Exception:  # a truncated or foreign file: any failure means "not cached"
        return None


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """One ``.npz``, written under a temporary name and renamed into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out:
            np.savez(out, **arrays)
        os.replace(temp, path)
    except BaseException:
        os.unlink(temp)
        raise


def cached(kind: str, key: str, names: Iterable[str], build: Callable[[], T],
           to_arrays: Callable[[T], dict[str, np.ndarray]], from_arrays: Callable[[dict[str, np.ndarray]], T | None],
           folder: str | os.PathLike[str] | None = None) -> tuple[T, bool]:
    """``build()``'s result, read from the cache when this key was built before -> (result, hit).

    ``from_arrays`` may return None for arrays that do not make a valid result (then it is a miss).
    """
    path = path_for(kind, key, folder)
    arrays = read_arrays(path, names)
    if arrays is not None:
        try:
            result = from_arrays(arrays)
        except Exception:  # arrays of the wrong shape or type: rebuilt like a foreign file
            result = None
        if result is not None:
            _touch(path)
            return result, True
    result = build()
    try:
        write_arrays(path, to_arrays(result))
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
