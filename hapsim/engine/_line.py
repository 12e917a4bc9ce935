"""The engine's 1-D layout (:class:`Line`, what :class:`hapsim.engine.Engine` returns for a
:class:`~hapsim.scene.Scene`): the scene as a struct of arrays, advanced by the kernel of
:mod:`hapsim.kernels.cordis` (or :mod:`hapsim.kernels.schemes`, or the multi-rate one of
:mod:`hapsim.kernels.audio`) that matches the link kinds the scene uses.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from hapsim.engine._api import Engine, mass_indices
from hapsim.errors import ConfigError
from hapsim.kernels import audio as audio_kernel
from hapsim.kernels import arguments, cordis, schemes, step1d
from hapsim.scene import Scene, audio_substeps

__all__ = ["KernelPack", "Line", "MultiRatePack"]

#: The array type port_step tells from a float by its class alone (the per-sample call of the
#: 1-D host loops: ``isinstance`` costs it ~10 % of its time).
_NDARRAY = np.ndarray
_EMPTY_REC = np.empty(0, dtype=np.int64)
_EMPTY_OUT = np.empty((0, 0), dtype=np.float64)
#: The arrays of a link kind a scene lacks (the kernels that take them loop over none).
_NO_SD = (_EMPTY_REC, _EMPTY_REC, np.empty(0), np.empty(0))
_NO_CONTACT = _NO_SD + (np.empty(0),)
#: The multi-rate kernel's name in hapsim.kernels.arguments.KERNELS.
_PERIODS = audio_kernel.run_periods.__name__


class KernelPack(NamedTuple):
    """An engine's kernel and its arrays by name: what a compiled caller (the host loop's
    port step, :func:`hapsim.host.fastloop_kernels.kernel_pack`) needs to advance the engine
    itself. The arrays are the engine's own (shared, not copied: the kernel updates them in
    place).

    Attributes
    ----------
    kernel : callable
        The module-level kernel of :mod:`hapsim.kernels.cordis` or
        :mod:`hapsim.kernels.schemes`, called as ``kernel(n, *args, rec, out, row0)``.
    args : tuple
        Its state arguments, in its order: those
        :data:`hapsim.kernels.arguments.KERNELS` declares (taken from the engine's arrays
        by name).
    state : tuple of ndarray
        ``(x, xp, f, mobile, t2m, fixed)``: positions [m] now and one period ago, forces
        [N], indices of the mobile masses, their ``T^2 / m`` [s^2/kg], indices of the port
        and grounds (shapes (n,), (n,), (n,), (nm,), (nm,), (n - nm,)).
    sd : tuple of ndarray or None
        ``(i1, i2, k, z)`` of the spring-dampers: mass indices, stiffness [N/m], damping
        per period ``B / T`` [N/m]; None without spring-dampers.
    contact : tuple of ndarray or None
        ``(i1, i2, k, z, thr)`` of the contacts (``thr`` the threshold [m]); None without.
    scheme : dict
        The integrator's own state and coefficients by name (empty for ``centred``; see
        :func:`hapsim.kernels.schemes.build`).
    port : int
        Index of the port in ``x`` (-1 without a port).
    """

    kernel: Callable
    args: tuple
    state: tuple
    sd: tuple | None
    contact: tuple | None
    scheme: dict
    port: int


class MultiRatePack(NamedTuple):
    """An engine's multi-rate kernel arguments (a scene with an ``audio`` section): what a
    caller of :func:`hapsim.kernels.audio.run_periods` or ``run_frames`` (the live sound,
    the contact replay) passes to step the engine's own arrays. Shared with the engine,
    not copied.

    Attributes
    ----------
    head : tuple
        ``(nsub, linear, last, port)``: audio sub-steps per device period, the port
        position interpolated (``audio.port_position == "linear"``) rather than held, the
        port force the last sub-step's (``audio.port_force == "last"``) rather than their
        mean, the port's index (-1 without).
    args : tuple
        ``(x, xp, f, mobile, t2m, fixed)`` (as :attr:`KernelPack.state`), the
        spring-dampers' ``(i1, i2, k, z)`` and the contacts' ``(i1, i2, k, z, thr)``
        (empty arrays when the scene has none), the listening points' ``(index, code,
        gain)`` and ``1 / Ta`` [1/s]: 19 entries (the state arguments of ``run_periods``
        in :data:`hapsim.kernels.arguments.KERNELS`, as ``head`` its head).
    """

    head: tuple
    args: tuple


class Line(Engine):
    """A 1-D scene compiled for simulation with the CORDIS-ANIMA scheme: the
    :class:`~hapsim.engine.Engine` of a :class:`~hapsim.scene.Scene` (build it as
    ``Engine(scene)``; its API there, with ``n = 1``).

    Parameters
    ----------
    scene : Scene
        A scene whose links all have numeric (K, B): calibrate ``target`` links first
        (:func:`hapsim.analysis.targets.apply_targets`). Every :class:`Scene` is validated
        when it is constructed, from a file or in code, so only the type is checked here.
    block : int, optional
        Unused (the n-D kernels' schedule): accepted so that one call builds every
        dimension's engine.
    precision : {"double"}, optional
        The 1-D kernels compute in float64 only.

    Raises
    ------
    TypeError
        When ``scene`` is not a :class:`Scene`.
    ConfigError
        When a link still has an uncalibrated ``target``; a precision other than
        ``double`` (key ``engine.precision``).

    Notes
    -----
    Scheme (docs/design.md, 'The scheme'; Florens-Voda-Urma Fig. 5): masses
    ``x[n+1] = 2 x[n] - x[n-1] + T^2 F[n] / m``; links
    ``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T`` applied ``-F`` on the first mass and
    ``+F`` on the second; contacts only while ``x2 - x1 < threshold``, with the spring term
    ``K (x1 - x2 + threshold)``. A mass starting with
    velocity ``v0`` gets ``x[-1] = x0 - v0 T``. The port and grounds never move by
    themselves; the port moves when :meth:`set_port_position` is called (once per device
    sample), which makes the port's velocity the backward difference of device samples.
    ``scene.integrator`` (``symplectic_euler``, ``exact``) swaps the mass integrator for one
    of :mod:`hapsim.kernels.schemes` (stability limits there); ``centred`` is the above.

    A scene with ``audio`` runs multi-rate (:class:`hapsim.scene.Audio`,
    :mod:`hapsim.kernels.audio`): the masses at the audio period ``Ta = T / N``, every
    device sample (:meth:`port_step`, :meth:`step`, :meth:`run`) being N audio sub-steps;
    the sub-steps' listened frames are in :attr:`frames` after :meth:`port_step`, and
    :meth:`play` renders a whole gesture offline.

    Examples
    --------
    >>> eng = Engine(load_scene("configs/oscillator.yaml"))   # doctest: +SKIP
    >>> t, x = eng.run(1000)                                  # doctest: +SKIP
    """

    #: The dimension ``n``.
    dim = 1
    #: The floating type of the state: float64 only.
    precision, dtype = "double", np.float64

    def __init__(self, scene: Scene, block: int | None = None,
                 precision: str | None = None) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"Engine needs a validated hapsim.scene.Scene or SceneND, got "
                            f"{type(scene).__name__}")
        if precision not in (None, "double"):
            raise ConfigError(f"a 1-D scene runs in double precision only, not {precision!r}",
                              key="engine.precision")
        if scene.unresolved_targets:
            lk = scene.unresolved_targets[0]
            raise ConfigError("link has a felt target (k, b) but no calibrated (K, B); "
                              "calibrate it first (hapsim run does this)",
                              file=scene.path, line=lk.line or None, key=f"links.{lk.name}")
        self.scene = scene
        self.period = scene.period
        self.names = tuple(m.name for m in scene.masses)
        audio = scene.audio
        #: Audio sub-steps per device sample N (1 without ``audio``).
        self.substeps = audio_substeps(audio.rate_hz, scene.rate_hz) if audio else 1
        #: Period the masses are integrated at [s]: the audio period with ``audio``.
        self.sim_period = T = self.period / self.substeps
        n = len(scene.masses)
        # (1, N) as every dimension's state; the kernels get its one row (a view)
        self._X = np.array([[m.x0 for m in scene.masses]], dtype=np.float64)
        self._XP = np.array([[m.x0 - (m.v0 * T if m.kind == "mass" else 0.0)
                              for m in scene.masses]], dtype=np.float64)
        self._x, self._xp = self._X[0], self._XP[0]
        self._f = np.zeros(n, dtype=np.float64)
        mobile = [i for i, m in enumerate(scene.masses) if m.kind == "mass"]
        self._mobile = np.array(mobile, dtype=np.int64)
        self._t2m = np.array([T * T / scene.masses[i].mass for i in mobile], dtype=np.float64)
        self._fixed = np.array([i for i, m in enumerate(scene.masses) if m.kind != "mass"],
                               dtype=np.int64)
        port = scene.port
        self._port = scene.index(port.name) if port is not None else -1

        def arrays(kind: str) -> tuple[np.ndarray, ...]:
            links = [lk for lk in scene.links if lk.kind == kind]
            i1 = np.array([scene.index(lk.m1) for lk in links], dtype=np.int64)
            i2 = np.array([scene.index(lk.m2) for lk in links], dtype=np.int64)
            k = np.array([lk.stiffness for lk in links], dtype=np.float64)
            z = np.array([lk.damping / T for lk in links], dtype=np.float64)
            if kind == "contact":
                thr = np.array([lk.threshold for lk in links], dtype=np.float64)
                return i1, i2, k, z, thr
            return i1, i2, k, z

        kinds = scene.kinds
        links = {kind: arrays(kind) if kind in kinds else None
                 for kind in ("spring_damper", "contact")}
        #: name -> (stiffness array, damping-per-sample array, slot): live changes.
        self._link_slot: dict[str, tuple[np.ndarray, np.ndarray, int]] = {}
        for kind, arr in links.items():
            if arr is not None:
                names = [lk.name for lk in scene.links if lk.kind == kind]
                self._link_slot.update({nm: (arr[2], arr[3], j) for j, nm in enumerate(names)})
        state = (self._x, self._xp, self._f, self._mobile, self._t2m, self._fixed)
        integrator = getattr(scene, "integrator", "centred")
        if integrator == "centred":
            kernel = cordis.KERNELS[kinds]
            extras = {}
        else:  # hapsim.kernels.schemes: symplectic_euler, exact
            kernel, _, extras = schemes.build(integrator, T, *state,
                                              sd=links["spring_damper"],
                                              contact=links["contact"])
        #: The kernels' arguments by name (empty link arrays for the kinds the scene
        #: lacks), taken in each kernel's order from hapsim.kernels.arguments.
        self._named = {**dict(zip(arguments.STATE_NAMES, state)),
                       **dict(zip(arguments.SD_NAMES, links["spring_damper"] or _NO_SD)),
                       **dict(zip(arguments.CONTACT_NAMES, links["contact"] or _NO_CONTACT)),
                       **extras}
        args = arguments.take(kernel.__name__, self._named)
        self._kernel, self._args = kernel, args
        self._pack = KernelPack(kernel, args, state, links["spring_damper"], links["contact"],
                                extras, self._port)
        #: Velocity state [m/s] of the non-default integrators (None for centred).
        self._v = extras.get("v")
        #: Samples advanced since construction.
        self.sample = 0
        self._multi = None
        #: Names of the listened channels (``"<mass>.<quantity>"``), empty without audio.
        self.channels: tuple[str, ...] = ()
        if audio is not None:
            self._init_audio(audio)
        self._init_step()

    @property
    def kernel_pack(self) -> KernelPack:
        """The kernel and its arrays by name (:class:`KernelPack`), shared with this engine.

        Returns
        -------
        KernelPack
            Fixed at construction: the arrays are updated in place by every step, live
            link changes (:meth:`set_link`) included.
        """
        return self._pack

    @property
    def multirate_pack(self) -> MultiRatePack | None:
        """The multi-rate kernel's arguments (:class:`MultiRatePack`), shared with this
        engine; None for a scene without an ``audio`` section.

        Returns
        -------
        MultiRatePack or None
        """
        return self._multi

    @property
    def port_index(self) -> int:
        """Index of the port mass in :attr:`positions` (-1 when the scene has none)."""
        return self._port

    def _init_audio(self, audio) -> None:
        """Arguments of :func:`hapsim.kernels.audio.run_periods` (every link kind given,
        empty when unused) and the one-period buffers :meth:`port_step` reuses."""
        ls = audio.listen
        self.channels = tuple(f"{x.mass}.{x.quantity}" for x in ls)
        self._l_idx = np.array([self.scene.index(x.mass) for x in ls], dtype=np.int64)
        self._l_code = np.array([audio_kernel.LISTEN_CODES[x.quantity] for x in ls],
                                dtype=np.int64)
        self._l_gain = np.array([x.gain for x in ls], dtype=np.float64)
        self._named.update(nsub=self.substeps, linear=audio.port_position == "linear",
                           last=audio.port_force == "last", port=self._port,
                           l_idx=self._l_idx, l_code=self._l_code, l_gain=self._l_gain,
                           inv_ta=1.0 / self.sim_period)
        self._multi = MultiRatePack(
            arguments.take(_PERIODS, self._named, (arguments.HEAD,)),
            arguments.take(_PERIODS, self._named))
        self._pos1 = np.zeros(1)
        self._force1 = np.zeros(1)
        #: Audio frames of the last :meth:`port_step`, shape (N, C) (reused buffer).
        self.frames = np.zeros((self.substeps, len(ls)))

    def _init_step(self) -> None:
        """The one-argument step (:mod:`hapsim.kernels.step1d`): the kernel's arguments
        packed once, so that :meth:`step` and :meth:`port_step` allocate nothing per call.
        The arrays named are the engine's own, updated in place and never rebound."""
        arrays = (arguments.STATE, arguments.CALL)
        if self._multi is None:
            self._step_ctx, self._step_keep = step1d.context(arguments.take(
                self._kernel.__name__, dict(self._named, rec=_EMPTY_REC, out=_EMPTY_OUT),
                arrays))
            self._step_run = step1d.RUNNERS[self._kernel]
            return
        head = self._multi.head
        # step: the port held, one period at a time on scratch position and frames
        # (dropped), its force kept as port_step's; port_step: the position given, frames
        # and force kept (self.frames, self._force1: port_force)
        self._step_scratch = pos, frames = (np.zeros(1), np.zeros_like(self.frames))
        self._step_ctx, self._step_keep = step1d.context(arguments.take(_PERIODS, dict(
            self._named, pos=pos, audio=frames, force=self._force1, rec=_EMPTY_REC,
            out=_EMPTY_OUT), arrays), head + (0,))
        self._port_ctx, self._port_keep = step1d.context(arguments.take(_PERIODS, dict(
            self._named, pos=self._pos1, audio=self.frames, force=self._force1,
            rec=_EMPTY_REC, out=_EMPTY_OUT), arrays), head + (1,))
        self._step_run = step1d.RUNNERS[audio_kernel.run_periods]

    def _periods(self, n, pos, audio, arow0, force, rec, out, row0) -> None:
        """``n`` device periods of the multi-rate kernel (:mod:`hapsim.kernels.audio`)."""
        audio_kernel.run_periods(*arguments.take(_PERIODS, dict(
            self._named, n=n, pos=pos, audio=audio, arow0=arow0, force=force, rec=rec,
            out=out, row0=row0), arguments.ROLES))

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1) -> None:
        """:meth:`Engine.step` on the 1-D kernels (one compiled call with one argument,
        :mod:`hapsim.kernels.step1d`; a multi-rate scene's port is held where it is and
        its sound dropped, as :meth:`run`)."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        ctx = self._step_ctx
        ctx[0] = n
        try:
            self._step_run(ctx)
        finally:
            ctx[0] = 1           # what port_step runs, without writing it per sample
        self.sample += n

    def port_step(self, position):
        """One device sample: set the port position, advance one sample, return its force.

        Parameters
        ----------
        position : float or ndarray, shape (1,)
            Device position at this sample [m]; a float (or a numpy scalar) is the
            ``n = 1`` shorthand of the 1-D host loops (no array made per sample), a
            :class:`numpy.ndarray` (that class exactly) the array form.

        Returns
        -------
        float or ndarray, shape (1,)
            Force on the port computed from this sample [N] (to be sent to the device): a
            float for a float position, else a new array.

        Raises
        ------
        ConfigError
            When the scene has no port (nothing is advanced: without this check the index
            -1 would overwrite the last mass).
        """
        if self._port < 0:
            raise ConfigError("the scene has no port to drive; port_step needs a mass of "
                              "kind port", file=self.scene.path, key="masses")
        if position.__class__ is _NDARRAY:      # the (1,) array form (a float: no check)
            return np.array([self.port_step(position.item(0))])
        if self._multi is not None:
            self._pos1[0] = position
            self._step_run(self._port_ctx)
            self.sample += 1
            return self._force1.item(0)
        self._x[self._port] = position
        self._step_run(self._step_ctx)      # ctx[0] is 1 (step restores it)
        self.sample += 1
        return self._f.item(self._port)

    def run(self, n: int, record: Sequence[str] | None = None,
            progress: Callable[[int, int], None] | None = None,
            chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``n`` samples recording positions.

        Parameters
        ----------
        n : int
            Number of samples, >= 0.
        record : sequence of str, optional
            Names of the masses to record, in this order; all masses when None.
        progress : callable, optional
            Called as ``progress(done, n)`` after each chunk.
        chunk : int
            Samples per kernel call between progress reports.

        Returns
        -------
        time : ndarray, shape (n + 1,)
            Time of each row [s], starting at the current sample.
        position : ndarray, shape (n + 1, R)
            Row 0 is the state before the run, row i the state after i samples [m].

        Raises
        ------
        ConfigError
            When a recorded name is not a mass of the scene (the valid names are listed).
        ValueError
            When ``n`` is negative.
        """
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        rec = self._indices(record)
        out = np.empty((n + 1, rec.size), dtype=np.float64)
        out[0] = self._x[rec]
        done = 0
        if self._multi is not None:   # port held where it is; the sound is dropped
            chunk = max(1, min(chunk, 65536 // self.substeps))
            pos = np.full(chunk, self._x[self._port] if self._port >= 0 else 0.0)
            frames = np.empty((chunk * self.substeps, self._l_idx.size))
            force = np.empty(chunk)
        while done < n:
            m = min(chunk, n - done)
            if self._multi is not None:
                self._periods(m, pos, frames, 0, force, rec, out, 1 + done)
            else:
                self._kernel(m, *self._args, rec, out, 1 + done)
            done += m
            if progress is not None:
                progress(done, n)
        t0 = self.sample * self.period
        self.sample += n
        time = t0 + np.arange(n + 1, dtype=np.float64) * self.period
        return time, out

    def play(self, positions: np.ndarray,
             progress: Callable[[int, int], None] | None = None,
             chunk: int = 1000) -> tuple[np.ndarray, np.ndarray]:
        """Render a port gesture offline: one device sample per position, with its sound.

        Parameters
        ----------
        positions : ndarray, shape (n,)
            Port position of each device sample [m] (a scripted or recorded gesture).
        progress : callable, optional
            Called as ``progress(done, n)`` after each chunk.
        chunk : int
            Device samples per kernel call between progress reports.

        Returns
        -------
        audio : ndarray, shape (n * N, C)
            Listened frames at the audio rate (N sub-steps per device sample, C listening
            points in scene order).
        force : ndarray, shape (n,)
            Port force of each device sample [N].

        Raises
        ------
        ConfigError
            When the scene has no ``audio`` section or no port.
        """
        if self._multi is None or self._port < 0:
            raise ConfigError("play needs a scene with an audio section and a port",
                              file=self.scene.path, key="audio")
        pos = np.ascontiguousarray(positions, dtype=np.float64).ravel()
        n = pos.size
        audio = np.zeros((n * self.substeps, self._l_idx.size))
        force = np.zeros(n)
        done = 0
        while done < n:
            m = min(chunk, n - done)
            self._periods(m, pos[done:done + m], audio, done * self.substeps,
                          force[done:], _EMPTY_REC, _EMPTY_OUT, 0)
            done += m
            if progress is not None:
                progress(done, n)
        self.sample += n
        return audio, force

    # ------------------------------------------------------------------ live changes
    def cells(self, name: str) -> dict:
        """Where the running engine reads a link's or a moving mass's parameters, so that
        a live change writes them between samples (:meth:`Engine.set_link`,
        :meth:`Engine.set_mass`).

        Parameters
        ----------
        name : str
            A link's name (``"stiffness"`` and ``"damping"`` cells) or a moving mass's
            (``"mass"``).

        Returns
        -------
        dict
            ``{"stiffness": [(array, index)], "damping": [(array, index)]}`` (the cells
            hold ``K`` [N/m] and ``B / Ta`` [N/m], ``Ta`` the integration period) or
            ``{"mass": [(t2m, index)]}`` (the cell holds ``Ta^2 / m`` [s^2/kg]).

        Raises
        ------
        KeyError
            No link or moving mass of that name.
        ConfigError
            An integrator other than ``centred`` (its matrices are built once; key
            ``integrator``).
        """
        if self._v is not None:
            raise ConfigError("live changes need integrator: centred", key="integrator")
        if name in self._link_slot:
            k, z, j = self._link_slot[name]
            return {"stiffness": [(k, j)], "damping": [(z, j)]}
        try:
            i = self.scene.index(name)
        except KeyError:
            raise KeyError(name) from None
        hit = np.nonzero(self._mobile == i)[0]
        if hit.size:
            return {"mass": [(self._t2m, int(hit[0]))]}
        raise KeyError(name)

    def _link_names(self) -> list[str]:
        """The names :meth:`cells` knows as links, in layout order."""
        return list(self._link_slot)

    # ------------------------------------------------------------------ state
    def set_port_position(self, position, at_rest: bool = False) -> None:
        """Set the port position for the next sample [m] (the device sample).

        Parameters
        ----------
        position : float or array_like, shape (1,)
            Device position [m] (a float: the ``n = 1`` shorthand).
        at_rest : bool
            Also set the previous position, so the port starts with zero velocity.

        Raises
        ------
        ConfigError
            When the scene has no port.
        """
        if self._port < 0:
            raise ConfigError("the scene has no port", file=self.scene.path, key="masses")
        if isinstance(position, np.ndarray):
            position = position.item(0)
        self._x[self._port] = position
        if at_rest:
            self._xp[self._port] = position

    def _port_force_row(self) -> np.ndarray:
        """The port's force [N] as a view of shape (1,): the last sample's (with
        ``audio``, the device period's, as :meth:`port_step` returns it: the sub-steps'
        mean or last, ``audio.port_force``)."""
        if self._multi is not None:
            return self._force1
        return self._f[self._port:self._port + 1]

    @property
    def x(self) -> np.ndarray:
        """Positions at the current sample [m], shape (1, N) (a view: writable)."""
        return self._X

    @property
    def xp(self) -> np.ndarray:
        """Positions one sample (one audio sub-step with ``audio``) earlier [m], shape
        (1, N) (a view: writable)."""
        return self._XP

    def _indices(self, names: Sequence[str] | None, key: str = "record") -> np.ndarray:
        """Indices of ``names`` (all masses when None): :func:`mass_indices`."""
        return mass_indices(self.names, names, key)

    def energy(self) -> float:
        """Discrete energy of the virtual network [J].

        Kinetic energy with the backward-difference velocity ``(x - xp)/T`` of every moving
        mass, plus the potential ``K/2 (x1 - x2)(x1p - x2p)`` of every spring-damper and
        engaged contact: the product form is the quantity the centred-difference scheme
        conserves exactly for undamped linear networks (the discrete energy of the
        leapfrog/Verlet scheme, Hairer, Lubich & Wanner, *Geometric Numerical
        Integration*, §I.1.4). With ``integrator: exact`` it is the continuous energy
        (velocity state, ``K/2 (x1 - x2)^2``), which that scheme conserves.

        Returns
        -------
        float
            ``sum m v^2 / 2 + sum K/2 (x1 - x2 + thr)(x1p - x2p + thr)`` [J] at the current
            sample (``thr`` = 0 except for engaged contacts; dampers store no energy).
        """
        T = self.sim_period
        x, xp = self._x, self._xp
        exact = getattr(self.scene, "integrator", "centred") == "exact"
        if exact:  # the exact scheme conserves the continuous energy: v state, K/2 d^2
            xp = x
        e = 0.0
        for j, i in enumerate(self._mobile):
            v = self._v[i] if exact else (x[i] - xp[i]) / T
            e += 0.5 * (T * T / self._t2m[j]) * v * v
        for lk in self.scene.links:
            a, c = self.scene.index(lk.m1), self.scene.index(lk.m2)
            off = lk.threshold if lk.kind == "contact" else 0.0
            if lk.kind == "contact" and not (x[c] - x[a] < off):
                continue
            e += 0.5 * lk.stiffness * (x[a] - x[c] + off) * (xp[a] - xp[c] + off)
        return e

    def __repr__(self) -> str:
        kinds = ", ".join(sorted(self.scene.kinds)) or "no links"
        return (f"Engine({len(self.names)} masses, {len(self.scene.links)} links [{kinds}], "
                f"rate {self.scene.rate_hz:g} Hz, sample {self.sample})")

