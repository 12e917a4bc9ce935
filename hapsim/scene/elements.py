"""The elements of a scene: the masses, links, device, hand, excitation, safety and
sound sections as frozen dataclasses (what :class:`~hapsim.scene.Scene` is made of), and
the audio sub-step count. Values only: :mod:`hapsim.scene.rules` checks them, when a
:class:`~hapsim.scene.Scene` holding them is built.

A 2-D or 3-D scene (:class:`~hapsim.scene.SceneND`) is made of :class:`MassND`,
:class:`LinkND`, :class:`PlaneND`, :class:`DeviceND`, :class:`ListenND` and
:class:`ExcitationND`, with vectors and matrices where the 1-D ones hold numbers; the
reader (:func:`hapsim.scene.parse_scene_nd`) checks them as it builds them."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hapsim.drivers import DEFAULT

__all__ = ["Mass", "Link", "Device", "Hand", "CORRECTIONS", "Impulse", "Excitation", "Safety",
           "Listen", "Audio", "audio_substeps", "device_from_dict", "excitation_from_dict", "MassND", "LinkND", "PlaneND", "DeviceND",
           "ListenND", "ExcitationND", "SafetyND"]

#: Corrections of the virtual element and their parameters (hapsim.analysis.corrections).
CORRECTIONS = {"velocity_sensor": (), "velocity_filter": ("cutoff_hz",),
               "prediction": ("horizon",), "inertia_compensation": ("mass",),
               "virtual_coupling": ("stiffness", "damping")}



@dataclass(frozen=True)
class Mass:
    """One point of the network.

    Parameters
    ----------
    name : str
        Unique name.
    kind : {"mass", "ground", "port"}
        ``mass`` moves under the forces on it; ``ground`` is a fixed point; ``port`` is
        moved by the device position and its force is sent to the device.
    mass : float
        Inertia [kg], > 0 for ``mass``; 0.0 for ``ground`` and ``port``.
    x0 : float
        Initial position [m].
    v0 : float
        Initial velocity [m/s] (``mass`` only).
    line : int
        Line of the entry in the scene file (0 when built in code).
    """

    name: str
    kind: str
    mass: float = 0.0
    x0: float = 0.0
    v0: float = 0.0
    line: int = 0


@dataclass(frozen=True)
class Link:
    """One interaction between two masses.

    Parameters
    ----------
    name : str
        Unique name.
    kind : {"spring_damper", "contact"}
        ``contact`` acts only while ``x2 - x1 < threshold``, with its spring force
        ``K (x1 - x2 + threshold)`` (Faust 2.54 ``mi.lib`` ``collision``).
    m1, m2 : str
        Names of the first and second mass (order fixes the sign convention).
    stiffness : float
        Virtual stiffness K [N/m], >= 0; NaN while a ``target`` awaits calibration.
    damping : float
        Virtual damping B [N s/m], >= 0; NaN while a ``target`` awaits calibration.
    threshold : float
        Contact threshold [m] (``contact`` only; 0.0 otherwise).
    target : tuple of float, optional
        Felt (k [N/m], b [N s/m]) the daemon calibrates (K, B) for; ``spring_damper``
        between the port and a ground only.
    line : int
        Line of the entry in the scene file (0 when built in code).
    calibrated : bool
        True when (K, B) were written by calibration (:meth:`Scene.with_link`): the
        damping may then be negative, because the device's real friction b0 can exceed
        the damping to be felt (docs/design.md, 'The forward map'). A scene file cannot set
        it.
    """

    name: str
    kind: str
    m1: str
    m2: str
    stiffness: float = 0.0
    damping: float = 0.0
    threshold: float = 0.0
    target: tuple[float, float] | None = None
    line: int = 0
    calibrated: bool = False


@dataclass(frozen=True)
class Device:
    """The real side of the temporary hybrid system, as the scene describes it.

    Parameters
    ----------
    mass : float
        Moving mass m of hand + handle [kg], in [1e-12, 1e12].
    friction : float
        Real viscous friction b0 [N s/m], >= 0, with b0 T / m <= 1e6.
    delay : int or float
        Delay d from the sample a force is computed from to the instant the force takes
        effect [periods], 0 to 500 (the analysis's cost: O(d^3)): an int for a whole
        delay (the plain hold), a float ``m + f`` for the split hold
        (:mod:`hapsim.analysis.subsample`).
    hold : {"zoh", "ideal"}
        Zero-order hold of the force, or the paper's idealised sampled image.
    force_limit : float
        Largest force magnitude sent to the device [N]; ``inf`` when none.
    position_resolution : float
        Encoder quantum of the mock device [m]; 0 for none.
    coulomb : float
        Coulomb friction of the mock device [N]; 0 for none.
    noise : float
        Standard deviation of the mock device's position noise [m]; 0 for none.
    velocity_resolution : float
        Quantum of the mock device's velocity sensor (VELOCITY frames) [m/s]; 0 for none.
    velocity_noise : float
        Standard deviation of the mock device's velocity-sensor noise [m/s]; 0 for none.
    hand : Hand, optional
        The hand holding the handle; then ``mass`` and ``friction`` are the handle's alone.
    correction : dict, optional
        ``{"kind": name, param: value, ...}``, a correction of the virtual element
        (:data:`CORRECTIONS`, :mod:`hapsim.analysis.corrections`).
    protocol : str
        The protocol the device speaks on its port, one of :data:`PROTOCOLS`
        (``"framed"``, hapsim's own, by default).
    protocol_options : dict, optional
        The device's parameters in its driver's terms (the keywords of the driver's
        constructor, :mod:`hapsim.drivers`: FireFader ``full_scale``, ``metres_per_count``,
        ``axis``; Haply ``resolution``, ``direction``, ``motor_direction``, ``device_id``,
        ``offset_deg``;
        Hapkit-serial ``function``, ``force_limit``); a driver's protocol only.
    """

    mass: float
    friction: float = 0.0
    delay: int | float = 1
    hold: str = "zoh"
    force_limit: float = math.inf
    position_resolution: float = 0.0
    coulomb: float = 0.0
    noise: float = 0.0
    velocity_resolution: float = 0.0
    velocity_noise: float = 0.0
    hand: "Hand | None" = None
    correction: dict | None = None
    protocol: str = DEFAULT
    protocol_options: dict | None = None


@dataclass(frozen=True)
class Hand:
    """The hand on the handle: a mass tied to the handle by a grip spring-damper.

    Each field is a number or a range ``(lo, hi)`` (a family of THS, Florens et al. Sec. 4).

    Parameters
    ----------
    mass : float or (float, float)
        Hand mass [kg], > 0.
    damping : float or (float, float)
        Hand damping to ground (the arm) [N s/m], >= 0.
    grip_stiffness : float or (float, float)
        Grip spring between hand and handle [N/m], > 0; ``inf`` for a rigid grip (then
        the hand mass and damping add to the handle's).
    grip_damping : float or (float, float)
        Grip damper between hand and handle [N s/m], >= 0.
    stiffness : float or (float, float)
        Hand (arm) stiffness to ground [N/m], >= 0 (Hogan's arm impedance: mass, damping,
        stiffness): a real spring in the THS (:mod:`hapsim.analysis.hand`).
    """

    mass: Any
    damping: Any = 0.0
    grip_stiffness: Any = math.inf
    grip_damping: Any = 0.0
    stiffness: Any = 0.0

    @property
    def rigid(self) -> bool:
        """Whether the grip is rigid (``grip_stiffness`` is ``inf``)."""
        return isinstance(self.grip_stiffness, float) and math.isinf(self.grip_stiffness)


@dataclass(frozen=True)
class Impulse:
    """A rectangular force pulse applied by the hand on the (mock) device.

    Parameters
    ----------
    force : float
        Pulse height [N], finite.
    start : float
        Time the pulse starts [s], >= 0.
    duration : float
        Pulse length [s], >= 0 (0: no pulse).
    """

    force: float
    start: float = 0.0
    duration: float = 0.0


@dataclass(frozen=True)
class Excitation:
    """How the (mock) device's hand sets the closed loop in motion.

    Parameters
    ----------
    x0 : float
        Initial device displacement [m].
    v0 : float
        Initial device velocity [m/s].
    impulse : Impulse, optional
        A force pulse from the hand.
    profile : str, optional
        Path of a recorded hand-force profile (``.csv`` or ``.npz``: time [s], force [N]),
        resolved relative to the scene file.
    """

    x0: float = 0.0
    v0: float = 0.0
    impulse: Impulse | None = None
    profile: str | None = None


def device_from_dict(d: dict) -> Device:
    """The :class:`Device` of ``dataclasses.asdict(device)`` sent as JSON (an emulated
    board's start-up spec): its hand a :class:`Hand` again (its ranges tuples), a
    ``force_limit`` of None (JSON's) infinite.

    Parameters
    ----------
    d : dict
        The device's fields, as JSON gives them back.

    Returns
    -------
    Device

    Raises
    ------
    TypeError
        A key that is no field of :class:`Device` or :class:`Hand`.
    """
    d = dict(d)
    if d.get("force_limit") is None:
        d["force_limit"] = math.inf
    if isinstance(d.get("hand"), dict):      # (a dict in JSON: read as no hand at all, a
        # hand of mass 0, it stopped the board the Haply driver's run embeds)
        d["hand"] = Hand(**{k: tuple(v) if isinstance(v, list) else v
                            for k, v in d["hand"].items()})
    return Device(**d)


def excitation_from_dict(e: dict) -> Excitation:
    """The :class:`Excitation` of ``dataclasses.asdict(excitation)`` sent as JSON: its
    impulse an :class:`Impulse` again; keys that are no field are left out.

    Parameters
    ----------
    e : dict

    Returns
    -------
    Excitation
    """
    fields = Excitation.__dataclass_fields__
    e = {k: v for k, v in e.items() if k in fields}
    if isinstance(e.get("impulse"), dict):
        e["impulse"] = Impulse(**e["impulse"])
    return Excitation(**e)


@dataclass(frozen=True)
class Safety:
    """Limits ``hapsim run`` enforces on the device (scene section ``safety:``).

    Parameters
    ----------
    position_limit : float or None
        Safety stop when ``|x|`` exceeds it [m]; None: ``max(0.1, 20 |excitation.x0|)``.
    velocity_limit : float
        Safety stop when the backward-difference velocity ``|v|`` exceeds it [m/s];
        ``inf``: none.
    energy_limit : float
        Safety stop when the passivity observer says the scene has given the hand this
        much energy [J] (Hannaford & Ryu 2002; see :mod:`hapsim.host.loop`).
    passivity_controller : bool
        Add the adaptive damping ``alpha = E / (T v^2)`` while ``E``, the energy given
        to the hand beyond what the scene stored at its (re)start, is positive.
    max_damping : float
        Cap of the adaptive damping [N s/m].
    brake : bool
        Brake the device to rest after a safety stop on its motion, before the zero force
        (:meth:`hapsim.host.recovery.Recovery._brake`); False: zero force at once.
    """

    position_limit: float | None = None
    velocity_limit: float = math.inf
    energy_limit: float = 1.0
    passivity_controller: bool = False
    max_damping: float = 50.0
    brake: bool = True


@dataclass(frozen=True)
class Listen:
    """One listening point of a scene's sound (scene section ``audio.listen``).

    Parameters
    ----------
    mass : str
        Name of the mass listened to.
    quantity : {"velocity", "position", "force"}
        What is heard: its backward-difference velocity ``(x[k] - x[k-1]) / Ta`` [m/s], its
        position [m] or the force on it [N], at every audio sample ``k``.
    gain : float
        Factor from that quantity to the output sample (full scale 1.0), finite.
    """

    mass: str
    quantity: str = "velocity"
    gain: float = 1.0


@dataclass(frozen=True)
class Audio:
    """The sound of a scene (section ``audio:``): a multi-rate model.

    Every virtual mass runs at the audio rate ``rate_hz`` (period ``Ta = 1 / rate_hz``);
    the device couples at the scene's rate (period ``T = N Ta``, ``N`` a whole number).
    Within device period ``n`` the port position at audio sub-step ``j = 0 .. N-1`` is
    ``p[n]`` (``"hold"``, a zero-order hold of the device sample) or
    ``p[n-1] + (j + 1) / N (p[n] - p[n-1])`` (``"linear"``, the miPhysics-style smoothing
    of the haptic input); the force sent to the device is the mean of the N sub-step port
    forces (``"mean"``, a boxcar decimator) or the last one (``"last"``). The closed-loop
    analysis (:func:`hapsim.analysis.network.closed_loop`) composes these N audio steps into
    one device-rate map, so ``check`` and the felt (k, b) stay exact for this model.

    Parameters
    ----------
    rate_hz : float
        Audio rate [Hz]: a whole multiple of the scene's ``rate_hz``.
    listen : tuple of Listen
        Listening points, one output channel each (non-empty).
    port_position : {"hold", "linear"}
        Port position up to the audio rate. With ``"hold"`` and ``"mean"`` a port-ground
        link renders exactly as at the device rate (so felt targets calibrate as there).
    port_force : {"mean", "last"}
        Port force down to the device rate.
    """

    rate_hz: float
    listen: tuple[Listen, ...]
    port_position: str = "hold"
    port_force: str = "mean"

    def __post_init__(self) -> None:
        if isinstance(self.listen, list):
            object.__setattr__(self, "listen", tuple(self.listen))

    @property
    def period(self) -> float:
        """Audio sample period Ta = 1 / rate_hz [s]."""
        return 1.0 / self.rate_hz




#: Most audio sub-steps per device period: 10000 (e.g. 192 kHz audio over a 19.2 Hz
#: loop). The check's multirate map and the engine's audio buffers grow with it; a ratio of
#: 1e6 kept ``hapsim check`` silent for minutes and one of 4.8e13 asked ``simulate`` for
#: 349 TiB (issue 31's fuzz).
MAX_AUDIO_SUBSTEPS = 10000


def audio_substeps(audio_rate: float, rate_hz: float) -> int:
    """Audio sub-steps per device period, ``N = audio_rate / rate_hz``.

    Parameters
    ----------
    audio_rate, rate_hz : float
        Audio and device rates [Hz].

    Returns
    -------
    int
        N >= 1.

    Raises
    ------
    ValueError
        When the ratio is not a whole number >= 1 (to 1e-9 relative), or is above
        :data:`MAX_AUDIO_SUBSTEPS`.
    """
    r = float(audio_rate) / float(rate_hz)
    n = round(r)
    if n < 1 or abs(r - n) > 1e-9 * r:
        raise ValueError(f"the audio rate {audio_rate:g} Hz must be a whole multiple of "
                         f"rate_hz {rate_hz:g} Hz (ratio {r:g})")
    if n > MAX_AUDIO_SUBSTEPS:
        raise ValueError(f"the audio rate {audio_rate:g} Hz is {r:g} times rate_hz "
                         f"{rate_hz:g} Hz; valid: at most {MAX_AUDIO_SUBSTEPS} audio steps "
                         f"per device period (audio.rate_hz <= "
                         f"{MAX_AUDIO_SUBSTEPS * float(rate_hz):g} Hz here)")
    return int(n)


@dataclass(frozen=True)
class MassND:
    """A point of an n-D scene: ``kind`` in mass/ground/port, ``mass`` [kg] (0 unless
    ``mass``), rest position ``x0`` [m] and velocity ``v0`` [m/s] (shape (n,))."""

    name: str
    kind: str
    mass: float
    x0: np.ndarray
    v0: np.ndarray
    line: int | None = None


@dataclass(frozen=True)
class LinkND:
    """A link of an n-D scene (its law: :mod:`hapsim.scene`, 'Link laws in two and three
    dimensions'): stiffness ``K`` [N/m],
    damping ``B`` [N s/m], rest ``length`` [m] (spring_damper) or ``threshold`` [m]
    (contact)."""

    name: str
    kind: str
    m1: str
    m2: str
    stiffness: float
    damping: float
    length: float
    threshold: float
    line: int | None = None


@dataclass(frozen=True)
class PlaneND:
    """A plane contact: unit ``normal``, ``offset`` [m] (the plane ``normal . x =
    offset``), ``stiffness`` [N/m], ``damping`` [N s/m], the ``masses`` it acts on."""

    name: str
    normal: np.ndarray
    offset: float
    stiffness: float
    damping: float
    masses: tuple
    line: int | None = None


@dataclass(frozen=True)
class DeviceND:
    """The device of an n-D scene, at its operating point.

    Attributes
    ----------
    kind : {"cartesian", "pantograph", "delta"}
    mass : ndarray, shape (n, n)
        Cartesian mass of hand + handle [kg] (for a kinematic device, ``J^-T M_q J^-1``
        plus the hand's).
    friction : ndarray, shape (n, n)
        Cartesian friction [N s/m].
    position : ndarray, shape (n,)
        The handle's rest position [m].
    delay : int or float
        [periods]: an int for a whole delay, a float ``m + f`` for the split hold
        (:mod:`hapsim.analysis.subsample`).
    hold : str
        ``"zoh"``.
    joints : ndarray or None
        Operating point [rad] of a kinematic device.
    geometry : str, hapsim.kinematics.PantographGeometry or None
        Its preset's name, or a pantograph's lengths given as numbers.
    joint_inertia, joint_friction : ndarray, shape (n, n), or None
        A kinematic device's joint-space inertia [kg m^2] and friction [N m s/rad].
    hand_mass, hand_damping : float
        The hand's isotropic mass [kg] and damping [N s/m] (in ``mass``, ``friction``).
    """

    kind: str
    mass: np.ndarray
    friction: np.ndarray
    position: np.ndarray
    delay: int | float
    hold: str
    joints: np.ndarray | None = None
    geometry: Any = None
    joint_inertia: np.ndarray | None = None
    joint_friction: np.ndarray | None = None
    hand_mass: float = 0.0
    hand_damping: float = 0.0


@dataclass(frozen=True)
class ListenND:
    """A listening point of an n-D scene: the ``axis`` (0..n-1) component of a mass's
    ``quantity`` (``"position"`` [m] or ``"velocity"`` [m/s], the backward difference
    ``(x[n] - x[n-1]) / T``) times ``gain`` [-] is one channel of the sound."""

    mass: str
    axis: int
    quantity: str
    gain: float
    line: int | None = None


@dataclass(frozen=True)
class ExcitationND:
    """The hand's force on the device's mass in an n-D scene: the 1-D excitation's
    ``impulse`` (:class:`Impulse`, [N], [s]) and/or ``profile`` (a
    file of time [s], force [N]; an absolute path) acting along the unit ``direction``
    (shape (n,)): force vector ``h(t) direction`` (``h`` as
    :func:`hapsim.device_model.hand_force_samples` samples it)."""

    direction: np.ndarray
    impulse: object | None = None
    profile: str | None = None
    line: int | None = None


@dataclass(frozen=True)
class SafetyND:
    """What a 2-D or 3-D run does after a stop on the device's motion (scene section
    ``safety:``).

    Attributes
    ----------
    brake : bool
        Brake the joints to rest (:mod:`hapsim.braking`: ``tau = -B q'``, ``B = g M_q /
        T``, at most :data:`hapsim.braking.BRAKE_MAX_S`) before the zero torque, after a
        stop on the motion (the 2DIY's joints out of the measurement's envelope, the
        Falcon's legs out of their envelope or the host too late for it); False: zero
        torque at once.
    """

    brake: bool = True
