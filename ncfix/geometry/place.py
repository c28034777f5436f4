"""Placing a mesh: a translation and a rotation given with its path, `PATH@translate=X,Y,Z@rotate_deg=RX,RY,RZ`.

A part, platform or head exported in another frame is placed by ncfix itself, on the command
line, in ncfix.toml (a table `{path = ..., translate = [...], rotate_deg = [...]}`) and in the
Python API alike; all three come down to this one text form, which the report's settings show.

The placed point of a mesh point p is Rz(rz)·Ry(ry)·Rx(rx)·p + translate: the mesh turns about
the X axis of its own frame first, then about Y, then about Z (fixed axes, right-handed, degrees),
then moves by the translation (mm, program units).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

KEYS = ("translate", "rotate_deg")
# A placement key after '@': the path ends at the first '@' followed by a key and '='.
_SPLIT = re.compile(r"@(?=[A-Za-z_]+=)")


@dataclass(frozen=True)
class Placement:
    """A mesh file and where to put it (identity when both are zero)."""

    path: str
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotate_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def identity(self) -> bool:
        return not any(self.translate) and not any(self.rotate_deg)

    def matrix(self) -> np.ndarray:
        """(4, 4) float64: the homogeneous transform of the module doc."""
        return transform(self.translate, self.rotate_deg)

    def text(self) -> str:
        """The text form (parses back to this placement)."""
        out = self.path
        if any(self.translate):
            out += "@translate=" + ",".join(_num(v) for v in self.translate)
        if any(self.rotate_deg):
            out += "@rotate_deg=" + ",".join(_num(v) for v in self.rotate_deg)
        return out


def transform(translate, rotate_deg) -> np.ndarray:
    """(4, 4) float64: x' = Rz·Ry·Rx·x + t (module doc)."""
    rx, ry, rz = (math.radians(float(a)) for a in rotate_deg)

    def rot(axis: int, a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        m = np.eye(3)
        m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
        return m

    out = np.eye(4)
    out[:3, :3] = rot(2, rz) @ rot(1, ry) @ rot(0, rx)
    out[:3, 3] = np.asarray(translate, dtype=np.float64)
    return out


def parse(text: str) -> tuple[Placement | None, str | None]:
    """(the placement, None) of a text form, or (None, what is wrong with it)."""
    pieces = _SPLIT.split(str(text))
    path, values = pieces[0], {}
    if not path:
        return None, "the mesh path is missing before '@'"
    for piece in pieces[1:]:
        key, _, raw = piece.partition("=")
        if key not in KEYS:
            return None, f"unknown placement '{key}'"
        if key in values:
            return None, f"'{key}' is given twice"
        vec, problem = vector(raw.split(","))
        if problem:
            return None, f"'{key}' needs three numbers X,Y,Z"
        values[key] = vec
    return Placement(path, **values), None


def vector(value: Any) -> tuple[tuple[float, float, float] | None, bool]:
    """(three finite floats, False) from a list or comma text, else (None, True)."""
    parts = value if isinstance(value, (list, tuple)) else str(value).split(",")
    try:
        vec = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        return None, True
    if len(vec) != 3 or not all(math.isfinite(v) for v in vec) or any(isinstance(p, bool) for p in parts):
        return None, True
    return vec, False  # type: ignore[return-value]


def _num(v: float) -> str:
    return repr(float(v)).removesuffix(".0") if float(v) == int(v) else repr(float(v))
