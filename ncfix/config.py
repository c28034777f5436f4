"""Options: defaults, the TOML config (table [ncfix]) and the command line, checked in one place."""

from __future__ import annotations

import difflib
import math
import os
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from ncfix.errors import ConfigError

STRATEGIES = ("graph", "epa")
DEVICES = ("auto", "cpu", "cuda")
PIVOTS = ("tip", "point")


@dataclass(frozen=True)
class EpaOptions:
    """The epa strategy's own settings: not command-line options, for the API, tests and
    benchmarks that tune the walk (docs/correction.md)."""

    variant: str = "lami"  # "lami": tilt budgets from the walk's own steps; "fixed": a fixed step
    step_deg: float | None = None  # the walk's step; None: half of --resolution
    threshold: float = 0.05  # CoACD's concavity threshold for the head's convex pieces
    cache_dir: str | None = None  # the decomposition cache; None: $NCFIX_CACHE or ~/.cache/ncfix
    graph_fallback: bool = True  # the graph searches again the episodes the walk leaves colliding


@dataclass(frozen=True)
class Options:
    """Every option of docs/contract.md, in mm and degrees. Field names are the config keys."""

    machine: str = "ijk"
    head: str | None = None
    head_tip: tuple[float, float, float] = (0.0, 0.0, 0.0)
    head_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    part: tuple[str, ...] = ()
    platform: str | None = None
    standoff: float = 6.0
    pivot: str = "tip"
    max_step: float = 2.0
    max_tilt: float = 30.0
    pitch: float = 0.5
    clearance: float = 0.0
    strategy: str = "epa"
    resolution: float = 1.0
    bead_radius: float = 1.0
    bead_width: float | None = None
    bead_height: float | None = None
    filament_diameter: float | None = None
    tip_allowance: float = 1.0
    deposit_codes: tuple[str, str] | None = None
    check: bool = False
    report: str | None = None
    diff: str | None = None
    html: str | None = None
    device: str = "auto"
    window: int = 2000
    quiet: bool = False
    verbose: bool = False
    epa: EpaOptions = field(default_factory=EpaOptions)  # --strategy epa's settings (not a config key)


OPTION_NAMES = tuple(f.name for f in fields(Options) if f.name != "epa")


def load_config(path: Path, explicit: bool) -> dict[str, Any]:
    """The [ncfix] table of a TOML file, keys checked; {} when the default file is absent."""
    if not path.exists():
        if explicit:
            raise ConfigError(f"config file '{path}' does not exist", fix="give an existing file with -c/--config")
        return {}
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}", where=str(path), fix="fix the TOML syntax") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the config: {exc}", where=str(path)) from None
    table = data.get("ncfix")
    if table is None:
        unknown = ", ".join(sorted(data)) or "nothing"
        raise ConfigError(f"no [ncfix] table (found: {unknown})", where=str(path),
                          fix="put the options under a [ncfix] table")
    if not isinstance(table, dict):
        raise ConfigError("'ncfix' must be a table", where=str(path), fix="write [ncfix] on its own line")
    for key in table:
        if key not in OPTION_NAMES:
            close = difflib.get_close_matches(key, OPTION_NAMES, n=1)
            hint = f"did you mean '{close[0]}'?" if close else "see ncfix --help for the options"
            raise ConfigError(f"unknown key '{key}' in [ncfix]", where=str(path), fix=hint)
    for key in data:
        if key != "ncfix" and key in OPTION_NAMES:
            form = f"[[ncfix.{key}]]" if key == "part" else f"[ncfix.{key}]"
            raise ConfigError(f"'{key}' is outside the [ncfix] table", where=str(path),
                              fix=f"write it as {form} or as a key under [ncfix]")
    base = path.parent
    for key in ("report", "diff", "html"):  # paths in a config are relative to it
        if isinstance(table.get(key), str):
            table[key] = str(base / table[key])
    for key in ("head", "platform"):
        if key in table:
            table[key] = _mesh_entry(table[key], key, base, path)
    if isinstance(table.get("part"), (list, dict)):
        entries = table["part"] if isinstance(table["part"], list) else [table["part"]]
        table["part"] = [_mesh_entry(p, "part", base, path) for p in entries]
    elif isinstance(table.get("part"), str):
        table["part"] = [_mesh_entry(table["part"], "part", base, path)]
    if isinstance(table.get("machine"), str) and table["machine"].endswith(".toml"):
        table["machine"] = str(base / table["machine"])
    return dict(table)


