"""YAML scene files: parsing and validation.

A scene is a CORDIS-ANIMA style mass-interaction network in SI units, plus the
description of the device it is felt through. Nothing reaches the engine or the
analysis without passing :func:`parse_scene`, which reports every problem as a
:class:`~hapsim.errors.ConfigError` naming the file, the line and the key.

Format
------
Every key, unit, default and limit is one row of :data:`hapsim.scene_schema.KEYS`, the
table this module reads and checks with; ``docs/scenes.md`` (the reference, with an example
for each key) is written from it by ``python -m hapsim.scene_doc``. A small scene:

.. code-block:: yaml

    rate_hz: 1000                 # sample rate [Hz]
    masses:
      - {name: hand, kind: port}                    # driven by the device position
      - {name: wall, kind: ground, x0: 0.0}         # fixed point [m]
    links:
      - {name: wall, kind: spring_damper, between: [hand, wall],
         stiffness: 1000, damping: 1.5}             # K [N/m], B [N s/m]
    device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10}
    excitation: {x0: 0.005}       # the hand starts 5 mm into the wall [m]

Link law (docs/design.md, 'The scheme'; Faust ``mi.lib`` ``spring``/``collision``): with
``x1``, ``x2`` the positions of the first and second mass named in ``between``,
``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T`` is applied as ``-F`` on the first
mass and ``+F`` on the second. A contact acts only while ``x2 - x1 < threshold``, with its
spring measured from the threshold, ``F = K (x1 - x2 + threshold) + B (...) / T``, so the
force is continuous when the contact engages (Faust 2.54 ``mi.lib`` ``collision``).

Format in two and three dimensions
----------------------------------
A scene file with ``dimension: 2`` or ``3`` (:func:`scene_dimension`) is read by
:func:`load_scene_nd` and :func:`parse_scene_nd` into a :class:`SceneND`: the same
structure with vector positions, Euclidean links, planes and a device that may be a
kinematic one (the pantograph, the delta of :mod:`hapsim.kinematics`) at an operating
point. Every value is checked, and an error names the file, the line and the key
(``masses[2].x0``) as the 1-D reader's do. n = ``dimension``; vectors are lists of n
numbers; a scalar where a vector is expected is refused:

.. code-block:: yaml

    dimension: 2                  # 2 or 3
    rate_hz: 1000                 # > 0 [Hz]
    integrator: centred           # the only one in n-D
    masses:                       # non-empty
      - {name: hand, kind: port}                       # at most one; rests where the
                                                       # device's handle is
      - {name: anchor, kind: ground, x0: [0.0, 0.02]}  # fixed point [m]
      - {name: bob, kind: mass, mass: 0.01, x0: [0.01, 0.0], v0: [0, 0]}  # [kg] [m] [m/s]
    links:
      - {name: s, kind: spring_damper, between: [hand, bob], stiffness: 300, damping: 0.5,
         length: 0.01}            # rest length [m] >= 0 (default 0)
      - {name: c, kind: contact, between: [hand, bob], stiffness: 800, threshold: 0.01}
    planes:
      - {name: wall, normal: [0, -1], offset: -0.02, stiffness: 1000, damping: 1.5,
         masses: [hand]}          # acts on the named masses (default: every moving one)
    excitation:                   # optional, with a port: the hand's force on the device's
      direction: [0, 1]           # mass along this direction (normalised; required)
      impulse: {force: 2.0, start: 0.0, duration: 0.002}   # [N] [s] [s]; and/or
      profile: hand_force.csv     # a recorded force profile (time [s], force [N]),
                                  # relative to the scene file (hapsim play plucks with
                                  # it, again every --pluck-every seconds)
    engine:                       # optional
      precision: double           # double (float64, the default) | single (float32:
                                  # twice the engine's speed on a mesh, 24-bit positions;
                                  # no port; docs/dimensions.md, 'Single precision')
    audio:                        # optional: the scene heard (hapsim simulate --audio)
      listen:                     # one WAV channel each, at rate_hz
        - {mass: bob, axis: z, quantity: velocity, gain: 10.0}   # axis x|y|z (0..n-1),
                                  # quantity position [m] | velocity [m/s], gain [-]
    device:                       # required with a port
      kind: cartesian             # cartesian | pantograph | delta
      mass: 0.1                   # cartesian: [kg], a number (isotropic), a vector
                                  # (diagonal) or an n x n matrix (SPD)
      friction: 0.5               # cartesian: [N s/m], same shapes (PSD)
      position: [0.0, 0.0]        # cartesian: the handle's rest position [m]
      delay: 1                    # [periods, a real number]
      hold: zoh                   # the only one in n-D
    # a kinematic device instead: kind: pantograph (n = 2) or delta (n = 3), geometry: a
    # preset (haply, falcon) or, for a pantograph, its lengths as numbers
    # {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02} [m], joints: the operating
    # point [deg], joint_inertia [kg m^2] and joint_friction [N m s/rad] (vectors or
    # matrices), hand_mass [kg] and hand_damping [N s/m] (isotropic, default 0); the
    # handle rests at the forward kinematics of the joints.

Link laws in two and three dimensions
-------------------------------------
Per sample, ``T`` the period; ``d = x1 - x2`` between the first and the second
mass of ``between``; ``F`` acts as ``-F`` on the first and ``+F`` on the second:

- ``spring_damper`` with ``length: 0`` (the default): ``F = K d + B (d - d_prev) / T``,
  the 1-D law on every axis (Faust ``mi.lib``; a 2-D scene whose links are all of this
  kind is n independent copies of the 1-D scene);
- ``spring_damper`` with ``length: L > 0``: ``F = [K (|d| - L) + B (|d| - |d_prev|) / T]
  d / |d|``: the Euclidean stretch and the damping on the relative velocity along the link
  (miPhysics ``SpringDamper3D``);
- ``contact`` (between spheres): the Euclidean law with ``L = threshold`` (> 0, the sum
  of the radii), acting only while ``|d| < threshold``;
- ``planes[]``: with the unit ``normal`` and the penetration ``p = offset - normal . x``,
  the force ``[K p + B (p - p_prev) / T] normal`` on each named mass while ``p > 0``.

:mod:`hapsim.analysis.scene_check` linearises the scene at its rest configuration
(contacts and planes engaged, as the 1-D check does) and analyses the coupled loop.

Rooms
-----
:mod:`hapsim.scene.elements` (the masses, links, device... as values, of every dimension),
:mod:`hapsim.scene.rules` (every rule of the format, checked on the values),
:mod:`hapsim.scene.model` (:class:`Scene`, checked by the rules whenever one is built;
:class:`SceneND`), :mod:`hapsim.scene.lines` (where the reader is in a file, and the values
it reads there), :mod:`hapsim.scene.devices` (a 2-D or 3-D scene's device at its operating
point) and :mod:`hapsim.scene.reader` (YAML with line numbers into the model:
:func:`load_scene`, :func:`parse_scene`, :func:`load_scene_nd`, :func:`parse_scene_nd`,
:func:`scene_dimension`), each importing only the ones before it; import from this package.
"""


