"""Time reading a large scene: hapsim's loader against PyYAML's pure-Python SafeLoader.

Usage::

    python tools/bench_scene_load.py [--masses N]

Writes a string of N beads (N masses, N + 1 links; ~130 bytes a line) to a temporary file
and prints, measured in the same run: PyYAML ``yaml.load(..., SafeLoader)`` (what
``hapsim.scene`` used before; the baseline), :func:`hapsim._yaml_lines.load_yaml` (libyaml
events, bounded) and the whole :func:`hapsim.scene.load_scene` (YAML + validation), with
the ratios to the baseline. Times are wall-clock on whatever load the machine has.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def string_scene(n: int) -> str:
    """YAML of a port, two grounds and a string of ``n`` beads between them."""
    lines = ["rate_hz: 1000", "masses:", "  - {name: hand, kind: port}",
             "  - {name: g0, kind: ground}"]
    lines += [f"  - {{name: m{i}, kind: mass, mass: 0.001}}" for i in range(n)]
    lines += ["  - {name: g1, kind: ground}", "links:",
              "  - {kind: spring_damper, between: [hand, m0], stiffness: 100, damping: 0.01}",
              "  - {kind: spring_damper, between: [g0, m0], stiffness: 100, damping: 0.01}"]
    lines += [f"  - {{kind: spring_damper, between: [m{i}, m{i + 1}], stiffness: 100, "
              "damping: 0.01}" for i in range(n - 1)]
    lines += [f"  - {{kind: spring_damper, between: [m{n - 1}, g1], stiffness: 100, "
              "damping: 0.01}", "device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh}"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    """Print the three timings and the ratios; return 0."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--masses", type=int, default=20000, help="beads (default 20000)")
    args = ap.parse_args(argv)
    import yaml

    from hapsim._yaml_lines import load_yaml
    from hapsim.scene import load_scene
    text = string_scene(args.masses)
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
        fh.write(text)
    try:
        t0 = time.perf_counter()
        yaml.load(text, Loader=yaml.SafeLoader)
        base = time.perf_counter() - t0
        t0 = time.perf_counter()
        load_yaml(text)
        ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        load_scene(fh.name)
        whole = time.perf_counter() - t0
    finally:
        os.remove(fh.name)
    print(f"{args.masses} masses, {len(text) / 1e6:.1f} MB")
    print(f"  PyYAML SafeLoader (baseline)  {base:8.2f} s")
    print(f"  hapsim load_yaml              {ours:8.2f} s   x{base / ours:.1f} faster")
    print(f"  hapsim load_scene (+checks)   {whole:8.2f} s   x{base / whole:.1f} faster")
    return 0


if __name__ == "__main__":
    sys.exit(main())
