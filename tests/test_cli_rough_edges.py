"""The rough edges of the command line (issue 21): each with its message and exit code.

- stdout closed by its reader (``| head``): no traceback, exit 141 (128 + SIGPIPE);
- an unknown option: the sub-command's usage and "did you mean", exit 2;
- Ctrl-C with ``--json``: the ``interrupted`` object on stdout, exit 130.
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hapsim.cli import EXIT_BROKEN_PIPE, _did_you_mean, build_parser, main
from test_new_user import interrupted  # same directory (pytest prepend import mode)

ROOT = Path(__file__).resolve().parents[1]
WALL = str(ROOT / "configs" / "wall.yaml")
LOOP = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1",
        "--hold", "zoh"]


class ClosedPipe(io.TextIOBase):
    """A stdout whose reader has gone: every write raises what a closed pipe raises."""

    def writable(self):
        return True

    def write(self, s):
        raise BrokenPipeError(32, "Broken pipe")


def journal(tmp_path) -> str:
    from hapsim.host.telemetry import write_journal
    n = 500
    rng = np.random.default_rng(2)
    cols = {"time": np.arange(n) * 1e-3, "position": rng.normal(size=n) * 1e-3,
            "force": rng.normal(size=n), "seq": np.arange(n, dtype=np.int64),
            "turnaround_us": rng.uniform(10, 90, n), "late": np.zeros(n, np.int8),
            "flags": np.zeros(n, np.uint8)}
    return write_journal(cols, str(tmp_path / "t.hst"))


@pytest.mark.parametrize("argv", [
    ["check", WALL, "--json"], ["check", WALL],
    ["render", *LOOP, "--K", "2000", "--B", "2"],
    ["render", *LOOP, "--K", "2000", "--B", "2", "--json"],
    ["calibrate", *LOOP, "--k", "2000", "--b", "3"],
    ["stability", *LOOP, "--B", "2"],
    ["telemetry", "JOURNAL", "--json"], ["telemetry", "JOURNAL"],
], ids=lambda a: " ".join(Path(x).name for x in a))
def test_closed_stdout_is_quiet_exit_141(argv, tmp_path, monkeypatch, capsys):
    """A reader that went away (``| head``) ends the command with 141 and nothing on
    stderr, whatever the command was printing (text, JSON, help)."""
    argv = [journal(tmp_path) if a == "JOURNAL" else a for a in argv]
    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    assert main(argv) == EXIT_BROKEN_PIPE == 128 + signal.SIGPIPE
    assert capsys.readouterr().err == ""


def test_head_on_a_real_pipe_leaves_no_traceback():
    """The console entry on a real pipe whose reader has closed: no ``BrokenPipeError``,
    no "Exception ignored" from the interpreter's last flush, status 141."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r, w = os.pipe()
    os.close(r)       # the reader is gone before hapsim writes a byte
    p = subprocess.run([sys.executable, "-m", "hapsim", "render", *LOOP, "--K", "1000",
                        "--json"], stdout=w, stderr=subprocess.PIPE, text=True, env=env,
                       cwd=ROOT, timeout=120)
    os.close(w)
    assert p.stderr == "" and p.returncode == EXIT_BROKEN_PIPE, (p.returncode, p.stderr)


