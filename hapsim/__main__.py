"""``python -m hapsim`` runs the command line."""

from hapsim.cli import entry

entry()
