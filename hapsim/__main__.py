"""``python -m hapsim`` runs the command line."""

import hapsim

hapsim._quiet_interrupt_at_start(force=True)   # before the imports Ctrl-C may land in

from hapsim.cli import entry  # noqa: E402

entry()
