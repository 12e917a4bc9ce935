"""docs/scenes.md is the validator's own table: regenerated equal, every example loads, every
range and choice in the table is what the validator enforces (through ``hapsim check``)."""

from __future__ import annotations

import dataclasses
import math
import os
import re

import pytest
import yaml

from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.scene import (Audio, Device, Excitation, Impulse, Link, Listen, Mass, Safety,
                          parse_scene)
from hapsim.scene_doc import default_path, example_scene, render_reference
from hapsim.scene_doc import main as doc_main
from hapsim.scene_schema import KEYS, REQUIRED, SECTIONS, section_keys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# examples name files relative to a scene in configs/ (excitation.profile)
AS_IF = os.path.join(ROOT, "configs", "example.yaml")


def test_committed_reference_is_the_generated_one():
    with open(os.path.join(ROOT, "docs", "scenes.md"), encoding="utf-8") as fh:
        assert fh.read() == render_reference(), "run: python -m hapsim.scene_doc"
    assert default_path() == os.path.join(ROOT, "docs", "scenes.md")
    assert doc_main(["--check"]) == 0


def test_check_flags_a_stale_reference(tmp_path, capsys):
    stale = tmp_path / "scenes.md"
    stale.write_text(render_reference().replace("| `friction` |", "| `frictoin` |"))
    assert doc_main(["--check", "--out", str(stale)]) == 1
    assert "out of date" in capsys.readouterr().err
    assert doc_main(["--out", str(stale)]) == 0 and stale.read_text() == render_reference()


def test_every_key_has_a_row_an_example_and_a_section_in_the_reference():
    text = render_reference()
    for k in KEYS.values():
        assert f"| `{k.name}` |" in text and f"- `{k.name}`: `{k.example}`" in text
        assert re.search(rf"(^|[{{ ,]){re.escape(k.name)}:", k.example), k.path
    assert len(SECTIONS) == len({k.section for k in KEYS.values()})


def _complete_scenes(text):
    return re.findall(r"```yaml\n(.*?)```", text, flags=re.S)


def test_every_complete_scene_in_the_reference_loads():
    with open(os.path.join(ROOT, "docs", "scenes.md"), encoding="utf-8") as fh:
        blocks = _complete_scenes(fh.read())
    assert len(blocks) >= 1 + sum(1 for s in SECTIONS if s.example)
    for block in blocks:
        parse_scene(block, AS_IF)


def _value(scene, k, frag):
    """The value the scene read for key ``k`` whose example is ``frag`` (None: not a scalar)."""
    parts = k.path.split(".")
    if parts[0] in ("masses[]", "links[]"):
        entry = frag[parts[0][:-2]][-1]
        seq = scene.masses if parts[0] == "masses[]" else scene.links
        obj = next(e for e in seq if e.name == entry.get("name", e.name)) if "name" in entry \
            else seq[-1]
        if parts[1:] == ["target", "k"] or parts[1:] == ["target", "b"]:
            return obj.target[0 if parts[2] == "k" else 1], entry["target"][parts[2]]
        if parts[1] == "between":
            return [obj.m1, obj.m2], entry["between"]
        if parts[1] in ("target",):
            return None
        return getattr(obj, "mass" if parts[1] == "mass" else parts[1]), entry[parts[1]]
    obj, want = scene, frag
    for p in parts:
        if p.endswith("[]"):                    # audio.listen[]: the last entry
            want, obj = want[p[:-2]][-1], getattr(obj, p[:-2])[-1]
            continue
        want = want[p]
        obj = getattr(obj, p)
    if isinstance(want, (dict, list)):
        return None
    return obj, want


@pytest.mark.parametrize("path", list(KEYS))
def test_every_key_example_loads_and_sets_that_key(path):
    k = KEYS[path]
    scene = parse_scene(example_scene(k.example), AS_IF)
    got = _value(scene, k, yaml.safe_load(k.example))
    if got is not None:
        have, want = got
        if k.path == "excitation.profile":
            assert os.path.samefile(have, os.path.join(ROOT, "configs", want))
        else:
            assert have == want, (path, have, want)


@pytest.mark.parametrize("cls, section", [(Device, "device"), (Safety, "safety"),
                                          (Excitation, "excitation"),
                                          (Impulse, "excitation.impulse"),
                                          (Audio, "audio"), (Listen, "audio.listen[]")])
