"""A rotary axis's figures said in its units, and a record inside a few sensor steps
said to be so.

1. The 1-D analyses are one code for every protocol, written in metres and newtons; on a
   rotary axis (the Haply joint, ``configs/haply.yaml``) those figures are radians and
   newton metres. ``hapsim run``'s report and every scene command's output say the
   joint's units (:func:`hapsim.drivers.in_axis_units`); before, ``hapsim run
   configs/haply.yaml`` printed ``k [N/m]`` and ``K_max 1.33222 N/m`` for a torsion
   spring of 0.5 N m/rad.
2. A record that never leaves a band of 5 sensor steps about its rest holds no
   oscillation above them, whatever amplitude a fit's cancelling modes give its pair: the
   Haply joint started at 0.002 rad (1.6 of its 0.00129 rad counts) was said to hold
   "only 1.6e-07 oscillation cycles" above them, with the remedy "fewer disturbances".
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.drivers import axis_units, in_axis_units

ROTARY = axis_units("haply")
SI = axis_units(None)

#: A figure followed by a linear axis's SI unit (what a rotary report must not hold).
_SI_AFTER_NUMBER = re.compile(r"\d (N s/m|N/m|m/s|kg(?! m\^2)|m|N(?! m))(?![\w/^])")


def test_si_units_after_a_number_or_in_brackets_are_said_in_the_joints():
    said = in_axis_units("k [N/m] b [N s/m]: K_max 1.3 N/m, B 0.2 N s/m, force 0.12 N, "
                         "mass 0.001 kg, speed 5 m/s, 2.5 mm, 3 um and 0.00129 m", ROTARY)
    assert said == ("k [N m/rad] b [N m s/rad]: K_max 1.3 N m/rad, B 0.2 N m s/rad, force "
                    "0.12 N m, mass 0.001 kg m^2, speed 5 rad/s, 2.5 mrad, 3 urad and "
                    "0.00129 rad")
    # said once: the rotary words are not said again
    assert in_axis_units(said, ROTARY) == said
    # words, milliseconds, microseconds and hertz are no units of length or force
    for text in ("the mass moved 5 ms later", "5 Hz, 20 ms + 5 us", "sample 5 of the N",
                 "mode m = 2", "0.1 N m and 2 kg m^2"):
        assert in_axis_units(text, ROTARY) == text
    # a linear axis: the same object back
    text = "K_max 1.3 N/m"
    assert in_axis_units(text, SI) is text
    nested = {"a": ["0.5 m", ("1 N",)], "b": 3, "c": None}
    assert in_axis_units(nested, ROTARY) == {"a": ["0.5 rad", ("1 N m",)], "b": 3, "c": None}


@pytest.fixture(scope="module")
def haply_run():
    """A run through the Haply board's bytes (lockstep by name: the words are checked,
    not the timing): the API's report."""
    import hapsim
    return hapsim.run("configs/haply.yaml", driver="haply", lockstep=True, duration=1.0,
                      handle_signals=False, rt_priority=0)


def test_hapsim_run_on_the_haply_joint_reports_in_its_units(haply_run):
    """The report of a run through the Haply board's bytes, against the framed wall's,
    SI."""
    from hapsim.pipeline.report import format_report
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    rep = haply_run.to_dict()
    assert rep["units"] == ROTARY
    text = format_report(rep)
    assert "k [N m/rad]" in text and "b [N m s/rad]" in text and "N m/rad;" in text
    assert not _SI_AFTER_NUMBER.findall(text), text
    # the verdict's sentence and the stated interval's note are the joint's too
    assert not _SI_AFTER_NUMBER.findall(str(rep["measured"]))
    wall = run_scene(load_scene("configs/wall.yaml"), transport="inprocess", lockstep=True,
                     handle_signals=False, duration=0.5)
    assert wall["units"] == SI
    assert "k [N/m]" in format_report(wall)


@pytest.mark.parametrize("command", [["check"], ["advise"], ["stability", "--scene"]])
def test_the_scene_commands_say_a_rotary_scenes_units(command, capsys):
    assert main(command + ["configs/haply.yaml"]) in (0, 1)
    out = capsys.readouterr().out
    assert "N m/rad" in out and not _SI_AFTER_NUMBER.findall(out), out
    assert main(command + ["configs/wall.yaml"]) in (0, 1)
    assert "N/m" in capsys.readouterr().out


