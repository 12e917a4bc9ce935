"""The FireFader's position scale, found from a sweep between its end stops.

Identification through the FireFader's bytes sees the gain ``full_scale / m`` in the
host's units, and the position scale enters the same way (``docs/drivers.md``, "Device
parameters"): the fit and ``--added-mass`` fix only the ratio of the force scale to the
position scale. A length reference separates them: the fader's travel between its end
stops, from its datasheet (the ALPS faders of the FireFader: 100 mm class), given by the
user, against the pot counts read at the two stops.

The sweep (:func:`find_travel`): arm the firmware (zero force while its touch and enable
filters come up), push the fader towards the low stop with a constant force until its
pot count has stayed within one count for :data:`STILL_S`, then towards the high stop,
then bring it back to the middle between them (a spring and a damper on the counts, until
it rests there) and end at zero force. A count taken as a stop must meet three conditions, each refused with its reason
otherwise:

- the count settled within :data:`MAX_PUSH_S` of pushing (else the fader did not reach
  a stop: too little force for its friction, or no stop);
- it settled *while the firmware's force was on*: the host replays the ``.ino``'s enable
  gate from the counts it read (:func:`hapsim.drivers.firefader.enable_passes`), and a
  fader that came to rest after the range gate (``pot <= 4`` or ``>= 251``) or a lost
  touch cut the force has coasted to rest, not reached a stop;
- it is not the pot's rail (0 or 254: the ADC saturates, ``SerialWriteNo255`` clips 255
  to 254), where the stop lies beyond what the pot can read.

The position scale is ``travel / (c_high - c_low)`` [m/count]. Each stop's count is the
mean of the settled window, known to half a count plus half the window's spread (the pot
is read as an 8-bit average, ``haptics_firmware.ino`` lines 339-344), so the stated
interval is ``travel / (span +- (h_low + h_high))``; the travel's own tolerance (the
datasheet's) adds to it relatively and is the user's to state.
"""

from __future__ import annotations

import dataclasses
import math

from hapsim.drivers.exchange import Exchange, SerialLink
from hapsim.errors import IdentificationError

__all__ = ["TravelSweep", "find_travel", "sweep_port", "stop_count", "STILL_S",
           "MAX_PUSH_S", "CENTRE_S"]

#: A count that stays within one count this long is settled [s].
STILL_S = 0.1
#: Longest push towards one stop [s].
MAX_PUSH_S = 3.0
#: Time allowed to bring the fader back to the middle after the sweep [s].
CENTRE_S = 2.0


@dataclasses.dataclass(frozen=True)
class TravelSweep:
    """What :func:`find_travel` found.

    Attributes
    ----------
    metres_per_count : float
        The position scale [m/count].
    lo, hi : float
        Its interval [m/count] (the stops' counts to their half-widths).
    counts : tuple of float
        The low and high stops' counts (means of the settled windows).
    half_widths : tuple of float
        Their half-widths [counts].
    travel : float
        The travel given [m].
    force : float
        The force pushed with [N] (in the host's full scale).
    writes : int
        Packets sent (periods).
    """

    metres_per_count: float
    lo: float
    hi: float
    counts: tuple
    half_widths: tuple
    travel: float
    force: float
    writes: int

    def to_dict(self) -> dict:
        """JSON-ready fields.

        Returns
        -------
        dict
            The fields by name, tuples as lists (``metres_per_count``, ``lo``, ``hi``
            [m/count], ``travel`` [m], ``force`` [N]).
        """
        return {"metres_per_count": self.metres_per_count, "lo": self.lo, "hi": self.hi,
                "counts": list(self.counts), "half_widths": list(self.half_widths),
                "travel": self.travel, "force": self.force, "writes": self.writes}


