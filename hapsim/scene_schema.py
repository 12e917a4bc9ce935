"""The scene format as one declarative table: every key, its type, unit, default and range.

:mod:`hapsim.scene` reads and checks scene files from this table (valid keys, defaults,
types, ranges, choices), and :mod:`hapsim.scene_doc` writes ``docs/scenes.md`` from it, so
the reference and the validator cannot drift. **Adding a key to a scene means adding a row
to** :data:`KEYS` (and, for a key of a dataclass section, the field of the same name; a test
checks that every row has its field with the same default, and that every row's example
loads). A rule that spans several keys (a target only between the port and a ground, no
contact with the exact integrator, ...) is code in :func:`hapsim.scene.rules.check_scene`; its
one-line statement for the reference is in :data:`CROSS_RULES`.

Paths: ``rate_hz`` (top level), ``device.friction`` (a key of a section),
``masses[].x0`` (a key of each entry of a list), ``links[].target.k`` (nested).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

from hapsim.drivers import DRIVERS
from hapsim.errors import ConfigError

__all__ = ["Key", "Section", "KEYS", "SECTIONS", "CROSS_RULES", "REQUIRED", "key",
           "section_keys", "key_names", "MASS_KINDS", "LINK_KINDS", "HOLDS", "PROTOCOLS",
           "INTEGRATORS", "BASE_SCENE", "LISTEN_QUANTITIES", "PORT_POSITION_MODES",
           "PORT_FORCE_MODES", "check_product"]

#: Mass kinds a scene may use.
MASS_KINDS = ("mass", "ground", "port")
#: Link kinds a scene may use.
LINK_KINDS = ("spring_damper", "contact")
#: Output holds a device may use (docs/design.md, 'The timing convention').
HOLDS = ("zoh", "ideal")
#: Protocols a device may speak: :data:`hapsim.drivers.DRIVERS`, the 1-D families of the
#: drivers' registry (first is the default: hapsim's own framed protocol).
PROTOCOLS = DRIVERS
#: Integrators of the virtual masses (first is the default; hapsim.kernels.schemes).
INTEGRATORS = ("centred", "symplectic_euler", "exact")

# The analysis's valid ranges (re-exported by hapsim.analysis.loop, which checks them;
# here, at the bottom of the house, so that a key's ``limits_from`` names them without
# importing the analysis).

#: Largest delay [samples] the analysis accepts. The closed loop has ``d + 3`` poles, found
#: as the eigenvalues of a dense ``(d + 3)``-square companion (state) matrix: ``O(d^3)``
#: time, about 0.4 s at ``d = 500`` on one idle core (1.7 s at 1000, several times more on a
#: loaded machine), and a stability limit needs several of them. 500 samples is 0.5 s at
#: 1 kHz, 50 ms at 10 kHz: beyond the loops a haptic device closes (a 16 ms USB latency
#: timer is 16 samples at 1 kHz, 80 at 5 kHz).
MAX_DELAY = 500
#: The smallest fraction of a period a sub-sample delay takes [-]: a delay whose fraction,
#: or whose distance to the next whole period, is below it (``0 < f < MIN_DELAY_FRACTION``)
#: is refused with its key: it is no timing a clock resolves (1 ps at 1 kHz), most likely
#: a typing slip. (The scene fuzz found ``delay: 1e-308`` giving ``hapsim check`` a
#: linear-algebra traceback, the split hold's first piece a subnormal time; the hold's
#: matrices are now exact there too, :func:`hapsim.analysis.hand._phi1_balanced`, and the
#: analysis' own loops, ``hapsim render --delay`` and :class:`hapsim.analysis.loop.
#: LoopModel` take any fraction: a loop built from a sum of delays may land a round-off
#: from a whole period.)
MIN_DELAY_FRACTION = 1e-9
#: Valid sample rates [Hz]: one sample per ~11.6 days to 1 GHz. Outside, ``T``, ``T^2``
#: or ``1/T^2`` leave the double range long before any product is formed.
RATE_RANGE = (1e-6, 1e9)
#: Valid masses [kg] (device and virtual): 1 ng to 1e12 kg; a subnormal mass turns every
#: ``T^2 / m`` into inf.
MASS_RANGE = (1e-12, 1e12)
#: Largest magnitude of the dimensionless loop products ``K T^2 / m`` (the spring's
#: ``(omega T)^2``), ``B T / m`` and ``b0 T / m`` (damping per sample). Beyond 1e6 the spring
#: rings a thousand times per sample or the damper settles in a millionth of one: no sampled
#: loop renders that (every K above ``4 m / T^2`` is already unstable), and the
#: characteristic coefficients would span more than the double range can resolve.
MAX_PRODUCT = 1e6


def check_product(value: float, scale: float, key: str, unit: str, what: str) -> None:
    """Refuse ``|value| * scale > MAX_PRODUCT`` (a dimensionless loop product).

    Parameters
    ----------
    value : float
        Physical value, e.g. ``K`` [N/m].
    scale : float
        Its factor to the dimensionless product, e.g. ``T^2 / m``.
    key : str
        Option or scene key named in the message.
    unit : str
        Unit of ``value``.
    what : str
        The product's formula, e.g. ``"K T^2/m"``.

    Raises
    ------
    ConfigError
        Naming the valid maximum ``MAX_PRODUCT / scale`` in ``unit``.
    """
    if abs(value) * scale > MAX_PRODUCT:
        raise ConfigError(f"{value:g} {unit} is too large for this loop: |{what}| = "
                          f"{abs(value) * scale:.3g} > {MAX_PRODUCT:g}; valid: |value| <= "
                          f"{MAX_PRODUCT / scale:.6g} {unit} (at this mass and rate)", key=key)


#: What a listening point hears (``audio.listen[i].quantity``; first is the default).
LISTEN_QUANTITIES = ("velocity", "position", "force")
#: How the port position is brought up to the audio rate (first is the default).
PORT_POSITION_MODES = ("hold", "linear")
#: How the port force is brought down to the device rate (first is the default).
PORT_FORCE_MODES = ("mean", "last")


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: Default of a key that must be given.
REQUIRED = _Required()

#: Value types a row may have: checked generically ("number", "integer", "choice", "string",
#: "boolean") or by the code of its section ("list", "mapping", "pair").
TYPES = ("number", "integer", "choice", "string", "boolean", "list", "mapping", "pair")


@dataclass(frozen=True)
class Key:
    """One key of the scene format (a row of :data:`KEYS`).

    Parameters
    ----------
    path : str
        Where the key lives: ``rate_hz``, ``device.friction``, ``masses[].x0``,
        ``links[].target.k``.
    type : str
        One of :data:`TYPES`.
    unit : str
        SI unit in brackets' words (``"N s/m"``), ``""`` for none.
    default : object
        Value when the key is absent; :data:`REQUIRED` when it must be given; None when
        absence means "none" (then ``null`` is refused: leave the key out).
    minimum : float, optional
        Smallest value allowed (numbers, integers).
    strict : bool
        ``minimum`` itself excluded (``> minimum`` instead of ``>= minimum``).
    maximum : float, optional
        Largest value allowed (numbers, integers).
    allow_inf : bool
        ``.inf`` allowed (a number that is otherwise finite).
    choices : tuple of str
        Valid values of a ``choice``.
    kinds : tuple of str
        For ``masses[]`` / ``links[]`` keys: the kinds that take the key (empty: all).
    doc : str
        What the key means (one or two sentences, for the reference).
    example : str
        A one-line YAML fragment using the key; merged into :data:`BASE_SCENE` it must load
        (mappings merged, list entries appended, an entry with the same name replaced).
    default_doc : str
        How the reference states the default when it is not a plain value.
    limits_from : str
        Name of a limit of :mod:`hapsim.analysis.loop` the value must also keep: a
        ``(lo, hi)`` tuple (``RATE_RANGE``) or a largest value (``MAX_DELAY``); it lives
        there, beside the analysis it protects, and is read when a scene is checked.
    why : str
        Why the range's largest value is what it is (appended to the message of a value
        above it, for the ``limits_from`` limit when there is one, and shown in the
        reference); ``{limit}`` stands for the largest value.
    """

    path: str
    type: str
    unit: str = ""
    default: Any = REQUIRED
    minimum: float | None = None
    strict: bool = False
    maximum: float | None = None
    allow_inf: bool = False
    choices: tuple = ()
    kinds: tuple = ()
    doc: str = ""
    example: str = ""
    default_doc: str = ""
    limits_from: str = ""
    why: str = ""

    @property
    def section(self) -> str:
        """Path of the section holding the key (``""`` at the top level)."""
        return self.path.rpartition(".")[0]

    @property
    def name(self) -> str:
        """The key as written in the file (last part of :attr:`path`)."""
        return self.path.rpartition(".")[2]

    @property
    def required(self) -> bool:
        """True when the key must be given."""
        return self.default is REQUIRED

    def analysis_limits(self) -> tuple:
        """``(lo, hi)`` of :attr:`limits_from` (``(None, None)`` without one).

        Returns
        -------
        tuple
            Smallest and largest value [the key's unit]; either may be None.
        """
        if not self.limits_from:
            return (None, None)
        v = globals()[self.limits_from]
        return tuple(v) if isinstance(v, tuple) else (None, v)

    def why_text(self) -> str:
        """:attr:`why` with ``{limit}`` filled in.

        Returns
        -------
        str
            ``{limit}``: the analysis limit's upper bound, else :attr:`maximum` (``%g``).
        """
        return self.why.format(limit=f"{self.analysis_limits()[1] or self.maximum:g}")

    def range_text(self) -> str:
        """The allowed values in words (``"> 0"``, ``"> 0, .inf allowed"``, ``"zoh | ideal"``).

        Returns
        -------
        str
            The parts joined by ``", "`` (a choice's values by ``" | "``); may be empty.
        """
        if self.type == "choice":
            return " | ".join(self.choices)
        parts = []
        if self.minimum is not None:
            parts.append(f"{'>' if self.strict else '>='} {self.minimum:g}")
        if self.maximum is not None:
            parts.append(f"<= {self.maximum:g}")
        lo, hi = self.analysis_limits()
        if lo is not None and hi is not None:
            parts.append(f"in [{lo:g}, {hi:g}]")
        elif hi is not None:
            parts.append(f"<= {hi:g}")
        if self.type == "integer":
            parts.append("whole number")
        elif self.type == "number":
            parts.append("finite" if not parts else "")
            if self.allow_inf:
                parts.append(".inf allowed")
        elif self.type == "boolean":
            parts.append("true | false")
        return ", ".join(p for p in parts if p)

    def default_text(self) -> str:
        """The default in words (``"required"``, ``"none"``, ``"0"``, ``"zoh"``).

        Returns
        -------
        str
            :attr:`default_doc` when set, else the default as the docs print it.
        """
        if self.default_doc:
            return self.default_doc
        if self.required:
            return "required"
        d = self.default
        if d is None:
            return "none"
        if isinstance(d, bool):
            return "true" if d else "false"
        if isinstance(d, float) and math.isinf(d):
            return "none (.inf)"
        if isinstance(d, float):
            return f"{d:g}"
        if d == ():
            return "empty"
        return str(d)


@dataclass(frozen=True)
class Section:
    """A section of the reference: title, what it is, and a complete example scene.

    Parameters
    ----------
    path : str
        Section path (``""``, ``masses[]``, ``device``, ...), as in :attr:`Key.section`.
    title : str
        Heading in the reference.
    doc : str
        What the section describes (Markdown).
    example : str
        A complete scene (YAML) showing the section; the tests load it.
    """

    path: str
    title: str
    doc: str
    example: str = ""


_P = ("port",)
_KEYS = [
    # ------------------------------------------------------------------ top level
    Key("rate_hz", "number", "Hz", minimum=0.0, strict=True, limits_from="RATE_RANGE",
        doc="Sample rate of the simulation and of the device loop; the period is "
            "T = 1 / rate_hz.",
        example="rate_hz: 2000"),
    Key("masses", "list",
        doc="The points of the network, in order (non-empty); see `masses[]`.",
        example="masses: [{name: bob, kind: mass, mass: 0.01}]"),
    Key("links", "list", default=(),
        doc="The interactions between masses, in order; see `links[]`.",
        example="links: [{name: spring, kind: spring_damper, between: [hand, wall], "
                "stiffness: 800, damping: 1}]"),
    Key("device", "mapping", default=None, default_doc="required with a port",
        doc="The device the scene is felt through; see `device`.",
        example="device: {mass: 0.2, friction: 0.3}"),
    Key("excitation", "mapping", default=None, default_doc="all zero",
        doc="How the (mock) device's hand starts the motion; see `excitation`.",
        example="excitation: {x0: 0.003}"),
    Key("integrator", "choice", default=INTEGRATORS[0], choices=INTEGRATORS,
        doc="Integrator of the virtual masses (hapsim.kernels.schemes); `exact` takes "
            "linear links only (no contact).",
        example="integrator: symplectic_euler"),
    Key("safety", "mapping", default=None, default_doc="the defaults below",
        doc="Limits `hapsim run` enforces; see `safety`.",
        example="safety: {velocity_limit: 1.0}"),
    Key("audio", "mapping", default=None,
        doc="The scene's sound: a multi-rate model and its listening points; see `audio`.",
        example="audio: {rate_hz: 8000, listen: [{mass: hand}]}"),
    Key("dimension", "integer", default=1, minimum=1, maximum=3,
        doc="Degrees of freedom of the scene: 1 is this format; 2 and 3 are the planar and "
            "spatial format of `hapsim.scene.load_scene_nd` (vector positions, Euclidean links, "
            "planes, kinematic devices: the pantograph and the delta), which `hapsim "
            "check`, `run`, `simulate`, `mock --scene` and `play` take; its keys and laws "
            "are in [Two and three dimensions](dimensions.md#scenes-in-2-and-3-dimensions), "
            "among them `engine: {precision: single}`, the engine in float32 "
            "([Single precision](dimensions.md#single-precision): twice as fast on a mesh; "
            "default `double`).",
        example="dimension: 1"),
    # ------------------------------------------------------------------ masses[]
    Key("masses[].name", "string",
        doc="Unique name of the mass (links refer to it).",
        example="masses: [{name: bob, kind: mass, mass: 0.01}]"),
    Key("masses[].kind", "choice", choices=MASS_KINDS,
        doc="`mass` moves under the forces on it; `ground` is a fixed point; `port` is "
            "moved by the device position and its force is sent to the device (at most "
            "one).",
        example="masses: [{name: anchor, kind: ground, x0: 0.01}]"),
    Key("masses[].mass", "number", "kg", minimum=0.0, strict=True, kinds=("mass",),
        limits_from="MASS_RANGE",
        doc="Inertia of a `mass`.",
        example="masses: [{name: bob, kind: mass, mass: 0.05}]"),
    Key("masses[].x0", "number", "m", default=0.0, kinds=("mass", "ground"),
        doc="Initial position (the fixed position of a `ground`).",
        example="masses: [{name: bob, kind: mass, mass: 0.01, x0: 0.002}]"),
    Key("masses[].v0", "number", "m/s", default=0.0, kinds=("mass",),
        doc="Initial velocity of a `mass`.",
        example="masses: [{name: bob, kind: mass, mass: 0.01, v0: 0.1}]"),
    # ------------------------------------------------------------------ links[]
    Key("links[].name", "string", default="", default_doc="link0, link1, ... (its index)",
        doc="Unique name of the link (`hapsim run` reports the port link by name).",
        example="links: [{name: w2, kind: spring_damper, between: [hand, wall], "
                "stiffness: 10}]"),
    Key("links[].kind", "choice", choices=LINK_KINDS,
        doc="`spring_damper` always acts; `contact` acts only while x2 - x1 < threshold "
            "(Faust mi.lib `collision`).",
        example="links: [{kind: contact, between: [hand, wall], stiffness: 500}]"),
    Key("links[].between", "pair",
        doc="The two masses joined, [first, second]: F = K (x1 - x2) + B ((x1 - x2) - "
            "(x1p - x2p)) / T acts as -F on the first, +F on the second.",
        example="links: [{kind: spring_damper, between: [wall, hand], stiffness: 10}]"),
    Key("links[].stiffness", "number", "N/m", default=0.0, minimum=0.0,
        doc="Virtual stiffness K (a link needs stiffness and/or damping, or a target).",
        example="links: [{kind: spring_damper, between: [hand, wall], stiffness: 300}]"),
    Key("links[].damping", "number", "N s/m", default=0.0, minimum=0.0,
        doc="Virtual damping B.",
        example="links: [{kind: spring_damper, between: [hand, wall], damping: 0.5}]"),
    Key("links[].threshold", "number", "m", default=0.0, kinds=("contact",),
        doc="Gap at which a contact engages; its spring is measured from it, "
            "F = K (x1 - x2 + threshold) + ..., so the force is continuous.",
        example="links: [{kind: contact, between: [hand, wall], stiffness: 500, "
                "threshold: 0.001}]"),
    Key("links[].target", "mapping", default=None, kinds=("spring_damper",),
        doc="A felt (k, b) instead of (K, B): the daemon calibrates (K, B) for the device; "
            "only between the port and a ground, not with stiffness/damping.",
        example="links: [{name: wall, kind: spring_damper, between: [hand, wall], "
                "target: {k: 1000, b: 3}}]"),
    Key("links[].target.k", "number", "N/m", minimum=0.0, strict=True,
        doc="Felt stiffness k.",
        example="links: [{name: wall, kind: spring_damper, between: [hand, wall], "
                "target: {k: 500, b: 2}}]"),
    Key("links[].target.b", "number", "N s/m", minimum=0.0,
        doc="Felt damping b.",
        example="links: [{name: wall, kind: spring_damper, between: [hand, wall], "
                "target: {k: 1000, b: 1}}]"),
    # ------------------------------------------------------------------ device
    Key("device.mass", "number", "kg", minimum=0.0, strict=True, limits_from="MASS_RANGE",
        doc="Moving mass m of hand + handle.",
        example="device: {mass: 0.25}"),
    Key("device.friction", "number", "N s/m", default=0.0, minimum=0.0,
        doc="Real viscous friction b0 of the device.",
        example="device: {mass: 0.1, friction: 0.5}"),
    Key("device.delay", "number", "periods", default=1, minimum=0.0, maximum=float(MAX_DELAY),
        why="the closed loop's d + 3 poles are eigenvalues of a dense (d + 3)-square matrix, "
            "O(d^3), ~0.4 s at d = {limit}",
        doc="Delay d from the sample a force is computed from to the instant the force "
            "takes effect [periods], a real number: a whole d is the plain hold; "
            "d = m + f (0 < f < 1) switches the held force f T into the period (the split "
            "hold, docs/stability.md: e.g. a FireFader at 250 Hz reading its ADC 1.1 ms "
            "after the packet is d = 1 - 1.1/4 = 0.725).",
        example="device: {mass: 0.1, delay: 1.3}"),
    Key("device.hold", "choice", default=HOLDS[0], choices=HOLDS,
        doc="`zoh`: the device holds each force over a period; `ideal`: the paper's "
            "idealised sampled image.",
        example="device: {mass: 0.1, hold: ideal}"),
    Key("device.force_limit", "number", "N", default=math.inf, minimum=0.0, strict=True,
        allow_inf=True,
        doc="Largest force magnitude sent to the device (the host and the mock clamp).",
        example="device: {mass: 0.1, force_limit: 5}"),
    Key("device.position_resolution", "number", "m", default=0.0, minimum=0.0,
        doc="Encoder quantum of the mock device (0: none).",
        example="device: {mass: 0.1, position_resolution: 1.0e-6}"),
    Key("device.coulomb", "number", "N", default=0.0, minimum=0.0,
        doc="Coulomb friction of the mock device (0: none). The run's prediction is "
            "linear and leaves it out: where its equivalent damping, 4 fc / (pi a w) at "
            "the record's weighted amplitude, exceeds the stated interval of b, a "
            "departure is \"not measurable\", never \"differs\".",
        example="device: {mass: 0.1, coulomb: 0.05}"),
    Key("device.noise", "number", "m", default=0.0, minimum=0.0,
        doc="Standard deviation of the mock device's position noise (0: none; seeded).",
        example="device: {mass: 0.1, noise: 1.0e-7}"),
    Key("device.velocity_resolution", "number", "m/s", default=0.0, minimum=0.0,
        doc="Quantum of the mock device's velocity sensor, the VELOCITY frames a "
            "`velocity_sensor` correction reads (0: none).",
        example="device: {mass: 0.1, velocity_resolution: 1.0e-4}"),
    Key("device.velocity_noise", "number", "m/s", default=0.0, minimum=0.0,
        doc="Standard deviation of the mock device's velocity-sensor noise (0: none; "
            "seeded, apart from the position noise).",
        example="device: {mass: 0.1, velocity_noise: 1.0e-4}"),
    Key("device.hand", "mapping", default=None,
        doc="The hand holding the handle (then `device.mass` and `device.friction` are the "
            "handle's alone): `mass` [kg] > 0 (required), `damping` to ground [N s/m] "
            ">= 0, `grip_stiffness` [N/m] > 0 or `rigid` (default), `grip_damping` "
            "[N s/m] >= 0, `stiffness` to ground [N/m] >= 0 (the arm's: a real spring, "
            "default 0); each a number or a range `[lo, hi]` (a family of hands: "
            "`hapsim family`; `--consistency` compares a real and a virtual spring). A "
            "compliant grip needs `hold: zoh`.",
        example="device: {mass: 0.05, hand: {mass: [0.05, 0.5], grip_stiffness: [300, 3000]}}"),
    Key("device.correction", "mapping", default=None,
        doc="One correction of the virtual element, acting at the port (any scene): `kind` "
            "`velocity_sensor` | `velocity_filter` (`cutoff_hz`) | `prediction` "
            "(`horizon` samples, default the delay) | `inertia_compensation` (`mass` [kg], "
            "below the moving mass) | `virtual_coupling` (`stiffness` [N/m], `damping` "
            "[N s/m]); see `hapsim compare-corrections`.",
        example="device: {mass: 0.1, correction: {kind: velocity_filter, cutoff_hz: 100}}"),
    Key("device.protocol", "choice", default=PROTOCOLS[0], choices=PROTOCOLS,
        doc="The protocol the device speaks on its port: `framed` is hapsim's own (COBS "
            "frames, CRC, sequence numbers, watchdog); the others are the drivers of "
            "devices with their own firmware (`hapsim run --help`, 'drivers'). `hapsim "
            "run` uses it (and its mock speaks it) unless `--driver` is given.",
        example="device: {mass: 0.05, protocol: firefader}"),
    Key("device.protocol_options", "mapping", default=None,
        doc="The device's own parameters in its protocol's units (a driver only; the "
            "embedded mock is built to match): `firefader`: `full_scale` [N] (force at 127 "
            "counts; 0.39, the repository's calibrated Pd patch), `metres_per_count` [m] "
            "(0.05/128), `axis` (0: fader A, 1: B); `haply`: `resolution` (encoder counts "
            "per revolution, 4880), `direction` (the encoder's: 0 CW, 1 CCW), "
            "`motor_direction` (the motor's; default the encoder's; `hapsim identify` "
            "finds it), `device_id` (1..255), "
            "`offset_deg` (the joint's angle when armed); `hapkit-serial`: `function` "
            "(0..255), `force_limit` [N]. See docs/drivers.md.",
        example="device: {mass: 0.05, protocol: firefader, protocol_options: "
                "{full_scale: 0.39}}"),
    # ------------------------------------------------------------------ excitation
    Key("excitation.x0", "number", "m", default=0.0,
        doc="Initial device displacement.",
        example="excitation: {x0: 0.002}"),
    Key("excitation.v0", "number", "m/s", default=0.0,
        doc="Initial device velocity.",
        example="excitation: {v0: -0.05}"),
    Key("excitation.impulse", "mapping", default=None,
        doc="A rectangular force pulse from the hand.",
        example="excitation: {impulse: {force: 1.0, start: 0.01, duration: 0.002}}"),
    Key("excitation.impulse.force", "number", "N",
        doc="Pulse height.",
        example="excitation: {impulse: {force: -0.5, duration: 0.001}}"),
    Key("excitation.impulse.start", "number", "s", default=0.0, minimum=0.0,
        doc="Time the pulse starts.",
        example="excitation: {impulse: {force: 1.0, start: 0.1, duration: 0.001}}"),
    Key("excitation.impulse.duration", "number", "s", default=0.0, minimum=0.0,
        doc="Pulse length (0: no pulse).",
        example="excitation: {impulse: {force: 1.0, duration: 0.005}}"),
    Key("excitation.profile", "string", default=None,
        doc="Recorded hand force, `.csv` (columns time [s], force [N]; a header allowed) "
            "or `.npz` (arrays `time`, `force`), relative to the scene file; the file "
            "must exist (the example: a scene in configs/).",
        example="excitation: {profile: hand_force.csv}"),
    # ------------------------------------------------------------------ audio
    Key("audio.rate_hz", "number", "Hz", minimum=0.0, strict=True, limits_from="RATE_RANGE",
        doc="Audio rate: every virtual mass runs at it; a whole multiple N of the scene's "
            "`rate_hz` (N audio steps per device period, N <= 10000).",
        example="audio: {rate_hz: 48000, listen: [{mass: hand}]}"),
    Key("audio.listen", "list",
        doc="Listening points, one output channel each (non-empty); see `audio.listen[]`.",
        example="audio: {rate_hz: 4000, listen: [{mass: hand}, {mass: wall}]}"),
    Key("audio.port_position", "choice", default=PORT_POSITION_MODES[0],
        choices=PORT_POSITION_MODES,
        doc="Port position up to the audio rate: `hold` the device sample, or `linear` "
            "from the previous one (no felt target with `linear`).",
        example="audio: {rate_hz: 4000, listen: [{mass: hand}], port_position: hold}"),
    Key("audio.port_force", "choice", default=PORT_FORCE_MODES[0], choices=PORT_FORCE_MODES,
        doc="Port force down to the device rate: the `mean` of the N sub-step forces, or "
            "the `last`.",
        example="audio: {rate_hz: 4000, listen: [{mass: hand}], port_force: last}"),
    Key("audio.listen[].mass", "string",
        doc="Name of the mass listened to.",
        example="audio: {rate_hz: 4000, listen: [{mass: wall}]}"),
    Key("audio.listen[].quantity", "choice", default=LISTEN_QUANTITIES[0],
        choices=LISTEN_QUANTITIES,
        doc="What is heard at each audio sample: backward-difference velocity [m/s], "
            "position [m] or the force on the mass [N].",
        example="audio: {rate_hz: 4000, listen: [{mass: hand, quantity: force}]}"),
    Key("audio.listen[].gain", "number", default=1.0,
        doc="Factor from that quantity to the output sample (full scale 1.0).",
        example="audio: {rate_hz: 4000, listen: [{mass: hand, gain: 200}]}"),
    # ------------------------------------------------------------------ safety
    Key("safety.position_limit", "number", "m", default=None, minimum=0.0, strict=True,
        allow_inf=True, default_doc="max(0.1, 20 |excitation.x0|)",
        doc="Safety stop when |x| exceeds it.",
        example="safety: {position_limit: 0.05}"),
    Key("safety.velocity_limit", "number", "m/s", default=math.inf, minimum=0.0,
        strict=True, allow_inf=True,
        doc="Safety stop when the backward-difference velocity |v| exceeds it.",
        example="safety: {velocity_limit: 2.0}"),
    Key("safety.energy_limit", "number", "J", default=1.0, minimum=0.0, strict=True,
        allow_inf=True,
        doc="Safety stop when the passivity observer (Hannaford & Ryu 2002) says the scene "
            "has given the hand this much energy.",
        example="safety: {energy_limit: 0.5}"),
    Key("safety.passivity_controller", "boolean", default=False,
        doc="Add the adaptive damping alpha = E / (T v^2) while the energy given to the "
            "hand beyond what the scene stored at its (re)start is positive.",
        example="safety: {passivity_controller: true}"),
    Key("safety.max_damping", "number", "N s/m", default=50.0, minimum=0.0,
        doc="Cap of the passivity controller's adaptive damping.",
        example="safety: {passivity_controller: true, max_damping: 20}"),
    Key("safety.brake", "boolean", default=True,
        doc="After a safety stop on the device's motion (force at the limit, position, "
            "velocity, energy, the host's lateness), brake the device to rest with the "
            "damping B = m / 4T (at most 0.25 s) before the zero force; false: zero force "
            "at once (docs/reliability.md).",
        example="safety: {brake: false}"),
]

#: Every key of the scene format, in the order the reference and the error messages list them.
KEYS: dict[str, Key] = {k.path: k for k in _KEYS}
assert len(KEYS) == len(_KEYS), "duplicate path in the scene table"
assert all(k.type in TYPES for k in _KEYS)

#: Rules that span several keys, checked in code (hapsim.scene.rules.check_scene), stated once here.
CROSS_RULES = (
    "Names of masses are unique, names of links are unique.",
    "At most one mass of kind `port`; a scene with a port needs a `device` section. A "
    "scene with 2 or 3 ports gives each its own device under `devices:` instead "
    "([Several ports](ports.md)).",
    "`mass` is given for kind `mass` only; a `ground` or a `port` has no inertia and no v0.",
    "A link joins two different existing masses.",
    "A link needs `stiffness` and/or `damping`, or a `target` (not both).",
    "A `target` is only for a `spring_damper` between the port and a ground.",
    "`threshold` is only for a `contact`; no `contact` with `integrator: exact`.",
    "`excitation.profile` must name an existing file.",
    "`null` is refused where leaving the key out means none (`excitation.profile`, "
    "`safety.position_limit`).",
)

#: The scene every key's example is merged into (a port held against a wall).
_WALL = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000, damping: 1.5}
"""
BASE_SCENE = _WALL + "device: {mass: 0.1, friction: 0.5}\n"

SECTIONS: tuple[Section, ...] = (
    Section("", "Top level", "A scene file is a YAML mapping with these keys.", """\
rate_hz: 1000
integrator: centred
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10}
excitation: {x0: 0.005}
safety: {energy_limit: 1.0}
"""),
    Section("masses[]", "masses[]: the points",
            "Each entry of `masses` is a mapping; which keys it takes depends on its `kind`.",
            """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: left, kind: ground, x0: 0.0}
  - {name: bead, kind: mass, mass: 0.01, x0: 0.001, v0: 0.0}
  - {name: right, kind: ground, x0: 0.02}
links:
  - {kind: spring_damper, between: [left, bead], stiffness: 200, damping: 0.01}
  - {kind: spring_damper, between: [bead, right], stiffness: 200, damping: 0.01}
  - {kind: contact, between: [hand, bead], stiffness: 500, damping: 0.1}
device: {mass: 0.1, friction: 0.5}
"""),
    Section("links[]", "links[]: the interactions",
            "Each entry of `links` is a mapping. Link law (docs/design.md, 'The scheme'; "
            "Faust `mi.lib`): with "
            "x1, x2 the positions of the first and second mass of `between`, "
            "F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T acts as -F on the first and "
            "+F on the second.", """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
  - {name: bob, kind: mass, mass: 0.01}
links:
  - {name: felt, kind: spring_damper, between: [hand, wall], target: {k: 1000, b: 3}}
  - {name: touch, kind: contact, between: [hand, bob], stiffness: 500, damping: 0.1,
     threshold: 0.0}
device: {mass: 0.1, friction: 0.5}
"""),
    Section("links[].target", "links[].target: a felt (k, b)",
            "The felt stiffness and damping `hapsim run` calibrates the link's (K, B) for "
            "(Florens, Voda & Urma's temporary hybrid system).", ""),
    Section("device", "device: the real side",
            "The hand + handle the scene is felt through, and the mock device's "
            "imperfections.", _WALL + """\
device:
  mass: 0.1
  friction: 0.5
  delay: 1
  hold: zoh
  force_limit: 10
  position_resolution: 1.0e-6
  coulomb: 0.0
  noise: 0.0
"""),
    Section("excitation", "excitation: how the hand starts the motion",
            "Used by the mock device (embedded in `hapsim run`, or `hapsim mock --scene`).",
            _WALL + """\
device: {mass: 0.1, friction: 0.5}
excitation:
  x0: 0.002
  v0: 0.0
  impulse: {force: 1.0, start: 0.0, duration: 0.001}
"""),
    Section("excitation.impulse", "excitation.impulse: a force pulse",
            "A rectangular pulse of the hand's force on the device.", ""),
    Section("audio", "audio: the scene's sound",
            "A multi-rate model (`hapsim check` analyses exactly the coupled model; "
            "`hapsim simulate --audio`, `hapsim run --sound`, `hapsim play`); "
            "`configs/audio_string.yaml` is a full example. Needs `integrator: centred`.",
            (_WALL + """\
  - {name: bow, kind: spring_damper, between: [wall, bead], stiffness: 400, damping: 0.01}
device: {mass: 0.1, friction: 0.5}
audio:
  rate_hz: 8000
  listen: [{mass: bead, quantity: velocity, gain: 0.5}, {mass: hand, quantity: force}]
  port_position: hold
  port_force: mean
""").replace("  - {name: wall, kind: ground}\n", "  - {name: wall, kind: ground}\n"
            "  - {name: bead, kind: mass, mass: 0.001}\n")),
    Section("audio.listen[]", "audio.listen[]: the listening points",
            "Each entry is one output channel.", ""),
    Section("safety", "safety: the limits of hapsim run",
            "Every limit ends the run with a zero force and STOP (exit 1), a device still "
            "moving braked to rest first (brake).", _WALL + """\
device: {mass: 0.1, friction: 0.5}
safety:
  position_limit: 0.1
  velocity_limit: 2.0
  energy_limit: 1.0
  passivity_controller: false
  max_damping: 50
  brake: true
"""),
)
assert {s.path for s in SECTIONS} == {k.section for k in _KEYS}, "a section without a heading"


def key(path: str) -> Key:
    """The row of ``path``.

    Parameters
    ----------
    path : str
        Key path (``device.friction``).

    Returns
    -------
    Key
        Its row of :data:`KEYS`.

    Raises
    ------
    KeyError
        When no row has that path.
    """
    return KEYS[path]


def section_keys(section: str, kind: str | None = None) -> tuple[Key, ...]:
    """The rows of one section, in table order.

    Parameters
    ----------
    section : str
        Section path (``""``, ``device``, ``masses[]``, ``links[].target``).
    kind : str, optional
        For ``masses[]`` / ``links[]``: only the keys an entry of this kind takes.

    Returns
    -------
    tuple of Key
        The rows (empty for an unknown section).
    """
    return _section_keys(section, kind)


@functools.lru_cache(maxsize=None)
def _section_keys(section: str, kind: str | None) -> tuple[Key, ...]:
    # the table is fixed at import: a scene's check (every Scene made, a measurement's
    # searches make thousands) asks for the same few sections each time
    return tuple(k for k in _KEYS if k.section == section
                 and (kind is None or not k.kinds or kind in k.kinds))


def key_names(section: str, kind: str | None = None) -> tuple[str, ...]:
    """The valid key names of a section (what an "unknown key" error lists).

    Parameters
    ----------
    section : str
        Section path.
    kind : str, optional
        Entry kind, as in :func:`section_keys`.

    Returns
    -------
    tuple of str
        Key names in table order.
    """
    return tuple(k.name for k in section_keys(section, kind))
