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

import collections
import dataclasses
import math
import threading
import time

import numpy as np

from hapsim.errors import ConfigError, HapsimError

__all__ = ["Controller", "Change", "Analyst", "ADDRESSES", "serve_osc", "identify_window",
           "Refused", "name_arg", "numbers", "send_telemetry", "revise_measurement",
           "write_journal"]

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
                 background: bool = True) -> None:
        self.scene = scene
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
        #: The last measurement's full result (:func:`identify_window`), or None.
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
            self._log("delay", "", [delay], reason=why, felt=[k, b],
                      stable=bool(pred["stable"]),
                      spectral_radius=pred.get("spectral_radius"))
            if not pred["stable"]:
                self.unstable = (f"{why}: the closed loop (delay {int(delay)} samples) is "
                                 f"unstable (spectral radius {pred['spectral_radius']:.6g})")

        self._rebasing = threading.Thread(target=work, name="hapsim-rebase", daemon=True)
        self._rebasing.start()

    def _predict(self, scene) -> dict:
        from hapsim.analysis.prediction import predict
        return self.analyst.call(predict, scene)

    def close(self) -> None:
        """Stop the analysis process (pending work is dropped)."""
        self.analyst.close()

    # ------------------------------------------------------------ any thread
    def _log(self, event: str, address: str, args, at: int | None = None, **extra) -> dict:
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
        for a in (0.25, 0.5, 0.75):
            mid = self.blend(old_scene, new_scene, a)
            p = self._predict(mid)
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
        self._log("request", address, args)
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
        except (Refused, HapsimError, KeyError, ValueError, TypeError) as exc:
            reason = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
            self.refused += 1
            self._log("refused", address, args, reason=reason)
            return False, reason
        self.accepted += 1
        k, b = self.felt.get("k"), self.felt.get("b")
        self._log("accepted", address, args, felt=[k, b], ramp_s=change.steps / self.scene.rate_hz,
                  predicted={q: self.felt.get(q) for q in ("k", "b", "f0_hz", "damping_ratio")})
        return True, (change.steps / self.scene.rate_hz, _num(k), _num(b))

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
        (:class:`hapsim.audio.live_nd.LiveND`) at ``sample``.

        Parameters
        ----------
        event : {"ramp_start", "ramp_end"}
            What the loop saw.
        change : Change
            The accepted change being ramped (its kind, name and end values journaled).
        sample : int
            The device sample it happened at [-].
        """
        self._log(event, change.kind, [change.name, *change.end], at=int(sample))

    def felt_reply(self) -> tuple:
        """The values of ``/hapsim/felt``: k, b, f0, zeta predicted, k, b measured."""
        f = self.felt
        return (_num(f.get("k")), _num(f.get("b")), _num(f.get("f0_hz")),
                _num(f.get("damping_ratio")), float(self.measured[0]),
                float(self.measured[1]))

    def _plan_common(self, address: str, args):
        """The changes every scene takes (pause, resume, gain): a :class:`Change`, or
        None for another address."""
        steps = self._steps()
        if address in ("/hapsim/pause", "/hapsim/resume"):
            kind = address.rsplit("/", 1)[1]
            return Change(kind, "", (self.force_scale,), (0.0 if kind == "pause" else 1.0,),
                          steps)
        if address == "/hapsim/gain":
            (g,) = numbers(args, 1, "gain", address)
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
                new = sc.with_link(name, stiffness=K, damping=B)
            nl = new.link(name)
            pred = self._check(new, sc)
            self.scene = new
            return Change("link", name, (lk.stiffness, lk.damping),
                          (nl.stiffness, nl.damping), steps), pred
        raise Refused(f"unknown address {address}; valid: {', '.join(ADDRESSES)}")

    def measure(self, x, wait: float = 0.0) -> None:
        """Measure the felt (k, b) of a free response window in the background.

        :func:`identify_window` on the scene as accepted now (in the analysis process);
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
        left running."""
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
            self._ramps = []
        self.sample += 1
        if self._mail:
            while self._mail:
                ch = self._mail.popleft()
                # a new change of the same thing restarts from where its ramp is now
                self._ramps = [r for r in self._ramps if (r.kind, r.name) != (ch.kind, ch.name)
                               or not _replace_start(ch, r)]
                self._ramps.append(ch)
                self._log("ramp_start", ch.kind, [ch.name, *ch.end])
        if not self._ramps:
            return
        keep = []
        for r in self._ramps:
            r.done += 1
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
            if a < 1.0:
                keep.append(r)
            else:
                self._log("ramp_end", r.kind, [r.name, *r.end])
        self._ramps = keep

    @property
    def ramping(self) -> bool:
        """Whether a change is still being ramped (or waits in the mailbox)."""
        return bool(self._ramps or self._mail)


class Analyst:
    """Where a :class:`Controller` runs its heavy analysis: a child process, or here.

    The child (a ``spawn`` :class:`multiprocessing.pool.Pool` of one worker, ``SCHED_OTHER``
    at nice 10, its stdout sent to stderr so nothing lands in a ``--json`` report) is
    started at once and kept; a call waits for its answer without holding the GIL, so the
    haptic loop and the sound callback of this process keep running. :meth:`close`
    terminates it, work under way included.

    Parameters
    ----------
    background : bool
        Use a child process (False: call in the calling thread).
    timeout_s : float
        Longest wait of :meth:`call` [s]; then :class:`hapsim.errors.HapsimError`.
    """

    def __init__(self, background: bool = True, timeout_s: float = 120.0) -> None:
        self._pool = None
        self.timeout_s = float(timeout_s)
        if background:
            import multiprocessing
            self._pool = multiprocessing.get_context("spawn").Pool(1, initializer=_background)

    @property
    def background(self) -> bool:
        """Whether calls go to the child process (False: in the calling thread, or
        after :meth:`close`)."""
        return self._pool is not None

    def submit(self, fn, args: tuple, done=None):
        """Start ``fn(*args)``; ``done(result)`` when it ends (``done({"error": ...})`` if
        it raised). Returns a handle with ``ready()`` and ``wait(timeout)``."""
        def failed(exc):
            if done is not None:
                done({"error": f"{type(exc).__name__}: {exc}"})

        if self._pool is not None:
            return self._pool.apply_async(fn, args, callback=done, error_callback=failed)
        h = _Done()
        try:
            res = fn(*args)
        except Exception as exc:
            failed(exc)
            return h
        if done is not None:
            done(res)
        return h

    def call(self, fn, *args):
        """``fn(*args)``, in the child when there is one (its exception re-raised).

        Raises
        ------
        HapsimError
            No answer within :attr:`timeout_s`.
        """
        if self._pool is None:
            return fn(*args)
        import multiprocessing
        try:
            return self._pool.apply_async(fn, args).get(self.timeout_s)
        except multiprocessing.TimeoutError:
            raise HapsimError(f"the analysis took longer than {self.timeout_s:g} s") from None

    def close(self) -> None:
        """Terminate the child (work under way is dropped)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None


