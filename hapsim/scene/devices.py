"""Reading a 2-D or 3-D scene's device: a Cartesian one (its mass and friction as given) or
a kinematic one, the pantograph or the delta of :mod:`hapsim.kinematics`, at an operating
point: its geometry (a preset, or a pantograph's five lengths), its joints, and its
Cartesian mass and friction there (:meth:`hapsim.analysis.ths.MatrixLoop.from_device`,
imported when a kinematic device is read), checked against the mass range and a
singular pose, every refusal naming the file, the line and the key."""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError, show, type_name
from hapsim.scene.elements import DeviceND
from hapsim.scene.lines import LineContext

__all__ = ["read_device_nd", "nd_key_without_dimension", "DEVICE_KINDS", "DEVICE_KEYS",
           "DEVICE_DOF",
           "PANTOGRAPH_GEOMETRY_KEYS"]

#: The kinds of device of a 2-D or 3-D scene (``device.kind``).
DEVICE_KINDS = ("cartesian", "pantograph", "delta")
#: The keys of ``device`` by kind.
DEVICE_KEYS = {"cartesian": ("kind", "mass", "friction", "position", "delay", "hold"),
               "pantograph": ("kind", "geometry", "joints", "joint_inertia",
                              "joint_friction", "hand_mass", "hand_damping", "delay", "hold"),
               "delta": ("kind", "geometry", "joints", "joint_inertia", "joint_friction",
                         "hand_mass", "hand_damping", "delay", "hold")}
#: A kinematic device's degrees of freedom: the scene's dimension it needs.
DEVICE_DOF = {"pantograph": 2, "delta": 3}
#: A pantograph's lengths given as numbers (``geometry: {l1: .., l2: .., L1: .., L2: ..,
#: d: ..}`` [m]: :class:`hapsim.kinematics.PantographGeometry`).
PANTOGRAPH_GEOMETRY_KEYS = ("l1", "l2", "L1", "L2", "d")


def _read_geometry(r: LineContext, d, key: str, kind: str, presets: dict):
    """A kinematic device's ``geometry``: a preset's name (the default: the first
    preset), or for a pantograph a mapping of its five lengths [m]
    (:data:`PANTOGRAPH_GEOMETRY_KEYS`; ``l1, l2, L1, L2`` > 0, ``d`` >= 0), returned as a
    :class:`hapsim.kinematics.PantographGeometry`. ConfigError naming the file, the line,
    the key (``device.geometry`` or ``device.geometry.l1``) and the valid forms."""
    from hapsim.kinematics import PantographGeometry
    if "geometry" not in d:
        return next(iter(presets))
    v = d["geometry"]
    where = f"{key}.geometry"
    line = r.line_of(d, "geometry")
    names = ", ".join(presets)
    forms = (f"a preset ({names}) or a mapping of the five lengths "
             "{l1, l2, L1, L2, d} [m]" if kind == "pantograph" else f"a preset ({names})")
    if isinstance(v, str):
        if v not in presets:
            raise r.error(f"unknown value {show(v)}; valid forms: {forms}", line, where)
        return v
    if kind != "pantograph" or not isinstance(v, dict):
        got = type_name(v) + ("" if v is None else f" {show(v)}")
        raise r.error(f"must be {forms}, got {got}", line, where)
    r.keys(v, PANTOGRAPH_GEOMETRY_KEYS, where, required=PANTOGRAPH_GEOMETRY_KEYS)
    vals = {k: r.number(v, k, where, minimum=0.0, strict=(k != "d"), unit="m")
            for k in PANTOGRAPH_GEOMETRY_KEYS}
    return PantographGeometry(**vals)


def _jacobian_regular(dev, q) -> bool:
    """Whether the device's Jacobian at ``q`` is finite and well conditioned (``cond(J)``
    below ``1 / sqrt(eps)``: its inverse has half the digits or more)."""
    try:
        J = np.asarray(dev.jacobian(q), float)
        c = float(np.linalg.cond(J))
    except Exception:           # a pose the kinematics refuse: not regular
        return False
    return math.isfinite(c) and c < 1.0 / math.sqrt(np.finfo(float).eps)


