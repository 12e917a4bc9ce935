"""The FireFader's felt damping with its own sub-sample timing, predicted at a whole and at
the real delay (issue 29 item 3).

Usage::

    python tools/firefader_subsample.py [--scene configs/firefader.yaml] [--adc-ms 1.1]
                                        [--delays 1,0.725] [--runs 1] [--json FILE]

Each run closes the scene's THS through the FireFader's bytes on its driver mock
(:class:`hapsim.emulated.driver_mock.FireFaderDevice` with ``adc_s``: the board sets the PWM when
a packet comes and reads the fader ``adc`` later, whatever the scene states), with the
scene's ``device.delay`` set to each value of ``--delays`` for the prediction. Printed per
delay: the predicted and measured (k, b), the run's stated uncertainty on b and its
verdict. The real delay is ``1 - adc / T`` (docs/stability.md, 'Sub-sample delay'). A
measurement program, not a test; progress on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys


def main(argv=None) -> int:
    """Run the table (module docstring).

    Parameters
    ----------
    argv : list of str, optional

    Returns
    -------
    int
        0.
    """
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="configs/firefader.yaml")
    p.add_argument("--adc-ms", type=float, default=1.1,
                   help="the board's fader read after the packet [ms] (default 1.1)")
    p.add_argument("--delays", default="1,0.725",
                   help="scene delays to predict with [periods], comma-separated")
    p.add_argument("--runs", type=int, default=1, help="runs per delay (seeds 0..)")
    p.add_argument("--json", metavar="FILE")
    a = p.parse_args(argv)
    sc = load_scene(a.scene)
    rows = []
    delays = [float(v) for v in a.delays.split(",")]
    for d in delays:
        s = dataclasses.replace(sc, device=dataclasses.replace(
            sc.device, delay=int(d) if d.is_integer() else d))
        for seed in range(a.runs):
            print(f"firefader_subsample: delay {d:g}, run {seed + 1}/{a.runs} ...",
                  file=sys.stderr, flush=True)
            rep = run_scene(s, driver="firefader", mock_options={"adc_s": a.adc_ms * 1e-3},
                            handle_signals=False, rt_priority=0, seed=seed)
            pr, me = rep["predicted"], rep["measured"]
            rows.append({"delay": d, "seed": seed, "k_pred": pr["k"], "b_pred": pr["b"],
                         "k_meas": me.get("k"), "b_meas": me.get("b"),
                         "b_interval": me.get("b_interval"), "within": me.get("within"),
                         "verdict": me.get("verdict")})
    print(f"{a.scene}: {sc.rate_hz:g} Hz, the board reads the fader {a.adc_ms:g} ms after "
          f"the packet (real delay 1 - {a.adc_ms:g}/{1e3 / sc.rate_hz:g} = "
          f"{1 - a.adc_ms * 1e-3 * sc.rate_hz:g} periods)")
    print(f"{'delay':>7} {'k pred':>9} {'k meas':>9} {'b pred':>9} {'b meas':>9} "
          f"{'+-b':>8} {'b err':>7}  verdict")
    for r in rows:
        err = (r["b_meas"] - r["b_pred"]) / r["b_pred"] if r["b_meas"] is not None else None
        print(f"{r['delay']:>7g} {r['k_pred']:>9.4f} {r['k_meas']:>9.4f} {r['b_pred']:>9.5f} "
              f"{r['b_meas']:>9.5f} {r['b_interval']:>8.2g} {err:>+7.1%}  {r['verdict']}")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