def test_an_n_d_scene_keeps_its_metres_whatever_its_driver():
    """The 2DIY's pantograph is driven through the Haply board (``--driver haply``), but
    its scene's coordinates are Cartesian metres: its output is not rewritten; a 1-D
    scene named with ``--driver haply`` is."""
    import argparse
    import sys

    from hapsim.cli import _in_scene_units
    before = sys.stdout
    for scene, driver, rotary in (("configs/pantograph_spring.yaml", "haply", False),
                                  ("configs/wall.yaml", None, False),
                                  ("configs/wall.yaml", "haply", True),
                                  ("configs/haply.yaml", None, True),
                                  ("configs/haply.yaml", "framed", True)):
        with _in_scene_units(argparse.Namespace(scene=scene, driver=driver)):
            assert (sys.stdout is not before) == rotary, (scene, driver)
        assert sys.stdout is before
        # identify's --mock-scene, by the same rule
        with _in_scene_units(argparse.Namespace(mock_scene=scene, driver=driver)):
            assert (sys.stdout is not before) == rotary, (scene, driver)
    # identify's --driver with no scene: the driver's axis (before, its refusals said
    # "kg" of the Haply joint whose fit said "kg m^2")
    import io
    err = sys.stderr
    try:
        for driver, said in (("haply", "0.000226 kg m^2"), ("firefader", "0.000226 kg"),
                             ("framed", "0.000226 kg"), (None, "0.000226 kg")):
            sys.stderr = io.StringIO()
            with _in_scene_units(argparse.Namespace(mock_scene=None, driver=driver)):
                sys.stderr.write("0.000226 kg")
            assert sys.stderr.getvalue() == said, driver
    finally:
        sys.stderr = err