def test_unknown_option_names_the_subcommand_and_the_close_option(capsys):
    """``run SCENE --duraton 2``: the usage of ``hapsim run`` (not the top level) and the
    option meant; exit 2; with ``--json`` the same message in the usage error object."""
    assert main(["run", WALL, "--duraton", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: hapsim run ")
    assert err.rstrip().endswith("hapsim run: error: unrecognized arguments: --duraton 2 "
                                 "(did you mean --duration?)"), err
    assert main(["check", WALL, "--jsn"]) == 2
    assert "usage: hapsim check " in (e := capsys.readouterr().err) \
        and "(did you mean --json?)" in e
    assert main(["run", WALL, "--duraton=2", "--sed", "3", "--json"]) == 2
    got = json.loads(capsys.readouterr().out)
    assert got["exit"] == 2 and got["error"]["type"] == "usage"
    assert got["error"]["message"] == (
        "hapsim run: unrecognized arguments: --duraton=2 --sed 3 "
        "(--duraton: did you mean --duration?; --sed: did you mean --seed?)")


def test_far_from_every_option_no_guess(capsys):
    assert main(["check", WALL, "--zzzzqqq"]) == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: --zzzzqqq" in err and "did you mean" not in err


def _command_names():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted(sub.choices)


@pytest.mark.parametrize("edit", ["swap", "drop", "double"])
def test_every_mistyped_command_is_suggested_back(edit, capsys):
    """``hapsim chekc``: for every command, two inner letters swapped, one dropped or one
    doubled gets "did you mean COMMAND?" on the usage error (exit 2), as a mistyped option
    does; a word close to no command gets the list of commands and no guess."""
    missed = []
    for name in _command_names():
        i = len(name) // 2
        typo = {"swap": name[:i] + name[i + 1] + name[i] + name[i + 2:],
                "drop": name[:i] + name[i + 1:],
                "double": name[:i] + name[i] + name[i:]}[edit]
        if typo == name:
            continue
        code = main([typo, WALL])
        err = capsys.readouterr().err
        if code != 2 or not err.rstrip().endswith(f"(did you mean {name}?)"):
            missed.append((typo, code, err.splitlines()[-1]))
    assert not missed, missed
    assert main(["zzzzqqq"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'zzzzqqq'" in err and "did you mean" not in err


def _long_options():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        known = sorted(o for a in p._actions for o in a.option_strings)
        for opt in known:
            if opt.startswith("--") and len(opt) >= 6:
                yield name, opt, known


def test_every_option_is_found_again_from_a_transposition():
    """For every long option of every command: the option with two inner letters swapped
    (a typo argparse's prefix matching does not absorb) is suggested back."""
    missed = []
    for name, opt, known in _long_options():
        i = len(opt) // 2
        typo = opt[:i] + opt[i + 1] + opt[i] + opt[i + 2:]
        if typo == opt:
            continue
        hint = _did_you_mean([typo], known)
        if hint != f" (did you mean {opt}?)":
            missed.append((name, opt, typo, hint))
    assert not missed


@pytest.mark.parametrize("argv", [["check", "configs/wall.yaml", "--json"],
                                  ["run", "configs/wall.yaml", "--json", "--duration", "5"]],
                         ids=["check", "run"])
def test_ctrl_c_with_json_prints_the_interrupted_object(tmp_path, argv):
    """Ctrl-C while hapsim is still importing (when its import of numpy starts: a SIGINT
    sent 0.1 s after start-up came after check had finished, or once run's own handler
    was in place, on a loaded machine): stdout holds the ``interrupted`` object the README
    promises, stderr one line, exit 130."""
    code, out, err = interrupted(argv, None, tmp_path, at_import="numpy")
    assert code == 130, (code, err)
    assert err.strip().splitlines()[-1].endswith("interrupted") and "Traceback" not in err
    got = json.loads(out)
    assert got == {"error": {"type": "interrupted", "message": "hapsim: interrupted",
                             "file": None, "line": None, "key": None}, "exit": 130}


def test_ctrl_c_in_an_import_is_reported_whatever_the_streams_are_doing():
    """The quiet Ctrl-C (``hapsim/__init__.py``) ends the process from a signal handler,
    which can interrupt a write to ``sys.stderr`` or ``sys.stdout`` (a buffered stream
    entered again raises ``RuntimeError``: one CI run's Ctrl-C test ended 130 with nothing
    after its start marker). Here both streams raise on every write and flush, and the
    SIGINT comes inside an import: the line and the ``--json`` object still come out, on
    the file descriptors, and the status is 130."""
    import subprocess
    import sys
    code = ("import os, signal, sys\n"
            "sys.argv[0] = '-m'\n"
            "import hapsim\n"
            "class Reentered:\n"
            "    def write(self, *a):\n"
            "        raise RuntimeError('reentrant call inside <_io.BufferedWriter>')\n"
            "    flush = write\n"
            "sys.stdout = sys.stderr = Reentered()\n"
            "class CtrlC:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'hapsim_test_absent':\n"
            "            os.kill(os.getpid(), signal.SIGINT)\n"
            "sys.meta_path.insert(0, CtrlC())\n"
            "import hapsim_test_absent\n")
    proc = subprocess.run([sys.executable, "-c", code, "check", "--json"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 130, proc
    assert proc.stderr == "hapsim: interrupted\n"
    assert json.loads(proc.stdout)["error"]["type"] == "interrupted"


# ------------------------------------------------------------------ the device's protocol
@pytest.fixture
def fake_run(monkeypatch):
    """``run_scene`` replaced by a recorder: it announces the start as the runner does,
    keeps its arguments, and ends the run with a DeviceError (nothing to report)."""
    from hapsim.pipeline import runner
    from hapsim.errors import DeviceError
    seen = {}

    def run_scene(scene, options=None, **kw):
        import dataclasses
        opts = dataclasses.replace(options if options is not None else runner.RunOptions(),
                                   **kw)
        seen.update({f.name: getattr(opts, f.name) for f in dataclasses.fields(opts)},
                    scene=scene)
        opts.on_start("/dev/fake", 1000)
        raise DeviceError("recorded")

    monkeypatch.setattr(runner, "run_scene", run_scene)
    import hapsim.pipeline.startup as startup
    monkeypatch.setattr(startup, "start_embedded_mock", lambda *a, **k: None)
    return seen


@pytest.mark.parametrize("config, protocol", [("firefader", "firefader"), ("haply", "haply"),
                                              ("hapkit_serial", "hapkit-serial")])
def test_a_scene_names_its_protocol_and_run_says_it(config, protocol, fake_run, capsys):
    path = str(ROOT / "configs" / f"{config}.yaml")
    assert main(["run", path]) == 1
    err = capsys.readouterr().err
    assert fake_run["driver"] == protocol
    assert (f"closing the loop on /dev/fake in the {protocol} protocol (the scene's "
            f"device.protocol) for 1000 samples") in err
    # another driver of the same axis kind (a linear one's other; the rotary joint has
    # none, and the framed protocol names no axis): said with the scene's; one of the
    # other kind is refused (tests/test_rotary_units.py)
    other = {"firefader": "hapkit-serial", "hapkit-serial": "firefader"}.get(protocol,
                                                                           "framed")
    assert main(["run", path, "--driver", other]) == 1
    assert fake_run["driver"] in ((None, "framed") if other == "framed" else (other,))
    assert (f"in the {other} protocol (--driver; the scene's device.protocol is {protocol})"
            in capsys.readouterr().err)
    assert main(["run", path, "--driver", "firefader" if protocol == "haply" else "haply"]) == 2


def test_framed_is_said_and_passed_as_no_driver(fake_run, capsys):
    """The run is handed hapsim's own protocol, which its options' check stores as no
    driver, once (RunOptions.check; the pipeline then tests ``driver is None`` only)."""
    from hapsim.pipeline.options import RunOptions
    assert main(["run", WALL]) == 1
    assert fake_run["driver"] in (None, "framed")
    opts = RunOptions(driver=fake_run["driver"], handle_signals=False, lockstep=True,
                      transport="inprocess")
    assert opts.protocol == "framed" and opts.check().driver is None
    assert RunOptions(driver="firefader").protocol == "firefader"
    assert "closing the loop on /dev/fake in the framed protocol for" in capsys.readouterr().err


def test_protocol_key_is_validated_and_drivers_follow_it(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text((ROOT / "configs" / "firefader.yaml").read_text()
                   .replace("protocol: firefader", "protocol: firefadr"))
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "device.protocol" in err and "firefadr" in err \
        and "valid choices: framed, firefader, haply, hapkit-serial" in err


def test_device_file_says_what_it_replaced_and_keeps_protocol_and_limit(tmp_path, fake_run,
                                                                        capsys):
    dev = tmp_path / "dev.yaml"
    dev.write_text("device:\n  mass: 0.06\n  friction: 0.12\n  delay: 0.725\n")
    assert main(["run", str(ROOT / "configs" / "firefader.yaml"), "--device", str(dev)]) == 1
    err = capsys.readouterr().err
    assert (f"hapsim run: the device of {dev} replaces the scene's (mass 0.05 -> 0.06; "
            f"friction 0.1 -> 0.12)") in err
    d = fake_run["scene"].device
    assert (d.mass, d.friction, d.protocol, d.force_limit) == (0.06, 0.12, "firefader", 0.38)
    assert fake_run["driver"] == "firefader"
    # a file that names them: its values win, and the line says so
    dev.write_text("device:\n  mass: 0.05\n  friction: 0.1\n  delay: 0.725\n  protocol: haply\n"
                   "  force_limit: 0.1\n")
    assert main(["run", str(ROOT / "configs" / "firefader.yaml"), "--device", str(dev)]) == 1
    err = capsys.readouterr().err
    assert "replaces the scene's (force_limit 0.38 -> 0.1; protocol firefader -> haply)" in err
    assert fake_run["driver"] == "haply"


# ------------------------------------------------------------------ play's report
def test_play_sound_line_is_readable():
    from hapsim.pipeline.play import sound_line
    line = sound_line({"backend": "JackOutput", "callback": "native", "xruns": 1,
                       "xrun_at_s": [0.25], "active_monotonic_s": 3.0, "block": 256,
                       "underrun_at_s": [], "pushed": 3000, "consumed": 3000,
                       "underruns": 0, "periods": 2990, "lead": 6, "waits": 2})
    assert line == ("sound: JackOutput (native callback), block 256 frames, lead 6 samples; "
                    "xruns 1 (at 0.250 s), underruns 0 frames; 2990 periods played, 2 waits")
    assert "{" not in line


def test_play_says_why_nothing_was_measured():
    """A window the identification refuses: the reason, not ``k = nan``."""
    from hapsim.audio.control import Controller
    from hapsim.engine import Engine
    from hapsim.scene import load_scene
    scene = load_scene(str(ROOT / "configs" / "wall.yaml"))
    ctl = Controller(scene, Engine(scene), background=False)
    try:
        assert ctl.unmeasured == "no free response has been measured yet"
        ctl.measure(np.zeros(80))
        assert math.isnan(ctl.measured[0])
        assert ctl.unmeasured.startswith("the last free response (80 samples) could not be "
                                         "measured: ")
        assert len(ctl.unmeasured) > len("the last free response (80 samples) could not be "
                                         "measured: ") + 10
    finally:
        ctl.close()


def test_play_measures_a_scene_released_by_x0_alone(capsys, monkeypatch):
    """wall.yaml has no hand force (x0 only): with --pluck-every its one free response,
    the first window, is measured (it never was), equal to the prediction (lockstep).
    The window is measured in a spawned analysis process that play waits END_WAIT_S
    (3 s) for after the run: on a loaded machine its start alone can take longer (the
    measurement is then dropped, and said so), so the test waits as long as it takes."""
    import hapsim.pipeline.play as play
    monkeypatch.setattr(play, "END_WAIT_S", 120.0)
    assert main(["play", WALL, "--sound", "none", "--lockstep", "--duration", "0.6",
                 "--pluck-every", "0.3", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["measured"]["why_not"] is None
    # measured 2.1e-15 relative (generic 3.3e-16), margin 4.8e5
    assert rep["measured"]["k"] == pytest.approx(rep["felt"]["k"], rel=1e-9)
    # measured 1.8e-13 relative (generic 3.1e-13), margin 3200
    assert rep["measured"]["b"] == pytest.approx(rep["felt"]["b"], rel=1e-9)


# ------------------------------------------------------------------ the plot extra
def test_missing_matplotlib_names_the_readmes_install_command(monkeypatch, tmp_path, capsys):
    from hapsim.plots import PLOT_INSTALL, pyplot
    from hapsim.errors import ConfigError
    assert f"`{PLOT_INSTALL}`" in (ROOT / "README.md").read_text(encoding="utf-8")
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)    # import matplotlib: ImportError
    with pytest.raises(ConfigError, match=re.escape(PLOT_INSTALL)):
        pyplot()
    assert main(["family", str(ROOT / "configs" / "hand_wall.yaml"), "--plot",
                 str(tmp_path / "f.png")]) == 2
    assert PLOT_INSTALL in capsys.readouterr().err


# ------------------------------------------------------------------ a string felt at the port
def test_check_says_a_string_mode_is_felt_and_the_static_stiffness(capsys):
    path = str(ROOT / "configs" / "audio_string.yaml")
    assert main(["check", path]) == 0
    out = capsys.readouterr().out
    # 30 beads, 31 segments of 1.5e5 N/m, plucked at s15 through a 200 N/m contact: the
    # port sees 200 in series with (15 segments) || (16 segments)
    k_static = 1 / (1 / 200 + 1 / (1.5e5 / 15 + 1.5e5 / 16))
    assert f"static at the port: k = {k_static:.6g} N/m (what a slow push feels" in out
    felt = re.search(r"felt at the port: k = (\S+) N/m.*f0 = (\S+) Hz", out)
    assert float(felt.group(1)) > 1000 * k_static
    assert (f"  that is a mode of the scene ringing at {felt.group(2)} Hz, felt at the port, "
            f"not a spring") in out
    assert main(["check", path, "--json"]) == 0
    # measured 1.4e-16 relative (generic 1.4e-16), margin 7000
    assert json.loads(capsys.readouterr().out)["static_k"] == pytest.approx(k_static, rel=1e-12)
    assert main(["check", WALL]) == 0      # no virtual mass: the felt k is the spring's
    out = capsys.readouterr().out
    assert "mode of the scene" not in out and "static at the port" not in out


def _chain_scene(springs, branches):
    """Port -- springs in series -- ground, plus parallel spring chains to other grounds."""
    lines = ["rate_hz: 1000", "masses:", "  - {name: p, kind: port}"]
    links = ["links:"]
    for c, chain in enumerate([springs, *branches]):
        prev = "p"
        for i, k in enumerate(chain):
            last = i == len(chain) - 1
            name = f"g{c}" if last else f"m{c}_{i}"
            lines.append(f"  - {{name: {name}, kind: {'ground' if last else 'mass'}"
                         f"{'' if last else ', mass: 0.01'}}}")
            links.append(f"  - {{kind: spring_damper, between: [{prev}, {name}], "
                         f"stiffness: {k!r}, damping: 0.1}}")
            prev = name
    return "\n".join(lines + links + ["device: {mass: 0.1, friction: 0.5}"]) + "\n"


def test_static_stiffness_is_series_and_parallel_springs():
    """Over random chains of springs from the port to grounds, in parallel: the static
    stiffness is the sum over chains of 1 / sum(1/K) (springs in series)."""
    from hapsim.analysis.virtual_network import static_stiffness
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(7)
    for _ in range(40):
        chains = [[float(k) for k in rng.uniform(10, 1e4, rng.integers(1, 6))]
                  for _ in range(rng.integers(1, 4))]
        scene = parse_scene(_chain_scene(chains[0], chains[1:]))
        want = sum(1 / sum(1 / k for k in ch) for ch in chains)
        # the Schur complement of the chain's Laplacian against the closed form: measured
        # 9.2e-15 relative over the 40 draws (generic 9.2e-15), margin 1e5
        assert static_stiffness(scene) == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("argv, where, fragment", [
    # no port: the run names the first mass's line and how to make one
    (["run", "oscillator.yaml"], "oscillator.yaml:6: masses:", "give the handle's mass "
                                                               "'kind: port'"),
    # the same refusal in 3-D (it said "a run needs a mass of kind 'port' and a device
    # section", with no line, no kinds and nothing to do instead)
    (["run", "membrane.yaml"], "membrane.yaml:14: masses:", "give the handle's mass "
                                                             "'kind: port'"),
    # family read the missing device before its own check: an AttributeError traceback
    (["family", "oscillator.yaml"], "oscillator.yaml:6: masses:", "needs a scene with a port"),
    (["advise", "oscillator.yaml"], "oscillator.yaml:6: masses:", "needs a scene with a port"),
    # family stepped the audio scene's network at 1 kHz only: "NOT ROBUSTLY STABLE
    # (certified)", spectral radius 597, for a scene check finds stable (0.9973)
    (["family", "audio_string.yaml"], "audio_string.yaml: audio:", "'hapsim check' predicts"),
    # advise met a rate of its ladder the audio rate is no multiple of: "audio.rate_hz: ...
    # 315 Hz", exit 2 as if the scene were bad; its matrices are single-rate too
    (["advise", "audio_string.yaml"], "audio_string.yaml: audio:", "'hapsim check' predicts"),
])
@pytest.mark.parametrize("json_out", [False, True])
def test_scene_a_command_cannot_take_is_exit_2_naming_file_and_key(capsys, argv, where,
                                                                   fragment, json_out):
    """A shipped scene given to a command that cannot take it: exit 2, one message with
    the file, the key (and the line where one exists) and what to do; with ``--json``
    stdout is the error object alone."""
    argv = [argv[0], str(ROOT / "configs" / argv[1])] + (["--json"] if json_out else [])
    assert main(argv) == 2
    out, err = capsys.readouterr()
    msg = json.loads(out)["error"]["message"] if json_out else err
    assert "Traceback" not in msg and where in msg and fragment in msg, msg


@pytest.mark.parametrize("lockstep", [False, True])
def test_a_scene_without_a_port_is_refused_alike_in_every_dimension(tmp_path, capsys,
                                                                    lockstep):
    """Random scenes with no mass of kind ``port`` (1 to 4 free masses on springs to
    grounds, in 1, 2 or 3 dimensions, their first mass on a random line): ``run`` (and
    ``run --lockstep``) refuses each with one message, whatever the dimension (issue 30:
    1-D is n = 1 of the same code): exit 2, the file and the first mass's line, the key
    ``masses``, the kinds its masses are, and what to do instead. The 2-D and 3-D run
    said "a run needs a mass of kind 'port' and a device section", with none of these."""
    rng = np.random.default_rng(30)
    for i in range(9):
        n = (1, 2, 3)[i % 3]
        pad = int(rng.integers(0, 4))                   # comment lines: the line moves
        free = int(rng.integers(1, 5))

        def at(v):
            return v if n == 1 else "[" + ", ".join([str(v)] + ["0.0"] * (n - 1)) + "]"
        lines = ["# a scene without a port"] * pad
        lines += ([f"dimension: {n}"] if n > 1 else []) + ["rate_hz: 1000", "masses:",
                                                          f"  - {{name: g, kind: ground, x0: {at(0.0)}}}"]
        lines += [f"  - {{name: m{j}, kind: mass, mass: {rng.uniform(0.01, 1.0):.4g}, "
                  f"x0: {at(0.01 * (j + 1))}}}" for j in range(free)]
        lines += ["links:"] + [
            f"  - {{name: s{j}, kind: spring_damper, between: [m{j}, g], stiffness: "
            f"{rng.uniform(10.0, 1000.0):.4g}, damping: 0.1}}" for j in range(free)]
        path = tmp_path / f"no_port_{i}.yaml"
        path.write_text("\n".join(lines) + "\n")
        line = pad + (4 if n > 1 else 3)                # the first mass's line
        argv = ["run", str(path)] + (["--lockstep"] if lockstep else [])
        assert main(argv) == 2, (n, lines)
        err = capsys.readouterr().err
        assert f"{path}:{line}: masses: the scene has no port" in err, (n, err)
        assert "its masses are 'ground', 'mass'" in err, (n, err)
        assert "give the handle's mass 'kind: port'" in err and "Traceback" not in err, err


@pytest.mark.parametrize("argv", [["family"]])
@pytest.mark.parametrize("name, line", [("pantograph_wall.yaml", 8), ("delta_mesh.yaml", 7),
                                        ("delta_sphere.yaml", 5)])
def test_nd_scene_to_a_1d_command_names_its_dimension_and_reason(capsys, argv, name, line):
    """A 2-D or 3-D scene given to a command that takes 1-D scenes (issue 30 item 2:
    refused by name with the reason): exit 2 at the line of ``dimension``, the command
    named with its own reason and what to use instead
    (:data:`hapsim.commands.dimension.ONE_D_ONLY`). The scenes with ``planes`` got
    "unknown key 'planes'" (the keys were checked before the dimension)."""
    from hapsim.commands.dimension import ONE_D_ONLY
    assert main([*argv, str(ROOT / "configs" / name)]) == 2
    err = capsys.readouterr().err
    assert f"{name}:{line}: dimension: a " in err, err
    assert f"hapsim {argv[0]} takes dimension 1: {ONE_D_ONLY[argv[0]]}" in err, err
    assert "unknown key" not in err


# ----------------------------------------------- every numeric option: bad values refused

#: A command line each sub-command parses (its positionals and required options): the
#: option under test is appended to it (argparse keeps the last value given).
NUMERIC_BASE = {
    "simulate": [WALL, "--steps", "5"], "render": [*LOOP, "--K", "1000"],
    "calibrate": [*LOOP, "--k", "1000", "--b", "1"], "stability": LOOP, "map": [],
    "check": [WALL], "run": [WALL], "mock": ["--scene", WALL], "bench": ["--out", "b.json"], "advise": [WALL],
    "play": [WALL], "telemetry": ["t.hst"], "identify": [], "family": [WALL],
    "compare-corrections": LOOP, "kinematics": ["delta", "--joints", "0", "0", "0"],
    "zwidth": [],
}


@functools.lru_cache(maxsize=1)
def _subparsers() -> dict:
    """Each sub-command's parser, by name (built once: the cases only read them)."""
    top = build_parser()
    return next(a for a in top._actions
                if isinstance(a, argparse._SubParsersAction)).choices


def _numeric_options() -> list:
    """(command, action) for every option whose values are numbers, read from the parsers."""
    return [(name, a) for name, p in _subparsers().items() for a in p._actions
            if a.option_strings and (a.type in (float, int) or hasattr(a.type, "describe"))]


def _bad_values(action) -> list[str]:
    """Values outside every numeric option's range, and below/above its declared bounds."""
    values = ["nan", "inf", "-inf", "abc"]
    kind = action.type
    if kind.low is not None:                     # below, and an open bound itself (0)
        values += [f"{kind.low - 1:g}"] + [f"{kind.low:g}"] * kind.open_low
    if kind.high is not None:                    # (past it by more than %g rounds off)
        values += [f"{kind.high + max(1.0, abs(kind.high) * 1e-3):g}"] + \
            [f"{kind.high:g}"] * kind.open_high
    return values


NUMERIC_CASES = [(name, action.option_strings[0], value)
                 for name, action in _numeric_options() for value in _bad_values(action)]


def test_every_numeric_option_declares_its_range():
    """A float or int option without a declared range (hapsim.option_values.Number) is
    refused here: then the generated cases below cover every new option."""
    from hapsim.option_values import Number
    bare = [f"{name} {a.option_strings[0]}" for name, a in _numeric_options()
            if not isinstance(a.type, Number)]
    assert not bare, f"declare type=Number(...) for: {bare}"
    assert set(NUMERIC_BASE) == set(_subparsers()), "give each command a base command line"
    assert len(NUMERIC_CASES) > 300


def test_defaults_are_in_their_declared_ranges():
    from hapsim.option_values import check_numbers
    for name, parser in _subparsers().items():
        check_numbers(parser, parser.parse_args(NUMERIC_BASE[name]))  # raises if not


@pytest.mark.parametrize("command, flag, value", NUMERIC_CASES,
                         ids=[f"{c}{f}={v}" for c, f, v in NUMERIC_CASES])
def test_bad_number_is_exit_2_naming_the_flag_and_the_range(capsys, command, flag, value):
    """nan, inf, -inf, a non-number, a value beyond a declared bound: exit 2 before any
    work, one line on stderr naming the flag as typed and the valid range; with --json
    stdout holds only the error object, keyed by the flag."""
    parser = _subparsers()[command]
    action = next(a for a in parser._actions if flag in a.option_strings)
    n = action.nargs if isinstance(action.nargs, int) else 1
    argv = [command, *NUMERIC_BASE[command], flag, value, *["1"] * (n - 1)]
    json_too = any("--json" in a.option_strings for a in parser._actions)
    assert main(argv + ["--json"] * json_too) == 2
    out, err = capsys.readouterr()
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    line = err.strip()
    assert line.startswith(f"hapsim {command}: error: {flag}: must be "), line
    assert action.type.describe() in line, line
    if json_too:
        doc = json.loads(out)
        assert out.count("\n") == 1 and doc["exit"] == 2, out
        assert doc["error"]["type"] == "ConfigError" and doc["error"]["key"] == flag
        assert doc["error"]["message"] == line
    else:
        assert out == ""


@pytest.mark.parametrize("argv, key", [
    (["kinematics", "delta", "--joints", "nan", "0", "0", "--json"], "--joints"),
    (["stability", *LOOP, "--B", "inf", "--json"], "--B"),
    (["simulate", WALL, "-n", "-3", "--json"], "-n"),           # the short form, as typed
    (["zwidth", "--B", "0", "nan", "--json"], "--B"),             # any of a list's values
])
def test_reported_cases_name_the_flag_as_typed(capsys, argv, key):
    assert main(argv) == 2
    doc = json.loads(capsys.readouterr().out)
    assert doc["error"] == {**doc["error"], "type": "ConfigError", "key": key}


@pytest.mark.parametrize("argv, key", [
    (["compare-corrections", "--mass", "0.1", "--rate", "1000", "--boundary-points",
      "100000000"], "--boundary-points"),
    (["compare-corrections", "--mass", "0.1", "--rate", "1000", "--n", "1000"], "--n"),
    (["zwidth", "--scene", "configs/hapkit.yaml", "--lockstep", "--duration", "1e6"],
     "--duration")])
def test_a_size_that_would_run_for_days_is_refused_by_its_range(capsys, argv, key):
    """Upper bounds on the sizes whose work grows with them (the boundary's exact limits,
    ~14 ms each; the grid's n^2 calibrations; a Z-width trial's record): refused with
    the range, exit 2 (before: ``--boundary-points 1e8`` ran silently for days)."""
    from hapsim.cli import main
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"error: {key}: must be" in err and ("to " in err or "<=" in err), err
