"""Machine profiles: TOML data in postprocessors/ naming a kinematic family, a word dialect and numbers.

Machine topology is code (ncfix.kinematics), the machine is data (this file's loader and the
profile files). Every key is checked; a bad profile fails naming the file, the key, the value and
the fix.
"""

from __future__ import annotations

import difflib
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from ncfix.errors import ProfileError
from ncfix.kinematics.base import Kinematics, RotaryAxis
from ncfix.kinematics.head_head import HeadHead
from ncfix.kinematics.head_table import HeadTable
from ncfix.kinematics.rotary import TwoAxisChain
from ncfix.kinematics.table_table import TableTable
from ncfix.kinematics.tool_vector import ToolVector
from ncfix.nc.dialects import DIALECTS as DIALECT_RULES

KINEMATICS = ("tool_vector", "table_table", "head_head", "head_table")
DIALECTS = tuple(DIALECT_RULES)
TCP_MODES = ("always", "never", "program")
AXIS_MODES = ("continuous", "modulo", "limited")

_TOP_KEYS = {
    "name", "description", "kinematics", "dialect", "tcp", "tcp_on", "tcp_off", "tcp_initial",
    "extrusion_letter", "vector", "axes", "tcp_off_geometry", "format", "platform",
}
_AXIS_KEYS = {"letter", "direction", "sign", "mode", "limits_deg", "on_head"}
_VECTOR_KEYS = {"letters", "max_tilt_deg"}
# [tcp_off_geometry] keys of each rotary family: another family's key is an error, never ignored.
_GEOMETRY_KEYS = {
    "table_table": {"centre_first_mm", "offset_mm", "centre_primary_mm"},
    "head_head": {"pivot_length_mm"},
    "head_table": {"table_centre_mm", "pivot_length_mm", "part_origin_mm"},
    "tool_vector": set(),
}
_PLATFORM_KEYS = {"translate", "rotate_deg", "mesh"}
_FORMAT_KEYS = {"linear", "angle", "vector", "force_decimal_point", "force_sign"}


@dataclass(frozen=True)
class NumberFormat:
    """Decimals for words ncfix has to add; words already in a block keep their own style."""

    linear: int = 3
    angle: int = 3
    vector: int = 6
    force_decimal_point: bool = False  # Fanuc-family: `X10.` (a bare `X10` may mean 10 µm)
    force_sign: bool = False  # Heidenhain: `X+10`


@dataclass(frozen=True)
class Profile:
    name: str
    description: str
    source: str  # file the profile came from
    kinematics: Kinematics
    kinematics_name: str
    dialect: str
    tcp: str
    tcp_on: tuple[str, ...]
    tcp_off: tuple[str, ...]
    tcp_initial: bool
    extrusion_letter: str
    number_format: NumberFormat = field(default_factory=NumberFormat)
    # [platform]: where the machine's build platform mesh (--platform FILE) goes in the part frame:
    # (translate (3,) mm, rotate_deg (3,) as ncfix.geometry.place), and the mesh it is meant for.
    platform: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    platform_mesh: str = ""

    @property
    def is_vector(self) -> bool:
        return self.kinematics_name == "tool_vector"


