"""hapsim: a real-time haptic simulator daemon that tells you what you actually feel.

See ``README.md`` for the command line, ``hapsim.scene`` for the YAML scene format,
``hapsim.engine`` for the mass-interaction engine and ``hapsim.analysis`` for the
temporary hybrid system (THS) analysis of Florens, Voda & Urma.
"""

from hapsim.errors import (ConfigError, DeviceError, HapsimError, ProtocolError,
                           UnstableConfigError)

__version__ = "0.1.0"

__all__ = ["HapsimError", "ConfigError", "ProtocolError", "DeviceError",
           "UnstableConfigError", "__version__"]
