"""What live control leaves behind: the felt pair identified over a window of the record
(:func:`identify_window`), the run's measurement revised by the journal of changes
(:func:`revise_measurement`: only the rows after the last change's ramp count), and the
journal written to a file (:func:`write_journal`)."""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["identify_window", "revise_measurement", "write_journal"]


def revise_measurement(measured: dict, journal: list, rate_hz: float) -> list:
    """Compare a run's measurement with the prediction of the scene it measured, after
    live changes (``hapsim run --osc``), as ``hapsim play`` re-predicts.

    The measured window is rows ``[first_row, first_row + samples_used)`` of the run; each
    accepted change acts from its ``sample`` over its ramp. A change inside the window
    makes the measurement a mix of two loops: not comparable. Changes that all ended
    before it: the measurement is compared with the prediction after the last of them
    (its felt k, b). Changes that all came after it: the start's prediction stands.

    Parameters
    ----------
    measured : dict
        The run's identification result (``k`` [N/m], ``b`` [N s/m], ``k_interval``,
        ``b_interval``, ``first_row``, ``samples_used``, ``rel_err``, ``verdict``);
        updated in place: ``compared_with`` says which prediction, ``rel_err`` (k and b),
        ``within`` and ``verdict`` follow it, or ``comparable`` False with the reason.
    journal : list of dict
        The controller's journal (:attr:`Controller.journal`).
    rate_hz : float
        Device rate [Hz] (ramp times to samples).

    Returns
    -------
    list of dict
        The accepted changes: ``sample``, ``address``, ``args``, ``ramp_s`` [s], the
        ``felt`` [k, b] predicted after each and that ``predicted`` pair (``k``, ``b``,
        ``f0_hz``, ``damping_ratio``).
    """
    changes = [{"sample": int(e["sample"]), "address": e["address"], "args": e["args"],
                "ramp_s": e.get("ramp_s", 0.0), "felt": e.get("felt"),
                "predicted": e.get("predicted")}
               for e in journal if e.get("event") == "accepted"]
    if not changes or "k" not in measured or measured.get("first_row") is None:
        return changes
    a = int(measured["first_row"])
    b = a + int(measured.get("samples_used", 0))

    def end(c):
        return c["sample"] + int(math.ceil(c["ramp_s"] * rate_hz)) + 1

    inside = [c for c in changes if c["sample"] < b and end(c) > a]
    before = [c for c in changes if end(c) <= a]
    if inside:
        c = inside[0]
        measured["comparable"] = False
        measured["compared_with"] = None
        measured["verdict"] = (f"not comparable: the scene changed while it was measured "
                               f"({c['address']} {' '.join(map(str, c['args']))} at sample "
                               f"{c['sample']}, window {a}..{b})")
        measured.pop("within", None)
        return changes
    if not before:
        measured["compared_with"] = "the start's prediction (every change came after the "\
                                    "measured window)"
        return changes
    c = before[-1]
    kp, bp = (float(v) for v in c["felt"])
    pred = {"k": kp, "b": bp, **{q: v for q, v in (c.get("predicted") or {}).items()
                                 if q not in ("k", "b")}}
    measured["compared_with"] = {**pred, "after": f"{c['address']} "
                                 f"{' '.join(map(str, c['args']))} at sample {c['sample']}"}
    measured["rel_err"] = {q: ((measured[q] - v) / v if v else math.nan)
                           if v is not None and measured.get(q) is not None else math.nan
                           for q, v in ((q, pred.get(q)) for q in
                                        ("k", "b", "f0_hz", "damping_ratio"))}
    if "k_interval" in measured:
        ok = (abs(measured["k"] - kp) <= measured["k_interval"]
              and abs(measured["b"] - bp) <= measured["b_interval"])
        measured["within"] = bool(ok)
        measured["verdict"] = ("measured = predicted after the changes within the stated "
                               "uncertainty" if ok else "measured differs from the prediction "
                               "after the changes by more than the stated uncertainty")
    return changes


def identify_window(x: np.ndarray, scene) -> dict:
    """Felt (k, b) of a free response window, measured as ``hapsim run`` measures it.

    :func:`hapsim.analysis.measurement.identify` with the run's arguments: the predicted non-zero
    closed-loop poles seen at the port and the predicted felt pole
    (:func:`hapsim.analysis.prediction.predicted_poles`), the equilibrium offset
    (:func:`hapsim.analysis.prediction.has_offset`), the device's sensor step and noise, so the
    answer is :func:`hapsim.analysis.identify.measure_felt` (exact matrix pencil for an
    exact record, variable projection started from the prediction otherwise).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Device positions [m], one per device sample, from the start of a free response.
    scene : hapsim.scene.Scene
        The calibrated scene of the loop that produced them (device delay included).

    Returns
    -------
    dict
        :func:`~hapsim.analysis.measurement.identify`'s result: ``k`` [N/m], ``b`` [N s/m],
        ``k_unc``, ``b_unc`` ... or ``error`` (str) when the window cannot carry a
        measurement.
    """
    from hapsim.analysis.network import device_body
    from hapsim.analysis.measurement import identify
    from hapsim.analysis.prediction import has_offset, predicted_poles

    x = np.asarray(x, dtype=float)
    dev = scene.device
    try:
        poles, felt = predicted_poles(scene)
        order = int(poles.size)
        if not order:
            return {"error": "the loop has no oscillation to measure"}
        response = None
        quantum = float(dev.position_resolution or 0.0)
        if quantum > 0 or dev.noise > 0:
            from hapsim.analysis.error_response import sensor_error_response
            response = sensor_error_response(scene, int(x.size))
        return identify(x, np.arange(x.size), scene.period, order, device_body(dev)[0], 0,
                        offset=has_offset(scene), skip=int(dev.delay) + 2,
                        predicted=poles, felt=felt, quantum=quantum, noise=float(dev.noise),
                        sensor_response=response)
    except (ConfigError, ValueError, np.linalg.LinAlgError) as exc:
        return {"error": str(exc)}


def write_journal(path: str, journal: list) -> None:
    """Write a change journal (:attr:`Controller.journal`) as JSON to ``path`` (through a
    ``.partial`` file renamed at the end: a reader never sees half of it).

    Parameters
    ----------
    path : str
        ``--journal FILE.json``.
    journal : list of dict
    """
    from hapsim.outputs import json_safe, write_json
    write_json(path, json_safe(journal), indent=1)
