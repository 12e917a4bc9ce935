"""What a new user hits (issue 10, "tracebacks and inconsistent answers"), through the CLI.

Every case goes through ``hapsim.cli.main(argv)`` and asserts the one-line message on
stderr and the exit code (0 ok, 1 negative verdict, 2 bad input; docs/commands.md, 'Exit codes').
"""

from __future__ import annotations

import json
import re
import string

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.scene import load_scene, parse_scene

WALL = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
excitation: {x0: 0.005}
"""


def one_line_error(capsys, argv, code=2):
    """Run ``main(argv)``; assert the exit code and one line on stderr; return that line."""
    got = main(argv)
    err = capsys.readouterr().err
    assert got == code, err
    # (an empty numba cache adds the notice of what it compiles, said before the scene)
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("hapsim run: compil")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# ----------------------------------------------------------------- 1. encodings

@pytest.mark.parametrize("name, data, fragment", [
    ("latin1", WALL.replace("wall]", "w\xe4ll]").encode("latin-1"), "0xe4"),
    ("binary", bytes(range(256)) * 4, "not"),
    ("nul", WALL.encode() + b"\0\0", "binary"),
])
def test_non_utf8_scene_is_one_line_exit_2(tmp_path, capsys, name, data, fragment):
    path = tmp_path / f"{name}.yaml"
    path.write_bytes(data)
    msg = one_line_error(capsys, ["check", str(path)])
    assert str(path) in msg and fragment in msg and "UTF-8" in msg


@pytest.mark.parametrize("codec", ["utf-16", "utf-8-sig", "utf-32"])
def test_text_with_a_byte_order_mark_is_read(tmp_path, capsys, codec):
    path = tmp_path / "bom.yaml"
    path.write_bytes(WALL.encode(codec))
    assert main(["check", str(path)]) == 0, capsys.readouterr().err


# ----------------------------------------------------------------- 2. hostile YAML

def billion_laughs(levels=9):
    out = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for i in range(1, levels):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        out += f"{cur}: &{cur} [" + ",".join(["*" + prev] * 9) + "]\n"
    return out


HOSTILE = [
    ("deep-flow", "[" * 500 + "]" * 500, 1, "nested deeper"),
    ("deep-unclosed", "rate_hz: " + "[" * 200000, 1, "nested deeper"),
    # past libyaml's own limit (1000 flow levels in its scanner, PyYAML 6.0.4's wheels),
    # met before the builder counts the events: the same refusal
    ("deep-flow-past-libyaml", "[" * 1500 + "]" * 1500, 1, "nested deeper"),
    ("deep-block", "".join(" " * i + "- \n" for i in range(0, 400, 2)), None, "nested deeper"),
    ("list-key", "rate_hz: 1000\n? [a, b]\n: 3\n", 2, "a list cannot be a mapping key"),
    ("map-key", "{{a: 1}: 2}\n", 1, "a mapping cannot be a mapping key"),
    ("alias-bomb", billion_laughs() + "rate_hz: *i\n", None, "alias"),
    ("alias-bomb-value", "rate_hz: [" + ", ".join(ln.split(": ", 1)[1] for ln in
                                                 billion_laughs(5).splitlines()) + "]\n"
     "masses: [{name: a, kind: ground}]\n", 1, "rate_hz: must be a number, got a list"),
    ("recursive-alias", "rate_hz: &r [*r]\n", 1, "recursive alias *r"),
    ("unknown-alias", "rate_hz: *nowhere\n", 1, "unknown alias *nowhere"),
    ("python-tag", "rate_hz: !!python/object/apply:os.system [ls]\n", 1, "unsupported tag"),
    ("two-documents", WALL + "---\nrate_hz: 5\n", 9, "more than one YAML document"),
    ("newline-name", WALL.replace("{name: wall, kind: ground}",
                                  '{name: "hand\\nx", kind: ground}\n  - {name: "hand\\nx", '
                                  "kind: ground}"), 5, "duplicate mass name 'hand\\nx'"),
    ("newline-key", WALL + '"x\\ny": 1\n', 9, "unknown key 'x\\ny'"),
    ("huge-string", WALL.replace("rate_hz: 1000", "rate_hz: " + "9" * 400 + "x"), 1,
     "must be a number"),
    ("duplicate-key", WALL + "rate_hz: 10\n", 9, "duplicate key 'rate_hz' (first on line 1)"),
    ("merge-not-mapping", "rate_hz: {<<: 3}\n", 1, "merge key"),
]


@pytest.mark.parametrize("name, text, line, fragment", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_hostile_yaml_is_one_short_line_exit_2(tmp_path, capsys, name, text, line, fragment):
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    msg = one_line_error(capsys, ["check", str(path)])
    assert fragment in msg, msg
    assert len(msg) < 300 + len(str(path)), msg        # a bounded message, whatever the value
    if line is not None:
        assert f"{path}:{line}:" in msg, msg


def test_merge_key_is_honoured_not_a_duplicate(tmp_path, capsys):
    text = ("rate_hz: 1000\nmasses:\n  - &s {name: s1, kind: mass, mass: 0.01, x0: 0.001}\n"
            "  - {<<: *s, name: s2}\n  - {name: g, kind: ground}\nlinks:\n"
            "  - {kind: spring_damper, between: [s1, g], stiffness: 10}\n"
            "  - {kind: spring_damper, between: [s2, g], stiffness: 10}\n")
    scene = parse_scene(text)
    assert [(m.name, m.mass, m.x0) for m in scene.masses[:2]] == [("s1", 0.01, 0.001),
                                                                   ("s2", 0.01, 0.001)]
    path = tmp_path / "merge.yaml"
    path.write_text(text)
    assert main(["check", str(path)]) == 0, capsys.readouterr().err
    # an explicit key given twice beside a merge is still a duplicate
    with pytest.raises(ConfigError, match="duplicate key 'name'"):
        parse_scene(text.replace("name: s2}", "name: s2, name: s3}"))


YAMLISH = st.text(alphabet=string.ascii_letters[:6] + string.digits[:4] + " \n\t:-[]{},&*!?<>|'\"#.%@`\\",
                  max_size=300)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(YAMLISH, YAMLISH.map(lambda t: WALL + t), YAMLISH.map(lambda t: t + WALL)))
def test_fuzz_yamlish_text_loads_or_config_error(text):
    try:
        parse_scene(text, "fuzz.yaml")
    except ConfigError as exc:
        assert "\n" not in str(exc)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=400))
def test_fuzz_bytes_load_or_config_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("fuzz") / "f.yaml"
    path.write_bytes(data)
    try:
        load_scene(path)
    except ConfigError as exc:
        assert "\n" not in str(exc)


# ----------------------------------------------------------------- 3. YAML 1.2 numbers

@pytest.mark.parametrize("text, value", [("1e3", 1e3), ("2E3", 2e3), ("+1e3", 1e3),
                                         ("1_000", 1000), ("1.0e+3", 1e3), ("1000", 1000)])
def test_exponent_without_dot_is_a_number(text, value):
    scene = parse_scene(WALL.replace("rate_hz: 1000", f"rate_hz: {text}"))
    assert scene.rate_hz == value


def test_yaml_12_floats_through_check(tmp_path, capsys):
    path = tmp_path / "e.yaml"
    path.write_text(WALL.replace("stiffness: 1000", "stiffness: 1e3").replace("rate_hz: 1000",
                                                                              "rate_hz: 1e3"))
    assert main(["check", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["verdict"] == "stable"
    # a quoted number stays a string, as YAML says
    path.write_text(WALL.replace("rate_hz: 1000", "rate_hz: '1e3'"))
    assert "got a string '1e3'" in one_line_error(capsys, ["check", str(path)])


# ----------------------------------------------------------------- 7. Ctrl-C at any time

#: Written once hapsim's own SIGINT handling is in place (its package imported, as the
#: first thing either entry point does), before anything else of hapsim is imported.
UP = "@hapsim-handles-sigint"

CONSOLE_SCRIPT = """\
import re
import sys
import hapsim  # what the next line imports first; its handler is then in place
sys.stderr.write("@hapsim-handles-sigint\\n"); sys.stderr.flush()
from hapsim.cli import entry
if __name__ == "__main__":
    sys.argv[0] = re.sub(r"(-script\\.pyw|\\.exe)?$", "", sys.argv[0])
    sys.exit(entry())