def test_dataclass_fields_are_the_table_rows_with_its_defaults(cls, section):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    rows = section_keys(section)
    assert [r.name for r in rows] == list(fields)
    for r in rows:
        f = fields[r.name]
        if r.default is REQUIRED:
            assert f.default is dataclasses.MISSING, r.path
        elif r.type != "mapping":
            assert f.default == r.default or (math.isinf(r.default) and math.isinf(f.default))


def test_entry_dataclasses_take_every_row():
    for cls, section in ((Mass, "masses[]"), (Link, "links[]")):
        names = {f.name for f in dataclasses.fields(cls)}
        for r in section_keys(section):
            assert r.name in names or r.name == "between", r.path   # between -> m1, m2


def _bad_values(k):
    """Values just outside the row's range (and of the wrong type), with what the error says."""
    out = []
    both = k.minimum is not None and k.maximum is not None
    if k.type in ("number", "integer") and k.minimum is not None:
        lo = int(k.minimum) if k.type == "integer" else k.minimum
        says = f"{'>' if k.strict else '>='} {lo:g}"
        out.append((lo if k.strict else lo - abs(lo) - 1,
                    f"between {k.minimum:g} and {k.maximum:g}" if both else says))
    if k.type in ("number", "integer") and k.maximum is not None:
        hi = int(k.maximum) if k.type == "integer" else k.maximum
        out.append((hi * 2 + 1, f"between {k.minimum:g} and" if both else f"<= {k.maximum:g}"))
    lo, hi = k.analysis_limits()             # the analysis's limits the row names
    if lo is not None:
        out.append((lo / 10, f"between {lo:g} and {hi:g} {k.unit}"))
    if hi is not None:
        out.append((hi * 10 if lo is not None else int(hi) + 1,
                    f"between {lo:g} and {hi:g} {k.unit}" if lo is not None
                    else f"<= {hi:g} {k.unit}"))
    if k.type == "number":
        out.append(("soft", "must be a number"))
        if not k.allow_inf:
            out.append((math.inf, "finite"))
    if k.type == "integer":
        out.append((1.5, "whole number"))
    if k.type == "choice":
        out.append(("nonsense", "valid choices: " + ", ".join(k.choices)))
    if k.type == "boolean":
        out.append(("yes please", "true or false"))
    return out


def _with_value(fragment, k, value):
    frag = yaml.safe_load(fragment)
    node = frag
    parts = k.path.split(".")
    for p in parts[:-1]:
        node = node[p[:-2]][-1] if p.endswith("[]") else node[p]
    node[parts[-1]] = value
    return frag


CHECKED = [k for k in KEYS.values() if _bad_values(k)]


@pytest.mark.parametrize("path", [k.path for k in CHECKED])
def test_every_range_in_the_table_is_enforced_by_hapsim_check(path, tmp_path, capsys):
    k = KEYS[path]
    for value, says in _bad_values(k):
        frag = _with_value(k.example, k, value)
        scene = tmp_path / "bad.yaml"
        scene.write_text(example_scene(yaml.safe_dump(frag, default_flow_style=True)))
        assert main(["check", str(scene)]) == 2, (path, value)
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(scene) in err, err
        shown = re.sub(r"\[\d+\]", "[]", err)
        assert k.path in shown and says in err, (path, value, err)
        with pytest.raises(ConfigError):
            parse_scene(scene.read_text(), str(scene))


@pytest.mark.parametrize("path", [k.path for k in KEYS.values() if k.why])
def test_a_ranges_why_is_said_beside_a_value_above_it_only(path, tmp_path, capsys):
    """A row's ``why`` says why its largest value is what it is: ``hapsim check`` says it
    beside a value above the range and not beside one below it (a delay of -1 periods was
    told the cost of the eigenvalues at 500)."""
    k = KEYS[path]
    lo = k.minimum if k.minimum is not None else k.analysis_limits()[0]
    hi = k.maximum if k.maximum is not None else k.analysis_limits()[1]
    for value, said in ((hi * 2 + 1, True), (lo - abs(lo) - 1, False)):
        scene = tmp_path / "bad.yaml"
        frag = _with_value(k.example, k, value)
        scene.write_text(example_scene(yaml.safe_dump(frag, default_flow_style=True)))
        assert main(["check", str(scene)]) == 2, (path, value)
        err = capsys.readouterr().err.strip()
        assert k.path in re.sub(r"\[\d+\]", "[]", err), err
        assert (k.why_text() in err) == said, (value, err)
