"""Golden records of the engine (issue 30 item 1): every shipped 1-D scene and four n-D
ones, run :data:`golden_engine.SAMPLES` samples with the port driven by a fixed seeded
trajectory, give the positions and port forces recorded before the engine of every
dimension became one (``tools/golden_engine.py`` wrote ``tests/data/golden_engine.npz``
from the engine as it was; it is not rewritten to make this test pass)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tolerance import measured

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))

import golden_engine as golden  # noqa: E402

#: Relative deviation allowed from a record, to its largest |value|: measured 2.64e-13
#: (delta_mesh.yaml's port force, NUMBA_CPU_NAME=generic OPENBLAS_CORETYPE=Sandybridge
#: against the record written on the host's AMD EPYC target with FMA; every 1-D scene
#: within 3.3e-16, one ulp of felt_wall's calibrated force), margin 30: a mesh's port
#: force sums some fifty link forces whose rounding follows the vector width, while a
#: wrong law, rate or a sample's shift moves these records by 1e-6 relative and more.
REL = measured(2.64e-13, 30)


@pytest.fixture(scope="module")
def records():
    """The stored records, by ``"<scene>/<key>"``."""
    with np.load(golden.OUT) as data:
        return {k: data[k] for k in data.files}


def test_records_are_small_and_complete(records):
    """Every scene of :data:`golden_engine.SCENES` is stored, in under 200 kB."""
    assert golden.OUT.stat().st_size < 200_000
    for name in golden.SCENES:
        for key in ("force", "x", "masses"):
            assert f"{name}/{key}" in records, (name, key)


@pytest.mark.numerical
@pytest.mark.parametrize("name", golden.SCENES)
def test_engine_matches_its_golden_record(records, name):
    """The engine run on ``configs/<name>`` gives the recorded port forces and positions
    within :data:`REL` of each record's largest value, the same masses kept."""
    got = golden.drive(golden.load(name))
    assert np.array_equal(got["masses"], records[f"{name}/masses"]), name
    for key in ("force", "x"):
        ref = records[f"{name}/{key}"]
        assert got[key].shape == ref.shape, (name, key)
        scale = float(np.max(np.abs(ref)))
        err = float(np.max(np.abs(got[key] - ref)))
        assert err <= REL * scale, f"{name} {key}: max |diff| {err:.3g} > {REL * scale:.3g}"
