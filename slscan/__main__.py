"""`python -m slscan ...` runs the command line."""

import sys

from slscan.cli import main

sys.exit(main())
