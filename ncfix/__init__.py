"""ncfix: find and fix head collisions in 5-axis additive-manufacturing NC programs."""

__version__ = "0.1.0"

from ncfix.errors import NcfixError
from ncfix.api import process

__all__ = ["NcfixError", "__version__", "process"]
