"""The help of the commands a user reaches for with a 2-D or 3-D scene teaches it (issue
23's audit): ``hapsim --help`` no longer says 1-DoF only, ``check``, ``run`` and
``stability`` say what they do with an n-D scene or where the per-direction limit is, and
every 2-D/3-D example they show names a shipped scene and runs (exit 0); a zero stiffness
limit from ``hapsim kinematics`` says why."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from hapsim.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _help(capsys, *argv):
    assert main([*argv, "--help"]) == 0
    return capsys.readouterr().out


def test_top_level_help_names_the_multi_dof_devices(capsys):
    out = _help(capsys)
    assert "1-DoF force-feedback devices" not in out
    assert "pantograph" in out and "delta" in out


@pytest.mark.parametrize("command, words", [
    ("check", ("2-D or 3-D", "felt_stiffness", "principal", "stiffness_limits", "--plot")),
    ("run", ("2-D or 3-D", "MATRICES", "--amplitude", "linearisation bound", "--driver haply")),
    ("stability", ("(one K_max per direction; a 1-D scene has one)", "hapsim kinematics", "--grid", "--out"))])
def test_help_teaches_the_nd_use(command, words, capsys):
    out = _help(capsys, command)
    for word in words:
        assert word in out, (command, word)
    for name in re.findall(r"configs/([\w.]+\.yaml)", out):
        assert (ROOT / "configs" / name).is_file(), (command, name)


def test_the_nd_check_examples_run(capsys, tmp_path, monkeypatch):
    """Every `hapsim check` example on a 2-D or 3-D scene shipped in the help exits 0
    (run from the repository root, the chart into a temporary directory)."""
    out = _help(capsys, "check")
    examples = [ln.strip() for ln in out.splitlines()
                if ln.startswith("  hapsim check configs/")
                and re.search(r"(pantograph|delta|membrane)", ln)]
    assert len(examples) >= 3, out
    monkeypatch.chdir(ROOT)
    for ex in examples:
        argv = shlex.split(re.split(r"\s{2,}", ex)[0])[1:]
        argv = [str(tmp_path / a) if a.endswith(".png") else a for a in argv]
        assert main(argv) == 0, ex
        capsys.readouterr()


def test_a_zero_stiffness_limit_says_why(capsys):
    """`hapsim kinematics ... --joint-inertia` without any damping: every K_max is 0 (a
    delayed loop with no damping is unstable for every K > 0) and the report says what
    to raise; with damping the limits are positive and the note is gone."""
    argv = ["kinematics", "pantograph", "--joints", "130", "50", "--joint-inertia", "2e-4",
            "--hand-mass", "0.05"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.count("K_max = 0\n") == 2 and "raise one of them" in out
    assert main(argv + ["--B", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "K_max = 0" not in out and "raise one of them" not in out


def test_every_command_is_in_the_commands_page():
    """docs/commands.md's table has a row for every command the CLI registers
    (`hapsim kinematics` had none)."""
    from hapsim.cli import COMMANDS
    text = (ROOT / "docs" / "commands.md").read_text(encoding="utf-8")
    table = text.split("## The commands", 1)[1].split("\n\n", 2)[1]
    for name in COMMANDS:
        assert f"| `hapsim {name.replace('_', '-')}" in table, name


def test_check_reports_progress_per_direction():
    """The stiffness limits (the long part of an n-D check when the delay is long) report
    their progress, one call per direction, through the API the CLI's bar uses."""
    from hapsim import api
    calls = []
    api.check_nd(str(ROOT / "configs" / "delta_sphere.yaml"),
                 progress=lambda done, total: calls.append((done, total)))
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_the_haply_generation_reaches_the_wire(capsys):
    """`--generation gen2` (hAPI hardwareVersion 2: other direction bytes) reaches the
    2DIY's set-up in lockstep and measures within its stated uncertainty what it states
    (the damping may be unstated since the wire's term is taken over the error box,
    hapsim.analysis.wire_box: "partly within"); it is refused, by name, where it means
    nothing (1-D scenes, another driver)."""
    wall = str(ROOT / "configs" / "pantograph_wall.yaml")
    assert main(["run", wall, "--driver", "haply", "--lockstep", "--generation", "gen2",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["generation"] == "gen2" and out["verdict"] in ("within", "partly within")
    assert any(s["name"] == "felt stiffness" for s in out["statements"]), out["not_stated"]
    for argv in (["run", str(ROOT / "configs" / "wall.yaml"), "--generation", "gen2"],
                 ["run", str(ROOT / "configs" / "delta_sphere.yaml"), "--lockstep",
                  "--generation", "gen2"]):
        assert main(argv) == 2, argv
        assert "--generation" in capsys.readouterr().err