"""


def interrupted(argv, after, tmp_path, console=False, at_import=None):
    """Start ``hapsim ARGV`` in a real process, SIGINT it ``after`` seconds later.

    The clock starts once hapsim handles SIGINT (a marker line on stderr, written once
    ``import hapsim`` has run ``_quiet_interrupt_at_start``, the package's first statement
    that does anything): a SIGINT before that lands in CPython's own start-up
    (``init_import_site``), in ``runpy`` finding the package or in reading its
    ``__init__``, the interpreter's, which no program can catch; on a loaded machine that
    alone took more than 0.1 s (a KeyboardInterrupt traceback from ``runpy`` once, with the
    clock started before it). From hapsim's first statement on, every moment counts.

    ``at_import`` (a module name; ``after`` is then unused): the process sends itself the
    SIGINT when that module's import starts, a moment no machine load can move (a SIGINT
    sent 0.1 s after start-up by a descheduled test process landed after ``check`` had
    finished, or once ``run``'s own handler was in place).
    """
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    if console:  # what pip writes for [project.scripts] hapsim = "hapsim.cli:entry"
        script = tmp_path / "hapsim"
        script.write_text(CONSOLE_SCRIPT)
        cmd = [sys.executable, str(script), *argv]
    else:  # python -m hapsim, the marker written once the package is imported
        hook = "" if at_import is None else (
            "import os, signal\n"
            "class CtrlC:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            f"        if name == {at_import!r}:\n"
            "            sys.meta_path.remove(self)\n"
            "            os.kill(os.getpid(), signal.SIGINT)\n"
            "sys.meta_path.insert(0, CtrlC())\n")
        boot = (f"import sys\n{hook}"
                "sys.argv[0] = '-m'\n"  # what python -m shows while it imports the package
                "import runpy, hapsim\n"  # as run_module's first step does
                f"sys.stderr.write({UP!r} + '\\n'); sys.stderr.flush()\n"
                "runpy.run_module('hapsim', run_name='__main__', alter_sys=True)")
        cmd = [sys.executable, "-c", boot, *argv]
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    first = proc.stderr.readline()
    assert first.strip() == UP, first
    if at_import is None:
        time.sleep(after)
        proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    return proc.returncode, out, err


@pytest.mark.parametrize("after", [0.1, 0.5, 1.0])
@pytest.mark.parametrize("argv", [["run", "configs/wall.yaml"],
                                  # a stable loop: finished, render exits 0 (an unstable one
                                  # exits 1 when it beats the Ctrl-C on a quiet machine)
                                  ["render", "--mass", "0.1", "--friction", "0.5", "--rate",
                                   "1000", "--K", "1000", "--B", "1.5"]],
                         ids=["run", "render"])
def test_ctrl_c_at_any_time_is_quiet(tmp_path, argv, after):
    """docs/getting-started.md: Ctrl-C ends cleanly. run exits 0 once its own SIGINT handler is in place
    (it stops the loop and reports); before that, and for every other command, exit 130
    with one line; a command that already finished exits with its own verdict (the code it
    has without Ctrl-C: render's example is unstable, 1). Never a traceback."""
    code, out, err = interrupted(argv, after, tmp_path)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    if code not in (0, 130) and argv[0] != "run":   # finished before the signal: its verdict
        from hapsim.cli import main
        assert code == main(list(argv)), (code, err)
        return
    if code == 130:
        assert err.strip().splitlines()[-1].endswith("interrupted"), err


def test_ctrl_c_during_imports_of_the_console_script(tmp_path):
    code, out, err = interrupted(["check", "configs/wall.yaml"], 0.1, tmp_path, console=True)
    assert "Traceback" not in err, err
    assert code in (0, 130), (code, err)


def test_library_import_keeps_the_callers_excepthook():
    import subprocess
    import sys
    got = subprocess.run([sys.executable, "-c", "import sys; h = sys.excepthook; import hapsim;"
                          " print(sys.excepthook is h)"], capture_output=True, text=True,
                         check=True)
    assert got.stdout.strip() == "True"


# ----------------------------------------------------------------- 8. one verdict, one code

UNRENDERABLE = (WALL.replace("name: wall, kind: spring_damper", "name: felt, kind: spring_damper")
                .replace("stiffness: 1000, damping: 1.5", "target: {k: 50000.0, b: 0.01}")
                .replace("friction: 0.5, delay: 1", "friction: 0.0, delay: 2"))


@pytest.mark.parametrize("argv", [
    ["calibrate", "--mass", "0.1", "--friction", "0", "--rate", "1000", "--delay", "2",
     "--k", "50000", "--b", "0.01"],
    ["check", "{scene}"], ["run", "{scene}", "--lockstep"],
    ["simulate", "{scene}", "--steps", "5", "--out", "{tmp}/o.npz"],
], ids=lambda a: a[0])
def test_not_renderable_is_exit_1_everywhere(tmp_path, capsys, argv):
    scene = tmp_path / "hard.yaml"
    scene.write_text(UNRENDERABLE)
    argv = [a.format(scene=scene, tmp=tmp_path) for a in argv]
    assert main(argv) == 1
    text = capsys.readouterr()
    assert "not renderable" in (text.out + text.err).replace("NO", "not renderable")
    if argv[0] != "calibrate":
        assert f"{scene}:6: links.felt.target: " in text.err


# ----------------------------------------------------------------- 9. --json always JSON

LOOP = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1"]
JSON_ERRORS = [
    # (argv, exit code, error type)
    (["render", *LOOP, "--K", "nan", "--json"], 2, "ConfigError"),
    (["render", "--mass", "0.1", "--json"], 2, "usage"),
    (["calibrate", *LOOP, "--k", "-5", "--b", "1", "--json"], 2, "ConfigError"),
    (["stability", *LOOP[:-2], "--delay", "-1", "--json"], 2, "ConfigError"),
    (["map", "--mass", "0.1", "--json"], 2, "ConfigError"),
    (["check", "{bad}", "--json"], 2, "ConfigError"),
    (["simulate", "{bad}", "--steps", "5", "--out", "{tmp}/o.npz", "--json"], 2, "ConfigError"),
    (["advise", "{bad}", "--json"], 2, "ConfigError"),
    (["run", "{bad}", "--json"], 2, "ConfigError"),
    (["run", "{unstable}", "--lockstep", "--json"], 1, "UnstableConfigError"),
    (["check", "{hard}", "--json"], 1, "UnrenderableTargetError"),
    (["run", "{hard}", "--lockstep", "--json"], 1, "UnrenderableTargetError"),
    (["play", "{bad}", "--json"], 2, "ConfigError"),
    (["play", "{unstable}", "--osc", "70000", "--sound", "none", "--json"], 2, "ConfigError"),
    (["telemetry", "{tmp}/missing.hst", "--json"], 2, "ConfigError"),
    (["identify", "--force-limit", "-1", "--json"], 2, "ConfigError"),
    (["compare-corrections", *LOOP, "--delay", "-1", "--json"], 2, "ConfigError"),
    (["family", "{bad}", "--json"], 2, "ConfigError"),
    (["kinematics", "delta", "--joints", "-170", "170", "90", "--json"], 2,
     "KinematicsError"),
    (["zwidth", "--scene", "{bad}", "--lockstep", "--json"], 2, "ConfigError"),
]


def test_json_error_cases_cover_every_command_with_json():
    """A command that gains --json is listed in JSON_ERRORS (read from the parsers)."""
    import argparse
    from hapsim.cli import build_parser
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    with_json = {name for name, p in sub.choices.items()
                 if any("--json" in a.option_strings for a in p._actions)}
    assert with_json == {argv[0] for argv, _, _ in JSON_ERRORS}


@pytest.mark.parametrize("argv, code, kind", JSON_ERRORS,
                         ids=[f"{a[0]}-{k}" for a, c, k in JSON_ERRORS])
def test_json_commands_print_json_on_failure(tmp_path, capsys, argv, code, kind):
    files = {"bad": WALL.replace("rate_hz: 1000", "rate_hz: -1"),
             "unstable": WALL.replace("stiffness: 1000", "stiffness: 90000"),
             "hard": UNRENDERABLE}
    for name, text in files.items():
        (tmp_path / f"{name}.yaml").write_text(text)
    argv = [a.format(tmp=tmp_path, **{n: tmp_path / f"{n}.yaml" for n in files})
            for a in argv]
    assert main(argv) == code
    text = capsys.readouterr()
    lines = text.out.strip().splitlines()
    assert len(lines) == 1, text.out
    doc = json.loads(lines[0])
    assert doc["exit"] == code and doc["error"]["type"] == kind, doc
    assert doc["error"]["message"] in text.err.replace("error: ", "", 1) or \
        doc["error"]["message"].split(": ", 1)[1] in text.err
    assert set(doc["error"]) >= {"type", "message", "file", "line", "key"}
    if kind == "ConfigError" and "{bad}" in argv:
        assert doc["error"]["key"] == "rate_hz" and doc["error"]["line"] == 1


# ----------------------------------------------------------------- 10. k/K, b/B hints

@pytest.mark.parametrize("argv, hint", [
    (["render", *LOOP, "--k", "1000"], "--k is the felt stiffness k [N/m] of 'hapsim calibrate'; "
                                       "for the virtual stiffness simulated use --K"),
    (["render", *LOOP, "--K", "1000", "--b", "1"], "--b is the felt damping"),
    (["calibrate", *LOOP, "--K", "1000", "--b", "1"], "for the felt stiffness to render use --k"),
    (["calibrate", *LOOP, "--k", "1000", "--B", "1"], "for the felt damping to render use --b"),
    (["stability", *LOOP, "--k", "1"], "hapsim stability does not take it"),
])
def test_k_K_confusion_gets_a_hint(capsys, argv, hint):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert hint in err and "Traceback" not in err


# ----------------------------------------------------------------- 5, 6. outputs and sizes

DIVERGING = """\
rate_hz: 1000
masses:
  - {name: g, kind: ground}
  - {name: a, kind: mass, mass: 0.0001, x0: 0.01}
  - {name: b, kind: mass, mass: 1.0}
links:
  - {kind: spring_damper, between: [g, a], stiffness: 1e6}
  - {kind: spring_damper, between: [g, b], stiffness: 1}
"""


@pytest.mark.parametrize("record", [[], ["--record", "b", "a"], ["--record", "b"]])
def test_simulate_stops_at_the_first_non_finite_position(tmp_path, capsys, record):
    """Centred scheme, K T^2 / m = 1e4 > 4: |z| > 1, the position grows by ~1e4 a step
    and overflows within ~80 steps. The finite rows are kept, the step and mass named."""
    import numpy as np
    scene, out = tmp_path / "div.yaml", tmp_path / "div.npz"
    scene.write_text(DIVERGING)
    assert main(["simulate", str(scene), "--steps", "100000", "--out", str(out),
                 *record]) == 1
    err = capsys.readouterr().err
    assert "diverged" in err and "mass 'a'" in err, err
    step = int(err.split(" step ")[1].split()[0])
    data = np.load(out)
    assert data["position"].shape[0] == step and np.isfinite(data["position"]).all()
    if "a" in record or not record:
        assert "at step" in err and 10 < step < 200
    else:  # only known to the end of the engine's chunk
        assert "mass 'a' (not recorded) is not finite by step" in err


@pytest.mark.parametrize("out, fragment", [
    ("/nonexistent/dir/s.npz", "the directory /nonexistent/dir does not exist"),
    ("{tmp}", "it is a directory"),
    ("{tmp}/file.txt/s.npz", "is not a directory"),
])
def test_simulate_checks_its_output_before_work(tmp_path, capsys, out, fragment):
    (tmp_path / "file.txt").write_text("x")
    scene = tmp_path / "wall.yaml"
    scene.write_text(WALL)
    out = out.format(tmp=tmp_path)
    if not out.endswith(".npz"):
        out = str(tmp_path)
        (tmp_path / "d.npz").mkdir()
        out = str(tmp_path / "d.npz")
    msg = one_line_error(capsys, ["simulate", str(scene), "--steps", "10", "--out", out])
    assert "--out: cannot write" in msg and fragment in msg


def test_simulate_refuses_what_cannot_fit(tmp_path, capsys):
    scene = tmp_path / "wall.yaml"
    scene.write_text(WALL)
    msg = one_line_error(capsys, ["simulate", str(scene), "--steps", "1e11",
                                  "--out", str(tmp_path / "s.npz")])
    assert "--steps: 100000000000 samples x 2 masses of positions need 2.18 TiB" in msg
    assert "available" in msg
    assert not (tmp_path / "s.npz").exists()


def test_simulate_refuses_duplicate_record_columns(tmp_path, capsys):
    scene = tmp_path / "wall.yaml"
    scene.write_text(WALL)
    msg = one_line_error(capsys, ["simulate", str(scene), "--steps", "5", "--out",
                                  str(tmp_path / "s.npz"), "--record", "hand", "hand"])
    assert "--record: names a mass twice: hand" in msg


@pytest.mark.parametrize("argv, fragment", [
    (["--telemetry", "/nonexistent/dir/t.npz"],
     "--telemetry: cannot write /nonexistent/dir/t.npz: the directory /nonexistent/dir "
     "does not exist"),
    (["--telemetry", "{tmp}"], "--telemetry: cannot write"),
    (["--duration", "1e300"], "--duration: 1e+300 s at 1000 Hz is 1e+303 samples"),
    (["--rate", "1e12"], "--rate: must be between 1e-06 and 1e+09 Hz"),  # RATE_RANGE
    (["--rate", "1e9", "--duration", "1000"], "telemetry rows (1e+09 Hz)"),
], ids=["telemetry-missing-dir", "telemetry-is-dir", "duration", "rate", "rate-rows"])
def test_run_checks_outputs_and_sizes_before_start(tmp_path, capsys, monkeypatch, argv,
                                                   fragment):
    # the machine is given 1 GiB, so that the test does not depend on the one it runs on
    monkeypatch.setattr("hapsim.outputs.available_memory", lambda: 2 ** 30)
    scene = tmp_path / "wall.yaml"
    scene.write_text(WALL)
    (tmp_path / "t.npz").mkdir()
    argv = [a.replace("{tmp}", str(tmp_path / "t.npz")) for a in argv]
    msg = one_line_error(capsys, ["run", str(scene), "--lockstep", *argv])
    assert fragment in msg
    if "rows" in fragment:
        assert "available" in msg


@pytest.mark.parametrize("rate, fragment", [
    ("1.0e+9", "rate_hz: 1e+09 telemetry rows"),                 # fits the range, not the memory
    ("1.0e+12", "rate_hz: must be between 1e-06 and 1e+09 Hz"),  # outside the analysis's range
])
def test_run_scene_rate_that_cannot_fit_names_the_file(tmp_path, capsys, monkeypatch, rate,
                                                       fragment):
    monkeypatch.setattr("hapsim.outputs.available_memory", lambda: 2 ** 30)
    scene = tmp_path / "fast.yaml"
    scene.write_text(WALL.replace("rate_hz: 1000", f"rate_hz: {rate}"))
    msg = one_line_error(capsys, ["run", str(scene), "--lockstep"])
    assert str(scene) in msg and fragment in msg, msg


# ----------------------------------------------------------------- 11. tidy output

def test_no_runtime_warnings_and_no_300_digit_numbers(capsys):
    """An extreme loop (K = 1e11, the largest K T^2/m the analysis accepts, 1e6; 1e300 is
    refused as bad input): the verdict is printed with significant digits, and numpy's
    overflow warnings stay off stderr."""
    import re
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)    # a warning would fail the command
        assert main(["render", "--mass", "0.1", "--rate", "1000", "--K", "1e11"]) == 1
    text = capsys.readouterr()
    assert "RuntimeWarning" not in text.err
    assert not re.search(r"\d{20}", text.out), text.out
    assert "UNSTABLE" in text.out


