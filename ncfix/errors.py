"""The one root exception: every message says where, which value, and what to do."""

from __future__ import annotations


class NcfixError(Exception):
    """A usage or input error; the command line prints it and exits 2.

    ``where`` is a file name, optionally with ``:line``; ``fix`` tells the user what to do.
    """

    exit_code = 2

    def __init__(self, message: str, *, where: str | None = None, fix: str | None = None):
        self.message = message
        self.where = where
        self.fix = fix
        super().__init__(str(self))

    def __str__(self) -> str:
        text = f"{self.where}: {self.message}" if self.where else self.message
        if self.fix:
            text += f" ({self.fix})"
        return text


class ProfileError(NcfixError):
    """A machine profile is missing, malformed, or names an unknown key or value."""


class ConfigError(NcfixError):
    """The TOML config or a command-line option has a bad key or value."""


class ProgramError(NcfixError):
    """The NC program cannot be read safely (e.g. an axis word that is not a number)."""


class GeometryError(NcfixError):
    """A head or part mesh cannot be used as given."""


class InternalError(NcfixError):
    """An unexpected failure inside ncfix (a bug, or the machine ran out of something): the
    command line says "internal error" and exits 2, ``-v`` shows the original traceback
    (``__cause__``). The API raises it so a hook's ``except NcfixError`` still catches it."""

    @classmethod
    def wrap(cls, exc: BaseException) -> "InternalError":
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        return cls(f"internal error: {type(exc).__name__}" + (f": {text}" if text else ""))
