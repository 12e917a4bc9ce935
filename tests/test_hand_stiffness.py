"""The hand's stiffness to ground (``device.hand.stiffness``): a real spring in the THS.

Independent references: the continuous poles of ``m s^2 + b s + k`` (closed form),
``scipy.signal.cont2discrete`` (not the analysis's phi1 series), the paper's Table 1 case V
closed form (:mod:`hapsim.analysis.table1`), and the lockstep daemon with the mock.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal

from hapsim.analysis.family import consistency, family, family_matrices
from hapsim.analysis.hand import body_zoh, ideal_rows, members
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.loop_poles import closed_loop_poles
from hapsim.analysis.network import closed_loop
from hapsim.analysis.ths import render
from hapsim.scene import parse_scene
from tolerance import measured


def scene_text(K=800.0, B=1.5, *, m=0.05, b0=0.3, d=1, hold="zoh", mh="0.2", bh="0.5",
               kg="rigid", bg="1.0", kh="300.0", x0=0.005, rate=1000, extra_links=""):
    return f"""
rate_hz: {rate}
masses: [{{name: hand, kind: port}}, {{name: wall, kind: ground}}]
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K}, damping: {B}}}
{extra_links}
device: {{mass: {m}, friction: {b0}, delay: {d}, hold: {hold}, force_limit: 1000000.0,
          hand: {{mass: {mh}, damping: {bh}, grip_stiffness: {kg}, grip_damping: {bg},
                  stiffness: {kh}}}}}
excitation: {{x0: {x0}}}
"""


def _mass_spring_poles(m, b, k, T):
    """exp(s T) of the roots of m s^2 + b s + k (closed form)."""
    disc = complex(b * b - 4 * m * k)
    s = np.array([(-b + np.sqrt(disc)) / (2 * m), (-b - np.sqrt(disc)) / (2 * m)])
    return np.sort_complex(np.exp(s * T))


@pytest.mark.parametrize("m,b,k,rate", [(0.25, 0.8, 300.0, 1000.0), (1.0, 0.0, 4000.0, 500.0),
                                        (0.1, 3.0, 10.0, 10000.0), (2.0, 40.0, 50.0, 1000.0)])
@pytest.mark.parametrize("hold", ["zoh", "ideal"])
def test_mass_spring_poles_are_exp_sT_without_delay_or_virtual_element(m, b, k, rate, hold):
    """d = 0, K = B = 0: the loop's poles are z = 0 and exp(s T) of m s^2 + b s + k = 0
    (both holds share the plant's poles), to 1e-12."""
    L = LoopModel(mass=m, friction=b, rate_hz=rate, delay=0, hold=hold, stiffness=k)
    p = closed_loop_poles(L, 0.0, 0.0)
    p = np.sort_complex(p[np.abs(p) > 1e-9])
    want = _mass_spring_poles(m, b, k, 1.0 / rate)
    assert p.size == 2
    # measured 5.3e-14 abs, 5.3e-14 rel (generic 5.3e-14, 5.3e-14), margin 19
    np.testing.assert_allclose(p, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("member", [(0.2, 0.5, math.inf, 0.0, 300.0),
                                    (0.1, 1.0, 2000.0, 0.5, 800.0),
                                    (0.5, 0.0, 300.0, 0.0, 50.0)])
def test_body_zoh_matches_cont2discrete(member):
    """The exact ZOH of handle + hand with the arm's spring equals scipy's (Van Loan)."""
    mc, bc, T = 0.05, 0.3, 1e-3
    Aw, Bd = body_zoh(mc, bc, member, T)
    n = Aw.shape[0]
    if n == 2:
        m, c, k = mc + member[0], bc + member[1], member[4]
        A = np.array([[0.0, 1.0], [-k / m, -c / m]])
        b = np.array([0.0, 1.0 / m])
    else:
        from hapsim.analysis.hand import hand_matrices
        A, b = hand_matrices(mc, bc, member)
    Ad, Bc, *_ = scipy.signal.cont2discrete((A, b[:, None], np.eye(n), np.zeros((n, 1))), T,
                                            method="zoh")
    # measured 1.4e-14 (generic 1.4e-14; the 1e-13 literal held by 7), margin 10
    np.testing.assert_allclose(Aw + np.eye(n), Ad, rtol=0, atol=measured(1.4e-14, 10))
    # measured 6.9e-18 abs, 4e-10 rel (generic 1e-17, 1.3e-9), margin 280
    np.testing.assert_allclose(Bd, Bc[:, 0], rtol=1e-11, atol=1e-13 * np.abs(Bc).max())


def test_ideal_rows_are_eq4_without_stiffness_and_case_V_without_damping():
    """k = 0: Florens et al. eq. (4) (tr = 1 + a, det = a, g = T (1 - a) / b); b = 0: the
    impulse image of table1.py (tr = 2 cos w0T, det = 1, g = T sin(w0T) / (m w0))."""
    m, b, T = 0.7, 2.0, 1e-2
    a = math.exp(-b * T / m)
    tr, det, g = ideal_rows(m, b, 0.0, T)
    # measured 0 (generic 0): exact on both targets
    assert (float(tr), float(det), float(g)) == pytest.approx((1 + a, a, T * (1 - a) / b),
                                                                rel=1e-13)
    k = 3000.0
    w0 = math.sqrt(k / m)
    tr, det, g = ideal_rows(m, 0.0, k, T)
    # measured 2e-16 relative (generic 2e-16), margin 4500
    assert (float(tr), float(det), float(g)) == pytest.approx(
        (2 * math.cos(w0 * T), 1.0, T * math.sin(w0 * T) / (m * w0)), rel=1e-13)


def test_property_scene_matrix_family_and_loop_polynomial_agree_over_random_hands():
    """40 seeded random hands (rigid and compliant, zoh and ideal, delays 0..3, arm
    stiffness 0..3000 N/m): the closed-loop state matrix of the scene, the family's batched
    matrices and the roots of P K + Q B + R of the member's LoopModel give the same poles."""
    rng = np.random.default_rng(14)
    for trial in range(40):
        rigid = trial % 2 == 0
        hold = "ideal" if rigid and trial % 4 == 0 else "zoh"
        d = int(rng.integers(0, 4))
        K, B = float(rng.uniform(50, 1500)), float(rng.uniform(0, 3))
        kg = "rigid" if rigid else repr(float(10 ** rng.uniform(2.5, 4.5)))
        sc = parse_scene(scene_text(K, B, d=d, hold=hold, m=float(rng.uniform(0.02, 0.2)),
                                    mh=repr(float(rng.uniform(0.05, 0.5))),
                                    bh=repr(float(rng.uniform(0, 2))), kg=kg,
                                    bg=repr(float(rng.uniform(0, 2))),
                                    kh=repr(float(rng.uniform(0, 3000)))))
        mem = members(sc.device.hand)[0]
        A, _ = closed_loop(sc, member=mem)
        ev = np.sort_complex(np.linalg.eigvals(A))
        Af, _ = family_matrices(sc, mem[None, :])
        # measured 0 (generic 0): exact on both targets
        np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(Af[0])), ev, atol=1e-12)
        po = np.sort_complex(closed_loop_poles(LoopModel.from_device(sc.device, sc.rate_hz,
                                                                     mem), K, B))
        ev, po = ev[np.abs(ev) > 1e-7], po[np.abs(po) > 1e-7]
        assert ev.size == po.size, trial
        # measured 4.7e-12 abs, 1.5e-9 rel (generic 3.6e-12, 1.5e-9), margin 210
        np.testing.assert_allclose(ev, po, rtol=0, atol=1e-9, err_msg=str(trial))


