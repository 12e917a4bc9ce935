"""Live control of a 2-D or 3-D scene while it plays: the 1-D controller's checked, ramped,
journaled changes (:mod:`hapsim.audio.control`), with the n-D scene's analysis.

The OSC addresses, the replies, the journal, the order of the answers and the ramp rule
are :class:`hapsim.audio.control.Controller`'s. What differs:

- **The check.** A change is accepted only if the changed scene's loop is stable by the
  MIMO criterion of ``hapsim check`` on an n-D scene: the spectral radius of the whole
  closed loop's one-step map (:func:`hapsim.analysis.scene_nd_check.check_scene_nd`: the
  device's exact ZOH, its delay, every virtual mass, every link linearised at rest; not
  axis by axis, Li, Tavakoli & Huang 2014), at the new values and at three points of the
  ramp toward them. A scene without a port (a struck membrane) is checked on its own
  (:func:`hapsim.analysis.modes.scene_modes_nd`).
- **What a change names.** ``/hapsim/link/stiffness|damping|kb NAME ...`` takes a
  spring-damper, a contact (between spheres) or a plane (its K, B on every mass it acts
  on); ``/hapsim/mass NAME m`` a moving mass. ``/hapsim/link/target`` (a felt (k, b)
  calibrated on a 1-D loop) is refused with the reason: an n-D port feels matrices.
- **Where the ramp runs.** The accepted changes are taken between chunks by the producer
  (:class:`hapsim.audio.live.LiveND`) and ramped sample by sample in its compiled call;
  it journals their start and end (:meth:`Controller.ramp_event`).
- **The felt values.** ``k``, ``b`` in ``/hapsim/ok`` and ``/hapsim/felt`` are the felt
  stiffness along its stiffest principal direction (the largest eigenvalue of the felt
  stiffness matrix [N/m]) and the felt damping along that direction [N s/m];
  ``/hapsim/felt`` appends ``n``, the felt stiffness matrix and the felt damping matrix
  (row by row). A scene without a port has no felt values (NaN); its ``f0``, ``zeta`` are
  its lowest mode's.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hapsim.audio.control import Change, Controller, Refused, name_arg, numbers

__all__ = ["ControllerND", "predict_nd"]


def predict_nd(scene) -> dict:
    """The stability verdict and felt values of an n-D scene as played (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND

    Returns
    -------
    dict
        ``stable``, ``spectral_radius`` [-], ``loop`` ("closed" through the device, or
        "free" without a port), ``k`` [N/m], ``b`` [N s/m] (along the stiffest felt
        direction; NaN without felt matrices), ``f0_hz`` [Hz], ``damping_ratio`` [-]
        (the least damped rendered pole, or the lowest mode), ``felt_stiffness``,
        ``felt_damping`` (n x n lists, or None), ``dof``.

    Raises
    ------
    hapsim.errors.ConfigError
        The scene cannot be analysed (too many states, a degenerate Euclidean link).
    """
    n = scene.dimension
    if scene.port is not None and scene.device is not None:
        from hapsim.analysis.scene_nd_check import check_scene_nd
        chk = check_scene_nd(scene)
        r = chk.render
        k = b = f0 = zeta = math.nan
        K, B = r.felt_stiffness, r.felt_damping
        if K is not None and B is not None:
            w, V = np.linalg.eigh(0.5 * (K + K.T))
            e = V[:, -1]
            k, b = float(w[-1]), float(e @ B @ e)
        if r.rendered_poles.size:
            z = r.rendered_poles[np.argmax(np.abs(r.rendered_poles))]
            s = np.log(z) * scene.rate_hz
            f0, zeta = float(abs(s.imag) / (2 * math.pi)), float(-s.real / abs(s))
        return {"dof": n, "loop": "closed", "stable": bool(chk.stable),
                "spectral_radius": float(r.spectral_radius), "k": k, "b": b,
                "f0_hz": f0, "damping_ratio": zeta,
                "felt_stiffness": None if K is None else np.asarray(K).tolist(),
                "felt_damping": None if B is None else np.asarray(B).tolist()}
    from hapsim.analysis.modes import scene_modes_nd
    m = scene_modes_nd(scene)
    low = m.modes[0] if m.modes else None
    return {"dof": n, "loop": "free", "stable": bool(m.stable),
            "spectral_radius": float(m.spectral_radius), "k": math.nan, "b": math.nan,
            "f0_hz": low.frequency_hz if low else math.nan,
            "damping_ratio": low.damping_ratio if low else math.nan,
            "felt_stiffness": None, "felt_damping": None}


class ControllerND(Controller):
    """Checks, ramps (through :class:`hapsim.audio.live.LiveND`) and journals live
    changes to a playing 2-D or 3-D scene (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The scene played.
    engine : hapsim.engine_nd.EngineND
        Its engine (changed by the producer's compiled ramps, never from here).
    live : hapsim.audio.live.LiveND, optional
        The producer (set :attr:`live` once made: it takes :attr:`mailbox`).
    ramp_s : float
        Ramp time of every change [s].
    background : bool
        Run the checks in a child process (default; :class:`hapsim.audio.analyst.Analyst`).

    Attributes
    ----------
    scene, journal, accepted, refused, felt
        As :class:`hapsim.audio.control.Controller`'s (``felt`` is :func:`predict_nd`'s).
    """

    def __init__(self, scene, engine, live=None, ramp_s: float = 0.05,
                 background: bool = True) -> None:
        super().__init__(scene, engine, live, ramp_s=ramp_s, background=background)
        if self.felt.get("loop") == "free":
            self.what = "scene (it has no port: checked on its own)"
        self.unmeasured = ("a 2-D or 3-D play does not identify the felt matrices "
                           "(hapsim run --lockstep measures them)")

    def _predict(self, scene) -> dict:
        return self.analyst.call(predict_nd, scene)

    def felt_reply(self) -> tuple:
        """``/hapsim/felt``'s values: the 1-D ones (k, b along the stiffest felt direction,
        f0, zeta, measured k, b: NaN), then n, the felt stiffness matrix [N/m] and the
        felt damping matrix [N s/m] row by row (NaN without a port)."""
        f = self.felt
        n = int(f.get("dof", self.scene.dimension))

        def flat(m):
            return [math.nan] * (n * n) if m is None else [float(v) for v in np.ravel(m)]
        return (*super().felt_reply(), n, *flat(f.get("felt_stiffness")),
                *flat(f.get("felt_damping")))

    def measure(self, x, wait: float = 0.0) -> None:
        """Not done in n-D (:attr:`unmeasured` says so); present for the 1-D interface."""

    def poll(self, engine=None) -> None:
        """Not used in n-D: :class:`hapsim.audio.live.LiveND` takes the changes."""
        raise NotImplementedError("an n-D scene's changes are ramped by LiveND")

    def _plan(self, address: str, args):
        common = self._plan_common(address, args)
        if common is not None:
            return common, None
        steps = self._steps()
        sc = self.scene
        if address == "/hapsim/mass":
            name, m = name_arg(args, address), numbers(args[1:], 1, "m", address)[0]
            if not m > 0:
                raise Refused(f"mass must be > 0, got {m:g}")
            moving = [mm.name for mm in sc.masses if mm.kind == "mass"]
            old = next((mm for mm in sc.masses if mm.name == name), None)
            if old is None or old.kind != "mass":
                what = "no mass" if old is None else f"{old.kind} (not a moving mass)"
                raise Refused(f"{name!r}: {what}; moving masses: {_some(moving)}")
            new = dataclasses.replace(sc, masses=tuple(
                dataclasses.replace(mm, mass=float(m)) if mm.name == name else mm
                for mm in sc.masses))
            pred = self._check(new, sc)
            self.scene = new
            return Change("mass", name, (old.mass,), (float(m),), steps), pred
        if address.startswith("/hapsim/link/"):
            what = address.rsplit("/", 1)[1]
            if what == "target":
                raise Refused("a felt target {k, b} is calibrated on a 1-D loop; an n-D "
                              "port feels matrices: set the link's K and B "
                              "(/hapsim/link/kb LINK K B), /hapsim/felt gives the felt "
                              "matrices")
            if what not in ("stiffness", "damping", "kb"):
                raise Refused(f"unknown address {address}; valid: /hapsim/link/stiffness, "
                              "/hapsim/link/damping, /hapsim/link/kb")
            name = name_arg(args, address)
            old = next((e for e in (*sc.links, *sc.planes) if e.name == name), None)
            if old is None:
                names = [e.name for e in (*sc.links, *sc.planes)]
                raise Refused(f"no link or plane {name!r}; links and planes: {_some(names)}")
            if what == "stiffness":
                K, B = numbers(args[1:], 1, "K", address)[0], old.damping
            elif what == "damping":
                K, B = old.stiffness, numbers(args[1:], 1, "B", address)[0]
            else:
                K, B = numbers(args[1:], 2, "K B", address)
            if K < 0 or B < 0:
                raise Refused(f"stiffness and damping must be >= 0, got K = {K:g} N/m, "
                              f"B = {B:g} N s/m")
            nl = dataclasses.replace(old, stiffness=float(K), damping=float(B))
            new = dataclasses.replace(
                sc, links=tuple(nl if e.name == name else e for e in sc.links),
                planes=tuple(nl if e.name == name else e for e in sc.planes))
            pred = self._check(new, sc)
            self.scene = new
            return Change("link", name, (old.stiffness, old.damping), (float(K), float(B)),
                          steps), pred
        raise Refused(f"unknown address {address}")


def _some(names, most: int = 12) -> str:
    """Names for a refusal: the first ``most`` of them, and how many more."""
    if not names:
        return "none"
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more
