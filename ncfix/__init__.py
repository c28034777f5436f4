"""ncfix: find and fix head collisions in 5-axis additive-manufacturing NC programs."""

__version__ = "0.1.0"

import logging

# Notices (e.g. a cache file rebuilt) go to the "ncfix" logger; the command line prints them, a
# library caller sees them only when it configures logging.
logging.getLogger("ncfix").addHandler(logging.NullHandler())

from ncfix.errors import NcfixError
from ncfix.api import process

__all__ = ["NcfixError", "__version__", "process"]
