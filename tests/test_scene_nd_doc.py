"""docs/dimensions.md's key table of the 2-D/3-D scene format names every key the n-D
reader (hapsim.scene.parse_scene_nd) accepts, in the right section, and no key it refuses; the
example scene above the table is read."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hapsim.scene import devices, parse_scene_nd, reader

DOC = Path(__file__).resolve().parent.parent / "docs" / "dimensions.md"


def _table():
    text = DOC.read_text(encoding="utf-8")
    part = text.split("### Every key of a 2-D or 3-D scene", 1)[1].split("\n\n", 3)[2]
    rows = {}
    for line in part.splitlines():
        if not line.startswith("| ") or line.startswith("| where") or "---" in line:
            continue
        where, keys = [c.strip() for c in line.strip("|").split("|")[:2]]
        rows.setdefault(where.strip("`"), set()).update(re.findall(r"`(\w+)`", keys))
    return rows


def test_every_key_the_reader_takes_is_in_the_table_and_only_those():
    rows = _table()
    want = {"top level": set(reader.TOP_KEYS_ND),
            "masses[]": set().union(*reader.MASS_KEYS_ND.values()),
            "links[]": set().union(*reader.LINK_KEYS_ND.values()),
            "planes[]": set(reader.PLANE_KEYS_ND),
            "device": set().union(*devices.DEVICE_KEYS.values()),
            "audio.listen[]": set(reader.LISTEN_KEYS_ND),
            "engine": set(reader.ENGINE_KEYS_ND),
            "safety": set(reader.SAFETY_KEYS_ND),
            "excitation": set(reader.EXCITATION_KEYS_ND),
            "excitation.impulse": set(reader.IMPULSE_KEYS_ND)}
    assert set(rows) == set(want)
    for where, keys in want.items():
        assert rows[where] == keys, (where, keys ^ rows[where])


def test_the_example_scene_is_read():
    text = DOC.read_text(encoding="utf-8")
    block = text.split("## Scenes in 2 and 3 dimensions", 1)[1].split("```yaml\n", 1)[1]
    scene = parse_scene_nd(block.split("```", 1)[0], "dimensions.md")
    assert scene.dimension == 2 and scene.device.kind == "pantograph"


@pytest.mark.parametrize("where, key", [("masses[]", "stiffness"), ("device", "length")])
def test_the_table_check_can_fail(where, key):
    """A key in the wrong section is told apart (the check above is not vacuous)."""
    assert key not in _table()[where]
