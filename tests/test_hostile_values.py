"""Hostile values in otherwise valid scenes (issue 10 audit): every scalar of every shipped
config replaced by a hostile YAML value (a 400-digit integer raised OverflowError from the
loader; NaN/inf literals, tags, aliases, nesting, merge keys) gives exit 0, 1 or 2 through
``check`` and ``check --json``, one stderr line on exit 2, JSON on stdout with ``--json``,
never a traceback."""

from __future__ import annotations

import glob
import json
import re

from hypothesis import HealthCheck, given, settings, strategies as st

from hapsim.cli import main

HOSTILE = ["!!float abc", "!!int 1.5x", ".nan", ".inf", "-.inf", "1e400", "-1e400", "1e-400", "9" * 400, "-" + "9" * 400,
           "[]", "{}", "null", "true", "'x'", "[[[[[[1]]]]]]", "{a: 1}", "*nope",
           "!!binary aGk=", "0x10", "1_0", "~", "-0", "!!float nan", "&a 1", "{<<: {a: 1}}",
           "[1, 2]", "1e12"]
BASES = [open(p).read() for p in sorted(glob.glob("configs/*.yaml"))]
SCALAR = re.compile(r"(?<=: )[^\s,{}\[\]#]+")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(st.sampled_from(range(len(BASES))), st.lists(st.tuples(st.integers(0, 10 ** 6),
                                                              st.sampled_from(HOSTILE)),
                                                    min_size=1, max_size=3))
def test_hostile_value_anywhere_is_a_verdict_or_one_line(tmp_path_factory, capsys, base, subs):
    text = BASES[base]
    for pos, value in subs:
        spots = list(SCALAR.finditer(text))
        m = spots[pos % len(spots)]
        text = text[:m.start()] + value + text[m.end():]
    path = tmp_path_factory.mktemp("hv") / "s.yaml"
    path.write_text(text)
    rc = main(["check", str(path)])
    err = capsys.readouterr().err.strip()
    assert rc in (0, 1, 2)
    assert "Traceback" not in err
    if rc == 2:
        assert len(err.splitlines()) == 1, err
    assert main(["check", str(path), "--json"]) == rc
    json.loads(capsys.readouterr().out)


def test_huge_whole_number_at_every_scalar_is_one_line():
    """Exhaustive over the class hypothesis found by chance: a whole number beyond the float
    range (400 digits, either sign) at *every* scalar of every shipped config is loaded or
    refused with a ConfigError whose message is one bounded line (it once raised
    OverflowError while formatting the range message). A 2-D or 3-D config is read by its
    reader (hapsim.scene.load_scene_nd). Every scalar of a distinct key and line shape: the hundreds
    of identical mass and link lines of the membrane and the strings once each (the same
    key in the same line goes through the same check; 1,500 loads were 500)."""
    from hapsim.errors import ConfigError
    from hapsim.scene import parse_scene
    from hapsim.scene import parse_scene_nd, parse_scene_ports
    n = 0
    for text in BASES:
        nd = re.search(r"^dimension: [23]\b", text, re.M) is not None
        ports = re.search(r"^devices:", text, re.M) is not None
        seen = set()
        for m in SCALAR.finditer(text):
            # the line's shape with this scalar marked, numbers and names out
            line_start = text.rfind("\n", 0, m.start()) + 1
            line_end = text.find("\n", m.end())
            shape = re.sub(r"[\w.+-]+", "v", text[line_start:m.start()]) + "@" + \
                re.sub(r"[\w.+-]+", "v", text[m.end():line_end])
            if shape in seen:
                continue
            seen.add(shape)
            for value in ("9" * 400, "-" + "9" * 400):
                try:
                    (parse_scene_nd if nd else parse_scene_ports if ports else parse_scene)(
                        text[:m.start()] + value + text[m.end():], "s.yaml")
                except ConfigError as exc:
                    msg = str(exc)
                    assert "\n" not in msg and len(msg) < 400, msg
                    n += 1
    assert n > 100                    # the class was exercised, not skipped
