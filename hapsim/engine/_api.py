"""The engine's one API for every dimension (:class:`Engine`), the helpers both layouts
share, and :func:`warm_up`; the layouts themselves are :mod:`hapsim.engine._line` (1-D) and
:mod:`hapsim.engine._space` (2-D and 3-D)."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["Engine", "LAYOUTS", "PRECISIONS", "mass_indices", "warm_up"]

#: The engine's precisions and the floating type of its state and parameters.
PRECISIONS = {"double": np.float64, "single": np.float32}
#: dimension -> a function returning the engine class laid out for it; filled by the
#: package (:mod:`hapsim.engine`), which imports the n-D layout on its first use only.
LAYOUTS: dict[int, Callable[[], type]] = {}


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
    """A scene of any dimension compiled for simulation with the CORDIS-ANIMA scheme.

    ``Engine(scene)`` returns the engine laid out for the scene's dimension: a 1-D
    :class:`hapsim.scene.Scene` on the kernels of :mod:`hapsim.kernels.cordis`,
    :mod:`hapsim.kernels.schemes` and :mod:`hapsim.kernels.audio` (one array per field,
    compiled per link kind), a 2-D or 3-D :class:`hapsim.scene.SceneND` on those of
    :mod:`hapsim.kernels.nd` (a ``(3, N)`` state, links in stripes per block of masses).
    Both are instances of this class and answer the one API below, in which ``n`` is the
    dimension (1 for a 1-D scene): positions are ``(n, N)`` arrays, the port's position
    and force ``(n,)`` arrays. For ``n = 1`` :meth:`port_step` and
    :meth:`set_port_position` also take a float (and :meth:`port_step` then returns one):
    the shorthand of the 1-D host loops, which call it once per device sample.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND
        A validated scene whose links all have numeric (K, B) (calibrate felt targets
        first: :func:`hapsim.analysis.targets.apply_targets`).
    block : int, optional
        n-D only: masses per block of the kernels' schedule
        (:data:`hapsim.kernels.nd.BLOCK`; smaller only to test the schedule).
    precision : {"double", "single"}, optional
        The floating type of the state (float64, float32); default the scene's
        (``engine.precision`` of an n-D scene, ``double`` for 1-D).
    families : bool, optional
        n-D only: run dense families of Euclidean links as families (default True;
        False only to test the pieces: :class:`hapsim.engine._space.Space`).

    Raises
    ------
    TypeError
        When ``scene`` is neither a :class:`~hapsim.scene.Scene` nor a
        :class:`~hapsim.scene.SceneND`.
    ConfigError
        A link with an uncalibrated ``target``; ``precision`` not one of
        :data:`PRECISIONS`, single precision with a port or in 1-D (key
        ``engine.precision``).

    Notes
    -----
    Scheme (docs/design.md, 'The scheme'; Florens-Voda-Urma Fig. 5, the discretisation of
    Faust's ``mi.lib``): every axis of every mass ``x[n+1] = 2 x[n] - x[n-1] + T^2 F[n] /
    m``; the link laws of each dimension in :mod:`hapsim.scene`. The port and the grounds
    never move by themselves; the port moves when its position is set, once per device
    sample, so its velocity is the backward difference of device samples.

    Attributes
    ----------
    scene : Scene or SceneND
        The scene it was built from.
    dim : int
        The dimension ``n`` (1, 2 or 3).
    names : tuple of str
        The masses' names, in scene order (the columns of :attr:`x`).
    period : float
        The device's sample period ``T`` [s].
    sample : int
        Device samples advanced since construction by the engine's own methods (a
        compiled caller that steps its context or kernel pack itself does not count).
    precision : str
        ``"double"`` or ``"single"``; :attr:`dtype` its floating type.

    Examples
    --------
    >>> eng = Engine(load_scene("configs/wall.yaml"))        # doctest: +SKIP
    >>> f = eng.port_step(0.001)                             # doctest: +SKIP
    >>> eng3 = Engine(load_scene_nd("configs/delta_sphere.yaml"))   # doctest: +SKIP
    >>> F = eng3.port_step(eng3.x[:, eng3.port_index])       # doctest: +SKIP
    """

    #: True for an engine whose port force follows a device correction
    #: (:func:`hapsim.host.correction.corrected_engine`): its port law is not the
    #: kernel's alone.
    corrected: bool = False

    def __new__(cls, scene=None, *args, **kwargs):
        if cls is Engine:
            from hapsim.scene import SceneND
            # a SceneND runs the n-D kernels whatever its dimension (the n-D kernels'
            # tests build ones of dimension 1)
            cls = Engine.layout(2 if isinstance(scene, SceneND) else 1)
        return super().__new__(cls)

    @staticmethod
    def layout(dimension: int) -> type:
        """The engine class laid out for ``dimension`` (the base of a subclass that adds
        to one dimension's engine: :func:`hapsim.host.correction.corrected_engine`).

        Parameters
        ----------
        dimension : int
            1, 2 or 3.

        Returns
        -------
        type
            A subclass of :class:`Engine`.

        Raises
        ------
        ValueError
            Another dimension.
        """
        if dimension not in LAYOUTS:
            raise ValueError(f"an engine has dimension 1, 2 or 3, got {dimension!r}")
        return LAYOUTS[dimension]()

    # ------------------------------------------------------------------ stepping
    def step(self, n: int = 1) -> None:
        """Advance ``n`` samples, the port held where it is (no allocation: each layout
        makes one compiled call with one argument).

        Parameters
        ----------
        n : int
            Number of samples, >= 0.

        Raises
        ------
        ValueError
            When ``n`` is negative.
        """
        raise NotImplementedError        # each layout's own (hapsim.engine._line, _space)

    # ------------------------------------------------------------------ one dimension's
    def _refuse(self, what: str, why: str):
        """Raise the :class:`ConfigError` of a capability this dimension's layout lacks."""
        raise ConfigError(f"{what} is not built for a {self.dim}-D engine: {why}",
                          file=getattr(self.scene, "path", None), key="dimension")

    def run(self, n: int, record=None, progress=None, chunk: int = 65536):
        """Advance ``n`` samples recording positions in the compiled kernel: the 1-D
        layout's (:meth:`hapsim.engine._line.Line.run`, positions ``(n + 1, R)``).

        Raises
        ------
        ConfigError
            On a 2-D or 3-D engine (key ``dimension``): record :attr:`x` after each
            :meth:`step` (``hapsim simulate`` does).
        """
        self._refuse("run", "record x after each step (hapsim simulate does)")

    def play(self, positions, progress=None, chunk: int = 1000):
        """Render a port gesture with its multi-rate sound: the 1-D layout's
        (:meth:`hapsim.engine._line.Line.play`).

        Raises
        ------
        ConfigError
            On a 2-D or 3-D engine (key ``dimension``): its sound is single-rate, read
            by :meth:`listen`.
        """
        self._refuse("play", "its sound is single-rate, recorded by listen()")

    def energy(self) -> float:
        """The network's discrete energy [J]: the 1-D layout's
        (:meth:`hapsim.engine._line.Line.energy`).

        Raises
        ------
        ConfigError
            On a 2-D or 3-D engine (key ``dimension``): not built there.
        """
        self._refuse("energy", "the Euclidean links' discrete energy is not derived")

    def listen(self, out, axis, mass, velocity, gain) -> None:
        """Advance recording listening points at the device rate: the n-D layout's
        (:meth:`hapsim.engine._space.Space.listen`).

        Raises
        ------
        ConfigError
            On a 1-D engine (key ``dimension``): its sound is multi-rate, the frames of
            :meth:`port_step` and :meth:`play`.
        """
        self._refuse("listen", "its sound is multi-rate: port_step's frames and play()")

    def listener(self, axis, mass, velocity, gain):
        """:meth:`listen` bound once: the n-D layout's.

        Raises
        ------
        ConfigError
            On a 1-D engine, as :meth:`listen`.
        """
        self._refuse("listener", "its sound is multi-rate: port_step's frames and play()")

    # ------------------------------------------------------------------ state
    @property
    def port(self) -> int | None:
        """Index of the port mass in :attr:`names`, or None without a port."""
        return None if self.port_index < 0 else self.port_index

    @property
    def positions(self) -> np.ndarray:
        """Current positions [m], shape (N, n), in scene order (a copy)."""
        return self.x.T.copy()

    @property
    def previous_positions(self) -> np.ndarray:
        """Positions one sample earlier [m], shape (N, n) (a copy)."""
        return self.xp.T.copy()

    def position(self, name: str) -> np.ndarray:
        """Current position of one mass [m], shape (n,) (a copy).

        Raises
        ------
        ConfigError
            No mass of that name (key ``name``; the valid names listed).
        """
        return self.x[:, mass_indices(self.names, [name], key="name")[0]].astype(np.float64)

    @property
    def port_force(self) -> np.ndarray:
        """Force on the port from the last sample advanced [N], shape (n,) (a copy; zeros
        without a port)."""
        if self.port_index < 0:
            return np.zeros(self.dim)
        return self._port_force_row().astype(np.float64)

    # ------------------------------------------------------------------ live changes
    def set_link(self, name: str, stiffness: float, damping: float) -> None:
        """Change one link's or plane's (K, B) in place, between two samples (the cells of
        :meth:`cells`; no allocation).

        Parameters
        ----------
        name : str
            Link (or n-D plane) name.
        stiffness : float
            K [N/m].
        damping : float
            B [N s/m].

        Raises
        ------
        ConfigError
            Unknown link (key ``link``; the valid names listed), or a 1-D integrator other
            than ``centred`` (its matrices are built once).

        Notes
        -----
        :attr:`scene` is not updated: the caller (:class:`hapsim.audio.control.Controller`)
        keeps the scene that describes the engine and checks it before changing anything.
        """
        try:
            cells = self.cells(name)
        except KeyError:
            cells = {}
        if "stiffness" not in cells:
            raise ConfigError(f"no link named {name!r}; links are: "
                              + ", ".join(self._link_names()), key="link") from None
        for arr, j in cells["stiffness"]:
            arr[j] = stiffness
        for arr, j in cells["damping"]:
            arr[j] = damping / self.sim_period

    def set_mass(self, name: str, mass: float) -> None:
        """Change one moving mass's inertia in place [kg], between two samples.

        Raises
        ------
        ConfigError
            No moving mass of that name (key ``mass``), or a 1-D integrator other than
            ``centred``.
        """
        mass_indices(self.names, [name], key="mass")
        try:
            cells = self.cells(name)
        except KeyError:
            cells = {}
        if "mass" not in cells:
            raise ConfigError(f"{name!r} is not a moving mass (kind mass)", key="mass")
        for arr, j in cells["mass"]:
            arr[j] = self.sim_period ** 2 / mass

    def __repr__(self) -> str:
        return (f"Engine({self.dim}-D, {len(self.names)} masses, "
                f"{len(self.scene.links)} links, rate {self.scene.rate_hz:g} Hz, "
                f"sample {self.sample})")


def warm_up(scene) -> None:
    """Load the numba kernels of the scene's engine (from numba's cache, or compile them)
    before a real-time loop: an engine of the scene advanced three samples.

    Parameters
    ----------
    scene : Scene or SceneND
        A calibrated scene (the engine of a copy is stepped; nothing of the caller's
        changes).

    Raises
    ------
    ConfigError
        As :class:`Engine` (a link with an uncalibrated target).
    """
    eng = Engine(scene)
    if eng.port_index >= 0:
        p = eng.x[:, eng.port_index].copy()
        eng.set_port_position(p, at_rest=True)
        for _ in range(3):
            eng.port_step(p)
    else:
        eng.step(3)