def _mesh_entry(entry: Any, key: str, base: Path, config: Path) -> Any:
    """A mesh entry of the config as the text form ``PATH@translate=..@rotate_deg=..`` (see
    ``ncfix.geometry.place``), its path relative to the config file: a string, or a table
    ``{path = ..., translate = [x, y, z], rotate_deg = [rx, ry, rz]}``."""
    from ncfix.geometry.place import KEYS, Placement, vector

    if isinstance(entry, str):
        return str(base / entry) if entry else entry
    if not isinstance(entry, dict):
        return entry  # _convert says what is wrong with it
    for name in entry:
        if name != "path" and name not in KEYS:
            raise ConfigError(f"unknown key '{name}' in a '{key}' table", where=str(config),
                              fix="use path, translate = [x, y, z] and rotate_deg = [rx, ry, rz]")
    if not isinstance(entry.get("path"), str) or not entry["path"]:
        raise ConfigError(f"a '{key}' table needs path = \"FILE\"", where=str(config), fix="give the mesh file's path")
    values = {}
    for name in KEYS:
        if name in entry:
            vec, bad = vector(entry[name])
            if bad:
                raise ConfigError(f"'{name}' of '{key}' {entry['path']!r} has a bad value {entry[name]!r}",
                                  where=str(config), fix="give three numbers, e.g. [0, 0, -40.5]")
            values[name] = vec
    return Placement(str(base / entry["path"]), **values).text()


OUTPUT_KEYS = ("report", "diff", "html")


def confine_outputs(config: dict[str, Any], path: Path, cli: dict[str, Any]) -> None:
    """Refuse output paths of a config that ncfix found beside the input (not given with -c,
    not in the working folder) when they lead outside that config's folder: a folder of programs
    from elsewhere must not make ncfix overwrite files anywhere (``../``, absolute paths,
    symlinks). Keys the command line overrides are not used, so not checked."""
    folder = Path(os.path.realpath(path.parent))
    for key in OUTPUT_KEYS:
        value = config.get(key)
        if not isinstance(value, str) or cli.get(key) is not None:
            continue
        target = Path(os.path.realpath(value))
        if target != folder and folder not in target.parents:
            raise ConfigError(f"key '{key}' writes outside the config's folder: '{value}'", where=str(path),
                              fix=f"a config found beside the input writes only inside its folder; give "
                                  f"--{key} on the command line or this config with -c")


def build_options(config: dict[str, Any], cli: dict[str, Any], where: str = "ncfix.toml") -> Options:
    """Defaults < config file (at ``where``) < command line; every value checked and converted."""
    merged: dict[str, Any] = {}
    for source, values in (("config", config), ("command line", cli)):
        for key, value in values.items():
            if value is not None:
                merged[key] = (source, value)
    out = Options()
    converted = {}
    for key, (source, value) in merged.items():
        converted[key] = _convert(key, value, source, where)
    _check_bead(merged, converted, where)
    return replace(out, **converted)


def _check_placement(text: str, name: str, source: str, config_path: str) -> None:
    from ncfix.geometry.place import parse

    _, problem = parse(text)
    if problem:
        raise ConfigError(f"{name} {text!r}: {problem}", where=config_path if source == "config" else None,
                          fix="write PATH@translate=X,Y,Z@rotate_deg=RX,RY,RZ (either part may be left out)")


def _check_bead(merged: dict[str, Any], converted: dict[str, Any], where: str) -> None:
    """A bead section is a width and a height together; --bead-radius 0 (no deposit model) with one
    is a contradiction, not a choice to guess."""
    given = [k for k in ("bead_width", "bead_height") if k in converted]

    def place(key: str) -> tuple[str, str | None]:
        source = merged[key][0]
        return ("--" + key.replace("_", "-"), None) if source == "command line" else (f"key '{key}'", where)

    if len(given) == 1:
        missing = "bead_height" if given[0] == "bead_width" else "bead_width"
        name, at = place(given[0])
        raise ConfigError(f"{name} needs {'--' + missing.replace('_', '-')} too (a bead's section is width × height)",
                          where=at, fix="give both, or --bead-radius R for a round bead")
    if given and converted.get("bead_radius", 1.0) == 0.0:
        name, at = place("bead_radius")
        raise ConfigError(f"{name} is 0 (no deposit model) but a bead width and height are stated", where=at,
                          fix="drop the bead width and height to turn the deposit model off, or the radius of 0")


