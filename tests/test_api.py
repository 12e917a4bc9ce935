"""The Python API (issue 21): each function's result has exactly the fields of its
command's --json object and the same values; the commands print what the API returns;
the example of docs/api.md runs as written; ``import hapsim`` stays light and the API
imports matplotlib only to draw."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hapsim
from hapsim import api
from hapsim.cli import main

ROOT = Path(__file__).resolve().parents[1]
LOOP = dict(mass=0.1, friction=0.5, rate_hz=1000.0, delay=1, hold="zoh")
LOOP_ARGS = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1",
             "--hold", "zoh"]


def _cli_json(argv, capsys) -> str:
    capsys.readouterr()
    main(argv)
    return capsys.readouterr().out.strip()


def _fields(cls) -> list:
    return [f.name for f in dataclasses.fields(cls)]


@pytest.mark.parametrize("config", ["wall", "felt_wall", "audio_string", "hand_wall"])
def test_check_is_the_commands_json(config, capsys):
    path = f"configs/{config}.yaml"
    rep = hapsim.check(path)
    assert isinstance(rep, hapsim.CheckReport) and rep.extra == {}
    assert json.dumps(rep.to_dict()) == _cli_json(["check", path, "--json"], capsys)
    assert list(rep.to_dict()) == _fields(hapsim.CheckReport)
    assert rep.k == rep.rendered["k"] and rep.b == rep.rendered["b"]


@pytest.mark.parametrize("K, B", [(1000.0, 1.5), (1000.0, 1.0), (5e4, 0.0)])
def test_render_calibrate_stability_are_the_commands_json(K, B, capsys):
    loop = hapsim.LoopModel(**LOOP)
    for rep, argv in ((hapsim.render(loop, K, B), ["render", *LOOP_ARGS, "--K", repr(K),
                                                   "--B", repr(B)]),
                      (hapsim.calibrate(loop, K, B + 0.1), ["calibrate", *LOOP_ARGS, "--k",
                                                            repr(K), "--b", repr(B + 0.1)]),
                      (hapsim.stability(loop, B), ["stability", *LOOP_ARGS, "--B", repr(B)])):
        assert rep.extra == {} and list(rep.to_dict()) == _fields(type(rep))
        assert json.dumps(rep.to_dict()) == _cli_json([*argv, "--json"], capsys)


def test_family_is_the_commands_json(capsys):
    rep = hapsim.family("configs/felt_wall.yaml", calibrate=True, grid=3, certify=0)
    assert rep.extra == {}
    # one link and no arm spring: no consistency to report (the command prints none)
    assert set(_fields(hapsim.FamilyReport)) - set(rep.to_dict()) == {"consistency"}
    assert json.dumps(rep.to_dict()) == _cli_json(
        ["family", "configs/felt_wall.yaml", "--calibrate", "--grid", "3", "--certify-boxes",
         "0", "--json"], capsys)
    plain = hapsim.family("configs/wall.yaml", grid=3, certify=0).to_dict()
    assert "family_calibrations" not in plain      # only when asked, as the command


def test_run_on_the_lockstep_mock_measures_the_prediction():
    rep = hapsim.run("configs/wall.yaml", lockstep=True, transport="inprocess")
    assert isinstance(rep, hapsim.RunReport) and rep.ok
    # the fields are the report's keys (the command prints the same dict)
    # (advice only with --auto, error only after a device lost beyond recovery)
    assert rep.extra == {}
    assert set(rep.to_dict()) == set(_fields(hapsim.RunReport)) - {"advice", "error"}
    # measured 1.3e-15 relative (generic 2.9e-15), margin 3.4e5
    assert rep.k == pytest.approx(rep.predicted["k"], rel=1e-9)
    # measured 1.3e-13 relative (generic 6.6e-14), margin 7700
    assert rep.b == pytest.approx(rep.predicted["b"], rel=1e-9)
    assert rep.loop["protocol"] == "framed"
    json.dumps(rep.to_dict(), allow_nan=False)          # JSON-safe, as --json


def test_run_refuses_an_unknown_option_with_the_valid_ones():
    with pytest.raises(hapsim.ConfigError) as info:
        hapsim.run("configs/wall.yaml", lockstpe=True)
    assert "unknown option(s) lockstpe; valid: port, baud, duration" in str(info.value)


def test_identify_report_fields_are_the_commands_json_keys():
    """The command prints the API's report (out and plot filled in); its keys are the
    fields (the identification itself is tested in test_identify.py)."""
    assert _fields(hapsim.IdentifyReport) == ["device", "loop", "hand", "out", "plot", "note",
                                              "error"]
    src = (ROOT / "hapsim" / "commands" / "identify.py").read_text()
    assert 'json.dumps({**rep.to_dict(), "out": args.out, "plot": args.plot})' in src


def test_a_report_keeps_a_key_it_has_no_field_for():
    rep = api.StabilityReport.from_dict({**dict.fromkeys(_fields(api.StabilityReport)),
                                     "new_key": 1})
    assert rep.extra == {"new_key": 1} and rep.to_dict()["new_key"] == 1


def test_docs_example_runs_as_written(tmp_path, monkeypatch, capsys):
    """docs/api.md: the python block marked for the tests prints the text block after it,
    and writes its chart."""
    text = (ROOT / "docs" / "api.md").read_text()
    m = re.search(r"<!-- test: python -->\n```python\n(.*?)^```\n\nprints\n\n```text\n(.*?)^```",
                  text, re.S | re.M)
    assert m, "docs/api.md lost its tested example"
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    exec(compile(m.group(1), "docs/api.md", "exec"), {})
    assert capsys.readouterr().out == m.group(2)
    assert (tmp_path / "wall_poles.png").stat().st_size > 10_000
    assert (tmp_path / "wall_felt.png").stat().st_size > 10_000


def test_run_chart_places_the_felt_pairs_where_the_report_says(tmp_path):
    """RunReport.plot draws the simulated (K, B), the predicted and the measured (k, b) and
    the target at their coordinates (a calibrated target: the felt pair is the target,
    the simulated one is not), into given axes or a file; a bad file is refused first."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt
    rep = hapsim.run("configs/felt_wall.yaml", lockstep=True, transport="inprocess")
    fig, ax = plt.subplots()
    assert rep.plot(ax) is fig
    at = {ln.get_label().split()[0]: tuple(np.ravel(d)[0] for d in ln.get_data())
          for ln in ax.get_lines() if not ln.get_label().startswith("_")}
    # measured 0 (generic 0): exact on both targets
    assert at["simulated"] == pytest.approx((rep.virtual["K"], rep.virtual["B"]))
    # measured 0 (generic 0): exact on both targets
    assert at["predicted"] == pytest.approx((rep.predicted["k"], rep.predicted["b"]))
    # measured 0 (generic 0): exact on both targets
    assert at["target"] == pytest.approx((rep.target["k"], rep.target["b"]))
    measured = [c for c in ax.containers if c.get_label().startswith("measured")]
    assert len(measured) == 1
    # measured 0 (generic 0): exact on both targets
    assert tuple(np.ravel(d)[0] for d in measured[0][0].get_data()) == pytest.approx(
        (rep.k, rep.b))
    # a calibrated target: the simulated K is not the target k (measured 6.6 % apart on
    # both targets), far beyond 1e-3 and 1e-3 far beyond round-off
    assert at["simulated"][0] != pytest.approx(at["target"][0], rel=1e-3)
    plt.close(fig)
    rep.plot(tmp_path / "felt.svg")
    assert (tmp_path / "felt.svg").read_text().lstrip().startswith("<?xml")
    with pytest.raises(hapsim.ConfigError) as info:
        rep.plot(tmp_path / "felt.nosuch")
    assert info.value.key == "plot" and ".png" in str(info.value)