class _Done:
    """The handle of work done in-process (already finished)."""

    def ready(self) -> bool:
        return True

    def wait(self, timeout=None) -> None:
        return None


def _background() -> None:
    """Analysis process initialiser: normal scheduling, low priority (it must never
    compete with the haptic loop or the sound callback that started it)."""
    import os
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass
    try:
        os.nice(10)
    except (AttributeError, OSError):
        pass
    try:
        os.dup2(2, 1)         # LAPACK and friends print on fd 1: keep it off the report
    except OSError:
        pass
    from hapsim.blas import limit_blas_threads
    limit_blas_threads(1)
    import hapsim.analysis.identify  # noqa: F401  (loaded before the first window counts)


class Refused(Exception):
    """A change refused, with the reason sent back to its sender (``/hapsim/refused``)."""


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


def _num(v) -> float:
    return float(v) if v is not None else math.nan


def serve_osc(ctl: Controller, port: int, host: str = "127.0.0.1", status=None):
    """Start the OSC server of a :class:`Controller` on a thread.

    Parameters
    ----------
    ctl : Controller
    port : int
        UDP port (0: any free port; the server's ``server_address`` says which).
    host : str
        Address to listen on (localhost by default).
    status : callable, optional
        ``status() -> dict`` with ``xruns`` and ``underruns`` for ``/hapsim/loop``.

    Returns
    -------
    server : pythonosc.osc_server.BlockingOSCUDPServer
        Running (``server.shutdown()`` stops it). One thread serves the datagrams in the
        order they arrive, so a sender's changes are checked, applied, journaled and
        answered in the order it sent them (a thread per datagram, as
        ``ThreadingOSCUDPServer`` does, let a quick ``/hapsim/gain`` overtake a
        ``/hapsim/link/kb`` still being checked, and two changes of one link end in
        either order).
    telemetry : dict
        ``{"client": SimpleUDPClient or None, "every": samples}``: where and how often the
        sample loop sends ``/hapsim/tel`` (set by ``/hapsim/telemetry``).
    """
    from pythonosc import dispatcher as osc_dispatcher
    from pythonosc import osc_server, udp_client
    from pythonosc.osc_message_builder import OscMessageBuilder

    tel = {"client": None, "every": 20}
    sock_holder = {}

    def reply(addr, address, *values):
        b = OscMessageBuilder(address=address)
        for v in values:
            b.add_arg(v)
        sock_holder["server"].socket.sendto(b.build().dgram, addr)

    def on_change(client, address, *args):
        ok, info = ctl.request(address, *args)
        if ok:
            reply(client, "/hapsim/ok", address, *info)
        else:
            reply(client, "/hapsim/refused", address, info)

    def on_felt(client, address, *args):
        reply(client, "/hapsim/felt", *ctl.felt_reply())

    def on_loop(client, address, *args):
        st = status() if status is not None else {}
        reply(client, "/hapsim/loop", int(ctl.sample), _num(ctl.felt.get("spectral_radius")),
              int(bool(ctl.felt.get("stable"))), int(ctl.accepted), int(ctl.refused),
              int(st.get("xruns", 0)), int(st.get("underruns", 0)))

    def on_telemetry(client, address, *args):
        try:
            host_, port_ = str(args[0]), int(args[1])
            rate = float(args[2]) if len(args) > 2 else 50.0
            tel["every"] = max(1, int(round(ctl.scene.rate_hz / rate)))
            tel["client"] = udp_client.SimpleUDPClient(host_, port_)
        except (IndexError, ValueError, TypeError) as exc:
            reply(client, "/hapsim/refused", address, f"expected host port [rate_hz]: {exc}")
            return
        ctl._log("telemetry", address, args)
        reply(client, "/hapsim/ok", address, 0.0, math.nan, math.nan)

    d = osc_dispatcher.Dispatcher()
    for a in ADDRESSES:
        if a == "/hapsim/felt":
            d.map(a, on_felt, needs_reply_address=True)
        elif a == "/hapsim/loop":
            d.map(a, on_loop, needs_reply_address=True)
        elif a == "/hapsim/telemetry":
            d.map(a, on_telemetry, needs_reply_address=True)
        else:
            d.map(a, on_change, needs_reply_address=True)
    def on_unknown(client, address, *args):
        # returns None: python-osc sends a handler's return value back as a message (a
        # tuple here was its BuildError traceback on stderr)
        ctl._log("refused", address, args, reason="unknown address")
        reply(client, "/hapsim/refused", address,
              f"unknown address; valid: {', '.join(ADDRESSES)}")

    d.set_default_handler(on_unknown, needs_reply_address=True)
    server = osc_server.BlockingOSCUDPServer((host, port), d)
    sock_holder["server"] = server
    threading.Thread(target=server.serve_forever, name="hapsim-osc", daemon=True).start()
    return server, tel


