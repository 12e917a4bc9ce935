"""The mass-interaction engine: a validated scene turned into arrays and numba kernels.

The API layer of the engine. It takes a :class:`~hapsim.scene.Scene` (never raw YAML),
lays it out as a struct of arrays and advances it with the kernel of
:mod:`hapsim.kernels.cordis` that matches the link kinds the scene uses.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from hapsim.errors import ConfigError
from hapsim.kernels import audio as audio_kernel
from hapsim.kernels import cordis, schemes, step1d
from hapsim.scene import Scene, audio_substeps

__all__ = ["Engine", "KernelPack", "MultiRatePack", "mass_indices", "warm_up"]

_EMPTY_REC = np.empty(0, dtype=np.int64)
_EMPTY_OUT = np.empty((0, 0), dtype=np.float64)


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
        Its arguments, in its order.
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
        gain)`` and ``1 / Ta`` [1/s]: 19 entries.
    """

    head: tuple
    args: tuple


def mass_indices(masses: Sequence[str], names: Sequence[str] | None,
                 key: str = "record") -> np.ndarray:
    """Indices of ``names`` among a scene's masses (all of them when None), checked before
    any engine is built (``hapsim simulate --record`` refuses a wrong name before it
    compiles anything).

    Parameters
    ----------
    masses : sequence of str
        The scene's mass names, in order (``Engine.names``).
    names : sequence of str or None
        The names asked for.
    key : str
        The argument named in the error (the names are an argument, not part of the scene
        file).

    Returns
    -------
    numpy.ndarray, shape (len(names),), int64

    Raises
    ------
    ConfigError
        When no mass has one of the names (the valid names are listed, the first 20).
    """
    if names is None:
        return np.arange(len(masses), dtype=np.int64)
    lookup = {nm: i for i, nm in enumerate(masses)}
    out = []
    for nm in names:
        if nm not in lookup:
            shown = ", ".join(masses[:20]) + (", ..." if len(masses) > 20 else "")
            raise ConfigError(f"no mass named {nm!r}; masses are: {shown}", key=key)
        out.append(lookup[nm])
    return np.array(out, dtype=np.int64)


