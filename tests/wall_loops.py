"""Random 1-D walls (a spring-damper from the port to a ground) run in lockstep on
hapsim's mock in process, on a device that matches the scene or one with more mass hidden
in it: the verdict tests' shared loop (tests/test_counts_verdict.py,
tests/test_coulomb_verdict.py)."""

from __future__ import annotations

import dataclasses


def wall_scene(case: dict, device_extra: str = ""):
    """The scene of ``case`` (``rate``, ``m``, ``b0``, ``d``, ``K``, ``B``, ``x0``, and
    optionally ``wall``, the ground's position [m]); ``device_extra``: more device keys,
    ``"key: value, "``."""
    from hapsim.scene import parse_scene
    return parse_scene(
        f"rate_hz: {case['rate']}\nmasses:\n  - {{name: handle, kind: port}}\n"
        f"  - {{name: wall, kind: ground, x0: {case.get('wall', 0.0)!r}}}\nlinks:\n"
        f"  - {{name: spring, kind: spring_damper, between: [handle, wall], "
        f"stiffness: {case['K']!r}, damping: {case['B']!r}}}\n"
        f"device: {{{device_extra}mass: {case['m']!r}, friction: {case['b0']!r}, "
        f"delay: {case['d']}, hold: zoh, force_limit: 1000.0}}\n"
        f"excitation: {{x0: {case['x0']!r}}}\n")


def run_hidden(scene, hidden: float = 1.0) -> dict:
    """The lockstep run's report on the in-process mock, its device ``hidden`` times
    heavier than the scene says (the prediction keeps the scene's)."""
    import hapsim.pipeline.runner as runner
    framed = runner.MockDevice

    def heavier(*a, **k):
        a = list(a)
        a[0] = dataclasses.replace(a[0], mass=hidden * a[0].mass)
        return framed(*a, **k)
    runner.MockDevice = heavier
    try:
        return runner.run_scene(scene, lockstep=True, handle_signals=False,
                                transport="inprocess")
    finally:
        runner.MockDevice = framed