def stop_count(counts, forces, silence, *, still: int):
    """Whether a push ended on a stop, and where: the count settled (within one count over
    the last ``still`` records) while the firmware's force was on.

    Parameters
    ----------
    counts : sequence of int, shape (n,)
        The fader's counts read, one per packet of the push (0..254).
    forces : sequence of int, shape (n,)
        The force count each of those packets carried.
    silence : sequence of float, shape (n,)
        Host silence before each packet [s] (the ``.ino``'s 0.1 s rule).
    still : int
        Records a settled count must last.

    Returns
    -------
    tuple
        ``(state, count, half_width)``: ``state`` one of ``"stop"``, ``"moving"`` (not
        settled), ``"unmoved"`` (settled where the push began), ``"coasted"`` (settled after the firmware's force went off), ``"rail"``
        (settled on the pot's 0 or 254); ``count`` the mean of the settled window and
        ``half_width`` half a count plus half its spread [counts] (None while moving).
    """
    import numpy as np

    from hapsim.drivers.firefader import POSITION_MAX, enable_passes
    c = np.asarray(counts, np.int64)
    if c.size < still:
        return "moving", None, None
    w = c[-still:]
    if w.max() - w.min() > 1:
        return "moving", None, None
    # where the final still run began: the first record from which every count is within
    # one count of the window's
    lo, hi = int(w.min()), int(w.max())
    k = c.size - still
    while k > 0 and max(hi, c[k - 1]) - min(lo, c[k - 1]) <= 1:
        k -= 1
        lo, hi = min(lo, int(c[k])), max(hi, int(c[k]))
    mean = float(w.mean())
    half = 0.5 + 0.5 * float(w.max() - w.min())
    if k == 0:
        return "unmoved", mean, half
    if lo <= 0 or hi >= POSITION_MAX:
        return "rail", mean, half
    # the force the firmware applied while the fader came to rest (its gate replayed;
    # the force of a packet acts in the pass that reads the next count)
    pwm = enable_passes(np.asarray(forces, np.int64), np.asarray(silence, float), c,
                        delay=0)
    if pwm[k] == 0:
        return "coasted", mean, half
    return "stop", mean, half


def _send(ex, count: int):
    """Send a packet of ``count`` force counts on the fader's axis (one period); return
    ``(pot count or None, host silence before it [s])``."""
    from hapsim.drivers.firefader import CENTRE, encode_packet
    got = ex.reply(encode_packet(count, 0) if ex.drv.axis == 0 else encode_packet(0, count))
    if got is None:
        return None, ex.silence
    return CENTRE + round(got / ex.drv.position_scale), ex.silence


_LOST = ("the FireFader does not answer its packets (no record for more than 50 packets "
         "in a row during the travel sweep): check the port")