class Engine:
    """A scene compiled for simulation with the CORDIS-ANIMA scheme.

    Parameters
    ----------
    scene : Scene
        A scene whose links all have numeric (K, B): calibrate ``target`` links first
        (:func:`hapsim.analysis.targets.apply_targets`). Every :class:`Scene` is validated
        when it is constructed, from a file or in code, so only the type is checked here.

    Raises
    ------
    TypeError
        When ``scene`` is not a :class:`Scene`.
    ConfigError
        When a link still has an uncalibrated ``target``.

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

    #: True for an engine whose port force follows a device correction
    #: (:func:`hapsim.host.correction.corrected_engine`): its port law is not the
    #: kernel's alone.
    corrected: bool = False

    def __init__(self, scene: Scene) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"Engine needs a validated hapsim.scene.Scene, got {type(scene).__name__}")
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
        self._x = np.array([m.x0 for m in scene.masses], dtype=np.float64)
        self._xp = np.array([m.x0 - (m.v0 * T if m.kind == "mass" else 0.0) for m in scene.masses],
                            dtype=np.float64)
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
            args = state + sum((arr for arr in links.values() if arr is not None), ())
            extras = {}
        else:  # hapsim.kernels.schemes: symplectic_euler, exact
            kernel, args, extras = schemes.build(integrator, T, *state,
                                                 sd=links["spring_damper"],
                                                 contact=links["contact"])
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
        e = np.empty(0, dtype=np.float64)
        ei = np.empty(0, dtype=np.int64)
        pack = self._pack
        sd = pack.sd if pack.sd is not None else (ei, ei, e, e)
        ct = pack.contact if pack.contact is not None else (ei, ei, e, e, e)
        ls = audio.listen
        self.channels = tuple(f"{x.mass}.{x.quantity}" for x in ls)
        self._l_idx = np.array([self.scene.index(x.mass) for x in ls], dtype=np.int64)
        self._l_code = np.array([audio_kernel.LISTEN_CODES[x.quantity] for x in ls],
                                dtype=np.int64)
        self._l_gain = np.array([x.gain for x in ls], dtype=np.float64)
        self._multi = MultiRatePack(
            (self.substeps, audio.port_position == "linear", audio.port_force == "last",
             self._port),
            (self._x, self._xp, self._f, self._mobile, self._t2m, self._fixed)
            + tuple(sd) + tuple(ct)
            + (self._l_idx, self._l_code, self._l_gain, 1.0 / self.sim_period))
        self._pos1 = np.zeros(1)
        self._force1 = np.zeros(1)
        #: Audio frames of the last :meth:`port_step`, shape (N, C) (reused buffer).
        self.frames = np.zeros((self.substeps, len(ls)))

    def _init_step(self) -> None:
        """The one-argument step (:mod:`hapsim.kernels.step1d`): the kernel's arguments
        packed once, so that :meth:`step` and :meth:`port_step` allocate nothing per call.
        The arrays named are the engine's own, updated in place and never rebound."""
        if self._multi is None:
            self._step_ctx, self._step_keep = step1d.context(
                self._args + (_EMPTY_REC, _EMPTY_OUT))
            self._step_run = step1d.RUNNERS[self._kernel]
            return
        head, state = self._multi
        # step: the port held, one period at a time on scratch position, frames and force
        # (dropped); port_step: the position given, frames and force kept (self.frames)
        self._step_scratch = pos, frames, force = (np.zeros(1), np.zeros_like(self.frames),
                                                   np.zeros(1))       # kept alive here
        self._step_ctx, self._step_keep = step1d.context(
            (pos,) + state + (frames, force, _EMPTY_REC, _EMPTY_OUT), head + (0,))
        self._port_ctx, self._port_keep = step1d.context(
            (self._pos1,) + state + (self.frames, self._force1, _EMPTY_REC, _EMPTY_OUT),
            head + (1,))
        self._step_run = step1d.RUNNERS[audio_kernel.run_periods]

    def _periods(self, n, pos, audio, arow0, force, rec, out, row0) -> None:
        """``n`` device periods of the multi-rate kernel (:mod:`hapsim.kernels.audio`)."""
        head, state = self._multi
        audio_kernel.run_periods(n, *head, pos, *state, audio, arow0, force, rec, out, row0)

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1) -> None:
        """Advance ``n`` samples (no allocation: one compiled call with one argument,
        :mod:`hapsim.kernels.step1d`; a multi-rate scene's port is held where it is and
        its sound dropped, as :meth:`run`).

        Parameters
        ----------
        n : int
            Number of samples, >= 0.

        Raises
        ------
        ValueError
            When ``n`` is negative.
        """
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        self._step_ctx[0] = n
        self._step_run(self._step_ctx)
        self.sample += n

    def port_step(self, position: float) -> float:
        """One device sample: set the port position, advance one sample, return its force.

        Parameters
        ----------
        position : float
            Device position at this sample [m].

        Returns
        -------
        float
            Force on the port computed from this sample [N] (to be sent to the device).

        Raises
        ------
        ConfigError
            When the scene has no port (nothing is advanced: without this check the index
            -1 would overwrite the last mass).
        """
        if self._port < 0:
            raise ConfigError("the scene has no port to drive; port_step needs a mass of "
                              "kind port", file=self.scene.path, key="masses")
        if self._multi is not None:
            self._pos1[0] = position
            self._step_run(self._port_ctx)
            self.sample += 1
            return self._force1.item(0)
        self._x[self._port] = position
        self._step_ctx[0] = 1
        self._step_run(self._step_ctx)
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
    def set_link(self, name: str, stiffness: float, damping: float) -> None:
        """Change one link's (K, B) in place, between two samples (no allocation).

        Parameters
        ----------
        name : str
            Link name.
        stiffness : float
            K [N/m].
        damping : float
            B [N s/m].

        Raises
        ------
        ConfigError
            Unknown link (key ``link``; the valid names listed), or an integrator other
            than ``centred`` (its matrices are built once).

        Notes
        -----
        :attr:`scene` is not updated: the caller (:class:`hapsim.audio.control.Controller`)
        keeps the scene that describes the engine and checks it before changing anything.
        """
        if self._v is not None:
            raise ConfigError("live changes need integrator: centred", key="integrator")
        try:
            k, z, j = self._link_slot[name]
        except KeyError:
            raise ConfigError(f"no link named {name!r}; links are: "
                              + ", ".join(self._link_slot), key="link") from None
        k[j] = stiffness
        z[j] = damping / self.sim_period

    def set_mass(self, name: str, mass: float) -> None:
        """Change one moving mass's inertia in place [kg], between two samples.

        Raises
        ------
        ConfigError
            No moving mass of that name (key ``mass``), or an integrator other than
            ``centred``.
        """
        if self._v is not None:
            raise ConfigError("live changes need integrator: centred", key="integrator")
        i = self._indices([name], key="mass")[0]
        hit = np.nonzero(self._mobile == i)[0]
        if hit.size == 0:
            raise ConfigError(f"{name!r} is not a moving mass (kind mass)", key="mass")
        self._t2m[hit[0]] = self.sim_period ** 2 / mass

    # ------------------------------------------------------------------ state
    def set_port_position(self, position: float, at_rest: bool = False) -> None:
        """Set the port position for the next sample [m] (the device sample).

        Parameters
        ----------
        position : float
            Device position [m].
        at_rest : bool
            Also set the previous position, so the port starts with zero velocity.

        Raises
        ------
        ConfigError
            When the scene has no port.
        """
        if self._port < 0:
            raise ConfigError("the scene has no port", file=self.scene.path, key="masses")
        self._x[self._port] = position
        if at_rest:
            self._xp[self._port] = position

    @property
    def port_force(self) -> float:
        """Force on the port from the last sample advanced [N] (0.0 when no port)."""
        return float(self._f[self._port]) if self._port >= 0 else 0.0

    @property
    def positions(self) -> np.ndarray:
        """Copy of the current positions [m], shape (n_masses,), in scene order."""
        return self._x.copy()

    @property
    def previous_positions(self) -> np.ndarray:
        """Copy of the positions one sample earlier [m], shape (n_masses,)."""
        return self._xp.copy()

    def position(self, name: str) -> float:
        """Current position of one mass.

        Parameters
        ----------
        name : str
            Mass name.

        Returns
        -------
        float
            Its position at the current sample [m].

        Raises
        ------
        ConfigError
            When no mass has that name (key ``name``; the valid names are listed).
        """
        return float(self._x[self._indices([name], key="name")[0]])

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


def warm_up(scene: Scene) -> None:
    """Load the numba kernel of the scene's link kinds (from numba's cache, or compile it)
    before a real-time loop: an engine of the scene advanced three samples.

    Parameters
    ----------
    scene : Scene
        A calibrated scene (the engine of a copy is stepped; nothing of the caller's
        changes).

    Raises
    ------
    ConfigError
        As :class:`Engine` (a link with an uncalibrated target).
    """
    eng = Engine(scene)
    if scene.port is not None:
        eng.set_port_position(0.0, at_rest=True)
        for _ in range(3):
            eng.port_step(0.0)
    else:
        eng.step(3)
