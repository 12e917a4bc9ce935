"""Sub-commands of the ``hapsim`` command line, one module each (see :mod:`hapsim.cli`)."""