@pytest.mark.parametrize("x0", [0.0015, 0.002, 0.0025])
def test_a_record_inside_five_counts_is_said_to_be_so(x0):
    """The shipped Haply joint started within 2 of its counts (0.00129 rad): the record
    never leaves 5 counts about its rest, so the measurement says that, with the record's
    excursion, never a count of cycles or a remedy of fewer disturbances (before: at
    0.002 rad, "only 1.6e-07 oscillation cycles ... fewer disturbances are needed")."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import parse_scene
    text = open("configs/haply.yaml").read().replace("x0: 0.2 ", f"x0: {x0} ")
    assert f"x0: {x0} " in text
    rep = run_scene(parse_scene(text), driver="haply", handle_signals=False, rt_priority=0,
                    lockstep=True)
    m = rep["measured"]
    q = 2.0 * math.pi / 4880.0              # the joint's count [rad] (configs/haply.yaml)
    assert m["record_amplitude"] < 5.0 * q
    assert m.get("k") is None and rep["verdict"] == "not measurable"
    assert m["error"].startswith("the record's largest excursion from rest ("), m["error"]
    assert "cycles" not in m["error"] and "disturbances" not in m["error"]


def test_a_record_inside_five_steps_over_random_quantised_loops():
    """The class, on hapsim's framed mock: random lightly damped loops started within
    0.6..4.5 encoder steps; whenever the record stays inside 5 steps of its rest, the
    measurement says so by its excursion."""
    from hapsim.pipeline.runner import run_scene
    from test_identify_quantised import _random_loop, _scene   # same directory
    rng = np.random.default_rng(20261129)
    for i in range(8):
        m, b0, K, B, d, rate, r = _random_loop(rng)
        q = float(rng.uniform(5e-6, 50e-6))
        x0 = float(rng.uniform(0.6, 4.5)) * q
        rep = run_scene(_scene(m, b0, K, B, d, rate, q, 0.0, x0), transport="inprocess",
                        lockstep=True, handle_signals=False, duration=1.5, seed=i)
        meas = rep["measured"]
        if meas.get("record_amplitude", math.inf) < 5.0 * q:
            assert meas["error"].startswith("the record's largest excursion"), meas["error"]


def test_the_live_views_layout_carries_the_axis_units():
    """``run --view``: the page labels its traces, sliders and felt pair from the hello's
    ``layout.units`` (the run's protocol: the scene's, or ``--driver``'s); an n-D scene's
    are SI. Its script writes no unit of a linear axis other than its SI default."""
    from pathlib import Path

    from hapsim.scene import load_scene, load_scene_nd
    from hapsim.view.sources import scene_layout
    assert scene_layout(load_scene("configs/haply.yaml"))["units"] == ROTARY
    assert scene_layout(load_scene("configs/wall.yaml"))["units"] == SI
    assert scene_layout(load_scene("configs/wall.yaml"), "haply")["units"] == ROTARY
    # the framed protocol names no axis: the scene's own
    assert scene_layout(load_scene("configs/haply.yaml"), "framed")["units"] == ROTARY
    assert scene_layout(load_scene_nd("configs/pantograph_spring.yaml"), "haply")["units"] == SI
    js = (Path(__file__).resolve().parents[1] / "hapsim" / "view" / "static" / "view.js"
          ).read_text()
    literal = [ln for ln in js.splitlines()
               if re.search(r"N/m|N s/m|\[m\]|\[N\]|\} N`|force: \"N\"", ln)]
    assert len(literal) == 1 and "units: {" in literal[0], literal


def test_the_charts_of_a_joints_run_and_identification_say_its_units(haply_run):
    """``run --plot`` (:func:`hapsim.plots.plot_felt`, the report's ``units``) and
    ``identify --plot`` (:func:`hapsim.plots.plot_identify`, the driver's units)."""
    pytest.importorskip("matplotlib", reason="the charts' optional extra (hapsim[plot])")
    from hapsim.plots import plot_felt, plot_identify
    fig = plot_felt(haply_run)
    ax = fig.axes[0]
    words = [ax.get_xlabel(), ax.get_ylabel()] + [t.get_text() for t in
                                                  ax.get_legend().get_texts()]
    assert words[:2] == ["k [N m/rad]", "b [N m s/rad]"]
    assert not _SI_AFTER_NUMBER.findall(" ".join(words)), words
    # (the figure's words only: a fit's fields, not an identification's 2 s)
    from types import SimpleNamespace as NS
    fit = NS(n_samples=100, period=1e-3, model=np.zeros(100), mass=NS(value=0.001),
             friction=NS(value=0.001), coulomb=NS(value=0.002), delay=1, hold="zoh")
    fig = plot_identify(fit, {"position": np.zeros(100), "loop": {}}, ROTARY)
    top, bottom = fig.axes
    assert top.get_ylabel() == "position [mrad]" and bottom.get_ylabel().endswith("[urad]")
    assert "kg m^2" in top.get_title() and not _SI_AFTER_NUMBER.findall(top.get_title())


def test_a_refusal_of_a_joints_scene_says_its_units(tmp_path, capsys):
    """A refusal on stderr (``hapsim run`` of a torsion spring beyond the joint's stability
    limit) names its K, B and K_max in the joint's units."""
    path = tmp_path / "stiff_joint.yaml"
    path.write_text(open("configs/haply.yaml").read().replace("stiffness: 0.5,",
                                                              "stiffness: 5.0,"))
    assert main(["run", str(path), "--lockstep"]) == 1
    err = capsys.readouterr().err
    assert "K_max = 1.33222 N m/rad" in err and "m = 0.001 kg m^2" in err, err
    assert not _SI_AFTER_NUMBER.findall(err), err


def test_a_driver_of_the_other_axis_kind_is_refused():
    """A scene written for a linear axis driven through a rotary joint, or the reverse,
    is another device (the FireFader's 0.05 kg fader read as a 0.05 kg m^2 joint, 50 times
    the Haply's inertia, under a 15 N m/rad spring): refused by name, on every pair of
    the registry's 1-D families of different kinds, by the command and by the API; a
    framed scene names no axis and takes any driver."""
    import hapsim
    from hapsim.drivers import DEFAULT, DRIVERS, protocol_of
    from hapsim.errors import ConfigError
    from hapsim.scene import load_scene
    scenes = {"firefader": "configs/firefader.yaml", "haply": "configs/haply.yaml",
              "hapkit-serial": "configs/hapkit_serial.yaml"}
    assert set(scenes) == set(DRIVERS) - {DEFAULT}
    pairs = 0
    for named, path in scenes.items():
        scene = load_scene(path)
        for driver in DRIVERS:
            if driver in (named, DEFAULT):
                assert protocol_of(scene, driver)[0] == driver
                continue
            if (axis_units(driver) == ROTARY) == (axis_units(named) == ROTARY):
                assert protocol_of(scene, driver)[0] == driver      # same kind: taken
                continue
            pairs += 1
            with pytest.raises(ConfigError) as err:
                protocol_of(scene, driver)
            assert err.value.key == "--driver" and named in str(err.value)
            with pytest.raises(ConfigError):
                hapsim.run(path, driver=driver, lockstep=True, handle_signals=False)
    assert pairs == 4
    wall = load_scene("configs/wall.yaml")
    assert all(protocol_of(wall, d)[0] == d for d in DRIVERS)


def test_identify_writes_a_rotary_scenes_device_file_in_its_units(tmp_path, capsys):
    """``identify --mock-scene configs/haply.yaml`` over the framed protocol (which names
    no axis): the device file written by ``--out`` says the joint's units, like the
    report on stdout, and still loads as a device section."""
    from hapsim.device_file import load_device
    out = tmp_path / "joint.yaml"
    assert main(["identify", "--mock-scene", "configs/haply.yaml", "--driver", "framed",
                 "--lockstep", "--out", str(out)]) == 0
    text = out.read_text()
    assert "[kg m^2]" in text and "[N m s/rad]" in text and "[kg]" not in text
    assert not _SI_AFTER_NUMBER.findall(text), text
    assert capsys.readouterr().out.count("[kg m^2]") >= 1
    dev = load_device(str(out))
    # (the file loads back; bound: 1 %, far above the stated interval, < 1e-9 relative)
    assert dev.mass == pytest.approx(0.001, rel=0.01)
