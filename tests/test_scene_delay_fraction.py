"""A delay a hair from a whole period (the scene fuzz: ``delay: 1e-308`` gave ``hapsim
check`` a linear-algebra traceback, the split hold's first piece a subnormal time) is
refused with file, line and key in every kind of scene: one port, several ports, 2-D/3-D
(hapsim.scene_schema.MIN_DELAY_FRACTION); a fraction at the limit and a whole delay are
taken."""

from __future__ import annotations

from pathlib import Path

import pytest

from inproc import hapsim_main

ROOT = Path(__file__).resolve().parents[1]
HAIRS = ["1e-308", "1e-12", "2.9999999999999", "5e-10"]


def _scene(name: str, old: str, new: str, tmp_path) -> tuple[Path, int]:
    text = (ROOT / "configs" / name).read_text()
    assert text.count(old) == 1, old
    lines = text.splitlines()
    line = next(i for i, s in enumerate(lines, 1) if old.strip() in s)
    p = tmp_path / name
    p.write_text(text.replace(old, new))
    return p, line


CASES = [("hand_wall.yaml", "  delay: 1\n", "  delay: {}\n", "device.delay"),
         ("two_faders.yaml", "delay: 0.7625", "delay: {}", "devices.fader_b.delay"),
         ("pantograph_wall.yaml", "hand_mass: 0.05, delay: 1}",
          "hand_mass: 0.05, delay: {}}}", "device.delay")]


@pytest.mark.parametrize("hair", HAIRS)
@pytest.mark.parametrize("name, old, new, key", CASES)
def test_a_delay_a_hair_from_whole_is_refused_with_file_line_key(name, old, new, key, hair,
                                                                 tmp_path):
    p, line = _scene(name, old, new.format(hair), tmp_path)
    code, out, err = hapsim_main(["check", str(p)], cwd=ROOT)
    assert code == 2 and out == "", (out, err)
    assert f"{p}:{line}: {key}: " in err and "no clock resolves it" in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize("name, old, new, key", CASES)
def test_a_fraction_at_the_limit_is_taken(name, old, new, key, tmp_path):
    p, _ = _scene(name, old, new.format("1.000000001"), tmp_path)
    code, out, err = hapsim_main(["check", str(p)], cwd=ROOT)
    assert code in (0, 1) and "no clock resolves it" not in err, err
