"""``hapsim stability --scene``: the stiffness limit per principal direction of a 2-D/3-D
scene's device and its map over the workspace (issue 23, item 4: "``stability`` gives the
stiffness limit per direction and its map over the workspace"; before, only ``check`` and
``kinematics --grid`` did).

Each stated ``K_max`` along a direction ``e`` is checked against an independent MIMO model
of the loop written here (scipy ``expm`` for the exact zero-order hold of the Cartesian
mass and friction, the delay as shift registers, the virtual law ``F[n] = -K x[n-d] -
B (x[n-d] - x[n-d-1]) / T``): the loop with the port stiffness along ``e`` replaced by
0.98 ``K_max`` is stable, by 1.02 ``K_max`` unstable (coupled stability from the whole
loop's spectral radius, not axis by axis)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from hapsim.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _rho(M, B0, K, B, T, d):
    """Spectral radius of the sampled loop (independent of hapsim's code)."""
    n = M.shape[0]
    Mi = np.linalg.inv(M)
    Ac = np.block([[np.zeros((n, n)), np.eye(n)], [np.zeros((n, n)), -Mi @ B0]])
    Bc = np.vstack([np.zeros((n, n)), Mi])
    E = expm(np.block([[Ac, Bc], [np.zeros((n, 3 * n))]]) * T)
    Ad, Bd = E[:2 * n, :2 * n], E[:2 * n, 2 * n:]
    # state: [x, v, x[n-1], ..., x[n-d-1]]: d + 1 delayed positions
    S = 2 * n + (d + 1) * n
    A = np.zeros((S, S))
    sel = np.zeros((n, S))                          # x[n-d]
    selp = np.zeros((n, S))                         # x[n-d-1]
    if d == 0:
        sel[:, :n] = np.eye(n)
    else:
        sel[:, 2 * n + (d - 1) * n:2 * n + d * n] = np.eye(n)
    selp[:, 2 * n + d * n:2 * n + (d + 1) * n] = np.eye(n)
    F = -K @ sel - (B / T) @ (sel - selp)
    A[:2 * n, :] = Bd @ F
    A[:2 * n, :2 * n] += Ad
    A[2 * n:3 * n, :n] = np.eye(n)                  # x[n-1] <- x[n]
    for j in range(1, d + 1):
        A[2 * n + j * n:2 * n + (j + 1) * n, 2 * n + (j - 1) * n:2 * n + j * n] = np.eye(n)
    return max(abs(np.linalg.eigvals(A)))


@pytest.mark.parametrize("name", ["pantograph_wall.yaml", "pantograph_spring.yaml",
                                  "delta_sphere.yaml"])
def test_each_direction_limit_against_an_independent_mimo_model(name, capsys):
    from hapsim import api
    path = ROOT / "configs" / name
    assert main(["stability", "--scene", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    scene = api.load_scene(path)
    dev = scene.device
    n = scene.dimension
    assert out["dof"] == n and len(out["K_max"]) == n
    Kp = np.array(out["port_stiffness"])
    Bp = np.array(out["port_damping"])
    T = 1.0 / scene.rate_hz
    for e, kmax in zip(np.array(out["directions"]), out["K_max"]):
        assert kmax is not None and kmax > 0
        rest = Kp - float(e @ Kp @ e) * np.outer(e, e)
        lo = _rho(dev.mass, dev.friction, rest + 0.98 * kmax * np.outer(e, e), Bp, T,
                  dev.delay)
        hi = _rho(dev.mass, dev.friction, rest + 1.02 * kmax * np.outer(e, e), Bp, T,
                  dev.delay)
        assert lo < 1.0 < hi, (name, e, kmax, lo, hi)
    # the same limits as 'hapsim check'
    main(["check", str(path), "--json"])
    chk = json.loads(capsys.readouterr().out)
    lims = chk.get("stiffness_limits") or chk["analysis"]["stiffness_limits"]
    # measured 0 (generic 0): exact on both targets
    assert [r["K_max"] for r in lims] == pytest.approx(out["K_max"], rel=1e-12)


def test_the_workspace_map_is_charted(tmp_path, capsys):
    png = tmp_path / "kmax.png"
    path = ROOT / "configs" / "pantograph_wall.yaml"
    assert main(["stability", "--scene", str(path), "--grid", "5", "--span", "10",
                 "--out", str(png), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ws = out["workspace"]
    assert len(ws["status"]) == 25 and len(ws["K_max"]) == 25
    assert png.stat().st_size > 10_000
    ok = [row for row, st in zip(ws["K_max"], ws["status"]) if st == "ok"]
    assert ok and all(all(v is None or v > 0 for v in row) for row in ok)
    # configuration-dependent mass: the limit changes across the workspace
    lowest = [min(v for v in row if v is not None) for row in ok]
    assert max(lowest) > 1.01 * min(lowest)
    assert main(["stability", "--scene", str(path), "--grid", "3", "--span", "5"]) == 0
    assert "over the workspace" in capsys.readouterr().out


@pytest.mark.parametrize("argv, key", [
    (["stability", "--scene", "configs/pantograph_wall.yaml", "--mass", "0.1"], "--mass"),
    (["stability", "--scene", "configs/pantograph_wall.yaml", "--B", "2"], "--B"),
    (["stability", "--scene", "configs/wall.yaml", "--grid", "3"], "--grid"),
    (["stability", "--scene", "configs/membrane.yaml"], "--scene"),
    (["stability", "--scene", "tests/data/play_nd_2d.yaml", "--grid", "3"], "--grid"),
    (["stability", "--scene", "configs/pantograph_wall.yaml", "--out", "x.png"], "--out"),
    (["stability", "--mass", "0.1", "--rate", "1000", "--grid", "3"], "--grid"),
    (["stability", "--rate", "1000"], "--mass"),
    (["stability", "--mass", "0.1"], "--rate"),
])
def test_refusals_name_the_option(argv, key, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    assert main(argv + ["--json"]) == 2
    err = json.loads(capsys.readouterr().out)["error"]
    assert err["key"] == key, err
