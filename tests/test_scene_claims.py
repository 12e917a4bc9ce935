"""docs/testing.md's table 'What each shipped scene states' (issue 31 item 4), held for its
cheap part: every shipped scene has its rows; each row's ``check`` verdict is what
``hapsim check SCENE --json`` says; where the prediction of what a run will state is cheap
(a 1-D scene's lockstep simulation of the closed loop before the run,
:func:`hapsim.pipeline.precheck.predict_comparable`; the framed protocol's n-D runs, which
say nothing before: binary64 on the wire), the row's 'said before the run' is it; and
every row's verdict agrees with it by the table's rule (``tools/scene_claims.py``). The
Falcon's predictions are held by tests/test_falcon_feasibility.py and
tests/test_falcon_spring.py, the faders' by tests/test_faders_realtime.py.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TESTING = (ROOT / "docs" / "testing.md").read_text()


def _rows() -> list:
    """The table's rows: (scene, run, check, said, states, agrees)."""
    sec = TESTING.split("## What each shipped scene states", 1)[1]
    out = []
    for line in sec.splitlines():
        if line.startswith("| `") and line.count("|") == 7:
            cells = [c.strip() for c in line.strip("|").split("|")]
            out.append(tuple(c.strip("`") if i < 2 else c for i, c in enumerate(cells)))
    return out


def test_every_shipped_scene_has_its_rows_and_each_row_agrees():
    """Every configs/*.yaml is in the table (a delta scene twice: the framed mock and the
    emulated Falcon; a pantograph scene twice: the framed mock and the emulated 2DIY),
    each row's "agrees" is the table's own rule, and a row that disagrees is named under
    'What still disagrees' with its cause."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from scene_claims import _agrees
    finally:
        sys.path.remove(str(ROOT / "tools"))
    rows = _rows()
    names = sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))
    assert sorted({r[0] for r in rows}) == names
    still = TESTING.split("What still disagrees:", 1)[1]
    for scene, run, check, said, states, agrees in rows:
        portless = "kind: port" not in (ROOT / "configs" / scene).read_text()
        verdict = states.rsplit(" (exit", 1)[0]
        ok = _agrees(portless, None if said == "-" else said, verdict)
        assert agrees == ("yes" if ok else "NO"), (scene, run)
        # a disagreement is named below the table, with its cause
        assert ok or f"- `configs/{scene}`" in still, (scene, run)
    for route, kind in (("--driver falcon", "kind: delta"),
                        ("--driver haply", "kind: pantograph")):
        assert {r[0] for r in rows if r[1] == route} == {
            p.name for p in (ROOT / "configs").glob("*.yaml") if kind in p.read_text()}


def test_the_check_column_and_the_cheap_predictions_are_the_commands(capsys):
    """Each row's ``check`` column is ``hapsim check``'s verdict (", no port" for a scene
    without one); a 1-D scene's 'said before the run' is "not measurable" exactly when
    its lockstep simulation before the run finds the record not comparable; an n-D
    scene's framed run says nothing before."""
    from hapsim.cli import main
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.precheck import predict_comparable
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene, scene_dimension, scene_has_ports
    for scene, run, check, said, states, agrees in _rows():
        path = ROOT / "configs" / scene
        assert main(["check", str(path), "--json"]) == 0
        got = json.loads(capsys.readouterr().out)["verdict"]
        portless = "kind: port" not in path.read_text()
        assert check == got + (", no port" if portless else ""), scene
        if run != "run" or portless or scene_has_ports(path):
            continue
        if scene_dimension(path) > 1:
            assert said == "-", scene
            continue
        sc = load_scene(str(path))
        # the run's options as hapsim run makes them: the scene's own driver, if any
        opts = RunOptions(driver=getattr(sc.device, "protocol", None)).check()
        pre = predict_comparable(prepare_run(sc, opts))
        assert (said == "not measurable") == (pre is not None and not pre["comparable"]), \
            (scene, said, pre)
