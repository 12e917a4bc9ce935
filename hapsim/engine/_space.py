"""The engine's n-D layout (:class:`Space`, what :class:`hapsim.engine.Engine` returns for a
2-D or 3-D scene, :class:`hapsim.scene.SceneND`) on the kernels of :mod:`hapsim.kernels.nd`.

This layer validates (the scene did) and lays the arrays out; the kernels never see a
Python object (docs/design.md, rule 3). Links: ``spring_damper`` with ``length: 0`` runs as a
``linear`` link, with ``length > 0`` as a ``euclid`` link; ``contact`` links and
``planes`` run as the kernels' contacts (the laws in :mod:`hapsim.scene`, 'Link laws in two
and three dimensions').
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.engine._api import PRECISIONS, Engine
from hapsim.errors import ConfigError
from hapsim.kernels.layout import family_offsets, placed
from hapsim.kernels.nd import (BLOCK, ROWS, context, euclid_layout, link_lengths,
                               run_context, run_context32, run_nd_listen, schedule,
                               shared_params, stripes)

__all__ = ["Space"]
#: The engine's arrays held in its precision (the rest are indices and flags).
_FLOAT_ARRAYS = ("_X", "_XP", "f", "port_f", "t2m", "lin_k", "lin_z", "eu_k", "eu_z",
                 "eu_rest", "eu_lprev", "W", "c_k", "c_z", "c_thr", "c_lprev", "p_normal",
                 "p_offset", "p_k", "p_z", "dn_G")

#: The arrays a mesh's dense families stream, by their names in
#: :func:`hapsim.kernels.layout.family_offsets`: placed in their pages where few of the
#: loops' loads alias a store.
_PLACED = {"_X": "x", "_XP": "xp", "t2m": "t2m", "dn_G": "G", "eu_lprev": "lprev",
           "eu_k": "k", "eu_z": "z", "eu_rest": "rest"}


class Space(Engine):
    """Run an n-D scene sample by sample (centred scheme on every axis): the
    :class:`~hapsim.engine.Engine` of a :class:`~hapsim.scene.SceneND` (build it as
    ``Engine(scene)``; its API there).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene.
    block : int, optional
        Masses per block of the kernels' schedule (:data:`hapsim.kernels.nd.BLOCK`; a
        smaller one only to test the schedule on small scenes).
    precision : {"double", "single"}, optional
        The floating type of the state and the parameters (float64 or float32); default
        the scene's ``engine.precision`` (itself ``double`` by default). Single precision
        is twice the vector lanes and half the bytes (the 44.1 kHz mesh target is met
        only there, docs/dimensions.md) and rounds the positions to 24 bits; it keeps
        the scheme's velocity form (the state's second row array is the increment
        ``x[n] - x[n-1]``, :mod:`hapsim.kernels.nd`): its accuracy is stated and measured
        in docs/dimensions.md, 'Single precision'.
    families : bool, optional
        Run a mesh's dense families of Euclidean links as families, their forces pulled
        by each mass (:func:`hapsim.kernels.layout.families`; the same forces to
        round-off, faster); False only to test the pieces on a grid.

    Raises
    ------
    ConfigError
        ``precision`` not one of :data:`PRECISIONS`, or single precision for a scene
        with a port (key ``engine.precision``).

    Notes
    -----
    Positions start at ``x0`` with ``xp = x0 - T v0``; grounds and the port have
    ``T^2/m = 0``. The port's position is set by :meth:`set_port_position` before a step;
    :attr:`port_force` is then the force the step computed on it [N] (``-F`` of its links).
    The per-field arrays (``t2m``, ``lin_k``, ``port_f``, ...) are the kernels' arguments,
    listed once in :meth:`_arrays` (the order of :data:`hapsim.kernels.nd.CONTEXT_ARRAYS`).
    """

    def __init__(self, scene, block: int = BLOCK, precision: str | None = None,
                 families: bool = True) -> None:
        self.scene = scene
        self.block = int(block)
        if precision is None:
            precision = getattr(scene, "precision", "double")
        if precision not in PRECISIONS:
            raise ConfigError(f"unknown precision {precision!r}; valid choices: "
                              f"{', '.join(PRECISIONS)}", key="engine.precision")
        if precision == "single" and scene.port is not None:
            raise ConfigError("single precision is for scenes without a port (a felt "
                              "scene runs the double-precision engine, exact to "
                              "round-off)", key="engine.precision")
        #: ``"double"`` or ``"single"``.
        self.precision = precision
        #: The floating type of the state and parameters.
        self.dtype = PRECISIONS[precision]
        T = scene.period
        #: The device's sample period and the integration period [s] (one rate in n-D).
        self.period = self.sim_period = T
        #: Samples advanced since construction.
        self.sample = 0
        self.names = tuple(m.name for m in scene.masses)
        index = {n: i for i, n in enumerate(self.names)}
        X0 = np.array([m.x0 for m in scene.masses], float)
        V0 = np.array([m.v0 for m in scene.masses], float)
        n, dim = len(scene.masses), scene.dimension
        self.dim = dim
        # three rows always (the kernels' layout); a lower dimension's extra rows stay 0
        self._X = np.zeros((ROWS, n))
        self._XP = np.zeros((ROWS, n))
        self._X[:dim] = X0.T
        self._XP[:dim] = (X0 - T * V0).T
        self.f = np.zeros((ROWS, n))
        self.port_f = np.zeros(ROWS)
        self.t2m = np.array([T * T / m.mass if m.kind == "mass" else 0.0
                             for m in scene.masses])
        #: Index of the port mass in :attr:`names` (-1 without a port).
        self.port_index = index[scene.port.name] if scene.port is not None else -1

        def pack(links, euclid=False):
            # lower index first (the laws are symmetric in the two ends), then stripes
            # and their pieces per block of masses; Euclidean links in dense families
            # (kernels.layout.families) stay out of the pieces
            empty = np.zeros((0, 4), np.int64)
            if not links:
                return empty, np.zeros(-(-n // block) + 1, np.int64), empty, \
                    np.zeros(0, np.int64)
            i1 = np.array([index[lk.m1] for lk in links])
            i2 = np.array([index[lk.m2] for lk in links])
            lo, hi = np.minimum(i1, i2), np.maximum(i1, i2)
            if euclid:
                return euclid_layout(lo, hi, n, block, dense=families)
            table, order = stripes(lo, hi)
            pieces, ptr = schedule(table, n, block)
            return pieces, ptr, empty, order

        def slot(order, values):
            out = np.zeros(order.size)
            real = order >= 0
            out[real] = np.asarray(values, float)[order[real]]
            return out
        lin = [lk for lk in scene.links if lk.kind == "spring_damper" and lk.length == 0]
        eu = [lk for lk in scene.links if lk.kind == "spring_damper" and lk.length > 0]
        con = [lk for lk in scene.links if lk.kind == "contact"]
        self.c_i1 = np.array([index[lk.m1] for lk in con], np.int64)
        self.c_i2 = np.array([index[lk.m2] for lk in con], np.int64)
        self.c_k = np.array([lk.stiffness for lk in con], float)
        self.c_z = np.array([lk.damping / T for lk in con], float)
        self.c_thr = np.array([lk.threshold for lk in con], float)
        d = self._XP[:, self.c_i1] - self._XP[:, self.c_i2]
        self.c_lprev = np.sqrt((d * d).sum(axis=0))
        pairs = [(pl, m) for pl in scene.planes for m in pl.masses]
        self.p_mass = np.array([index[m] for _, m in pairs], np.int64)
        self.p_normal = np.ascontiguousarray(
            np.array([pl.normal for pl, _ in pairs], float).reshape(-1, dim).T)
        self.p_offset = np.array([pl.offset for pl, _ in pairs], float)
        self.p_k = np.array([pl.stiffness for pl, _ in pairs], float)
        self.p_z = np.array([pl.damping / T for pl, _ in pairs], float)
        self.lin_pieces, self.lin_ptr, _, lo = pack(lin)
        self.eu_pieces, self.eu_ptr, fam, eo = pack(eu, euclid=True)
        # the dense families, three rows always (a missing one zero), and their force
        # rows with max(s) leading zero columns (kernels.nd.step_nd)
        self.dn_fam = np.zeros((3 if len(fam) else 0, 4), np.int64)
        self.dn_fam[:len(fam)] = fam
        self.dn_G = np.zeros((9, int(fam[:, 1].max()) + n) if len(fam) else (0, 0))
        # where each named element's parameters live (cells()): slot of each link
        self._slot = {}
        for links, order, kind in ((lin, lo, "linear"), (eu, eo, "euclid")):
            for j, i in enumerate(order):
                if i >= 0:
                    self._slot[links[i].name] = (kind, j)
        for j, lk in enumerate(con):
            self._slot[lk.name] = ("contact", j)
        self._pairs = {}
        for j, (pl, _) in enumerate(pairs):
            self._pairs.setdefault(pl.name, []).append(j)
        self.lin_k = slot(lo, [lk.stiffness for lk in lin])
        self.lin_z = slot(lo, [lk.damping / T for lk in lin])
        self.eu_k = slot(eo, [lk.stiffness for lk in eu])
        self.eu_z = slot(eo, [lk.damping / T for lk in eu])
        self.eu_rest = slot(eo, [lk.length for lk in eu])
        self.eu_lprev = link_lengths(self._XP, np.concatenate([self.eu_pieces, fam]),
                                     eo.size)
        # per piece, then per family (the kernels read a family's entry after the
        # pieces': one K, B / T and rest length for all its links when they share them)
        self.eu_shared = shared_params(np.concatenate([self.eu_pieces, fam]), eo,
                                       self.eu_k, self.eu_z, self.eu_rest)
        self.W = np.zeros((ROWS, block))
        if self.dtype is not np.float64:      # the values above, rounded once
            # the velocity form: the second row array holds x[n] - x[n-1] (kernels)
            self._XP = self._X - self._XP
            for name in _FLOAT_ARRAYS:
                setattr(self, name, getattr(self, name).astype(self.dtype))
            self.eu_shared = tuple(a.astype(self.dtype) if a.dtype == np.float64 else a
                                   for a in self.eu_shared)
        if len(fam):
            # the arrays the families' loops stream, each started where in its page few
            # of their loads alias a store in flight (kernels.layout.family_offsets)
            shared = bool(self.eu_shared[0][len(self.eu_pieces):].all())
            off = family_offsets(n, fam, self.dn_G.shape[1] - n, self._X.itemsize, shared)
            for name, key in _PLACED.items():
                setattr(self, name, placed(getattr(self, name), off[key]))
        # the port's coordinates in the state (a view made once: set_port_position
        # writes through it, no allocation per sample)
        self._port_x = None if self.port_index < 0 else self._X[:dim, self.port_index]
        self._port_xp = None if self.port_index < 0 else self._XP[:dim, self.port_index]
        self._run = run_context if self.dtype is np.float64 else run_context32
        # every array the step reads or writes, by address: one argument per step call
        # (the arrays above are updated in place, never rebound)
        self._ctx = context(self.dim, self.block, *self._arrays(), self.port_index,
                            self.port_f, dtype=self.dtype)

    def _arrays(self) -> tuple:
        """The kernels' arrays after ``dim`` and ``block``, from ``x`` to ``dn_G``, in
        their order (:data:`hapsim.kernels.nd.CONTEXT_ARRAYS`, the arguments of
        :func:`hapsim.kernels.nd.step_nd`): the one place this engine writes the layout."""
        return (self._X, self._XP, self.f, self.t2m, self.lin_pieces, self.lin_ptr,
                self.lin_k, self.lin_z, self.eu_pieces, self.eu_ptr, self.eu_k, self.eu_z,
                self.eu_rest, self.eu_lprev, *self.eu_shared, self.W, self.c_i1, self.c_i2,
                self.c_k, self.c_z, self.c_thr, self.c_lprev, self.p_mass, self.p_normal,
                self.p_offset, self.p_k, self.p_z, self.dn_fam, self.dn_G)

    @property
    def context(self) -> np.ndarray:
        """The int64 context of the engine's step (:func:`hapsim.kernels.nd.context`),
        for compiled code that steps it: set slot 0 to the samples and call
        :func:`hapsim.kernels.nd.run_context` (:mod:`hapsim.kernels.play` does).

        In single precision its arrays are float32: step it with
        :func:`hapsim.kernels.nd.run_context32` (:attr:`precision` says which), never
        :func:`~hapsim.kernels.nd.run_context`, which would read them as float64."""
        return self._ctx

    @property
    def step_rows(self) -> tuple:
        """The two state arrays the compiled step advances, as views (dim, N) in the
        engine's precision, for compiled callers that read them between samples
        (:mod:`hapsim.kernels.play`): the positions ``x[n]`` [m] and, in double
        precision, ``x[n-1]`` [m]; in single precision (the scheme's velocity form) the
        last step ``x[n] - x[n-1]`` [m].

        Returns
        -------
        tuple of ndarray, shape (dim, N) each
        """
        return self._X[:self.dim], self._XP[:self.dim]

    def cells(self, name: str) -> dict:
        """Where the running engine reads a link's, a plane's or a mass's parameters, so
        that a live change can write them between (or within compiled) samples.

        A Euclidean link in a piece whose links shared one ``(K, B, rest)``
        (:func:`hapsim.kernels.nd.shared_params`) makes its piece read per-link values from
        now on (the same forces: the per-link arrays hold the same numbers).

        Parameters
        ----------
        name : str
            A link's or plane's name (``"stiffness"`` and ``"damping"`` cells) or a moving
            mass's (``"mass"``).

        Returns
        -------
        dict
            ``{"stiffness": [(array, index), ...], "damping": [...]}`` (the cells hold
            ``K`` [N/m] and ``B / T`` [N/m]; a plane has one per mass it acts on) or
            ``{"mass": [(t2m, index)]}`` (the cell holds ``T^2 / m`` [s^2/kg]).

        Raises
        ------
        KeyError
            No link, plane or moving mass of that name.
        """
        if name in self._slot:
            kind, j = self._slot[name]
            if kind == "contact":
                return {"stiffness": [(self.c_k, j)], "damping": [(self.c_z, j)]}
            if kind == "euclid":
                sh = self.eu_shared[0]      # the pieces' entries, then the families'
                for r, (_, _, c, j0) in enumerate(np.concatenate([self.eu_pieces,
                                                                   self.dn_fam])):
                    if j0 <= j < j0 + c:
                        sh[r] = False
                return {"stiffness": [(self.eu_k, j)], "damping": [(self.eu_z, j)]}
            return {"stiffness": [(self.lin_k, j)], "damping": [(self.lin_z, j)]}
        if name in self._pairs:
            js = self._pairs[name]
            return {"stiffness": [(self.p_k, j) for j in js],
                    "damping": [(self.p_z, j) for j in js]}
        if name in self.names and self.t2m[self.names.index(name)] > 0:
            return {"mass": [(self.t2m, self.names.index(name))]}
        raise KeyError(name)

    def _link_names(self) -> list[str]:
        """The names :meth:`cells` knows as links and planes."""
        return list(self._slot) + list(self._pairs)

    @property
    def x(self) -> np.ndarray:
        """Positions at the current sample [m], shape (dim, N), in the engine's
        precision (a view: writable)."""
        return self._X[:self.dim]

    @property
    def xp(self) -> np.ndarray:
        """Positions at the previous sample [m], shape (dim, N), in the engine's
        precision (in double precision a view, writable; in single precision, whose
        state holds the last increment ``x[n] - x[n-1]`` instead, a copy).

        Returns
        -------
        ndarray, shape (dim, N)
        """
        if self.dtype is np.float64:
            return self._XP[:self.dim]
        return self._X[:self.dim] - self._XP[:self.dim]

    def step(self, n: int = 1) -> None:
        """:meth:`Engine.step` on the n-D kernels (one compiled call with one argument,
        :func:`hapsim.kernels.nd.run_context`)."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        self._ctx[0] = n
        self._run(self._ctx)
        self.sample += n

    def listen(self, out, axis, mass, velocity, gain) -> None:
        """Advance ``out.shape[0]`` samples, recording listening points (no allocation);
        a port is held where it is.

        Parameters
        ----------
        out : ndarray, shape (n, C)
            Written: channel ``c`` after each sample is ``gain[c]`` times the ``axis[c]``
            position [m] of mass ``mass[c]`` or, where ``velocity[c]``, its change over
            the sample [m] (pass ``gain = g / T`` for a velocity [m/s]).
        axis, mass : ndarray of int64, shape (C,)
            Axis (0..dim-1) and mass index (:attr:`names`).
        velocity : ndarray of bool, shape (C,)
        gain : ndarray, shape (C,)

        Raises
        ------
        ConfigError
            An axis or mass index out of range (key ``audio``).
        """
        self.listener(axis, mass, velocity, gain)(out)

    def listener(self, axis, mass, velocity, gain):
        """:meth:`listen` with its listening points checked and bound once, for a caller
        that records chunk after chunk (live sound: nothing is made per chunk).

        Parameters
        ----------
        axis, mass, velocity, gain
            As :meth:`listen`.

        Returns
        -------
        callable
            ``f(out)``: :meth:`listen` into ``out`` (shape (n, C), float64, C-contiguous).
            A port is held at the position it has now (the engine's port must not be
            moved between calls).

        Raises
        ------
        ConfigError
            An axis or mass index out of range (key ``audio``).
        """
        axis = np.ascontiguousarray(axis, np.int64)
        mass = np.ascontiguousarray(mass, np.int64)
        velocity = np.ascontiguousarray(velocity, np.bool_)
        gain = np.ascontiguousarray(gain, float)
        if np.any((axis < 0) | (axis >= self.dim)) or \
                np.any((mass < 0) | (mass >= len(self.names))):
            raise ConfigError("a listening point's axis or mass is out of range", key="audio")
        port = self.port_index
        port_x = self._X[:, port].copy() if port >= 0 else np.zeros(ROWS)
        args = (axis, mass, velocity, gain, self.dim, self.block, *self._arrays(), port,
                self.port_f, port_x)

        def f(out) -> None:
            run_nd_listen(out, *args)
            self.sample += out.shape[0]
        return f

    def set_port_position(self, position, at_rest: bool = False) -> None:
        """Set the port's position [m] (shape (dim,)) for the next step; unless
        ``at_rest``, its previous position stays the one it had in the last step (not
        given: the step extrapolates it, ``2 x - xp``, as the scheme moves a mass without
        force).

        Parameters
        ----------
        position : array_like, shape (dim,)
            The port's position [m].
        at_rest : bool
            Also set the previous position, so the port starts with zero velocity.

        Raises
        ------
        ConfigError
            The scene has no port (key ``masses``), or ``position`` is not ``dim`` finite
            coordinates (key ``position``).
        """
        if self.port_index < 0:
            raise ConfigError("the scene has no port", key="masses")
        p = np.asarray(position, float)
        px = self._port_x
        if p.shape != px.shape or not _finite(p):
            raise ConfigError(f"must be {self.dim} finite coordinates [m], got "
                              f"{position!r}", key="position")
        np.copyto(px, p)
        if at_rest:       # double precision only (single precision has no port)
            np.copyto(self._port_xp, p)

    def port_step(self, position) -> np.ndarray:
        """One device sample: set the port's position, advance one sample, return its
        force.

        Parameters
        ----------
        position : array_like, shape (dim,)
            Device position at this sample [m].

        Returns
        -------
        ndarray, shape (dim,)
            Force on the port computed from this sample [N] (a new array).

        Raises
        ------
        ConfigError
            As :meth:`set_port_position`.
        """
        self.set_port_position(position)
        self.step(1)
        return self.port_f[:self.dim].astype(np.float64)

    def _port_force_row(self) -> np.ndarray:
        """The port's force [N] as a view of shape (dim,)."""
        return self.port_f[:self.dim]


def _finite(p) -> bool:
    """Whether the 1, 2 or 3 coordinates of ``p`` are finite (element by element: no
    temporary array, for the real-time loops' per-sample calls)."""
    isf = math.isfinite
    n = p.shape[0]
    return (isf(p.item(0)) and (n < 2 or isf(p.item(1)))
            and (n < 3 or isf(p.item(2))) and n <= 3)
