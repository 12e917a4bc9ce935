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

__all__ = ["ADDRESSES", "USAGE", "Change", "Refused", "name_arg", "numbers", "number",
           "no_args", "gain_arg", "telemetry_args", "MAX_GAIN", "MAX_TELEMETRY_HZ"]

#: The largest master gain a change takes [-] (+120 dB: beyond it a loud scene's frames
#: left float32's range, inf on the sound card; before: 1e300 was accepted).
MAX_GAIN = 1e6
#: The fastest telemetry a subscriber may ask for [Hz] (one message a sample at most).
MAX_TELEMETRY_HZ = 1e6

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
        Fewer or more than ``n`` (before: the extra ones were dropped and the change
        taken), not numbers (booleans refused), or not finite (an int beyond the float
        range too).
    """
    if len(args) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                 for v in args):
        missing = ("missing" if len(args) < n else f"{len(args)} given" if len(args) > n
                   else "not a number")
        raise Refused(f"expected {n} number(s) ({what}): {missing}" + _usage(address))
    try:
        vals = tuple(float(v) for v in args)
    except OverflowError:
        vals = (math.inf,)
    if not all(math.isfinite(v) for v in vals):
        raise Refused(f"{what} must be finite, got {', '.join(map(str, args))}"
                      + _usage(address))
    return vals


def no_args(args, address: str) -> None:
    """Refuse arguments given to an address that takes none (pause, resume, the
    queries; before: taken and ignored).

    Parameters
    ----------
    args : sequence
    address : str

    Raises
    ------
    Refused
        Any argument given.
    """
    if args:
        raise Refused(f"{address} takes no argument, got {len(args)}")


def gain_arg(args, address: str = "/hapsim/gain") -> float:
    """The master gain a change asks for: a finite number in [0, :data:`MAX_GAIN`].

    Parameters
    ----------
    args : sequence
    address : str

    Returns
    -------
    float

    Raises
    ------
    Refused
        As :func:`numbers`, or outside [0, MAX_GAIN] (a negative gain is no volume;
        before: -1 and 1e300 were taken, inf frames reached the sound card).
    """
    (g,) = numbers(args, 1, "gain", address)
    if not 0.0 <= g <= MAX_GAIN:
        raise Refused(f"gain must be in [0, {MAX_GAIN:g}] (0 silences), got {g:g}")
    return g


def telemetry_args(args, rate_hz: float) -> tuple:
    """A telemetry subscription's ``HOST PORT [RATE_HZ]``, checked before it is taken.

    Parameters
    ----------
    args : sequence
        The message's arguments.
    rate_hz : float
        The loop's rate [Hz] (the subscription's rate is at most that).

    Returns
    -------
    (str, int, int)
        Host, port and the samples between two messages (>= 1).

    Raises
    ------
    Refused
        A host that is no name, a port outside 1-65535, a rate that is not a finite
        number > 0 (before: a rate 0 was a ZeroDivisionError out of the handler, -1 sent
        every sample, a port of 70000 was taken and raised in the sample loop).
    """
    usage = _usage("/hapsim/telemetry")
    if not 2 <= len(args) <= 3 or not isinstance(args[0], str) or not args[0]:
        raise Refused("expected a host name, a port and an optional rate" + usage)
    from hapsim.errors import ConfigError
    from hapsim.option_values import option_value
    try:                                # (the options' one check: a range, a whole number)
        port = option_value("port", args[1], whole=True, low=1, high=65535)
        rate = option_value("rate_hz", 50.0 if len(args) < 3 else args[2], "Hz", low=0,
                            low_ok=False, high=MAX_TELEMETRY_HZ)
    except ConfigError as exc:
        raise Refused(str(exc) + usage) from None
    return args[0], port, max(1, int(round(rate_hz / rate)))


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