def revise_measurement(measured: dict, journal: list, rate_hz: float) -> list:
    """Compare a run's measurement with the prediction of the scene it measured, after
    live changes (``hapsim run --osc``), as ``hapsim play`` re-predicts.

    The measured window is rows ``[first_row, first_row + samples_used)`` of the run; each
    accepted change acts from its ``sample`` over its ramp. A change inside the window
    makes the measurement a mix of two loops: not comparable. Changes that all ended
    before it: the measurement is compared with the prediction after the last of them
    (its felt k, b). Changes that all came after it: the start's prediction stands.

    Parameters
    ----------
    measured : dict
        The run's identification result (``k`` [N/m], ``b`` [N s/m], ``k_interval``,
        ``b_interval``, ``first_row``, ``samples_used``, ``rel_err``, ``verdict``);
        updated in place: ``compared_with`` says which prediction, ``rel_err`` (k and b),
        ``within`` and ``verdict`` follow it, or ``comparable`` False with the reason.
    journal : list of dict
        The controller's journal (:attr:`Controller.journal`).
    rate_hz : float
        Device rate [Hz] (ramp times to samples).

    Returns
    -------
    list of dict
        The accepted changes: ``sample``, ``address``, ``args``, ``ramp_s`` [s], the
        ``felt`` [k, b] predicted after each and that ``predicted`` pair (``k``, ``b``,
        ``f0_hz``, ``damping_ratio``).
    """
    changes = [{"sample": int(e["sample"]), "address": e["address"], "args": e["args"],
                "ramp_s": e.get("ramp_s", 0.0), "felt": e.get("felt"),
                "predicted": e.get("predicted")}
               for e in journal if e.get("event") == "accepted"]
    if not changes or "k" not in measured or measured.get("first_row") is None:
        return changes
    a = int(measured["first_row"])
    b = a + int(measured.get("samples_used", 0))

    def end(c):
        return c["sample"] + int(math.ceil(c["ramp_s"] * rate_hz)) + 1

    inside = [c for c in changes if c["sample"] < b and end(c) > a]
    before = [c for c in changes if end(c) <= a]
    if inside:
        c = inside[0]
        measured["comparable"] = False
        measured["compared_with"] = None
        measured["verdict"] = (f"not comparable: the scene changed while it was measured "
                               f"({c['address']} {' '.join(map(str, c['args']))} at sample "
                               f"{c['sample']}, window {a}..{b})")
        measured.pop("within", None)
        return changes
    if not before:
        measured["compared_with"] = "the start's prediction (every change came after the "\
                                    "measured window)"
        return changes
    c = before[-1]
    kp, bp = (float(v) for v in c["felt"])
    pred = {"k": kp, "b": bp, **{q: v for q, v in (c.get("predicted") or {}).items()
                                 if q not in ("k", "b")}}
    measured["compared_with"] = {**pred, "after": f"{c['address']} "
                                 f"{' '.join(map(str, c['args']))} at sample {c['sample']}"}
    measured["rel_err"] = {q: ((measured[q] - v) / v if v else math.nan)
                           if v is not None and measured.get(q) is not None else math.nan
                           for q, v in ((q, pred.get(q)) for q in
                                        ("k", "b", "f0_hz", "damping_ratio"))}
    if "k_interval" in measured:
        ok = (abs(measured["k"] - kp) <= measured["k_interval"]
              and abs(measured["b"] - bp) <= measured["b_interval"])
        measured["within"] = bool(ok)
        measured["verdict"] = ("measured = predicted after the changes within the stated "
                               "uncertainty" if ok else "measured differs from the prediction "
                               "after the changes by more than the stated uncertainty")
    return changes


