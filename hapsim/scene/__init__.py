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

Rooms
-----
:mod:`hapsim.scene.elements` (the masses, links, device... as values),
:mod:`hapsim.scene.rules` (every rule of the format, checked on the values),
:mod:`hapsim.scene.model` (:class:`Scene`, checked by the rules whenever one is built) and
:mod:`hapsim.scene.reader` (YAML with line numbers into the model: :func:`load_scene`,
:func:`parse_scene`), each importing only the ones before it; import from this package.
"""


from __future__ import annotations

from hapsim.scene.elements import (CORRECTIONS, Audio, Device, Excitation, Hand, Impulse, Link,
                                   Listen, Mass, Safety, audio_substeps)
from hapsim.scene.model import Scene
from hapsim.scene.reader import load_scene, parse_scene
from hapsim.scene_schema import (HOLDS, INTEGRATORS, LINK_KINDS, LISTEN_QUANTITIES, MASS_KINDS,
                                 PORT_FORCE_MODES, PORT_POSITION_MODES, PROTOCOLS)

__all__ = ["Mass", "Link", "Device", "Hand", "CORRECTIONS", "Impulse", "Excitation", "Safety",
           "Listen", "Audio",
           "Scene", "load_scene", "parse_scene", "MASS_KINDS", "LINK_KINDS", "HOLDS",
           "INTEGRATORS", "LISTEN_QUANTITIES", "PORT_POSITION_MODES", "PORT_FORCE_MODES",
           "PROTOCOLS", "audio_substeps"]
