"""A driver's numeric options (``--protocol-option KEY=VALUE``, a device file's
``device.protocol_options``), checked where the driver is built
(:func:`hapsim.option_values.option_value`).

Before, a device id or a function code of NaN or infinity was a traceback from
``int()`` through ``hapsim identify`` ("cannot convert float NaN to integer"), and the
same text with no key through a scene; a device id of 2.5 was taken as 2; a word was
"must be real number, not str"; a resolution or an offset beyond binary32 was an
``OverflowError`` when the set-up was packed.
"""

from __future__ import annotations

import inspect
import math

import pytest
import yaml

from hapsim.drivers import FAMILIES
from hapsim.errors import ConfigError
from hapsim.option_values import option_value


def _numeric_parameters():
    """(family, parameter) of every driver whose default is a number (not a bool), and
    the numeric ones whose default is None (a device id, a 2DIY's resolution)."""
    out = []
    for fam in FAMILIES:
        if not fam.driver:
            continue
        cls = fam.load()
        for name, p in inspect.signature(cls.__init__).parameters.items():
            d = p.default
            if (isinstance(d, (int, float)) and not isinstance(d, bool)) or \
                    (d is None and name in ("device_id", "resolution")):
                out.append((fam, cls, name, d))
    return out


PARAMETERS = _numeric_parameters()


def test_the_parameters_are_found():
    """The introspection above finds the options it is meant to (a renamed one would
    leave the test below with nothing to try)."""
    names = {(f.name, f.dimension, n) for f, _, n, _ in PARAMETERS}
    assert {("haply", 1, "device_id"), ("haply", 1, "resolution"), ("haply", 1, "offset_deg"),
            ("haply", 2, "device_id"), ("haply", 2, "resolution"),
            ("hapkit-serial", 1, "function"), ("hapkit-serial", 1, "force_limit"),
            ("firefader", 1, "full_scale"), ("falcon", 3, "read_timeout")} <= names, names


@pytest.mark.parametrize("fam, cls, name, default", PARAMETERS,
                         ids=[f"{f.name}{f.dimension}-{n}" for f, _, n, _ in PARAMETERS])
def test_every_numeric_driver_option_refuses_a_non_number_by_its_key(fam, cls, name,
                                                                     default):
    """NaN, both infinities, a word, a bool, a value beyond binary32 (a Haply board's
    floats) and (for a whole number's option) 2.5: each refused as a ConfigError keyed by
    the option, before any port is opened; the default still builds (the Falcon's needs
    its USB device, which the check comes before)."""
    whole = isinstance(default, int) or name == "device_id"
    bads = [math.nan, math.inf, -math.inf, "many", True] + (
        [2.5] if whole else [1e39] if fam.name == "haply" else [])   # (binary32 there)
    for bad in bads:
        if bad is True and name in ("axis", "direction"):
            continue            # (a bool is 0/1 where the option is a direction bit)
        with pytest.raises(ConfigError) as info:
            cls(**{name: bad})
        assert info.value.key == name, (name, bad, info.value.key, str(info.value))
        assert "Traceback" not in str(info.value)
    if fam.name != "falcon":
        cls(**{name: default} if default is not None else {})


@pytest.mark.parametrize("value, says", [
    (".nan", "device_id: must be a whole number in [1, 255], got nan"),
    ("2.5", "device_id: must be a whole number in [1, 255], got 2.5"),
    ("abc", "device_id: must be a whole number in [1, 255], got 'abc'"),
    ("0", "device_id: must be a whole number in [1, 255], got 0")])
def test_a_scenes_device_id_is_refused_with_its_key_and_range(tmp_path, capsys, value, says):
    """The same check through a device file: ``hapsim run`` of the shipped Haply joint
    with ``protocol_options: {device_id: V}``; exit 2, one line, the key named."""
    from hapsim.cli import main
    scene = yaml.safe_load(open("configs/haply.yaml"))
    scene["device"].setdefault("protocol_options", {})["device_id"] = yaml.safe_load(value)
    path = tmp_path / "h.yaml"
    path.write_text(yaml.safe_dump(scene))
    assert main(["run", str(path), "--lockstep", "--duration", "0.2"]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err, err


def test_option_value_states_its_range():
    """The helper's own message and return types, one case per kind of range."""
    assert option_value("k", 3, whole=True, low=1, high=255) == 3
    assert isinstance(option_value("k", 3.0, whole=True), int)
    assert option_value("k", 0.5, "s", low=0) == 0.5
    for kw, says in ((dict(low=0, low_ok=False, unit="N"), "must be a finite number > 0 [N]"),
                     (dict(low=0), "must be a finite number >= 0"),
                     (dict(high=1), "must be a finite number <= 1"),
                     (dict(low=1, high=2, whole=True), "must be a whole number in [1, 2]"),
                     ({}, "must be a finite number, got")):
        with pytest.raises(ConfigError) as info:
            option_value("k", -math.inf, **kw)
        assert says in str(info.value) and info.value.key == "k", str(info.value)
