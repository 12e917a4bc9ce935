"""firmware_protocol — the framed serial protocol between hapsim and a force-feedback device.

Standalone and I/O-free: it imports nothing from ``hapsim`` and touches no port or file.
The specification is ``PROTOCOL.md`` next to this file; a C99 reference implementation for
firmware is in ``c/`` and the golden vectors shared by both are in ``vectors/vectors.json``.

Examples
--------
>>> import firmware_protocol as fp
>>> frame = fp.encode(fp.Force(seq=7, force=(0.5,)))
>>> fp.decode_frame(frame)
Force(seq=7, force=(0.5,))
>>> dec = fp.StreamDecoder()
>>> dec.feed(b"garbage\\x00" + frame[:5]), dec.feed(frame[5:])
([], [Force(seq=7, force=(0.5,))])
"""

from .codec import *  # noqa: F401,F403
from .codec import __all__  # noqa: F401
