"""`python -m slscan ...` runs the command line."""

from slscan.cli import run

run()
