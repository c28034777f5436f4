"""ncfix: find and fix head collisions in 5-axis additive-manufacturing NC programs."""

import logging

from ncfix.api import process
from ncfix.errors import NcfixError
from ncfix.version import __version__

# Notices (e.g. a cache file rebuilt) go to the "ncfix" logger; the command line prints them, a
# library caller sees them only when it configures logging.
logging.getLogger("ncfix").addHandler(logging.NullHandler())

__all__ = ["NcfixError", "__version__", "process"]
