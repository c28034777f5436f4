"""`python -m ncfix` runs the command line."""

import sys

from ncfix.cli import main

sys.exit(main())