from __future__ import annotations

from hapsim.scene.devices import DEVICE_KINDS
from hapsim.scene.elements import (CORRECTIONS, Audio, Device, DeviceND, Excitation, ExcitationND,
                                   Hand, Impulse, Link, LinkND, Listen, ListenND, Mass, MassND,
                                   PlaneND, Safety, SafetyND, audio_substeps, device_from_dict,
                                   excitation_from_dict)
from hapsim.scene.model import Scene, SceneND, ScenePorts
from hapsim.scene.reader import (load_scene, load_scene_nd, load_scene_ports, parse_scene,
                                 parse_scene_nd, parse_scene_ports, scene_dimension,
                                 scene_has_ports, scene_protocol)
from hapsim.scene_schema import (HOLDS, INTEGRATORS, LINK_KINDS, LISTEN_QUANTITIES, MASS_KINDS,
                                 PORT_FORCE_MODES, PORT_POSITION_MODES, PROTOCOLS)

__all__ = ["Mass", "Link", "Device", "Hand", "CORRECTIONS", "Impulse", "Excitation", "Safety",
           "Listen", "Audio", "device_from_dict", "excitation_from_dict",
           "Scene", "load_scene", "parse_scene", "MASS_KINDS", "LINK_KINDS", "HOLDS",
           "INTEGRATORS", "LISTEN_QUANTITIES", "PORT_POSITION_MODES", "PORT_FORCE_MODES",
           "PROTOCOLS", "audio_substeps",
           "MassND", "LinkND", "PlaneND", "DeviceND", "ListenND", "ExcitationND", "SafetyND",
           "SceneND",
           "scene_dimension", "scene_protocol", "load_scene_nd", "parse_scene_nd", "DEVICE_KINDS",
           "ScenePorts", "load_scene_ports", "parse_scene_ports", "scene_has_ports"]
