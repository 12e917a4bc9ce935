"""Golden records of the engine on the shipped scenes (issue 30 item 1): short runs whose
positions and port forces ``tests/test_golden_engine.py`` compares against, so that a change
of the engine's code (the one engine for every dimension) is shown to keep today's numbers.

Each record is a run of :data:`SAMPLES` samples of one scene of ``configs/``: a scene with a
port has it driven by a fixed seeded trajectory (:func:`trajectory`), one without is
advanced freely. Stored: the port force of every sample and the positions of at most
:data:`KEEP` masses (spread over the scene) every :data:`EVERY` samples, as float64 in one
compressed ``.npz`` (``tests/data/golden_engine.npz``, under 200 kB).

Usage::

    python tools/golden_engine.py            # write tests/data/golden_engine.npz
    python tools/golden_engine.py --compare  # the largest deviation of this run from it

The record must be written once, before the engine changes, and not again to make a test
pass: the test compares within a stated round-off bound (``NUMBA_CPU_NAME=generic`` computes
without fused multiply-add, so the bits may differ across CPUs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
OUT = ROOT / "tests" / "data" / "golden_engine.npz"

#: Shipped 1-D scenes (every one a :class:`hapsim.scene.Scene`; ``two_faders.yaml`` has
#: several ports, a :class:`hapsim.scene.ScenePorts` no engine runs alone) and three n-D
#: ones (a 2-D wall, a 3-D sphere and a 3-D mesh with a port; a 3-D drum without).
SCENES = ("audio_string.yaml", "felt_wall.yaml", "firefader.yaml", "first_wall.yaml",
          "hand_wall.yaml", "hapkit.yaml", "hapkit_serial.yaml", "haply.yaml",
          "oscillator.yaml", "string.yaml", "wall.yaml",
          "pantograph_wall.yaml", "delta_sphere.yaml", "delta_mesh.yaml", "membrane.yaml")
#: The rate [Hz] a record was written at, where the shipped scene's rate changed since (the
#: scene changed, not the engine): ``hapkit_serial.yaml`` went from 250 Hz to 252.016 Hz
#: (4 of the Hapkit sketch's 0.992 ms ticks) in stop 57, and to 201.613 Hz (5 ticks: the
#: most that holds the sketch's latest answer) in stop 60.
RECORDED_RATE_HZ = {"hapkit_serial.yaml": 250.0}
#: The links' stiffness [N/m] a record was written with, where the shipped scene's changed
#: since: ``hapkit_serial.yaml``'s spring went from 50 to 35 N/m in stop 60 (a delay
#: margin of one period at 5 ticks).
RECORDED_STIFFNESS = {"hapkit_serial.yaml": {"spring": 50.0}}
#: Samples of each run [-].
SAMPLES = 300
#: Positions stored every this many samples [-].
EVERY = 3
#: Masses whose positions are stored, at most [-].
KEEP = 6
#: Seed of the port trajectories.
SEED = 30


def trajectory(n: int, dim: int, rate_hz: float, seed: int) -> np.ndarray:
    """A smooth seeded port displacement: three sinusoids per axis, 1 mm in all.

    Parameters
    ----------
    n : int
        Samples.
    dim : int
        Axes (1, 2 or 3).
    rate_hz : float
        Sample rate [Hz] (the frequencies are drawn in 2..40 Hz, below every scene's
        Nyquist frequency).
    seed : int
        Seed of :func:`numpy.random.default_rng`.

    Returns
    -------
    ndarray, shape (n, dim)
        Displacement from the port's rest position [m], zero at sample 0.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(1, n + 1)[:, None] / rate_hz
    out = np.zeros((n, dim))
    for _ in range(3):
        f = rng.uniform(2.0, 40.0, dim)
        a = rng.uniform(1e-4, 4e-4, dim)
        ph = rng.uniform(0.0, 2 * np.pi, dim)
        out += a * (np.sin(2 * np.pi * f * t + ph) - np.sin(ph))
    return out


def load(name: str):
    """The scene ``configs/<name>``, calibrated (felt targets turned into (K, B)).

    Parameters
    ----------
    name : str
        File name in ``configs/``.

    Returns
    -------
    hapsim.scene.Scene or hapsim.scene.SceneND
    """
    from hapsim.analysis.targets import apply_targets
    from hapsim.scene import load_scene, load_scene_nd, scene_dimension
    path = CONFIGS / name
    if scene_dimension(path) > 1:
        return load_scene_nd(path)
    scene = load_scene(path)
    if name in RECORDED_RATE_HZ:
        scene = scene.with_rate(RECORDED_RATE_HZ[name])
    if name in RECORDED_STIFFNESS:
        import dataclasses
        was = RECORDED_STIFFNESS[name]
        scene = dataclasses.replace(scene, links=tuple(
            dataclasses.replace(lk, stiffness=was[lk.name]) if lk.name in was else lk
            for lk in scene.links))
    if scene.unresolved_targets:
        scene = apply_targets(scene)[0]
    return scene


def kept(n_masses: int) -> np.ndarray:
    """Indices of the masses stored: all of them up to :data:`KEEP`, else :data:`KEEP`
    spread evenly from the first to the last (int64)."""
    return np.unique(np.linspace(0, n_masses - 1, min(KEEP, n_masses)).round().astype(np.int64))


def drive(scene) -> dict[str, np.ndarray]:
    """Run the engine on ``scene`` for :data:`SAMPLES` samples and record it.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND
        A calibrated scene.

    Returns
    -------
    dict
        ``force`` shape (SAMPLES, dim): the port force of every sample [N] (zeros without
        a port); ``x`` shape (SAMPLES // EVERY + 1, len(masses), dim): the kept masses'
        positions before the run and after every EVERY samples [m]; ``masses`` their
        indices.
    """
    from hapsim.engine import Engine
    eng = Engine(scene)
    dim, port = eng.dim, eng.port_index
    idx = kept(len(eng.names))
    force = np.zeros((SAMPLES, dim))
    xs = [eng.x[:, idx].T.copy()]
    if port >= 0:
        rest = eng.x[:, port].copy()
        eng.set_port_position(rest, at_rest=True)
        path = rest + trajectory(SAMPLES, dim, scene.rate_hz, SEED)
    for s in range(SAMPLES):
        if port >= 0:
            force[s] = eng.port_step(path[s])
        else:
            eng.step(1)
        if (s + 1) % EVERY == 0:
            xs.append(eng.x[:, idx].T.copy())
    return {"force": force, "x": np.array(xs), "masses": idx}


def main(argv=None) -> int:
    """Write the records, or compare this run with them (``--compare``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--compare", action="store_true",
                    help="print each scene's largest deviation from the stored record")
    args = ap.parse_args(argv)
    if args.compare:
        ref = np.load(OUT)
        for name in SCENES:
            got = drive(load(name))
            for key in ("force", "x"):
                a, b = got[key], ref[f"{name}/{key}"]
                scale = float(np.max(np.abs(b))) or 1.0
                print(f"{name:24s} {key:5s} max |diff| {np.max(np.abs(a - b)):.3e}  "
                      f"relative to max |value| {np.max(np.abs(a - b)) / scale:.3e}")
        return 0
    data = {}
    for name in SCENES:
        for key, val in drive(load(name)).items():
            data[f"{name}/{key}"] = val
    OUT.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(OUT, **data)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes, {len(SCENES)} scenes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
