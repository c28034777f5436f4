"""Memory estimates before the large allocations (the voxel grids): refuse with the figure.

A grid's memory grows with the cube of extent / pitch: ``--pitch 0.01`` on a 200 mm mold asks for
terabytes, a head exported in µm instead of mm for petabytes. Each grid builder calls
:func:`ensure_fits` with its cell count before it allocates, and stops with a
:class:`ResourceError` naming the grid, the bytes it would need, the memory available and the
pitch that would fit, instead of a ``MemoryError`` or numpy's "array is too big" part way.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ncfix.errors import NcfixError

# The largest --pitch the options accept (config.py's limit): a suggestion above it is no help.
PITCH_MAX_MM = 50.0


class ResourceError(NcfixError):
    """A grid would need more memory than this machine has available."""


def available_bytes() -> int:
    """Memory this process may still take: the kernel's MemAvailable, lowered by a cgroup (v2)
    limit; 1 TiB where neither can be read (the estimate then only stops the absurd)."""
    have = None
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    have = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            room = max(int(limit) - used, 0)
            have = room if have is None else min(have, room)
    except (OSError, ValueError):
        pass
    return have if have is not None else 1 << 40


def grid_cells(bounds_mm: np.ndarray, pitch_mm: float, pad_cells: float = 2.0) -> float:
    """Cells of a grid over ``bounds_mm`` (2, 3) at ``pitch_mm`` with ``pad_cells`` on each side,
    as a float (it may be far beyond what an integer index can hold)."""
    bounds = np.asarray(bounds_mm, dtype=np.float64)
    with np.errstate(all="ignore"):
        per_axis = np.maximum((bounds[1] - bounds[0]) / float(pitch_mm), 0.0) + 2.0 * pad_cells + 1.0
        cells = float(np.prod(per_axis))
    return cells if math.isfinite(cells) else math.inf


def ensure_fits(what: str, cells: float, bytes_per_cell: float, *, pitch_mm: float | None = None,
                extent_mm: float | None = None) -> None:
    """Raise :class:`ResourceError` when ``cells`` cells of ``bytes_per_cell`` (the build's peak,
    measured) exceed the available memory. ``pitch_mm``: the grid follows --pitch (the message
    then names a pitch that fits); ``extent_mm``: the body's largest extent, named when no pitch
    up to the largest allowed would fit (a mesh in the wrong units)."""
    need = cells * bytes_per_cell
    have = available_bytes()
    if need <= have:
        return
    message = f"{what} at pitch {pitch_mm:g} mm" if pitch_mm is not None else what
    message += f" needs {format_bytes(need)}, more than the {format_bytes(have)} of memory available"
    fits = None
    if pitch_mm is not None and math.isfinite(need):
        fits = _round_up(pitch_mm * (need / have) ** (1.0 / 3.0) * 1.05)
    if fits is not None and fits <= PITCH_MAX_MM:
        fix = f"use --pitch {fits:g} or coarser"
    elif extent_mm is not None:
        fix = f"the mesh spans {extent_mm:.4g} mm: check that it is in the program's units"
    else:
        fix = "use a coarser --pitch or smaller meshes"
    raise ResourceError(message, fix=fix)


def format_bytes(n: float) -> str:
    if not math.isfinite(n):
        return "more bytes than can be counted"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if n < 1024 or unit == "EiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}" if n < 1e4 else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.1f} EiB"  # pragma: no cover - the loop returns


def _round_up(value: float) -> float:
    """``value`` rounded up to two significant digits (0.0523 → 0.053)."""
    if value <= 0 or not math.isfinite(value):
        return value
    scale = 10.0 ** (math.floor(math.log10(value)) - 1)
    return math.ceil(value / scale - 1e-9) * scale