@pytest.mark.parametrize("kg,hold,d", [("rigid", "zoh", 1), ("2000.0", "zoh", 1),
                                       ("rigid", "zoh", 0), ("rigid", "ideal", 1),
                                       ("5000.0", "zoh", 2)])
def test_lockstep_measured_equals_predicted_with_a_hand_stiffness(kg, hold, d):
    """The mock models the arm's spring (rigid: one body on a spring; grip: on the hand
    mass): measured (k, b) == render(k, b) of the same LoopModel to 1e-6; the felt k
    includes the real spring (more than K alone would give)."""
    from hapsim.pipeline.runner import run_scene
    sc = parse_scene(scene_text(800.0, 1.5, d=d, hold=hold, kg=kg))
    rep = run_scene(sc, transport="inprocess", lockstep=True, handle_signals=False,
                    duration=1.0)
    L = LoopModel.from_device(sc.device, sc.rate_hz)
    assert L.stiffness == 300.0
    r = render(L, 800.0, 1.5)
    assert r.stable
    # measured 1.9e-12 relative (generic 6.9e-13), margin 5e5
    assert rep["measured"]["k"] == pytest.approx(r.k, rel=1e-6)
    # measured 3.1e-12 relative (generic 1.7e-11), margin 60000
    assert rep["measured"]["b"] == pytest.approx(r.b, rel=1e-6)
    r0 = render(LoopModel.from_device(sc.device, sc.rate_hz,
                                      np.append(members(sc.device.hand)[0][:4], 0.0)),
                800.0, 1.5)
    assert r.k > r0.k + 100.0


