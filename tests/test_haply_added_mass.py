"""``hapsim identify --driver haply --added-mass`` end to end (issue 20): the emulated
Haply board (firmware V1.5's bytes, :class:`hapsim.emulated.driver_mock.HaplyDevice`, behind a
pty) with an encoder whose true counts per revolution the host does not know (a seeded
random one, the host assuming 4880). Through a wrong resolution the joint's angle is read
``g = cpr / 4880`` times too large, so the identified inertia is ``m / g``
(:mod:`hapsim.analysis.calibration`); two identifications, without and with a known
added inertia, give ``g`` and so the true resolution, written to the device file's
protocol_options. The command's own steps (``hapsim.commands.identify.run``) are taken
through the API so that each record's link can be read: the mock answers each write, but
a machine loaded enough to stall its process past the transport's reply deadline makes
missing samples and re-synchronisations (counted in the record). Those are in the stated
uncertainty, so the intervals must hold the truth whatever the load; only on such a
spoiled link may the command refuse instead (with its reason), never on a clean one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tolerance import rel_tol

#: The joint's inertia in configs/haply.yaml [kg m^2] and the inertia added [kg m^2].
INERTIA = 0.001
ADDED = 0.002


def test_added_mass_finds_the_true_resolution(tmp_path):
    """The resolution found has an interval that holds the true one, the device's inertia
    in its own units an interval that holds 0.001 kg m^2, the direction probe ran first
    (the motor byte of this wiring: 0), and the device file's protocol_options hold the
    resolution found (what ``run`` then sends in its set-up)."""
    from hapsim.api import calibrate_scale, identify
    from hapsim.device_file import device_yaml, load_device
    from hapsim.drivers import get_driver
    from hapsim.scene import load_scene
    cpr = float(np.random.default_rng(2026).integers(2500, 12000))
    dev = load_scene("configs/haply.yaml").device
    kw = dict(force_limit=0.1, envelope=1.0, duration=4.0, rate_hz=250.0, max_delay=4,
              lockstep=True, seed=0, driver="haply", driver_options={"resolution": 4880.0},
              progress=False, handle_signals=False,
              mock_options={**get_driver("haply", resolution=4880.0).mock_hardware(),
                            "cpr": cpr})
    from hapsim.errors import HapsimError
    links = []
    try:
        bare = identify(None, device=dev, **kw)
        links.append(bare.record["loop"]["driver"])
        loaded = identify(None, device=dataclasses.replace(dev, mass=dev.mass + ADDED), **kw)
        links.append(loaded.record["loop"]["driver"])
        sc, fit, found = calibrate_scale(bare, loaded, ADDED,
                                         get_driver("haply", **bare.record["protocol_options"]))
    except HapsimError as exc:
        # a refusal, with its reason, is an honest answer only for a record the machine's
        # load spoiled (missing samples, re-synchronisations, counted in the record); on a
        # clean link the two identifications must resolve the added inertia
        assert links and any(link["missing"] or link["resyncs"] for link in links), exc
        assert str(exc)
        return
    # the intervals hold the truth whether or not the link was clean: the missing samples
    # and re-synchronisations are in the stated uncertainty (never a wrong answer)
    probe = bare.record["loop"]["direction_probe"]
    assert probe["motor_direction"] == 0 and probe["relative"] == 1
    assert sc.full_scale_lo <= cpr <= sc.full_scale_hi, (cpr, sc)
    # one division each side: derived rel_tol(2); measured 0
    assert sc.gain == pytest.approx(sc.full_scale / 4880.0, rel=rel_tol(2))
    assert fit.mass.lo <= INERTIA <= fit.mass.hi, fit.mass
    out = tmp_path / "dev.yaml"
    out.write_text(device_yaml(fit, 0.1, driver=found))
    d = load_device(out)
    assert d.protocol == "haply" and d.protocol_options["motor_direction"] == 0
    # (the file holds 6 digits: far inside the interval)
    # derived: 6 significant digits round by half a unit of the sixth at most, 5e-6 of the
    # value, and reading it back rounds once more (measured 7.1e-7)
    assert d.protocol_options["resolution"] == pytest.approx(sc.full_scale,
                                                             rel=5e-6 + rel_tol(1))