def send_telemetry(tel: dict, t: float, x, f, ctl: Controller) -> None:
    """Send one ``/hapsim/tel t x f k b`` message when a telemetry client is set
    (called by the sample loop every ``tel["every"]`` samples; UDP, never blocks long).

    Parameters
    ----------
    tel : dict
        :func:`serve_osc`'s telemetry dict.
    t : float
        Time [s].
    x, f : float or array_like
        Device position [m] and port force [N]: a number (1-D) or n of each (a 2-D or
        3-D scene: ``/hapsim/tel t x1 .. xn f1 .. fn k b``).
    ctl : Controller
        Its felt ``k``, ``b`` are sent.
    """
    c = tel.get("client")
    if c is not None:
        try:
            c.send_message("/hapsim/tel", [float(t), *(float(v) for v in np.ravel(x)),
                                           *(float(v) for v in np.ravel(f)),
                                           _num(ctl.felt.get("k")), _num(ctl.felt.get("b"))])
        except OSError:
            pass


def identify_window(x: np.ndarray, scene) -> dict:
    """Felt (k, b) of a free response window, measured as ``hapsim run`` measures it.

    :func:`hapsim.analysis.measurement.identify` with the run's arguments: the predicted non-zero
    closed-loop poles seen at the port and the predicted felt pole
    (:func:`hapsim.analysis.prediction.predicted_poles`), the equilibrium offset
    (:func:`hapsim.analysis.prediction.has_offset`), the device's sensor step and noise, so the
    answer is :func:`hapsim.analysis.identify.measure_felt` (exact matrix pencil for an
    exact record, variable projection started from the prediction otherwise).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Device positions [m], one per device sample, from the start of a free response.
    scene : hapsim.scene.Scene
        The calibrated scene of the loop that produced them (device delay included).

    Returns
    -------
    dict
        :func:`~hapsim.analysis.measurement.identify`'s result: ``k`` [N/m], ``b`` [N s/m],
        ``k_unc``, ``b_unc`` ... or ``error`` (str) when the window cannot carry a
        measurement.
    """
    from hapsim.analysis.network import device_body
    from hapsim.analysis.measurement import identify
    from hapsim.analysis.prediction import has_offset, predicted_poles

    x = np.asarray(x, dtype=float)
    dev = scene.device
    try:
        poles, felt = predicted_poles(scene)
        order = int(poles.size)
        if not order:
            return {"error": "the loop has no oscillation to measure"}
        response = None
        quantum = float(dev.position_resolution or 0.0)
        if quantum > 0 or dev.noise > 0:
            from hapsim.analysis.error_response import sensor_error_response
            response = sensor_error_response(scene, int(x.size))
        return identify(x, np.arange(x.size), scene.period, order, device_body(dev)[0], 0,
                        offset=has_offset(scene), skip=int(dev.delay) + 2,
                        predicted=poles, felt=felt, quantum=quantum, noise=float(dev.noise),
                        sensor_response=response)
    except (ConfigError, ValueError, np.linalg.LinAlgError) as exc:
        return {"error": str(exc)}


def write_journal(path: str, journal: list) -> None:
    """Write a change journal (:attr:`Controller.journal`) as JSON to ``path`` (through a
    ``.partial`` file renamed at the end: a reader never sees half of it).

    Parameters
    ----------
    path : str
        ``--journal FILE.json``.
    journal : list of dict
    """
    import json
    import os

    from hapsim.outputs import json_safe
    tmp = path + ".partial"
    with open(tmp, "w") as fh:
        json.dump(json_safe(journal), fh, indent=1)
    os.replace(tmp, path)