def _mass_in_range(r: LineContext, M, line, key: str, what: str = "") -> None:
    """Refuse a device mass matrix whose eigenvalues leave
    :data:`hapsim.scene_schema.MASS_RANGE` (the 1-D device's range, and its reason)."""
    from hapsim.scene_schema import MASS_RANGE
    s = max(float(np.max(np.abs(M))), np.finfo(float).tiny)
    lam = s * np.linalg.eigvalsh(0.5 * (M / s) + 0.5 * (M.T / s))
    if not (MASS_RANGE[0] <= lam[0] and lam[-1] <= MASS_RANGE[1]):
        raise r.error(f"the mass along every direction must be between {MASS_RANGE[0]:g} "
                      f"and {MASS_RANGE[1]:g} kg{what}, got eigenvalues "
                      f"{show([float(x) for x in lam])}", line, key)


def read_device_nd(r: LineContext, doc, n: int, max_delay: int) -> DeviceND:
    """The ``device`` section of a 2-D or 3-D scene, at its operating point.

    Parameters
    ----------
    r : LineContext
        The file read (every refusal names it, the line and the key ``device.*``).
    doc : mapping
        The scene document (line-numbered), holding ``device``.
    n : int
        The scene's dimension, 2 or 3.
    max_delay : int
        The largest ``delay`` [periods] (:data:`hapsim.scene_schema.MAX_DELAY`).

    Returns
    -------
    DeviceND
        A Cartesian device as given, or a kinematic one (pantograph: n = 2, delta: n = 3)
        with its Cartesian mass ``J^-T M_q J^-1 + m_h I`` [kg] and friction
        ``J^-T B_q J^-1 + b_h I`` [N s/m] at the joints given
        (:meth:`hapsim.analysis.ths.MatrixLoop.from_device`; Khatib 1987), its handle
        at their forward kinematics.

    Raises
    ------
    ConfigError
        Unknown or missing keys, a kind of another dimension, masses or frictions not
        symmetric positive (semi-)definite or out of :data:`hapsim.scene_schema.MASS_RANGE`,
        joints the kinematics refuse (singular, unreachable, beyond one turn), values whose
        Cartesian mass or friction is not finite.
    """
    key = "device"
    d = r.mapping(doc["device"], key, r.line_of(doc, "device"))
    kind = r.choice(d, "kind", key, DEVICE_KINDS, default="cartesian")
    need = ("mass",) if kind == "cartesian" else ("joints", "joint_inertia")
    r.keys(d, DEVICE_KEYS[kind], key, required=need)
    # a real number of periods (hapsim.analysis.subsample); a whole one stays an int
    delay = r.number(d, "delay", key, default=1, minimum=0.0, maximum=float(max_delay),
                     unit="periods")
    from hapsim.scene.rules import delay_fraction_refusal
    why = delay_fraction_refusal(delay)
    if why is not None:
        raise r.error(why, r.line_of(d, "delay"), f"{key}.delay")
    if float(delay).is_integer():
        delay = int(delay)
    hold = r.choice(d, "hold", key, ("zoh",), default="zoh")
    if kind == "cartesian":
        M = r.matrix(d, "mass", key, n, None, "kg", definite="positive")
        _mass_in_range(r, M, r.line_of(d, "mass"), f"{key}.mass")
        B0 = r.matrix(d, "friction", key, n, np.zeros((n, n)), "N s/m", definite="semi")
        pos = r.vector(d, "position", key, n)
        return DeviceND(kind, M, B0, pos, delay, hold)
    if DEVICE_DOF[kind] != n:
        raise r.error(f"a {kind} has {DEVICE_DOF[kind]} degrees of freedom; this scene has "
                      f"dimension {n}", r.line_of(d, "kind"), f"{key}.kind")
    from hapsim.errors import KinematicsError
    from hapsim.kinematics import DELTA_PRESETS, PANTOGRAPH_PRESETS, device as make
    presets = PANTOGRAPH_PRESETS if kind == "pantograph" else DELTA_PRESETS
    geometry = _read_geometry(r, d, key, kind, presets)
    q = np.radians(r.vector(d, "joints", key, n, unit="deg"))
    Mq = r.matrix(d, "joint_inertia", key, n, None, "kg m^2", definite="positive")
    Bq = r.matrix(d, "joint_friction", key, n, np.zeros((n, n)), "N m s/rad",
                  definite="semi")
    from hapsim.scene_schema import MASS_RANGE
    mh = r.number(d, "hand_mass", key, default=0.0, minimum=0.0, maximum=MASS_RANGE[1],
                  unit="kg")
    bh = r.number(d, "hand_damping", key, default=0.0, minimum=0.0, unit="N s/m")
    dev = make(kind, geometry)
    try:
        from hapsim.analysis.ths.matrix_loop import MatrixLoop
        with np.errstate(over="ignore", invalid="ignore"):   # refused below when not finite
            loop = MatrixLoop.from_device(dev, q, Mq, Bq, hand_mass=mh, hand_damping=bh,
                                          rate_hz=1.0, delay=0)
        pos = dev.forward(q)
    except (KinematicsError, ConfigError) as exc:
        # a configuration the kinematics refuse, or one so near a singularity that the
        # Cartesian mass is not finite (e.g. a link of 1e-300 m)
        given = ("" if isinstance(geometry, str) else " with the geometry given ("
                 + ", ".join(f"{k} = {getattr(geometry, k):g}" for k in
                             PANTOGRAPH_GEOMETRY_KEYS) + " m)")
        if isinstance(exc, ConfigError) and _jacobian_regular(dev, q):
            # a regular Jacobian: the joint values, not the pose, overflowed the mass
            raise r.error(f"the device's Cartesian mass J^-T M_q J^-1 at these joints is "
                          f"not finite ({exc.key}: {exc.reason}): the joint inertia, "
                          "friction or hand values are beyond the double range",
                          r.line_of(d, "joint_inertia"), f"{key}.joint_inertia") from None
        what = exc.reason if isinstance(exc, KinematicsError) else (
            f"the device's Cartesian mass at these joints is not usable ({exc.key}: "
            f"{exc.reason}): too near a singularity")
        raise r.error(what + given, r.line_of(d, "joints"), f"{key}.joints") from None
    _mass_in_range(r, loop.mass, r.line_of(d, "joint_inertia"), f"{key}.joint_inertia",
                   " (the Cartesian mass J^-T M_q J^-1 at these joints, hand included)")
    if not np.all(np.isfinite(loop.friction)):
        # (a hand_damping of 1e308 with the joint friction mapped: inf; it passed the
        # reader and failed later without file or line, issue 31's fuzz)
        k_bad = "hand_damping" if bh > 0 and "hand_damping" in d else "joint_friction"
        raise r.error("the device's Cartesian friction J^-T B_q J^-1 + hand_damping at these "
                      "joints is not finite: the value is beyond the double range",
                      r.line_of(d, k_bad), f"{key}.{k_bad}")
    return DeviceND(kind, loop.mass, loop.friction, pos, delay, hold, joints=q,
                    geometry=geometry, joint_inertia=Mq, joint_friction=Bq, hand_mass=mh,
                    hand_damping=bh)