def _convert(key: str, value: Any, source: str, config_path: str) -> Any:
    flag = "--" + key.replace("_", "-")
    name = flag if source == "command line" else f"key '{key}'"

    def bad(expected: str) -> ConfigError:
        return ConfigError(f"{name} has a bad value {value!r}", where=config_path if source == "config" else None,
                           fix=expected)

    if key in ("standoff", "max_step", "max_tilt", "pitch", "clearance", "bead_radius", "tip_allowance",
               "resolution"):
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise bad("give a number") from None
        if isinstance(value, bool) or not math.isfinite(number):
            raise bad("give a number")
        limits = {
            "standoff": (0.0, 1000.0, True), "max_step": (0.0, 90.0, False), "max_tilt": (0.0, 90.0, False),
            "pitch": (0.0, 50.0, False), "clearance": (0.0, 100.0, True), "bead_radius": (0.0, 100.0, True),
            "tip_allowance": (0.0, 1000.0, True), "resolution": (0.05, 10.0, True),
        }
        lo, hi, lo_ok = limits[key]
        if number > hi or number < lo or (number == lo and not lo_ok):
            low = f"from {lo:g}" if lo_ok else f"above {lo:g}"
            raise bad(f"give a number {low} up to {hi:g}")
        return number
    if key in ("bead_width", "bead_height", "filament_diameter"):
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise bad("give a number above 0 up to 100") from None
        if isinstance(value, bool) or not math.isfinite(number) or not 0.0 < number <= 100.0:
            raise bad("give a number above 0 up to 100")
        return number
    if key == "window":
        if isinstance(value, bool):
            raise bad("give a whole number of blocks, at least 16")
        try:
            number = int(value)
        except (TypeError, ValueError):
            raise bad("give a whole number of blocks, at least 16") from None
        if number < 16:
            raise bad("give a whole number of blocks, at least 16")
        return number
    if key in ("head_tip", "head_axis"):
        parts = value if isinstance(value, (list, tuple)) else str(value).split(",")
        try:
            vec = tuple(float(p) for p in parts)
        except (TypeError, ValueError):
            vec = ()
        if len(vec) != 3 or not all(math.isfinite(v) for v in vec):
            raise bad("give three numbers X,Y,Z, e.g. 0,0,1")
        if key == "head_axis" and sum(v * v for v in vec) < 1e-12:
            raise bad("the axis must not be 0,0,0")
        return vec
    if key == "deposit_codes":
        parts = value if isinstance(value, (list, tuple)) else str(value).split(",")
        codes = tuple(str(p).strip().upper() for p in parts)
        if len(codes) != 2 or not all(codes) or codes[0] == codes[1]:
            raise bad("give two different codes ON,OFF, e.g. M3,M5")
        return codes
    if key == "part":
        parts = value if isinstance(value, (list, tuple)) else [value]
        if not all(isinstance(p, str) and p for p in parts):
            raise bad("give mesh file paths")
        for p in parts:
            _check_placement(p, name, source, config_path)
        return tuple(parts)
    choices = {"strategy": STRATEGIES, "device": DEVICES, "pivot": PIVOTS}
    if key in choices:
        if value not in choices[key]:
            raise bad(f"use one of: {', '.join(choices[key])}")
        return value
    if key in ("check", "quiet", "verbose"):
        if not isinstance(value, bool):
            raise bad("use true or false")
        return value
    if key in ("machine", "head", "platform", "report", "diff", "html"):
        if not isinstance(value, str) or not value:
            raise bad("give a name or a path")
        if key in ("head", "platform"):
            _check_placement(value, name, source, config_path)
        return value
    raise ConfigError(f"unknown option {name}")