def test_import_hapsim_is_light_and_the_api_draws_only_when_asked():
    """``import hapsim`` (what the command line starts with) loads neither numpy nor the
    API; the API names resolve on first use; the API module imports matplotlib nowhere
    (its plot methods call hapsim.plots, the one module that does)."""
    import ast
    code = ("import json, sys, hapsim; print(json.dumps([m for m in ('numpy', 'hapsim.api', "
            "'matplotlib') if m in sys.modules]))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert json.loads(p.stdout.strip().splitlines()[-1]) == []
    assert {"load_scene", "check", "render", "calibrate", "stability", "family",
            "identify", "run", "LoopModel"} <= set(hapsim.__all__)
    assert all(getattr(hapsim, n) is not None for n in hapsim.__all__)
    imported = set()
    for path in sorted((ROOT / "hapsim" / "api").glob("*.py")):
        tree = ast.parse(path.read_text())
        imported |= {a.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                     for a in node.names} | {node.module for node in ast.walk(tree)
                                             if isinstance(node, ast.ImportFrom)}
    assert not {m for m in imported if m and m.split(".")[0] == "matplotlib"}
    assert not {m for m in imported if m and m.startswith("hapsim.commands")}


def test_every_api_name_is_bound_where_checkers_look_and_lazy_ones_load_on_use():
    """Each name of ``hapsim.api.__all__`` is bound at the module's top level (a def, a
    class, an assignment or an import, a ``TYPE_CHECKING`` one included), as pyflakes
    and type checkers read ``__all__``; the lazy ones (the analysis's LoopModel) are not
    imported by ``import hapsim.api`` and resolve on first use to the defining object."""
    import ast
    tree = ast.parse((ROOT / "hapsim" / "api" / "__init__.py").read_text())
    bound = set()
    for node in tree.body:
        body = node.body if isinstance(node, ast.If) else [node]
        for n in body:
            if isinstance(n, (ast.FunctionDef, ast.ClassDef)):
                bound.add(n.name)
            elif isinstance(n, (ast.Import, ast.ImportFrom)):
                bound |= {(a.asname or a.name).split(".")[0] for a in n.names}
            elif isinstance(n, ast.Assign):
                bound |= {t.id for t in n.targets if isinstance(t, ast.Name)}
            elif isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
                bound.add(n.target.id)
    api = sys.modules.get("hapsim.api") or __import__("hapsim.api").api
    assert set(api.__all__) - bound == set()
    code = ("import json, sys, hapsim.api as a; before = 'hapsim.analysis.loop' in sys.modules;"
            " import hapsim.analysis.loop as l; print(json.dumps([before, a.LoopModel is "
            "l.LoopModel, 'LoopModel' in dir(a)]))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert json.loads(p.stdout.strip().splitlines()[-1]) == [False, True, True]


def test_pole_chart_marks_the_felt_pair():
    pytest.importorskip("matplotlib")
    rep = hapsim.check("configs/wall.yaml")
    fig = rep.plot()
    ax = fig.axes[0]
    felt = [ln for ln in ax.get_lines() if ln.get_label().startswith("felt: k = 1019 N/m")]
    assert len(felt) == 1
    x, y = felt[0].get_data()
    # measured 0 (generic 0): exact on both targets
    assert x[0] == pytest.approx(rep.rendered["z_re"]) and abs(y[0]) == pytest.approx(
        rep.rendered["z_im"])
    poles = [ln for ln in ax.get_lines() if ln.get_label() == "closed-loop poles"][0]
    assert len(poles.get_xdata()) == len(rep.eigenvalues)
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_identify_chart_is_measured_against_model():
    """hapsim.plots.plot_identify draws the fitted rows of the record against the fit's
    model (positions in mm), the residual model - measured in micrometres, and the fit's
    figures in the title (a stand-in fit: the drawing is under test, not the fit)."""
    pytest.importorskip("matplotlib")
    from types import SimpleNamespace as NS

    import numpy as np

    from hapsim.plots import plot_identify
    n, a = 300, 50
    t = np.arange(a + n + 20) * 1e-3
    position = 1e-3 * np.sin(40 * t)
    model = position[a:a + n] + 1e-7 * np.cos(7 * t[a:a + n])
    model[:5] = np.nan                              # the model's warm-up rows
    fit = NS(n_samples=n, period=1e-3, model=model, mass=NS(value=0.1), friction=NS(value=0.5),
             coulomb=NS(value=0.02), delay=1, hold="zoh")
    fig = plot_identify(fit, {"position": position, "loop": {"fitted_rows": [a, a + n]}})
    top, bottom = fig.axes
    meas, mod = top.get_lines()
    assert np.array_equal(meas.get_xdata(), t[a:a + n])
    assert np.array_equal(meas.get_ydata(), position[a:a + n] * 1e3)
    assert np.array_equal(mod.get_ydata(), model * 1e3, equal_nan=True)
    # measured 0 (generic 0): exact on both targets
    assert np.allclose(bottom.get_lines()[0].get_ydata(),
                       (model - position[a:a + n]) * 1e6, equal_nan=True)
    assert top.get_title() == "m = 0.1 kg, b0 = 0.5 N s/m, fc = 0.02 N, d = 1, zoh"
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_a_chart_without_matplotlib_names_the_plot_extra(monkeypatch):
    """The API's charts give the command's hint when matplotlib is missing."""
    from hapsim.plots import PLOT_INSTALL
    rep = hapsim.render(hapsim.LoopModel(**LOOP), K=1000.0, B=1.5)
    monkeypatch.setitem(sys.modules, "matplotlib", None)     # import matplotlib fails
    with pytest.raises(hapsim.ConfigError) as info:
        rep.plot()
    assert PLOT_INSTALL in str(info.value)


# ---------------------------------------------------------------------------- n-D
@pytest.mark.parametrize("config", ["pantograph_wall", "delta_sphere"])
def test_check_nd_is_the_commands_json(config, capsys):
    """2-D and 3-D scenes felt through a device: the fields are the keys of ``hapsim check
    --json``, the values its values; k and b are the n x n felt matrices."""
    path = f"configs/{config}.yaml"
    rep = hapsim.check_nd(path)
    assert isinstance(rep, hapsim.CheckReportND) and rep.extra == {}
    assert list(rep.to_dict()) == _fields(hapsim.CheckReportND)
    assert json.dumps(rep.to_dict()) == _cli_json(["check", path, "--json"], capsys)
    n = rep.dof
    assert rep.k.shape == rep.b.shape == (n, n)
    assert np.array_equal(rep.k, np.array(rep.felt_stiffness))
    assert hapsim.load_scene_nd(path).dimension == n


def test_modes_nd_is_the_commands_json(capsys):
    rep = hapsim.modes_nd("configs/membrane.yaml")
    assert isinstance(rep, hapsim.ModesReportND) and rep.extra == {}
    assert list(rep.to_dict()) == _fields(hapsim.ModesReportND)
    assert json.dumps(rep.to_dict()) == _cli_json(
        ["check", "configs/membrane.yaml", "--json"], capsys)
    assert rep.frequencies.size == len(rep.modes) and np.all(np.diff(rep.frequencies) >= 0)
    with pytest.raises(hapsim.ConfigError, match="modes_nd"):
        hapsim.check_nd("configs/membrane.yaml")


def test_run_nd_is_the_commands_json(capsys):
    """``run --lockstep`` on a 2-D scene: the API's report is the command's JSON (the
    lockstep measurement is deterministic), its fields the keys (the port's only over a
    port); the measured felt matrices equal the predicted ones to 1e-6."""
    path = "configs/pantograph_wall.yaml"
    rep = hapsim.run_nd(path)
    assert isinstance(rep, hapsim.RunReportND) and rep.extra == {}
    assert list(rep.to_dict()) == [f for f in _fields(hapsim.RunReportND)
                                   if f not in api.RunReportND._OPTIONAL]
    assert json.dumps(rep.to_dict()) == _cli_json(["run", path, "--lockstep", "--json"],
                                                  capsys)
    pk = np.array(rep.predicted["felt_stiffness"])
    # measured 2.4e-11 relative (generic 2.4e-11), margin 41000
    assert np.max(np.abs(rep.k - pk)) <= 1e-6 * np.max(np.abs(pk))
    with pytest.raises(hapsim.ConfigError):
        hapsim.run_nd(path, amplitude=-1.0)


def test_replace_keeps_what_a_result_carries_beside_its_fields():
    """``Report.replace`` keeps ``exit_code``, the extra keys and the analysis objects that
    ``dataclasses.replace`` drops (``hapsim run --auto`` replaced its report's advice and
    lost ``exit_code``: AttributeError), for every result class of the API."""
    import dataclasses
    from hapsim import api

    def subclasses(c):
        for s in c.__subclasses__():
            yield s
            yield from subclasses(s)
    api.RunReportND                     # the 2-D/3-D results load on first use
    classes = list(subclasses(api.Report))
    assert api.RunReport in classes and len(classes) >= 8
    for cls in classes:
        obj = cls.from_dict({"not_a_field": 7}, exit_code=3)
        first = dataclasses.fields(cls)[0].name
        new = obj.replace(**{first: "changed"})
        assert getattr(new, first) == "changed" and type(new) is cls
        assert new.exit_code == 3 and new.extra == {"not_a_field": 7}, cls
        with pytest.raises(TypeError):
            obj.replace(no_such_field=1)
