"""How fast the Falcon's host loop runs: packets per second of ``run_falcon`` through pyftdi
over the emulated FT232R and Falcon, the same without USB, the emulated device alone, and
the delta's kinematics per sample (from the last position and from a fresh start).

A real Falcon's firmware answers at ~1 kHz; the host keeps up when its own share of a
packet (everything but the device) stays under 1 ms. The emulated device's share is
measured and taken away to estimate it. Prints a summary and writes JSON
(``--out``, default ``docs/bench_falcon.json``), with the machine's load average: figures
on a loaded machine say so.

    python tools/bench_falcon.py [--packets 2000] [--out docs/bench_falcon.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import command_line, portable_path  # noqa: E402  (tools/, beside this file)

ROOT = Path(__file__).resolve().parents[1]
IMAGE = bytes(np.random.default_rng(7).integers(0, 256, 4000, dtype=np.uint8))


def _rate(make_link, scene, packets):
    from hapsim.pipeline.falcon_run import run_falcon
    link, dev = make_link()
    try:
        res = run_falcon(scene, link, IMAGE, packets, truth=dev.counts, timeout=0.005)
    finally:
        if hasattr(link, "close"):
            link.close()
    assert res["verdict"] == "ok", res["reason"]
    return res["packets_per_s"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packets", type=int, default=2000)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench_falcon.json"))
    a = ap.parse_args(argv)
    from hapsim.emulated.falcon_device import EmulatorLink, FalconDevice, load_firmware
    from hapsim.pipeline.falcon_run import emulated_falcon
    from hapsim.drivers import falcon as fa
    from hapsim.kinematics import device
    from hapsim.scene import load_scene_nd
    scene = load_scene_nd(ROOT / "configs" / "delta_sphere.yaml")
    load0 = os.getloadavg()[0]

    def usb():
        link, dev, _ = emulated_falcon(scene, IMAGE)
        return link, dev

    def direct():
        dev = FalconDevice(scene, expected_image=IMAGE)
        return EmulatorLink(dev), dev
    full = _rate(usb, scene, a.packets)
    nousb = _rate(direct, scene, a.packets)
    dev = FalconDevice(scene, expected_image=IMAGE)
    load_firmware(dev, IMAGE)
    pk = fa.host_packet((0, 0, 0))
    t0 = time.perf_counter()
    for _ in range(a.packets):
        dev.feed(pk)
    emu = (time.perf_counter() - t0) / a.packets
    kin = device("delta", scene.device.geometry)
    q = np.asarray(scene.device.joints, float)
    x = kin.forward(q)
    n = 500
    t0 = time.perf_counter()
    for _ in range(n):
        kin.forward_jacobian(q, x)
    warm = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for _ in range(20):
        kin.forward(q), kin.jacobian(q)
    cold = (time.perf_counter() - t0) / 20
    out = {"command": command_line("tools/bench_falcon.py", ["--packets", str(a.packets),
                                                             "--out", a.out]),
           "packets": a.packets, "cpus": os.cpu_count(),
           "load_average": [load0, os.getloadavg()[0]],
           "packets_per_s_usb": full, "packets_per_s_no_usb": nousb,
           "emulated_device_ms": emu * 1e3,
           "host_ms_per_packet_usb": 1e3 / full - emu * 1e3,
           "host_ms_per_packet_no_usb": 1e3 / nousb - emu * 1e3,
           "kinematics_from_last_position_ms": warm * 1e3,
           "kinematics_fresh_ms": cold * 1e3}
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"load {load0:.2f} on {os.cpu_count()} cpus (a shared machine: the figures are "
          "loaded ones when the load is above ~1)")
    print(f"through pyftdi and the emulated FT232R: {full:.0f} packets/s; without USB "
          f"{nousb:.0f} packets/s; the emulated device {emu * 1e3:.3f} ms a packet")
    print(f"host per packet (the device's share taken away): through pyftdi "
          f"{out['host_ms_per_packet_usb']:.3f} ms, without USB "
          f"{out['host_ms_per_packet_no_usb']:.3f} ms")
    print(f"kinematics per sample: from the last position {warm * 1e3:.3f} ms, fresh "
          f"{cold * 1e3:.2f} ms")
    print(f"wrote {portable_path(a.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