def find_travel(drv, link, *, travel: float, force: float, rate_hz: float = 250.0,
                pace: bool = True, timeout: float = 0.05) -> TravelSweep:
    """Find the FireFader's position scale from a sweep between its end stops (module
    notes).

    Parameters
    ----------
    drv : hapsim.drivers.firefader.FireFader
        The driver (its axis and full scale; its position scale is not used).
    link : object
        ``write(bytes)`` and ``read(timeout [s]) -> bytes`` on the fader's port.
    travel : float
        The fader's travel between its end stops [m] (its datasheet's).
    force : float
        The force to push with [N] (clamped to the protocol's 126 counts).
    rate_hz : float
        Packet rate [Hz].
    pace : bool
        Pace the packets at ``rate_hz`` on the host's clock (False: as fast as the link
        answers, for a mock that advances one period per packet).
    timeout : float
        Longest wait for a record [s].

    Returns
    -------
    TravelSweep

    Raises
    ------
    ConfigError
        A travel or force that is not a positive number.
    IdentificationError
        A stop not reached, reached with the force off (coasted), or on the pot's rail;
        two stops less than 20 counts apart.
    DeviceError
        The fader does not answer.
    """
    from hapsim.drivers.firefader import CENTRE, FORCE_MAX, force_counts
    from hapsim.errors import ConfigError
    if not (math.isfinite(travel) and travel > 0):
        raise ConfigError(f"must be a positive length [mm], got {travel * 1e3!r}",
                          key="--travel")
    n_force = min(abs(force_counts(force, drv.full_scale)), FORCE_MAX)
    if not (math.isfinite(force) and n_force > 0):
        raise ConfigError(f"no force to push the fader with: {force!r} N is 0 counts at "
                          f"full scale {drv.full_scale:g} N", key="--force-limit")
    ex = Exchange(drv, link, rate_hz, pace, timeout, max_missing=50, lost=_LOST)
    still = max(3, round(STILL_S * rate_hz))
    n_push = max(still + 1, round(MAX_PUSH_S * rate_hz))
    found = []
    last = None
    try:
        for _ in range(drv.arming_records):   # the touch and enable filters come up
            c, _s = _send(ex, 0)
            last = c if c is not None else last
        for sign, name in ((-1, "low"), (1, "high")):
            cs, fs, ss = [], [], []
            state = "moving"
            for _ in range(n_push):
                c, s = _send(ex, sign * n_force)
                if c is None:
                    continue
                cs.append(c)
                fs.append(sign * n_force)
                ss.append(s)
                last = c
                state, mean, half = stop_count(cs, fs, ss, still=still)
                if state != "moving":
                    break
            if state == "moving":
                raise IdentificationError(
                    f"the FireFader did not reach its {name} end stop: its count was still "
                    f"changing after {MAX_PUSH_S:g} s at {sign * n_force * drv.force_scale:+.3g} "
                    f"N (counts {cs[0] if cs else '-'} -> {cs[-1] if cs else '-'}): no "
                    f"stop within the pot's range, or too little force for its friction "
                    f"(raise --force-limit)")
            if state == "unmoved":
                raise IdentificationError(
                    f"the FireFader did not move towards its {name} end stop under "
                    f"{sign * n_force * drv.force_scale:+.3g} N (count {mean:.1f} "
                    f"throughout): it is blocked or held, untouched (the firmware's force "
                    f"needs a finger on the fader's cap sense), or its friction exceeds "
                    f"--force-limit")
            if state == "coasted":
                raise IdentificationError(
                    f"the FireFader came to rest at count {mean:.1f} towards its {name} "
                    f"end with the firmware's force off (its enable gate: pot <= 4 or >= "
                    f"251, or the touch lost), so that count need not be the stop: "
                    f"keep a finger on the fader, or push harder (--force-limit) so that "
                    f"it reaches the stop before the gate cuts the force")
            if state == "rail":
                raise IdentificationError(
                    f"the FireFader's pot reads its rail ({mean:.1f}) at the {name} end "
                    f"stop: the stop lies beyond what the pot can read, so the counts "
                    f"between the stops are not the travel's; no length reference (give "
                    f"metres_per_count as --protocol-option)")
            found.append((mean, half))
        (c_lo, h_lo), (c_hi, h_hi) = found
        span = c_hi - c_lo
        if span < 20:
            raise IdentificationError(
                f"the FireFader's end stops read {c_lo:.1f} and {c_hi:.1f}: {span:.1f} "
                f"counts apart (at least 20 needed): the fader did not move between them "
                f"(blocked, held, or pushed the wrong way)")
        # back to the middle between the stops (a spring and a damper on the counts:
        # 1 force count per count, 40 per count per packet), at rest, then zero force
        mid = 0.5 * (c_lo + c_hi)
        prev = last
        rest = 0
        for _ in range(max(1, round(CENTRE_S * rate_hz))):
            x = last if last is not None else CENTRE
            v = x - (prev if prev is not None else x)
            n = int(max(-n_force, min(n_force, round((mid - x) - 40.0 * v))))
            prev = x
            c, _s = _send(ex, n)
            last = c if c is not None else last
            rest = rest + 1 if (last is not None and abs(last - mid) <= 3
                                and last == prev) else 0
            if rest >= still:
                break
    finally:
        try:
            link.write(drv.encode_force(0.0))
        except Exception:  # noqa: BLE001 -- best effort: the port may be gone
            pass
    h = h_lo + h_hi
    return TravelSweep(travel / span, travel / (span + h), travel / (span - h),
                       (c_lo, c_hi), (h_lo, h_hi), float(travel),
                       n_force * drv.force_scale, ex.writes)


def sweep_port(drv, port: str, *, travel: float, force: float, rate_hz: float = 250.0,
               timeout: float = 0.05, pace: bool = True) -> TravelSweep:
    """:func:`find_travel` on a serial port (hardware, or the driver mock's pty).

    Parameters
    ----------
    drv : hapsim.drivers.firefader.FireFader
    port : str
    travel, force, rate_hz, timeout, pace
        As :func:`find_travel` ([m], [N], [Hz], [s]).

    Returns
    -------
    TravelSweep

    Raises
    ------
    IdentificationError, DeviceError
        As :func:`find_travel`; DeviceError also when the port cannot be opened.
    """
    link = SerialLink(port, drv.baud, drv.rtscts)
    try:
        return find_travel(drv, link, travel=travel, force=force, rate_hz=rate_hz,
                           timeout=timeout, pace=pace)
    finally:
        link.close()