@pytest.mark.parametrize("value, spec, want", [
    (0.997586016, ">12.9f", " 0.997586016"), (2.2360679e147, ">12.9f", "2.2360679e+147"),
    (1e300, "<14.10f", "1e+300        "), (12.5, "12.4f", "     12.5000"),
])
def test_fixed_never_prints_hundreds_of_digits(value, spec, want):
    from hapsim.errors import fixed
    assert fixed(value, spec) == want


def test_passivity_limit_says_none_when_B_exceeds_b0(capsys):
    argv = ["stability", "--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--B", "2"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "|B| >= b0: no K >= 0 is passive" in out and "-3000" not in out
    assert main([*argv[:-1], "0.1"]) == 0   # b0 > |B|: K < 2 (b0 - |B|) / T = 800 N/m
    assert re.search(r"passivity \(C&S 1997\)\s+800 N/m", capsys.readouterr().out)


def test_help_texts_have_no_none_default_and_baud_metavar(capsys):
    assert main(["map", "--help"]) == 0
    out = capsys.readouterr().out
    assert "default: None" not in out and "(default: the --paper preset, else 0.0)" in " ".join(
        out.split())
    for argv in (["run", "--help-all"], ["identify", "--help"]):  # B: a damping, not a baud
        assert main(argv) == 0
        assert "--baud BAUD" in capsys.readouterr().out


def test_check_counts_in_the_right_number(capsys):
    assert main(["check", "configs/wall.yaml"]) == 0
    out = capsys.readouterr().out
    assert "0 virtual masses, 1 link (" in out


# ----------------------------------------------------------------- 12. figures

@pytest.mark.parametrize("number", [7, 9])
def test_grid_figure_labels_do_not_overlap_and_axes_say_normalised(number):
    pytest.importorskip("matplotlib")
    import numpy as np
    from hapsim.analysis.grid import grid, paper_preset
    from hapsim.plots import plot_grid
    loop, k_range, b_range, title = paper_preset(number, "ideal")
    g = grid(loop, np.linspace(*k_range, 9), np.linspace(*b_range, 9), samples=60)
    fig = plot_grid(g, title=title)
    ax = fig.axes[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in ax.texts]
    assert len(boxes) >= 9                      # most curves keep a label
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not a.overlaps(b), (a, b)
    assert "normalised" in ax.get_xlabel() and "[N/m]" not in ax.get_xlabel()
    assert "normalised" in ax.get_ylabel()
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_capacity_chart_legend_tells_quantiles_apart():
    pytest.importorskip("matplotlib")
    from hapsim.plots.bench import plot_capacity
    row = {"turnaround_us": {"p50": 10, "p99": 20, "p999": 40}, "missed_pct": 0.1}
    fig = plot_capacity({"rates": [1000, 2000], "echo": [row, row], "daemon": [row, row],
                         "machine": "test"})
    handles = fig.axes[0].get_legend().legend_handles
    styles = {(h.get_linestyle(), h.get_marker()) for h in handles
              if h.get_label() in ("p50", "p99", "p999")}
    assert len(styles) == 3
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_accuracy_chart_axis_spans_the_naive_errors():
    """The calibrated loops (round-off) sit on a 1e-7 floor, not 19 decades down."""
    pytest.importorskip("matplotlib")
    from pathlib import Path
    from hapsim.plots.bench import plot_accuracy_vs_rate
    data = json.loads((Path(__file__).resolve().parents[1] / "docs" / "bench"
                       / "accuracy_vs_rate.json").read_text())
    fig = plot_accuracy_vs_rate(data)
    low, high = fig.axes[0].get_ylim()
    assert 1e-9 < low < 1e-7 and high >= 1e3
    import matplotlib.pyplot as plt
    plt.close(fig)


# ----------------------------------------------------------------- 4. large scenes

def test_large_scene_reports_progress_and_loads():
    """A 2000-bead string (~40000 parser events): the reader reports characters read,
    increasing, out of len(text); every mass and link arrives with its line."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from bench_scene_load import string_scene
    text = string_scene(2000)
    calls = []
    scene = parse_scene(text, "big.yaml", progress=lambda done, total: calls.append((done, total)))
    assert len(scene.masses) == 2003 and len(scene.links) == 2002
    assert scene.masses[-2].line == 2004 and scene.links[0].line == 2007
    assert calls and all(t == len(text) for _, t in calls)
    done = [d for d, _ in calls]
    assert done == sorted(done) and 0 < done[-1] <= len(text)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(K=st.sampled_from([0.0, 1.0, 100.0, 500.0]), B=st.sampled_from([0.0, 0.1, 1.0]),
       d=st.integers(0, 4), hold=st.sampled_from(["zoh", "ideal"]),
       cmd=st.sampled_from(["render", "calibrate"]))
def test_mode_tables_never_print_inf_or_nan(capsys, K, B, d, hold, cmd):
    """Delay poles at z = 0 (no ln 0) and free modes at z = 1 (no damping ratio) are the class
    of mode a table once printed as 'inf' / 'nan' / '-0'. Over random loops, render's and
    calibrate's mode tables hold only finite figures or '-', and dead-beat modes are counted
    on their own line. The count is checked against the closed loop's poles at z = 0."""
    from hapsim.analysis import render as render_loop
    from hapsim.analysis import LoopModel
    args = ["--mass", "0.1", "--rate", "1000", "--delay", str(d), "--hold", hold]
    if cmd == "render":
        argv = ["render", *args, "--K", str(K), "--B", str(B)]
    else:
        argv = ["calibrate", *args, "--k", str(max(K, 1.0)), "--b", str(max(B, 0.1))]
    main(argv)
    out = capsys.readouterr().out
    table = out.split("modes:", 1)[1] if "modes:" in out else ""
    assert not re.search(r"\b(inf|nan)\b|(?<![\w.])-0(?![\w.])", table), out
    if cmd == "render":
        r = render_loop(LoopModel(mass=0.1, rate_hz=1000.0, delay=d, hold=hold), K, B)
        n0 = sum(1 for md in r.modes if md.z == 0)
        assert (f"{n0} dead-beat" in table) == (n0 > 0), out