def nd_key_without_dimension(doc, top_keys_1d, device_keys_1d, top_keys_nd):
    """The first key of a 2-D or 3-D scene in a file without ``dimension`` (read as 1-D,
    where "unknown key 'kind'" hid why: the fuzz of stop 92 deleted the line).

    Parameters
    ----------
    doc : mapping
        The scene file's top level.
    top_keys_1d, device_keys_1d, top_keys_nd : collection of str
        The 1-D reader's top-level and ``device`` keys, the 2-D/3-D reader's top-level
        keys (:data:`hapsim.scene.reader.TOP_KEYS_ND`).

    Returns
    -------
    (str, mapping, str) or None
        The dotted key, the mapping that holds it and its own key there; None when every
        key is a 1-D scene's.
    """
    for k in doc:
        if k in top_keys_nd and k not in top_keys_1d:
            return k, doc, k
    dev = doc.get("device")
    if isinstance(dev, dict):
        nd = {k for keys in DEVICE_KEYS.values() for k in keys}
        for k in dev:
            if k in nd and k not in device_keys_1d:
                return f"device.{k}", dev, k
    for i, m in enumerate(doc.get("masses") if isinstance(doc.get("masses"), list) else ()):
        for k in ("x0", "v0"):              # a position or velocity given as a vector
            if isinstance(m, dict) and isinstance(m.get(k), list):
                return f"masses[{i}].{k}", m, k
    exc, aud = doc.get("excitation"), doc.get("audio")
    if isinstance(exc, dict) and "direction" in exc:
        return "excitation.direction", exc, "direction"
    listen = aud.get("listen") if isinstance(aud, dict) else None
    for i, it in enumerate(listen if isinstance(listen, list) else ()):
        if isinstance(it, dict) and "axis" in it:           # a listening point's axis
            return f"audio.listen[{i}].axis", it, "axis"
    return None
