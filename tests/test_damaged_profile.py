"""A hand-force (or gesture) profile that is damaged is a :class:`ConfigError` naming the
scene key, never a traceback (:func:`hapsim.device_model.load_profile`; the same errors
as a damaged telemetry file, :data:`hapsim.errors.DAMAGED_FILE_ERRORS`)."""

from __future__ import annotations

import random

import numpy as np
import pytest

from hapsim.device_model import load_profile
from hapsim.errors import ConfigError


def _npz(tmp_path) -> bytes:
    path = tmp_path / "clean.npz"
    t = np.linspace(0.0, 0.1, 11)
    np.savez(path, time=t, force=np.sin(40 * t))
    return path.read_bytes()


@pytest.mark.parametrize("how", ["header", "version", "flip", "cut"])
def test_a_damaged_npz_profile_is_a_config_error(tmp_path, how):
    """An ``.npz`` profile with a member's header dict opened by "(" (numpy parses it as a
    Python literal: ``tokenize.TokenError``), a zip "version needed" of 21.9
    (``NotImplementedError``), seeded flipped bytes, or cut short: a ConfigError naming
    ``excitation.profile``, or, where the damage left a readable file, its columns."""
    data = bytearray(_npz(tmp_path))
    rng = random.Random(how)
    if how == "header":
        j = data.find(b"{'descr'") + 1
        data[j:j + 1] = b"("
    elif how == "version":
        k = data.find(b"PK\x01\x02")
        data[k + 6:k + 8] = (219).to_bytes(2, "little")
    elif how == "flip":
        for _ in range(20):
            data[rng.randrange(len(data))] = rng.randrange(256)
    else:
        data = data[:len(data) // 2]
    path = tmp_path / "damaged.npz"
    path.write_bytes(bytes(data))
    if how in ("header", "version", "cut"):
        with pytest.raises(ConfigError, match="cannot read the force profile") as exc:
            load_profile(str(path))
        assert exc.value.key == "excitation.profile"
    else:
        try:
            t, f = load_profile(str(path))
        except ConfigError as exc:
            assert exc.key == "excitation.profile"
        else:
            assert t.shape == f.shape
