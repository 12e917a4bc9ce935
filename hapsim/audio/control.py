"""Live control of a running scene: checked, ramped, journaled changes (OSC front end).

A change (a link's stiffness or damping, a felt target {k, b}, a mass's inertia, the sound
gain, pause/resume) arrives on any thread (the OSC server's). It is checked there, before
anything moves: the changed scene's closed loop must be stable, by the check ``hapsim run``
makes (:func:`hapsim.analysis.prediction.predict`, i.e. :func:`hapsim.analysis.check_scene` of the
whole scene coupled to its device, multi-rate included), at the new values and at three
points of the ramp toward them; a felt target is calibrated first
(:func:`hapsim.analysis.targets.apply_targets`) and refused when no (K, B) renders it. A
refused change is answered with its reason and leaves everything as it was. An accepted
change is posted to a mailbox (a ``collections.deque``: atomic append/popleft) that the
sample loop polls between samples (:meth:`Controller.poll`, a few float operations per
sample while a ramp runs, one emptiness test otherwise); it is ramped linearly over
``ramp_s`` so the hand feels no step and the sound does not click. Every request, verdict,
ramp start and ramp end is journaled with the sample index.

The addresses, their arguments and replies, and how a refusal reads:
:mod:`hapsim.audio.messages`.

**A 2-D or 3-D scene** (:class:`ControllerND`, :func:`predict_nd`): the same checked,
ramped, journaled changes with the n-D scene's analysis.

The OSC addresses, the replies, the journal, the order of the answers and the ramp rule
are :class:`Controller`'s. What differs:

- **The check.** A change is accepted only if the changed scene's loop is stable by the
  MIMO criterion of ``hapsim check`` on an n-D scene: the spectral radius of the whole
  closed loop's one-step map (:func:`hapsim.analysis.scene_check.check_scene_nd`: the
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

import collections
import dataclasses
import math
import threading
import time

import numpy as np

from hapsim.audio.analyst import Analyst
from hapsim.audio.journal import identify_window
from hapsim.audio.messages import (ADDRESSES, USAGE, Change, Refused, gain_arg, name_arg,
                                   no_args, number, numbers)
from hapsim.errors import HapsimError

__all__ = ["Controller", "ControllerND", "predict_nd"]


class Controller:
    """Checks, ramps and journals live changes to a running scene.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The calibrated scene the engine runs.
    engine : hapsim.engine.Engine
        Its engine (changed in place by :meth:`poll`, on the sample loop's thread).
    live : hapsim.audio.live.LiveSound, optional
        Its live sound (gain).
    ramp_s : float
        Ramp time of every change [s] (default 50 ms).
    background : bool
        Run the checks and the identifications in a child process (default): they are
        seconds of Python on a large scene, and in a thread of this process they hold the
        GIL against the haptic loop and the sound callback (a descheduled holder stalled
        both: hundreds of starved frames, the sound server dropping the client). False:
        in the calling thread (tests, small scenes).
    latency : (float, float), optional
        A board that renders after its read (``hapsim run``'s driver: the Hapkit sketch's
        0.15-0.55 ms): the middle of its bounds and their end [s]. The felt pair is
        predicted, and a target calibrated, with the middle in the delay (as the run
        predicts and calibrates); a change must also be stable with the end in it (the
        limit falls with the delay: where the board may render last). Default none.
    late_reading_s : float, optional
        The delay [s] a reading taken late adds (``hapsim run``'s driver's
        ``late_reading_periods`` periods: :func:`hapsim.pipeline.render_latency.
        late_reading`): a change must also be stable with the latency's end and this in
        the delay, as the run's loop must be. Default 0.

    Attributes
    ----------
    scene : Scene
        The scene as accepted so far (what the engine reaches at the end of the ramps).
    journal : list of dict
        Every request and event: ``t`` [s since start], ``sample``, ``event`` (request,
        accepted, refused, ramp_end), ``address``, ``args``, ``reason`` / ``felt``.
    force_scale : float
        Factor on the port force (ramped to 0 by pause, back to 1 by resume).
    paused : bool
    """

    def __init__(self, scene, engine, live=None, ramp_s: float = 0.05,
                 background: bool = True, latency: tuple = (0.0, 0.0),
                 late_reading_s: float = 0.0) -> None:
        self.scene = scene
        self.latency = (float(latency[0]), float(latency[1]))
        self.late_reading_s = float(late_reading_s)
        self.engine = engine
        self.live = live
        self.ramp_s = float(ramp_s)
        self.journal: list[dict] = []
        self.force_scale = 1.0
        self.paused = False
        self.sample = 0
        self.refused = 0
        self.accepted = 0
        self.measured = (math.nan, math.nan)
        #: The last measurement's full result (:func:`hapsim.audio.journal.identify_window`), or None.
        self.measurement: dict | None = None
        #: Why :attr:`measured` is NaN (None once a window has been measured): no free
        #: response handed in yet, the last window's refusal, or a change since.
        self.unmeasured: str | None = "no free response has been measured yet"
        self._gen = 0                          # accepted scene changes so far
        self._pending = None                   # the identification under way (a Future)
        self._mail: collections.deque = collections.deque()
        self._gain_before_pause = 1.0
        self._ramps: list[Change] = []
        self._lock = threading.Lock()          # serialises checks (one scene at a time)
        self._t0 = time.monotonic()
        #: Where journal records are also appended (``hapsim run``: the loop's event list,
        #: which the telemetry journal ``.hst`` writes), and the loop's sample counter.
        self.events: list | None = None
        self.sample_of = None
        #: Why the loop must stop (set by :meth:`rebase_delay` when the new loop is
        #: unstable), else None.
        self.unstable: str | None = None
        self._rebasing: threading.Thread | None = None
        self.analyst = Analyst(background)
        #: What a refusal calls the loop checked.
        self.what = "closed loop"
        self.felt = self._predict(scene)

    def rebase_delay(self, delay: int, why: str) -> None:
        """The loop's delay changed outside hapsim (the sound server's block, hence the
        live sound's lead): the scene takes the new delay now, the prediction follows in
        the background (the sample loop does not wait for it).

        A measurement under way, or of a window that started before the change, is
        dropped (:meth:`measure`). When the new loop is unstable, :attr:`unstable`
        holds the reason (the sample loop stops on it).

        Parameters
        ----------
        delay : int or float
            The loop's delay now [device periods] (device delay + lead; real for a
            sub-sample device delay).
        why : str
            What changed it (journaled, and in :attr:`unstable`).
        """
        self._gen += 1
        old = self.scene
        new = dataclasses.replace(old, device=dataclasses.replace(
            old.device, delay=int(delay) if float(delay).is_integer() else float(delay)))
        self.scene = new
        self.measured = (math.nan, math.nan)
        self.measurement = None
        self.unmeasured = f"none since {why}"

        def work():
            with self._lock:
                pred = self._predict(self.scene)
                self.felt = pred
            k, b = pred.get("k"), pred.get("b")
            self.log("delay", "", [delay], reason=why, felt=[k, b],
                      stable=bool(pred["stable"]),
                      spectral_radius=pred.get("spectral_radius"))
            if not pred["stable"]:
                self.unstable = (f"{why}: the closed loop (delay {int(delay)} samples) is "
                                 f"unstable (spectral radius {pred['spectral_radius']:.6g})")

        self._rebasing = threading.Thread(target=work, name="hapsim-rebase", daemon=True)
        self._rebasing.start()

    def _predict(self, scene, at: int = 0) -> dict:
        """The prediction of ``scene``'s loop, with :attr:`latency`'s middle (``at`` 0)
        or end (1) in its delay, or its end and a reading taken late (2)."""
        from hapsim.analysis.prediction import predict, timed_scene
        lat = (*self.latency, self.latency[1] + self.late_reading_s)[at]
        return self.analyst.call(predict, timed_scene(scene, lat) if lat else scene)

    def close(self) -> None:
        """Stop the analysis process (pending work is dropped)."""
        self.analyst.close()

    # ------------------------------------------------------------ any thread
    def log(self, event: str, address: str, args, at: int | None = None, **extra) -> dict:
        """Journal one event (:attr:`journal`; also :attr:`events` when set).

        Parameters
        ----------
        event : str
            ``"request"``, ``"refused"``, ``"accepted"``, ``"ramp_start"``, ``"ramp_end"``,
            ``"telemetry"``, ``"delay"``...
        address : str
            The OSC address (or the change's kind) it concerns.
        args : sequence
            Its arguments.
        at : int, optional
            The sample it happened at (default: the loop's sample now).
        **extra
            More fields of the record (``reason``, ``felt``, ``ramp_s``...).

        Returns
        -------
        dict
            The record: ``t`` [s] since the controller started, ``sample``, ``event``,
            ``address``, ``args`` and the extra fields.
        """
        sample = at if at is not None else (
            self.sample_of() if self.sample_of is not None else self.sample)
        rec = {"t": time.monotonic() - self._t0, "sample": sample, "event": event,
               "address": address, "args": list(args), **extra}
        self.journal.append(rec)
        if self.events is not None:
            self.events.append({**rec, "event": f"osc {event}"})
        return rec

    def _steps(self) -> int:
        return max(1, int(round(self.ramp_s * self.scene.rate_hz)))

    def _check(self, new_scene, old_scene) -> dict:
        """Stability of the new scene and of three points of the ramp toward it
        (:func:`hapsim.analysis.prediction.predict`); the prediction of the new scene."""
        pred = self._predict(new_scene)
        if not pred["stable"]:
            raise Refused(f"the {self.what} would be unstable (spectral radius "
                           f"{pred['spectral_radius']:.6g} > 1)")
        if self.latency[1]:
            p = self._predict(new_scene, 1)
            if not p["stable"]:
                raise Refused(f"the {self.what} would be unstable where the board renders "
                              f"{self.latency[1] * 1e3:.3g} ms after its read (spectral "
                              f"radius {p['spectral_radius']:.6g} > 1)")
        if self.late_reading_s:
            p = self._predict(new_scene, 2)
            if not p["stable"]:
                raise Refused(f"the {self.what} would be unstable with the board's reply "
                              f"taken {self.late_reading_s * 1e3:.3g} ms late, as a host "
                              f"that wakes a little late takes it (spectral radius "
                              f"{p['spectral_radius']:.6g} > 1)")
        ends = (0,) + ((1,) if self.latency[1] else ()) + ((2,) if self.late_reading_s else ())
        for a in (0.25, 0.5, 0.75):
            mid = self.blend(old_scene, new_scene, a)
            for at in ends:
                p = self._predict(mid, at)
                if not p["stable"]:
                    raise Refused(f"the ramp passes through an unstable loop at {a:.0%} "
                                   f"(spectral radius {p['spectral_radius']:.6g})")
        return pred

    def request(self, address: str, *args) -> tuple[bool, str | tuple]:
        """Check a change and, when accepted, post it to the sample loop.

        Parameters
        ----------
        address : str
            One of :data:`ADDRESSES` that changes something.
        *args
            Its OSC arguments.

        Returns
        -------
        (bool, reason or (ramp_s, k, b))
            ``(False, reason)`` when refused (nothing changes), ``(True, (ramp time [s],
            felt k [N/m], felt b [N s/m]))`` when accepted.
        """
        self.log("request", address, args)
        try:
            with self._lock:
                change, pred = self._plan(address, args)
                if pred is not None:
                    self.felt = pred
                    self.measured = (math.nan, math.nan)
                    self.measurement = None
                    self.unmeasured = (f"no free response measured since the change "
                                       f"{address} {' '.join(map(str, args))}")
                    self._gen += 1
            self._mail.append(change)
        except (Refused, HapsimError, KeyError, ValueError, TypeError, ArithmeticError) as exc:
            reason = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
            self.refused += 1
            self.log("refused", address, args, reason=reason)
            return False, reason
        self.accepted += 1
        k, b = self.felt.get("k"), self.felt.get("b")
        self.log("accepted", address, args, felt=[k, b], ramp_s=change.steps / self.scene.rate_hz,
                  predicted={q: self.felt.get(q) for q in ("k", "b", "f0_hz", "damping_ratio")})
        return True, (change.steps / self.scene.rate_hz, number(k), number(b))

    def blend(self, a, b, w):
        """Scene ``a`` moved the fraction ``w`` [-] toward ``b`` (links' K, B and masses
        linearly): the points of a ramp checked before a change is accepted.

        Parameters
        ----------
        a, b : Scene or SceneND
            The scenes before and after the change (the same masses and links).
        w : float
            Fraction of the way from ``a`` to ``b`` [-], in [0, 1].

        Returns
        -------
        Scene or SceneND
            Each link's stiffness [N/m] and damping [N s/m], each mass [kg] (and an n-D
            scene's planes' K, B) at ``a + w (b - a)``: a linear ramp, as the sample loop
            applies it.
        """
        return _blend(a, b, w)

    @property
    def mailbox(self) -> collections.deque:
        """The accepted changes (:class:`Change`) not yet taken by the sample loop."""
        return self._mail

    def ramp_event(self, event: str, change: Change, sample: int) -> None:
        """Journal a ramp's start or end seen by a loop that ramps the changes itself
        (:class:`hapsim.audio.live.LiveND`) at ``sample``.

        Parameters
        ----------
        event : {"ramp_start", "ramp_end"}
            What the loop saw.
        change : Change
            The accepted change being ramped (its kind, name and end values journaled).
        sample : int
            The device sample it happened at [-].
        """
        self.log(event, change.kind, [change.name, *change.end], at=int(sample))

    def felt_reply(self) -> tuple:
        """The values of ``/hapsim/felt``: k, b, f0, zeta predicted, k, b measured.

        Returns
        -------
        tuple of 6 float
            k [N/m], b [N s/m], f0 [Hz], zeta [-] predicted, k, b measured (NaN: not known).
        """
        f = self.felt
        return (number(f.get("k")), number(f.get("b")), number(f.get("f0_hz")),
                number(f.get("damping_ratio")), float(self.measured[0]),
                float(self.measured[1]))

    def _plan_common(self, address: str, args):
        """The changes every scene takes (pause, resume, gain): a :class:`Change`, or
        None for another address."""
        steps = self._steps()
        if address in ("/hapsim/pause", "/hapsim/resume"):
            no_args(args, address)
            kind = address.rsplit("/", 1)[1]
            return Change(kind, "", (self.force_scale,), (0.0 if kind == "pause" else 1.0,),
                          steps)
        if address == "/hapsim/gain":
            g = gain_arg(args, address)
            if self.live is None:
                raise Refused("no live sound in this run (--sound)")
            return Change("gain", "", (self.live.gain,), (g,), steps)
        return None

    def _plan(self, address: str, args):
        steps = self._steps()
        sc = self.scene
        common = self._plan_common(address, args)
        if common is not None:
            return common, None
        if address == "/hapsim/mass":
            name, m = name_arg(args, address), numbers(args[1:], 1, "m", address)[0]
            if not m > 0:
                raise Refused(f"mass must be > 0, got {m:g}")
            moving = [mm.name for mm in sc.masses if mm.kind == "mass"]
            try:
                i = sc.index(name)
            except KeyError:
                raise Refused(f"no mass {name!r}; moving masses: "
                               f"{', '.join(moving) or 'none'}") from None
            old = sc.masses[i]
            if old.kind != "mass":
                why = ("a ground has no mass to change" if old.kind == "ground" else
                       "the port's mass is the device's (device.mass), not the scene's")
                raise Refused(f"{name!r} is a {old.kind}, not a moving mass: {why}; moving "
                               f"masses: {', '.join(moving) or 'none'}")
            new = dataclasses.replace(sc, masses=tuple(
                dataclasses.replace(mm, mass=float(m)) if j == i else mm
                for j, mm in enumerate(sc.masses)))
            pred = self._check(new, sc)
            self.scene = new
            return Change("mass", name, (old.mass,), (float(m),), steps), pred
        if address.startswith("/hapsim/link/"):
            what = address.rsplit("/", 1)[1]
            if address not in USAGE:
                raise Refused(f"unknown address {address}; valid: {', '.join(ADDRESSES)}")
            name = name_arg(args, address)
            try:
                lk = sc.link(name)
            except KeyError:
                raise Refused(f"no link {name!r}; links: "
                               f"{', '.join(x.name for x in sc.links) or 'none'}") from None
            if what == "target":
                k, b = numbers(args[1:], 2, "k b", address)
                from hapsim.analysis.targets import apply_targets
                tl = dataclasses.replace(lk, target=(k, b), stiffness=math.nan,
                                         damping=math.nan, calibrated=False)
                new = dataclasses.replace(sc, links=tuple(tl if x.name == name else x
                                                          for x in sc.links))
                if self.latency[0]:
                    # calibrated for the loop the board runs, as the run's targets
                    from hapsim.analysis.prediction import timed_scene
                    timed, _ = apply_targets(timed_scene(new, self.latency[0]))
                    new = dataclasses.replace(timed, device=new.device)
                else:
                    new, _ = apply_targets(new)
            else:
                if what == "stiffness":
                    K, B = numbers(args[1:], 1, "K", address)[0], lk.damping
                elif what == "damping":
                    K, B = lk.stiffness, numbers(args[1:], 1, "B", address)[0]
                elif what == "kb":
                    K, B = numbers(args[1:], 2, "K B", address)
                else:
                    raise Refused(f"unknown address {address}; valid: {', '.join(ADDRESSES)}")
                if what != "stiffness" and B < 0:   # (the file's rule, and n-D's: before, taken)
                    raise Refused(f"link {name!r}: damping must be >= 0 [N s/m], got {B:g} "
                                  "(a felt damping below the device's: /hapsim/link/target)")
                new = sc.with_link(name, stiffness=K, damping=B)
            nl = new.link(name)
            pred = self._check(new, sc)
            self.scene = new
            return Change("link", name, (lk.stiffness, lk.damping),
                          (nl.stiffness, nl.damping), steps), pred
        raise Refused(f"unknown address {address}; valid: {', '.join(ADDRESSES)}")

    def measure(self, x, wait: float = 0.0) -> None:
        """Measure the felt (k, b) of a free response window in the background.

        :func:`hapsim.audio.journal.identify_window` on the scene as accepted now (in the analysis process);
        :attr:`measured` and :attr:`measurement` are set when it ends, unless a change was
        accepted meanwhile (the window then shows a loop that is no longer the one
        predicted). A window handed in while the previous one is still being measured is
        dropped (:meth:`finish` waits for that one).

        Parameters
        ----------
        x : array_like, shape (n,)
            Device positions [m] from the start of a free response (copied).
        wait : float
            Wait up to this long [s] for this one (end of a run; 0: return at once).
        """
        if self._pending is not None and not self._pending.ready():
            return
        gen, scene, x = self._gen, self.scene, np.array(x, dtype=float)

        def done(res):
            if self._gen != gen:       # a change came meanwhile: not the loop of now
                return
            if "k" in res:
                self.measurement = res
                self.measured = (float(res["k"]), float(res["b"]))
                self.unmeasured = None
            elif math.isnan(self.measured[0]):
                self.unmeasured = (f"the last free response ({x.size} samples) could not "
                                   f"be measured: {res.get('error', 'no result')}")

        self._pending = self.analyst.submit(identify_window, (x, scene), done)
        if wait > 0:
            self.finish(wait)

    def finish(self, timeout_s: float = 10.0) -> bool:
        """Wait up to ``timeout_s`` [s] for the identification under way; whether none is
        left running.

        Parameters
        ----------
        timeout_s : float
            Longest wait [s], for the rebasing and for the identification each.

        Returns
        -------
        bool
        """
        if self._rebasing is not None:
            self._rebasing.join(timeout_s)
        if self._pending is None:
            return True
        self._pending.wait(timeout_s)
        return self._pending.ready()

    # ------------------------------------------------------------ sample loop
    def poll(self, engine=None) -> None:
        """Between two samples: take new changes from the mailbox, advance the ramps.

        Call once per device sample from the loop's thread; it only touches the engine's
        arrays (:meth:`hapsim.engine.Engine.set_link`, :meth:`~hapsim.engine.Engine.set_mass`),
        the live gain and :attr:`force_scale`.

        Parameters
        ----------
        engine : Engine, optional
            The engine the loop steps now: when the loop rebuilt it (a recovery restarts
            the scene from the file's values), the accepted values are set on it at once.
        """
        if engine is not None and engine is not self.engine:
            self.engine = engine
            for lk in self.scene.links:
                engine.set_link(lk.name, lk.stiffness, lk.damping)
            for m in self.scene.masses:
                if m.kind == "mass":
                    engine.set_mass(m.name, m.mass)
            # the ramps under way end here, at their values (on the new engine, the force
            # scale, the live gain's own ramp), and the journal says so: before, they
            # were dropped unjournaled and a force scale stayed where its ramp was (a run
            # recovered mid-ramp under a loaded CI journaled "ramp_start" alone)
            for r in self._ramps:
                r.done = r.steps
                self._apply(r)
                self.log("ramp_end", r.kind, [r.name, *r.end])
            self._ramps = []
        self.sample += 1
        if self._mail:
            while self._mail:
                ch = self._mail.popleft()
                # a new change of the same thing restarts from where its ramp is now
                self._ramps = [r for r in self._ramps if (r.kind, r.name) != (ch.kind, ch.name)
                               or not _replace_start(ch, r)]
                self._ramps.append(ch)
                self.log("ramp_start", ch.kind, [ch.name, *ch.end])
        if not self._ramps:
            return
        keep = []
        for r in self._ramps:
            r.done += 1
            if self._apply(r) < 1.0:
                keep.append(r)
            else:
                self.log("ramp_end", r.kind, [r.name, *r.end])
        self._ramps = keep

    def _apply(self, r: Change) -> float:
        """Set ramp ``r`` at its step ``r.done`` (the engine's link or mass, the live
        gain, the force scale); the fraction of it done, in [0, 1]."""
        a = min(1.0, r.done / r.steps)
        v = tuple(s + a * (e - s) for s, e in zip(r.start, r.end))
        if r.kind == "link":
            self.engine.set_link(r.name, v[0], v[1])
        elif r.kind == "mass":
            self.engine.set_mass(r.name, v[0])
        elif r.kind == "gain":
            if r.done == 1:
                self.live.set_gain(r.end[0], r.steps / self.scene.rate_hz)
        else:
            self.force_scale = v[0]
            self.paused = r.kind == "pause"
            if r.done == 1 and self.live is not None:   # the sound follows
                if self.paused:
                    self._gain_before_pause = self.live.gain_target
                self.live.set_gain(0.0 if self.paused else self._gain_before_pause,
                                   r.steps / self.scene.rate_hz)
        return a

    @property
    def ramping(self) -> bool:
        """Whether a change is still being ramped (or waits in the mailbox)."""
        return bool(self._ramps or self._mail)


def _replace_start(new: Change, old: Change) -> bool:
    """Start ``new`` where the ramp ``old`` of the same thing is now; True (drop ``old``)."""
    a = min(1.0, old.done / old.steps)
    new.start = tuple(s + a * (e - s) for s, e in zip(old.start, old.end))
    return True


def _blend(a, b, w):
    """Scene ``a`` moved the fraction ``w`` toward ``b`` (links' K, B and masses linearly;
    an n-D scene's planes' K, B too)."""
    links = tuple(dataclasses.replace(la, stiffness=la.stiffness + w * (lb.stiffness - la.stiffness),
                                      damping=la.damping + w * (lb.damping - la.damping))
                  if (la.stiffness, la.damping) != (lb.stiffness, lb.damping) else la
                  for la, lb in zip(a.links, b.links))
    masses = tuple(dataclasses.replace(ma, mass=ma.mass + w * (mb.mass - ma.mass))
                   if ma.mass != mb.mass else ma for ma, mb in zip(a.masses, b.masses))
    extra = {}
    if hasattr(a, "planes"):
        extra["planes"] = tuple(
            dataclasses.replace(pa, stiffness=pa.stiffness + w * (pb.stiffness - pa.stiffness),
                                damping=pa.damping + w * (pb.damping - pa.damping))
            if (pa.stiffness, pa.damping) != (pb.stiffness, pb.damping) else pa
            for pa, pb in zip(a.planes, b.planes))
    return dataclasses.replace(a, links=links, masses=masses, **extra)


# ---------------------------------------------------------------- a 2-D or 3-D scene
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
        from hapsim.analysis.scene_check import check_scene_nd
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
    engine : hapsim.engine.Engine
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
        As :class:`Controller`'s (``felt`` is :func:`predict_nd`'s).
    """

    def __init__(self, scene, engine, live=None, ramp_s: float = 0.05,
                 background: bool = True) -> None:
        super().__init__(scene, engine, live, ramp_s=ramp_s, background=background)
        if self.felt.get("loop") == "free":
            self.what = "scene (it has no port: checked on its own)"
        self.unmeasured = ("a 2-D or 3-D play does not identify the felt matrices "
                           "(hapsim run --lockstep measures them)")

    def _predict(self, scene, at: int = 0) -> dict:
        return self.analyst.call(predict_nd, scene)

    def felt_reply(self) -> tuple:
        """``/hapsim/felt``'s values: the 1-D ones (k, b along the stiffest felt direction,
        f0, zeta, measured k, b: NaN), then n, the felt stiffness matrix [N/m] and the
        felt damping matrix [N s/m] row by row (NaN without a port).

        Returns
        -------
        tuple of float
            ``6 + 1 + 2 n^2``: :meth:`Controller.felt_reply`'s, ``n``, the matrices row-major.
        """
        f = self.felt
        n = int(f.get("dof", self.scene.dimension))

        def flat(m):
            return [math.nan] * (n * n) if m is None else [float(v) for v in np.ravel(m)]
        return (*super().felt_reply(), n, *flat(f.get("felt_stiffness")),
                *flat(f.get("felt_damping")))

    def measure(self, x, wait: float = 0.0) -> None:
        """Not done in n-D (:attr:`unmeasured` says so); present for the 1-D interface.

        Parameters
        ----------
        x, wait
            Ignored (:meth:`Controller.measure`'s).
        """

    def poll(self, engine=None) -> None:
        """Not used in n-D: :class:`hapsim.audio.live.LiveND` takes the changes.

        Parameters
        ----------
        engine : optional
            Ignored: it raises ``NotImplementedError`` whatever is given.
        """
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
