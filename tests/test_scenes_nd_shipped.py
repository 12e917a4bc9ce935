"""The shipped 2-D and 3-D scenes (configs/pantograph_*.yaml, configs/delta_*.yaml; issue 23
item 7): `hapsim check --json` on each gives its dof and felt matrices, and for a handle held
by grounds they are the THS matrix of hapsim.analysis.ths with the device's Cartesian
mass built here from the kinematics' Jacobian and the link blocks from their laws; the
files are what tools/make_nd_scenes.py writes; `simulate` runs each; `--plot` draws one and
its ellipse at the operating point is the check's felt stiffness."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from from_file import load_module  # same directory
from hapsim.analysis.ths import MatrixLoop, render
from hapsim.cli import main
from hapsim.kinematics import device
from hapsim.scene import scene_dimension

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
ALL_ND = sorted(p.name for p in CONFIGS.glob("*.yaml") if scene_dimension(p) > 1)
# the scenes felt through a device (membrane.yaml, a sounding object without a port, is
# checked by tests/test_membrane.py)
SHIPPED_ND = [n for n in ALL_ND if "kind: port" in (CONFIGS / n).read_text()]


def _generator():
    return load_module(ROOT / "tools" / "make_nd_scenes.py")


def test_the_shipped_nd_scenes_are_the_generators():
    """The seven scenes the docs list, each byte for byte what the generator writes (the
    ground points come from the forward kinematics, so a hand edit would break them)."""
    gen = _generator()
    assert ALL_ND == sorted(gen.SCENES) == ["delta_mesh.yaml", "delta_sphere.yaml",
                                            "falcon_spring.yaml",
                                            "membrane.yaml", "pantograph_circle.yaml",
                                            "pantograph_spring.yaml",
                                            "pantograph_wall.yaml"]
    assert SHIPPED_ND == [n for n in ALL_ND if n != "membrane.yaml"]
    for name, make in gen.SCENES.items():
        assert (CONFIGS / name).read_text() == make(), name


def _port_blocks(doc, hand):
    """The port's stiffness and damping matrices from the scene file's links and planes,
    written from their laws (docs/dimensions.md), not from hapsim.analysis."""
    n = doc["dimension"]
    pos = {m["name"]: np.array(m["x0"], float) for m in doc["masses"] if "x0" in m}
    K, B = np.zeros((n, n)), np.zeros((n, n))
    for lk in doc.get("links", []):
        assert "hand" in lk["between"]
        other = pos[[x for x in lk["between"] if x != "hand"][0]]
        L = lk.get("threshold", lk.get("length", 0.0))
        if L == 0:
            K += lk["stiffness"] * np.eye(n)
            B += lk["damping"] * np.eye(n)
            continue
        d = hand - other
        l0 = np.linalg.norm(d)
        assert l0 < L                                # the contact is engaged at rest
        P = np.outer(d, d) / l0 ** 2
        K += lk["stiffness"] * (P + (1 - L / l0) * (np.eye(n) - P))
        B += lk["damping"] * P
    for pl in doc.get("planes", []):
        u = np.array(pl["normal"], float)
        u /= np.linalg.norm(u)
        assert pl["offset"] - u @ hand > 0           # engaged at rest
        K += pl["stiffness"] * np.outer(u, u)
        B += pl["damping"] * np.outer(u, u)
    return K, B


@pytest.mark.parametrize("name", SHIPPED_ND)
def test_check_json_felt_matrices_are_the_ths_matrix(name, capsys):
    """`check --json`: exit 0 (stable), dof n, n x n felt matrices; when every port link
    ends on a ground the felt matrices, poles and spectral radius equal
    hapsim.analysis.ths.render of the matrix loop M = J^-T M_q J^-1 + m_h I,
    B0 = J^-T B_q J^-1 (from the kinematics' Jacobian) with the port's (K, B) from the
    links' laws (1e-9)."""
    assert main(["check", str(CONFIGS / name), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    doc = yaml.safe_load((CONFIGS / name).read_text())
    n, dev = doc["dimension"], doc["device"]
    assert out["dof"] == n and out["stable"] is True
    k, b = np.array(out["felt_stiffness"]), np.array(out["felt_damping"])
    assert k.shape == b.shape == (n, n)
    # the felt stiffness is positive definite along every principal direction
    assert all(v > 0 for v in out["direction_stiffness"])
    geometry = dev["geometry"]
    if isinstance(geometry, dict):                  # the five-bar's lengths as numbers
        from hapsim.kinematics import PantographGeometry
        geometry = PantographGeometry(**geometry)
    kin = device(dev["kind"], geometry)
    q = np.radians(dev["joints"])
    hand = kin.forward(q)
    Ji = np.linalg.inv(kin.jacobian(q))
    M = Ji.T @ np.diag(dev["joint_inertia"]) @ Ji + dev["hand_mass"] * np.eye(n)
    B0 = Ji.T @ np.diag(dev["joint_friction"]) @ Ji
    # measured 2.5e-18 abs, 3.4 rel (generic 3.5e-18, 0.5), margin 45000
    assert np.allclose(out["device"]["mass"], M, rtol=0, atol=1e-12 * np.max(M))
    if name == "delta_mesh.yaml":             # the port holds a membrane mass: not a THS
        assert out["stiffness_limits"] is None
        return
    K, B = _port_blocks(doc, hand)
    r = render(MatrixLoop(mass=M, friction=B0, rate_hz=doc["rate_hz"],
                          delay=dev["delay"]), K, B)
    # measured 6.4e-14 relative (generic 5.6e-14), margin 15000
    assert np.max(np.abs(k - r.felt_stiffness)) <= 1e-9 * np.max(np.abs(k))
    # measured 2.8e-13 relative (generic 2.7e-13), margin 3500
    assert np.max(np.abs(b - r.felt_damping)) <= 1e-9 * np.max(np.abs(b))
    # measured 8.9e-16 (generic 1.6e-15), margin 640
    assert out["spectral_radius"] == pytest.approx(r.spectral_radius, abs=1e-12)
    # measured 1.1e-13 abs, 1.2e-16 rel (generic 1.1e-13, 1.2e-16), margin 17000
    assert np.allclose(out["port_stiffness"], K, rtol=1e-12, atol=1e-9)
    assert all(lim["K_max"] > 0 for lim in out["stiffness_limits"])


def test_simulate_runs_every_shipped_nd_scene(tmp_path, capsys):
    """`simulate` on each (100 samples, the port held at rest): exit 0, finite positions,
    and the rest is an equilibrium to the file's rounding (0.1 nm): nothing moves more
    than 1 nm and the force on the port at rest is below 1 uN."""
    from hapsim.engine import Engine
    from hapsim.scene import load_scene_nd
    for name in SHIPPED_ND:
        out = tmp_path / (name + ".npz")
        assert main(["simulate", str(CONFIGS / name), "--steps", "100", "--out",
                     str(out)]) == 0, name
        pos = np.load(out)["position"]
        assert np.all(np.isfinite(pos))
        # measured 4e-11 (generic 4e-11), margin 24
        assert np.max(np.abs(pos - pos[0])) < 1e-9, name
        eng = Engine(load_scene_nd(CONFIGS / name))
        eng.step()
        assert np.max(np.abs(eng.port_force)) < 1e-6, name
    capsys.readouterr()


def test_plot_draws_the_workspace_and_the_felt_ellipses(tmp_path, capsys):
    """`check --plot` writes the picture; the felt matrices over the workspace at the
    scene's own joints are the check's (a 3 x 3 grid's centre is the operating point);
    a 1-D scene's --plot is refused (exit 2)."""
    pytest.importorskip("matplotlib")
    from hapsim.analysis.scene_check import check_scene_nd, felt_over_workspace
    from hapsim.scene import load_scene_nd
    fig = tmp_path / "wall.png"
    assert main(["check", str(CONFIGS / "pantograph_wall.yaml"), "--plot", str(fig)]) == 0
    assert fig.stat().st_size > 10_000
    scene = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    felt = felt_over_workspace(scene, points=6, ellipses=3)
    assert felt.positions.shape == (9, 2) and felt.stable.all()
    k = check_scene_nd(scene).render.felt_stiffness
    # measured 4.3e-14 relative (generic 5.2e-14), margin 19000
    assert np.max(np.abs(felt.felt_stiffness[4] - k)) <= 1e-9 * np.max(np.abs(k))
    # measured 0 (generic 0): exact on both targets
    assert np.allclose(felt.positions[4], scene.device.position, atol=1e-12)
    # the configuration-dependent mass: the felt stiffness differs across the workspace
    spread = np.ptp(felt.felt_stiffness[:, 1, 1])
    assert spread > 1e-3 * abs(k[1, 1])
    capsys.readouterr()
    assert main(["check", str(CONFIGS / "wall.yaml"), "--plot", str(fig)]) == 2
    assert "--plot" in capsys.readouterr().err