def _case_v(k):
    from hapsim.analysis.table1 import tuned_stiffness
    return f"""
rate_hz: 1
masses: [{{name: h, kind: port}}, {{name: g, kind: ground}}]
links:
  - {{name: virtual, kind: spring_damper, between: [h, g], stiffness: {tuned_stiffness(k)!r},
     damping: 0}}
device: {{mass: 0.5, friction: 0.0, delay: 0, hold: ideal, hand: {{mass: 0.5, stiffness: {k!r}}}}}
"""


@pytest.mark.parametrize("k", [0.01, 0.1, 0.5, 1.0, 2.0, 3.0])
def test_consistency_pins_table1_case_V(k):
    """A virtual K tuned by eq. (2) and the arm's real k together (m = T = 1, d = 0, ideal
    hold, no damping): the assembly of the felt parts is k + k = 2k (II rings like I) and
    the felt assembly over it is Table 1's felt k V / 2k, to 1e-9."""
    from hapsim.analysis.table1 import table1_experiment
    c = consistency(parse_scene(_case_v(k)))
    row = table1_experiment([k])[0]
    assert c["real_spring"] and c["links"] == ["virtual"]
    # measured 5.4e-15 relative (generic 5.4e-15), margin 2200
    assert c["k_sum"][0] == pytest.approx(2 * k, rel=1e-12)
    # measured 2.7e-14 relative (generic 2.7e-14), margin 36000
    assert c["k"][0] / c["k_sum"][0] == pytest.approx(row["kfelt_V"], rel=1e-9)
    # measured 2.7e-14 (generic 2.7e-14), margin 36
    assert c["worst_k"] == pytest.approx(row["kfelt_V"] - 1.0, abs=1e-12)


def test_consistency_of_a_real_and_a_virtual_spring_over_a_family_in_the_cli(capsys):
    """A wall felt with an arm stiffness range 100..1000 N/m and a hand mass range: the
    report compares the felt whole with kh + (the wall felt without the arm) per member;
    the arm's stiffness alone does not make a consistency check without a virtual part."""
    import json
    import os
    import tempfile
    from hapsim.cli import main
    from hapsim.errors import ConfigError
    text = scene_text(800.0, 1.5, mh="[0.1, 0.4]", kh="[100, 1000]")
    with tempfile.TemporaryDirectory() as tmp:
        p = os.path.join(tmp, "arm.yaml")
        with open(p, "w") as f:
            f.write(text)
        assert main(["family", p, "--grid", "3", "--json"]) == 0
        c = json.loads(capsys.readouterr().out)["consistency"]
        assert main(["family", p, "--grid", "3"]) == 0
        out = capsys.readouterr().out
    assert c["real_spring"] and c["links"] == ["wall"] and c["members"] == 4 + 1 + 9
    # the sampled loop (d = 1, ZOH) distorts: neither exactly consistent nor far off
    assert 0.0 < c["worst_k"] < 0.2
    assert "real spring" in out and "k / (sum of the parts)" in out
    sc = parse_scene(text)
    res = family(sc, grid=3)
    full = consistency(sc, grid=3)
    nom = res.corners
    kh = res.members[nom, 4]
    # measured 0 (generic 0): exact on both targets
    assert kh == pytest.approx(math.sqrt(100 * 1000))
    alone = render(LoopModel.from_device(sc.device, sc.rate_hz,
                                         np.append(res.members[nom, :4], 0.0)), 800.0, 1.5)
    # measured 8.1e-16 relative (generic 8.1e-16), margin 1e6
    assert full["k_sum"][nom] == pytest.approx(kh + alone.k, rel=1e-9)
    # the real spring with no virtual link to ground (the port drives a virtual mass):
    # one part only, refused
    no_link = parse_scene(text.replace(
        "{name: wall, kind: ground}", "{name: wall, kind: mass, mass: 0.1}"))
    with pytest.raises(ConfigError, match="two or more parts"):
        consistency(no_link)


def test_bad_hand_stiffness_is_refused_naming_the_key():
    """A negative stiffness is a scene error; one beyond MAX_PRODUCT (kh T^2/mh > 1e6) is
    refused by the analysis naming device.hand.stiffness, as LoopModel refuses it."""
    from hapsim.errors import ConfigError
    with pytest.raises(ConfigError, match="device.hand.stiffness"):
        parse_scene(scene_text(kh="-1.0"))
    with pytest.raises(ConfigError, match="device.hand.stiffness"):
        closed_loop(parse_scene(scene_text(kh="[1, 1e12]")))
    with pytest.raises(ConfigError, match="stiffness"):
        LoopModel(mass=0.1, rate_hz=1000.0, stiffness=-1.0)
    with pytest.raises(ConfigError, match="kh T\\^2/m"):
        LoopModel(mass=0.1, rate_hz=1000.0, stiffness=1e12)
