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
class Options:
    """Every option of CONTRACT.md, in mm and degrees. Field names are the config keys."""

    machine: str = "ijk"
    head: str | None = None
    head_tip: tuple[float, float, float] = (0.0, 0.0, 0.0)
    head_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    part: tuple[str, ...] = ()
    standoff: float = 6.0
    pivot: str = "tip"
    max_step: float = 2.0
    max_tilt: float = 30.0
    pitch: float = 0.5
    clearance: float = 0.0
    strategy: str = "epa"
    resolution: float = 1.0
    bead_radius: float = 1.0
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
    extra: dict[str, Any] = field(default_factory=dict, compare=False)


OPTION_NAMES = tuple(f.name for f in fields(Options) if f.name != "extra")


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
    base = path.parent
    for key in ("head", "report", "diff", "html"):  # paths in a config are relative to it
        if isinstance(table.get(key), str):
            table[key] = str(base / table[key])
    if isinstance(table.get("part"), str):  # one part: the same as a list of one
        table["part"] = [table["part"]]
    if isinstance(table.get("part"), list):
        table["part"] = [str(base / p) if isinstance(p, str) else p for p in table["part"]]
    if isinstance(table.get("machine"), str) and table["machine"].endswith(".toml"):
        table["machine"] = str(base / table["machine"])
    return dict(table)


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
    return replace(out, **converted)


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
    if key in ("machine", "head", "report", "diff", "html"):
        if not isinstance(value, str) or not value:
            raise bad("give a name or a path")
        return value
    raise ConfigError(f"unknown option {name}")
