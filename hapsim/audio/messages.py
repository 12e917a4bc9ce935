"""The messages a running scene takes (OSC, and the live view's requests): the addresses,
their arguments, the refusal and the accepted change.

What a message asks for is checked, ramped and journaled by :mod:`hapsim.audio.control`
(:class:`hapsim.audio.control.Controller` for a 1-D scene, its ``ControllerND`` for a 2-D or
3-D one); :mod:`hapsim.audio.osc` serves the addresses over UDP. Here: what each address
takes and answers (:data:`ADDRESSES`, :data:`USAGE`), how its arguments are read
(:func:`name_arg`, :func:`numbers`; a missing or wrong argument is a :class:`Refused`
naming the address's usage), and the accepted change on its way to the sample loop
(:class:`Change`).

OSC addresses (:data:`ADDRESSES`; replies go to the sender's address and port):

==============================  ==============================  =========================
address                         arguments                       reply
==============================  ==============================  =========================
/hapsim/link/stiffness          link K[N/m]                     /hapsim/ok or /refused
/hapsim/link/damping            link B[N s/m]                   /hapsim/ok or /refused
/hapsim/link/kb                 link K B                        /hapsim/ok or /refused
/hapsim/link/target             link k[N/m] b[N s/m] (felt)     /hapsim/ok or /refused
/hapsim/mass                    mass m[kg]                      /hapsim/ok or /refused
/hapsim/gain                    g (sound master gain)           /hapsim/ok or /refused
/hapsim/pause, /hapsim/resume   (none)                          /hapsim/ok
/hapsim/felt                    (none)                          /hapsim/felt k b f0 zeta
                                                                k_meas b_meas
/hapsim/loop                    (none)                          /hapsim/loop sample
                                                                spectral_radius stable
                                                                changes refused xruns
                                                                underruns
/hapsim/telemetry               host port [rate_hz]             /hapsim/ok; then
                                                                /hapsim/tel t x f ...
==============================  ==============================  =========================

``/hapsim/ok`` carries the request address, the ramp time [s] and the new felt k, b;
``/hapsim/refused`` carries the request address and the reason. Measured values are NaN
until a free response has been identified after the last change.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["ADDRESSES", "USAGE", "Change", "Refused", "name_arg", "numbers", "number"]

#: The OSC addresses the server maps (module docstring).
ADDRESSES = ("/hapsim/link/stiffness", "/hapsim/link/damping", "/hapsim/link/kb",
             "/hapsim/link/target", "/hapsim/mass", "/hapsim/gain", "/hapsim/pause",
             "/hapsim/resume", "/hapsim/felt", "/hapsim/loop", "/hapsim/telemetry")

#: The arguments each address takes (said in a refusal for missing or wrong arguments).
USAGE = {"/hapsim/link/stiffness": "LINK K [N/m]", "/hapsim/link/damping": "LINK B [N s/m]",
         "/hapsim/link/kb": "LINK K [N/m] B [N s/m]",
         "/hapsim/link/target": "LINK k [N/m] b [N s/m]", "/hapsim/mass": "MASS m [kg]",
         "/hapsim/gain": "G", "/hapsim/pause": "", "/hapsim/resume": "",
         "/hapsim/felt": "", "/hapsim/loop": "", "/hapsim/telemetry": "HOST PORT [RATE_HZ]"}


@dataclasses.dataclass
class Change:
    """An accepted change on its way to the sample loop.

    Attributes
    ----------
    kind : {"link", "mass", "gain", "pause", "resume"}
    name : str
        Link or mass name ("" otherwise).
    start, end : tuple of float
        Values at the start and end of the ramp: (K, B) [N/m, N s/m], (m,) [kg], (g,).
    steps : int
        Device samples the ramp lasts (>= 1).
    done : int
        Samples of the ramp applied so far.
    """

    kind: str
    name: str
    start: tuple
    end: tuple
    steps: int
    done: int = 0


class Refused(Exception):
    """A change refused, with the reason sent back to its sender (``/hapsim/refused``)."""


def _usage(address: str) -> str:
    return f" (usage: {address} {USAGE[address]})" if address in USAGE else ""


def name_arg(args, address: str = "") -> str:
    """The name a change's first OSC argument gives.

    Parameters
    ----------
    args : sequence
        The message's OSC arguments.
    address : str
        The OSC address, for the usage in the refusal (none when empty or unknown).

    Returns
    -------
    str
        ``args[0]``.

    Raises
    ------
    Refused
        No first argument, or not a string (the address's usage said).
    """
    if not args or not isinstance(args[0], str):
        got = "nothing" if not args else f"{type(args[0]).__name__} {args[0]!r}"
        raise Refused(f"the first argument must be a name (string), got {got}"
                      + _usage(address))
    return args[0]


def numbers(args, n: int, what: str, address: str = "") -> tuple:
    """The first ``n`` OSC arguments as finite floats.

    Parameters
    ----------
    args : sequence
        The message's OSC arguments.
    n : int
        How many numbers the address takes (>= 1).
    what : str
        What they are, for the refusal (``"K, B"``).
    address : str
        The OSC address, for the usage in the refusal.

    Returns
    -------
    tuple of float
        The first ``n`` arguments (units as the address documents them).

    Raises
    ------
    Refused
        Fewer than ``n``, not numbers (booleans refused) or not finite.
    """
    if len(args) < n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                for v in args[:n]):
        missing = "missing" if len(args) < n else "not a number"
        raise Refused(f"expected {n} number(s) ({what}): {missing}" + _usage(address))
    vals = tuple(float(v) for v in args[:n])
    if not all(math.isfinite(v) for v in vals):
        raise Refused(f"{what} must be finite")
    return vals


def number(v) -> float:
    """A reply's value as a float: ``v``, or NaN when it is None (a value not known).

    Parameters
    ----------
    v : float or None

    Returns
    -------
    float
    """
    return float(v) if v is not None else math.nan