def builtin_dir() -> Path:
    """The shipped profiles: ``ncfix/postprocessors`` when installed, ``postprocessors/`` in a checkout."""
    try:
        return Path(str(resources.files("ncfix.postprocessors")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[1] / "postprocessors"


def builtin_names() -> list[str]:
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def load_profile(name_or_path: str) -> Profile:
    """A built-in profile by name, or a profile file by path."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists() or "/" in name_or_path or "\\" in name_or_path:
        if not path.is_file():
            raise ProfileError(f"machine profile file '{name_or_path}' does not exist",
                               fix="give a built-in name (ncfix --list-machines) or the path of a profile .toml file")
        return _load_file(path)
    candidate = builtin_dir() / f"{name_or_path}.toml"
    if not candidate.is_file():
        known = builtin_names()
        close = difflib.get_close_matches(name_or_path, known, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise ProfileError(f"unknown machine '{name_or_path}'",
                           fix=f"{hint}known machines: {', '.join(known)}; or give a profile file path")
    return _load_file(candidate)


def _load_file(path: Path) -> Profile:
    where = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"not valid TOML: {exc}", where=where, fix="fix the TOML syntax") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"cannot read the profile: {exc}", where=where) from None
    return build_profile(data, where)


def build_profile(data: dict[str, Any], where: str) -> Profile:
    r = _Reader(data, where)
    r.known_keys(data, _TOP_KEYS, "")
    kin_name = r.choice("kinematics", KINEMATICS)
    dialect = r.choice("dialect", DIALECTS)
    tcp = r.choice("tcp", TCP_MODES, default="always")
    fmt_data = r.table("format")
    r.known_keys(fmt_data, _FORMAT_KEYS, "format.")
    number_format = NumberFormat(
        linear=r.integer(fmt_data, "format.linear", 3, 0, 9),
        angle=r.integer(fmt_data, "format.angle", 3, 0, 9),
        vector=r.integer(fmt_data, "format.vector", 6, 3, 12),
        force_decimal_point=r.boolean(fmt_data, "format.force_decimal_point", False),
        force_sign=r.boolean(fmt_data, "format.force_sign", DIALECT_RULES[dialect].signed_numbers),
    )
    geometry = r.table("tcp_off_geometry")
    for key in set(geometry) - _GEOMETRY_KEYS[kin_name]:
        owner = next((fam for fam, keys in _GEOMETRY_KEYS.items() if key in keys), None)
        if owner is not None:
            known = ", ".join(sorted(_GEOMETRY_KEYS[kin_name])) or "none"
            raise ProfileError(f"key 'tcp_off_geometry.{key}' belongs to kinematics '{owner}', not '{kin_name}'",
                               where=where, fix=f"{kin_name} takes: {known}")
    r.known_keys(geometry, _GEOMETRY_KEYS[kin_name], "tcp_off_geometry.")
    platform_data = r.table("platform")
    r.known_keys(platform_data, _PLATFORM_KEYS, "platform.")
    platform = None
    if platform_data:
        platform = (r.vec3(platform_data, "platform.translate"), r.vec3(platform_data, "platform.rotate_deg"))
    platform_mesh = platform_data.get("mesh", "")
    if not isinstance(platform_mesh, str):
        raise r.fail("platform.mesh", platform_mesh, 'name the mesh file it is meant for, e.g. mesh = "platform.stl"')

    if kin_name == "tool_vector":
        vec = r.table("vector")
        r.known_keys(vec, _VECTOR_KEYS, "vector.")
        letters = vec.get("letters", ["I", "J", "K"])
        if not (isinstance(letters, list) and len(letters) == 3 and all(isinstance(x, str) and x for x in letters)):
            raise ProfileError(f"key 'vector.letters' must be three word addresses, got {letters!r}", where=where,
                               fix='e.g. letters = ["I", "J", "K"]')
        kinematics: Kinematics = ToolVector(tuple(x.upper() for x in letters),
                                            r.number(vec, "vector.max_tilt_deg", 180.0, 0.0, 180.0))
    else:
        axes_data = data.get("axes")
        if not isinstance(axes_data, list) or len(axes_data) != 2:
            raise ProfileError(f"key 'axes' must list exactly two rotary axes, got {axes_data!r}", where=where,
                               fix="add two [[axes]] tables, from the workpiece to the tool")
        axes = tuple(r.axis(a, i) for i, a in enumerate(axes_data))
        if kin_name == "table_table":
            transform = TableTable(r.vec3(geometry, "tcp_off_geometry.centre_first_mm"),
                                   r.vec3(geometry, "tcp_off_geometry.offset_mm"),
                                   r.vec3(geometry, "tcp_off_geometry.centre_primary_mm"))
        elif kin_name == "head_head":
            transform = HeadHead(r.number(geometry, "tcp_off_geometry.pivot_length_mm", 0.0, -1e4, 1e4))
        else:
            transform = HeadTable(r.vec3(geometry, "tcp_off_geometry.table_centre_mm"),
                                  r.number(geometry, "tcp_off_geometry.pivot_length_mm", 0.0, -1e4, 1e4),
                                  r.vec3(geometry, "tcp_off_geometry.part_origin_mm"))
        kinematics = TwoAxisChain(axes, transform)  # type: ignore[arg-type]

    return Profile(
        name=r.string("name"),
        description=r.string("description", default=""),
        source=where,
        kinematics=kinematics,
        kinematics_name=kin_name,
        dialect=dialect,
        tcp=tcp,
        tcp_on=r.codes("tcp_on"),
        tcp_off=r.codes("tcp_off"),
        tcp_initial=r.boolean(data, "tcp_initial", False),
        extrusion_letter=r.string("extrusion_letter", default="E").upper(),
        number_format=number_format,
        platform=platform,
        platform_mesh=platform_mesh,
    )


class _Reader:
    """Typed access to profile keys with messages that name file, key, value and fix."""

    def __init__(self, data: dict[str, Any], where: str):
        self.data, self.where = data, where

    def fail(self, key: str, value: Any, fix: str) -> ProfileError:
        return ProfileError(f"key '{key}' has a bad value {value!r}", where=self.where, fix=fix)

    def known_keys(self, table: dict[str, Any], known: set[str], prefix: str) -> None:
        for key in table:
            if key not in known:
                close = difflib.get_close_matches(key, sorted(known), n=1)
                hint = f"did you mean '{prefix}{close[0]}'?" if close else f"known keys: {', '.join(sorted(known))}"
                raise ProfileError(f"unknown key '{prefix}{key}'", where=self.where, fix=hint)

    def string(self, key: str, default: str | None = None) -> str:
        value = self.data.get(key, default)
        if not isinstance(value, str) or (default is None and not value):
            raise self.fail(key, value, f"set {key} = \"...\"")
        return value

    def choice(self, key: str, options: tuple[str, ...], default: str | None = None) -> str:
        value = self.data.get(key, default)
        if value not in options:
            raise self.fail(key, value, f"use one of: {', '.join(options)}")
        return value

    def table(self, key: str) -> dict[str, Any]:
        value = self.data.get(key, {})
        if not isinstance(value, dict):
            raise self.fail(key, value, f"[{key}] must be a table")
        return value

    def codes(self, key: str) -> tuple[str, ...]:
        value = self.data.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
            raise self.fail(key, value, 'give a list of codes, e.g. ["G43.4"]')
        return tuple(v.strip().upper() for v in value)

    def boolean(self, table: dict[str, Any], key: str, default: bool) -> bool:
        value = table.get(key.rsplit(".", 1)[-1], default)
        if not isinstance(value, bool):
            raise self.fail(key, value, "use true or false")
        return value

    def number(self, table: dict[str, Any], key: str, default: float, lo: float, hi: float) -> float:
        value = table.get(key.rsplit(".", 1)[-1], default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
            raise self.fail(key, value, f"use a number from {lo:g} to {hi:g}")
        return float(value)

    def integer(self, table: dict[str, Any], key: str, default: int, lo: int, hi: int) -> int:
        value = table.get(key.rsplit(".", 1)[-1], default)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise self.fail(key, value, f"use a whole number from {lo} to {hi}")
        return value

    def vec3(self, table: dict[str, Any], key: str, default=(0.0, 0.0, 0.0)) -> tuple[float, float, float]:
        value = table.get(key.rsplit(".", 1)[-1], list(default))
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise self.fail(key, value, "give three numbers, e.g. [0, 0, 1]")
        return (float(value[0]), float(value[1]), float(value[2]))

    def axis(self, data: Any, index: int) -> RotaryAxis:
        prefix = f"axes[{index}]."
        if not isinstance(data, dict):
            raise self.fail(f"axes[{index}]", data, "each [[axes]] entry must be a table")
        self.known_keys(data, _AXIS_KEYS, prefix)
        letter = data.get("letter")
        if not isinstance(letter, str) or len(letter) != 1 or not letter.isalpha():
            raise self.fail(prefix + "letter", letter, 'use one letter, e.g. letter = "C"')
        direction = self.vec3(data, prefix + "direction")
        norm = sum(v * v for v in direction) ** 0.5
        if abs(norm - 1.0) > 1e-6:
            raise self.fail(prefix + "direction", list(direction), "give a unit vector, e.g. [0, 0, 1]")
        sign = data.get("sign", 1)
        if sign not in (1, -1) or isinstance(sign, bool):
            raise self.fail(prefix + "sign", sign, "use 1 (ISO 841) or -1 (reversed axis)")
        mode = data.get("mode", "limited")
        if mode not in AXIS_MODES:
            raise self.fail(prefix + "mode", mode, f"use one of: {', '.join(AXIS_MODES)}")
        limits = data.get("limits_deg", [-360.0, 360.0] if mode == "limited" else [-1e9, 1e9])
        if (not isinstance(limits, list) or len(limits) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in limits)
                or not limits[0] < limits[1]):
            raise self.fail(prefix + "limits_deg", limits, "give [low, high] in degrees with low < high")
        on_head = self.boolean(data, prefix + "on_head", False)
        return RotaryAxis(letter.upper(), direction, int(sign), mode, (float(limits[0]), float(limits[1])), on_head)
