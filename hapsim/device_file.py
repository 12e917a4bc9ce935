"""The ``device:`` section as a file of its own: written by ``hapsim identify``, read by
``hapsim run --device``."""

from __future__ import annotations

import math
import os

from hapsim.errors import ConfigError

__all__ = ["device_yaml", "load_device"]


def _num(v: float) -> str:
    return "inf" if v == math.inf else f"{v:.6g}"


def device_yaml(fit, force_limit: float, *, hand: bool = False, source: str = "",
                driver=None) -> str:
    """YAML text of the identified ``device:`` section, its intervals as comments.

    Parameters
    ----------
    fit : hapsim.analysis.device_fit.DeviceFit
        The identification.
    force_limit : float
        The excitation's force limit [N] ([N m] through a rotary driver; named in a
        comment; the device's own limit is not identified, so the file leaves it to the
        scene).
    hand : bool
        The record was taken with a hand on the handle (mass and friction are the THS's).
    source : str
        What was identified (port or mock), for the header comment.
    driver : hapsim.drivers.base.Driver, optional
        The driver the record was taken through: its name is written as ``protocol`` and
        its parameters as ``protocol_options`` (the units the host assumed: the mass and
        friction found are in them, module notes of :mod:`hapsim.drivers`); a rotary
        one's (:attr:`hapsim.drivers.base.Driver.rotary`) units are the comments'
        (inertia [kg m^2], [N m s/rad], [N m], [rad]).

    Returns
    -------
    str
        A YAML document with one key, ``device``, that any scene's device section can
        be replaced by (:func:`load_device`, ``hapsim run --device``).
    """
    lv = f"{fit.level * 100:g}"
    from hapsim.drivers import axis_units
    u = axis_units(driver)        # (the fit's figures, in the units its protocol carries)

    def iv(e, scale=1.0, unit=""):
        return f"[{e.lo * scale:.4g}, {e.hi * scale:.4g}]{unit}"
    dev = fit.device(force_limit)
    lines = [f"# identified by hapsim identify{' on ' + source if source else ''}; "
             f"{lv} % intervals in the comments",
             f"# {fit.verdict}"]
    if hand:
        lines.append("# measured with a hand on the handle: mass and friction are the "
                     "THS's (hand + handle), valid for this grip only")
    d0, d1 = fit.delay_range
    lines += [
        "device:",
        f"  mass: {_num(dev.mass)}              # [{u['mass']}] {iv(fit.mass)}",
        f"  friction: {_num(dev.friction)}      # b0 [{u['friction']}] {iv(fit.friction)}",
        f"  delay: {dev.delay}                  # [samples] "
        + (f"{d0}..{d1} fit as well" if d1 > d0 else "unambiguous")
        + (f"; d + f = {fit.delay_estimate.value:.3f} {iv(fit.delay_estimate)}"
           if getattr(fit, "delay_estimate", None) is not None else ""),
        f"  hold: {dev.hold}                    # "
        + ("the other hold fits worse" if fit.hold_certain else "the other hold fits as well"),
        f"  # force_limit: not identified (the excitation stayed within {_num(force_limit)} "
        f"{u['force']}); 'hapsim run --device' keeps the scene's",
        f"  coulomb: {_num(dev.coulomb)}         # [{u['force']}] {iv(fit.coulomb)}; +: "
        f"{fit.coulomb_pos.value:.4g} {iv(fit.coulomb_pos)}, -: {fit.coulomb_neg.value:.4g} "
        f"{iv(fit.coulomb_neg)}",
        f"  position_resolution: {_num(dev.position_resolution)}   # [{u['position']}] "
        f"{iv(fit.position_resolution)}",
        f"  noise: {_num(dev.noise)}            # [{u['position']}] {iv(fit.noise)}",
        f"# residual RMS {fit.rms_residual:.4g} {u['position']} over {fit.n_samples} samples at "
        f"{1.0 / fit.period:g} Hz",
    ]
    if driver is not None:
        opts = ", ".join(f"{k}: {_num(v) if isinstance(v, float) else v}"
                         for k, v in driver.options().items())
        lines[-1:-1] = [
            f"  protocol: {driver.name}",
            f"  protocol_options: {{{opts}}}",
            "  # identification sees the force-to-acceleration gain (force scale / mass) "
            "and the position scale",
            "  # only through these options: mass and friction above are in their units "
            "(docs/drivers.md: a known",
            "  # added mass separates the force scale from the mass)"]
    return "\n".join(lines) + "\n"


def device_keys(path: str) -> set[str]:
    """The keys a device file gives in its ``device`` section (read after
    :func:`load_device` has accepted the file).

    Parameters
    ----------
    path : str
        A device file.

    Returns
    -------
    set of str
        The keys written in the file (``mass``, ``friction``, ...); what is missing takes
        the scene schema's default, which ``hapsim run --device`` replaces by the scene's
        own value for ``force_limit`` and ``protocol``.
    """
    from hapsim._yaml_lines import load_yaml
    with open(os.fspath(path), encoding="utf-8") as fh:
        doc = load_yaml(fh.read(), os.fspath(path))
    return set(doc["device"]) if isinstance(doc, dict) and isinstance(doc.get("device"),
                                                                        dict) else set()


def load_device(path: str):
    """Read a device file (a YAML document whose only key is ``device``).

    Parameters
    ----------
    path : str
        File written by ``hapsim identify --out`` (or by hand).

    Returns
    -------
    hapsim.scene.Device

    Raises
    ------
    ConfigError
        Unreadable file, invalid YAML, other top-level keys than ``device``, or an invalid
        device section (file, line and key named, as for scenes).
    """
    from hapsim.scene.lines import LineContext, read_text
    from hapsim.scene.reader import read_device
    from hapsim.scene.rules import Invalid, check_device
    path = os.fspath(path)
    # (the scene's reader: a regular file of bounded size, its bytes decoded as the scene's
    # are; before, a FIFO hung, /dev/zero filled the memory, a byte that is no UTF-8 was
    # a UnicodeDecodeError traceback)
    text = read_text(path, "device file")
    from hapsim._yaml_lines import load_yaml
    doc = load_yaml(text, path)
    ctx = LineContext(path)
    if doc is None:
        raise ctx.error("the device file is empty; it needs a 'device:' section", 1, "device")
    doc = ctx.mapping(doc, "", 1)
    ctx.keys(doc, ("device",), "", required=("device",))
    dev = read_device(ctx, doc)
    try:
        check_device(dev)
    except Invalid as exc:
        raise ConfigError(exc.message, file=path, key=exc.key) from None
    return dev
