"""``hapsim simulate`` on a 2-D or 3-D scene: the n-D engine offline, trajectories out."""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from hapsim.errors import ConfigError


def run_nd(args) -> int:
    """Simulate an n-D scene (``dimension: 2`` or ``3``; :mod:`hapsim.scene_nd`).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``steps``, ``out`` (``.npz``), ``record``, ``json``, ``audio`` (a
        ``.wav`` path: the scene's ``audio`` listening points instead of a trajectory,
        :func:`hapsim.audio.offline_nd.render_nd`).

    Returns
    -------
    int
        0, or 1 when a position becomes NaN or infinite (the rows before it are written).
        The ``.npz`` holds ``time`` [s] shape (N+1,), ``position`` [m] shape (N+1, R, n)
        and ``names`` shape (R,); row 0 is the initial state. The port (if any) is held at
        its rest position, the device's handle position (no device is simulated; the
        closed loop is :class:`hapsim.lockstep_nd.LockstepND`).

    Raises
    ------
    ConfigError
        An output that is not ``.npz`` (``.wav`` with ``--audio``), a scene without an
        ``audio`` section with ``--audio``, negative ``--steps``, an unknown or repeated
        ``--record`` name, an invalid scene (file, line, key).
    """
    from hapsim.engine_nd import EngineND
    from hapsim.outputs import check_fits, check_writable
    from hapsim.progress import Progress
    from hapsim.scene_nd import load_scene_nd
    if args.audio is not None:
        return _run_audio(args)
    if args.out is None or os.path.splitext(args.out)[1].lower() != ".npz":
        raise ConfigError(f"a 2-D or 3-D trajectory is written as .npz (time, position "
                          f"(N+1, R, n), names), got {args.out!r}", key="--out")
    check_writable(args.out, "--out")
    scene = load_scene_nd(args.scene)
    engine = EngineND(scene)
    names = list(args.record) if args.record else list(engine.names)
    for nm in names:
        if nm not in engine.names:
            raise ConfigError(f"no mass named {nm!r}; masses: {', '.join(engine.names)}",
                              key="--record")
    if len(set(names)) != len(names):
        raise ConfigError("names a mass twice; each once", key="--record")
    idx = np.array([engine.names.index(nm) for nm in names], dtype=np.int64)
    n = scene.dimension
    check_fits(8.0 * (args.steps + 1) * (len(names) * n + 1),
               f"{args.steps} samples x {len(names)} masses x {n} axes", "--steps")
    pos = np.empty((args.steps + 1, len(names), n))
    pos[0] = engine.x[:, idx].T
    rest = None if engine.port is None else engine.x[:, engine.port].copy()
    bad = None
    t0 = time.perf_counter()
    with Progress(args.steps, "simulate", unit="samples") as bar:
        for k in range(1, args.steps + 1):
            if rest is not None:
                engine.set_port_position(rest)
            engine.step()
            pos[k] = engine.x[:, idx].T
            if not np.all(np.isfinite(engine.x)):
                bad = k
                break
            if k % 4096 == 0:
                bar.update(k)
    elapsed = time.perf_counter() - t0
    rows = args.steps + 1 if bad is None else bad
    t = np.arange(rows) / scene.rate_hz
    np.savez(args.out, time=t, position=pos[:rows], names=np.array(names))
    summary = {"scene": args.scene, "out": args.out, "dimension": n,
               "steps": args.steps if bad is None else bad, "rate_hz": scene.rate_hz,
               "recorded": len(names), "seconds": elapsed}
    if bad is not None:
        summary.update(diverged={"step": bad}, exit=1)
        print(f"hapsim simulate: the scene diverged: a position is not finite at step {bad} "
              f"(t = {bad / scene.rate_hz:.6g} s); wrote the {bad} rows before it to "
              f"{args.out}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    elif bad is None:
        print(f"wrote {args.out}: {args.steps} samples x {len(names)} masses x {n} axes "
              f"({args.steps / scene.rate_hz:g} s simulated in {elapsed:.3f} s)")
    return 0 if bad is None else 1


def _run_audio(args) -> int:
    """``simulate --audio`` on an n-D scene: its listening points to a WAV file."""
    from hapsim.audio.offline import write_wav
    from hapsim.audio.offline_nd import render_nd
    from hapsim.engine_nd import EngineND
    from hapsim.outputs import check_writable
    from hapsim.progress import Progress
    from hapsim.scene_nd import load_scene_nd
    if not args.audio.lower().endswith(".wav"):
        raise ConfigError(f"the sound file must end in .wav, got {args.audio!r}",
                          key="--audio")
    if getattr(args, "gesture", "excitation") != "excitation":
        raise ConfigError("a 2-D or 3-D scene is heard from its initial state (no gesture "
                          "drives its port yet): leave --gesture out", key="--gesture")
    for opt, val in (("--out", args.out), ("--record", args.record)):
        if val:
            raise ConfigError(f"--audio writes the sound only: {opt} is not taken with it",
                              key=opt)
    check_writable(args.audio, "--audio")
    scene = load_scene_nd(args.scene)
    if not scene.audio:
        raise ConfigError("the scene needs an audio section (listen: [{mass, axis, "
                          "quantity, gain}]) to be heard; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    if scene.rate_hz != int(scene.rate_hz):
        raise ConfigError(f"a sound's rate is a whole number of Hz, got {scene.rate_hz:g}",
                          file=scene.path, key="rate_hz")
    t0 = time.perf_counter()
    with Progress(args.steps, "simulate", unit="samples") as bar:
        audio = render_nd(EngineND(scene), args.steps, progress=bar.update)
    elapsed = time.perf_counter() - t0
    try:
        info = write_wav(args.audio, audio, scene.rate_hz)
    except ValueError as e:
        print(f"hapsim simulate: {e}", file=sys.stderr)
        return 1
    summary = {"scene": args.scene, "audio": args.audio, "dimension": scene.dimension,
               "steps": args.steps, "rate_hz": scene.rate_hz, "frames": info["frames"],
               "channels": info["channels"], "peak": info["peak"],
               "clipped": info["clipped"], "seconds": elapsed}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.audio}: {info['frames']} frames x {info['channels']} "
              f"channel(s) at {scene.rate_hz:g} Hz, peak {info['peak']:.3g}"
              + (f", {info['clipped']} samples clipped" if info["clipped"] else "")
              + f" ({elapsed:.2f} s)")
    return 0
