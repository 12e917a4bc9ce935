"""``python -m hapsim`` runs the command line."""

import sys

from hapsim.cli import main

sys.exit(main())
