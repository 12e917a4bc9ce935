"""The n-D engine (hapsim.kernels.nd, the n-D layout of hapsim.engine) against a plain-numpy step
written here over random meshes of both link kinds, the stripe layout's bookkeeping, and
hapsim's 1-D engine on a 1-D scene laid along x."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapsim.engine import Engine
from hapsim.kernels.nd import stripes
from hapsim.scene import parse_scene
from hapsim.scene import parse_scene_nd
from tolerance import measured, rel_tol

pytestmark = pytest.mark.numerical

#: The compiled kernels against the plain numpy reference, relative to the motion: the
#: worst measured over this module's meshes (1.2e-13 with NUMBA_CPU_NAME=generic, 7.7e-14
#: on the host target: FMA contraction differs between them), margin 1000 (a wrong force
#: law or a link applied twice moves the motion by >= 1e-6 of itself).
KERNEL_VS_REFERENCE = measured(1.3e-13, 1000)
#: The n-D engine against the 1-D engine on a string along x: 3.8e-13 measured on the
#: host target (0 with the generic one), margin 1000.
ND_VS_1D = measured(3.8e-13, 1000)


def reference_steps(X, XP, t2m, links, T, n, contacts=(), planes=()):
    """Plain numpy, one element at a time: X, XP of shape (N, dim); links (i1, i2, K, B,
    L, euclid); contacts (i1, i2, K, B, threshold); planes (mass, unit normal, offset, K,
    B)."""
    X, XP = X.copy(), XP.copy()
    for _ in range(n):
        F = np.zeros_like(X)
        for a, b, K, B, L, eu in links:
            d, dp = X[a] - X[b], XP[a] - XP[b]
            if eu:
                ln, lp = np.linalg.norm(d), np.linalg.norm(dp)
                force = (K * (ln - L) + B / T * (ln - lp)) * d / ln
            else:
                force = K * d + B / T * (d - dp)
            F[a] -= force
            F[b] += force
        for a, b, K, B, thr in contacts:
            d, dp = X[a] - X[b], XP[a] - XP[b]
            ln, lp = np.linalg.norm(d), np.linalg.norm(dp)
            if 0 < ln < thr:
                force = (K * (ln - thr) + B / T * (ln - lp)) * d / ln
                F[a] -= force
                F[b] += force
        for m, u, off, K, B in planes:
            p, pp = off - u @ X[m], off - u @ XP[m]
            if p > 0:
                F[m] += (K * p + B / T * (p - pp)) * u
        X, XP = 2 * X - XP + t2m[:, None] * F, X
    return X


def random_scene(rng, dim, n_masses, n_links):
    lines = [f"dimension: {dim}", "rate_hz: 2000", "masses:"]
    X0 = rng.normal(size=(n_masses, dim)) * 0.02
    V0 = rng.normal(size=(n_masses, dim)) * 0.01
    kinds = []
    for i in range(n_masses):
        kind = "ground" if i % 7 == 0 else "mass"
        kinds.append(kind)
        m = f", mass: {rng.uniform(0.001, 0.01)!r}, v0: {V0[i].tolist()}" \
            if kind == "mass" else ""
        lines.append(f"  - {{name: m{i}, kind: {kind}, x0: {X0[i].tolist()}{m}}}")
    lines.append("links:")
    links = []
    pairs = set()
    while len(links) < n_links:
        a, b = rng.integers(0, n_masses, 2)
        if a == b or (a, b) in pairs or (b, a) in pairs:
            continue
        pairs.add((a, b))
        K, B = rng.uniform(10, 300), rng.uniform(0, 0.05)
        L = float(rng.choice([0.0, rng.uniform(0.005, 0.03)]))
        lines.append(f"  - {{kind: spring_damper, between: [m{a}, m{b}], stiffness: {K!r}, "
                     f"damping: {B!r}, length: {L!r}}}")
        links.append((a, b, K, B, L, L > 0))
    return "\n".join(lines) + "\n", links


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_kernel_equals_the_plain_reference_on_random_meshes(dim):
    """Random topology (any offsets, both orientations), per-link K, B, rest length,
    linear and Euclidean links, grounds: 300 samples agree to round-off (relative to the
    motion, KERNEL_VS_REFERENCE)."""
    rng = np.random.default_rng(dim)
    text, links = random_scene(rng, dim, 40, 90)
    scene = parse_scene_nd(text) if dim > 1 else None
    if dim == 1:   # the n-D kernels run a 1-D mesh too (the scene format starts at 2)
        scene = parse_scene_nd(text.replace("dimension: 1", "dimension: 2")
                               .replace("x0: [", "x0: [0.0, ").replace("v0: [", "v0: [0.0, "))
    eng = Engine(scene)
    if dim == 1:
        # drop the zero first axis: the second row moves to the first, the kernels
        # then run one live axis
        from hapsim.kernels.nd import link_lengths
        for a in (eng._X, eng._XP):
            a[0], a[1] = a[1].copy(), 0.0
        eng.dim = 1
        eng.eu_lprev[:] = link_lengths(eng._XP, np.concatenate([eng.eu_pieces, eng.dn_fam]),
                                       eng.eu_k.size)
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    ref = reference_steps(X0, XP0, eng.t2m, links, scene.period, 300)
    eng.step(300)
    scale = np.max(np.abs(ref - X0))
    assert scale > 1e-4
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale


@settings(max_examples=12, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), dim=st.sampled_from([2, 3]),
       block=st.integers(1, 24), n_masses=st.integers(3, 50))
def test_blocked_schedule_equals_the_plain_reference(seed, dim, block, n_masses):
    """Property: on random meshes (any topology and orientation, per-link K, B, rest
    length, both link kinds, grounds) cut into blocks of any size, so that links cross
    many blocks and masses advance block by block within a sample, 80 samples agree with
    the plain one-link-at-a-time reference to round-off (KERNEL_VS_REFERENCE)."""
    rng = np.random.default_rng(seed)
    n_links = int(rng.integers(1, 3 * n_masses))
    n_links = min(n_links, n_masses * (n_masses - 1) // 2)
    text, links = random_scene(rng, dim, n_masses, n_links)
    scene = parse_scene_nd(text)
    eng = Engine(scene, block=block)
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    ref = reference_steps(X0, XP0, eng.t2m, links, scene.period, 80)
    eng.step(80)
    scale = np.max(np.abs(ref - X0)) + 1e-300
    assert np.all(np.isfinite(ref))
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale


def grid_scene(rng, nx, ny, nz, odd):
    """A 3-D grid mesh joined to its +x, +y, +z neighbours by Euclidean links sharing one
    (K, B, L) (``odd``: one link differs), the z = 0 face ground, displaced at random."""
    K, B, L = rng.uniform(50, 300), rng.uniform(0, 0.02), rng.uniform(0.005, 0.02)
    idx = np.arange(nx * ny * nz).reshape(nz, ny, nx)
    lines = ["dimension: 3", "rate_hz: 2000", "masses:"]
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                x0 = (np.array([i, j, k]) * L + rng.uniform(-0.2, 0.2, 3) * L).tolist()
                kind = "ground" if k == 0 else "mass"
                m = f", mass: {rng.uniform(0.002, 0.01)!r}" if kind == "mass" else ""
                lines.append(f"  - {{name: m{idx[k, j, i]}, kind: {kind}, x0: {x0}{m}}}")
    lines.append("links:")
    pairs = [(a, b) for sl in ((np.s_[:, :, :-1], np.s_[:, :, 1:]),
                               (np.s_[:, :-1, :], np.s_[:, 1:, :]),
                               (np.s_[:-1], np.s_[1:]))
             for a, b in zip(idx[sl[0]].ravel(), idx[sl[1]].ravel())]
    links = []
    # the odd link joins a moving mass (one between two grounds does not enter the
    # engine, which would leave every piece shared: dims (3, 1, 2) did)
    moving = [q for q, (a, b) in enumerate(pairs) if max(a, b) >= nx * ny]
    q_odd = moving[len(moving) // 2]
    for q, (a, b) in enumerate(pairs):
        k = K * 1.5 if odd and q == q_odd else K
        lines.append(f"  - {{kind: spring_damper, between: [m{a}, m{b}], stiffness: {k!r}, "
                     f"damping: {B!r}, length: {L!r}}}")
        links.append((a, b, k, B, L, True))
    return "\n".join(lines) + "\n", links


@settings(max_examples=12, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), block=st.integers(1, 40),
       dims=st.tuples(st.integers(2, 5), st.integers(1, 4), st.integers(2, 4)),
       odd=st.booleans(), families=st.booleans())
def test_grid_pieces_and_families_equal_the_plain_reference(seed, block, dims, odd,
                                                            families):
    """Property: a grid mesh whose links share (K, B, L) runs, with ``families``, its +x,
    +y and +z links as dense families whose forces each mass pulls (padding slots where
    a family has no link, their forces dropped; one (K, B, L) per family, per-link
    parameters in the odd link's); without, its pieces on the shared
    parameters (their padding links' forces dropped), and, with one link different, the
    piece holding it on per-link ones; 80 samples agree with the plain reference to
    round-off (KERNEL_VS_REFERENCE)."""
    rng = np.random.default_rng(seed)
    text, links = grid_scene(rng, *dims, odd)
    scene = parse_scene_nd(text)
    eng = Engine(scene, block=block, families=families)
    if families:        # every link in a family: no piece left
        assert eng.dn_fam.shape == (3, 4) and eng.eu_pieces.shape[0] == 0
        # each family on one (K, B, L) but the odd link's, on per-link values
        fam_shared = eng.eu_shared[0][eng.eu_pieces.shape[0]:]
        assert fam_shared.sum() == fam_shared.size - odd
    else:
        shared = eng.eu_shared[0]
        assert shared.any() and (not odd or not shared.all())
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    ref = reference_steps(X0, XP0, eng.t2m, links, scene.period, 80)
    eng.step(80)
    scale = np.max(np.abs(ref - X0))
    assert scale > 0
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale


def link_force(X, XP, a, b, K, B, L, eu, T):
    """The plain reference's force of one link on its first mass [N] (``-force`` of
    :func:`reference_steps`)."""
    d, dp = X[a] - X[b], XP[a] - XP[b]
    if eu:
        ln, lp = np.linalg.norm(d), np.linalg.norm(dp)
        return -(K * (ln - L) + B / T * (ln - lp)) * d / ln
    return -(K * d + B / T * (d - dp))


@settings(max_examples=10, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), block=st.integers(1, 40),
       dims=st.tuples(st.integers(3, 6), st.integers(2, 4), st.integers(2, 3)))
def test_families_beside_pieces_planes_and_a_port_equal_the_plain_reference(seed, block,
                                                                           dims):
    """Property: a grid mesh with random holes (a fifth of its links missing, none at
    the port) and
    per-link (K, B, L), its first mass the port (held) inside a family, plus random
    extra links of both kinds (pieces) and a floor plane: the families' pulled forces
    add to the pieces' and the plane's, and 80 samples agree with the plain reference to
    round-off (KERNEL_VS_REFERENCE), the port's force too."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = dims
    n = nx * ny * nz
    idx = np.arange(n).reshape(nz, ny, nx)
    h = 0.01
    lines = ["dimension: 3", "rate_hz: 2000", "masses:"]
    for q, (k, j, i) in enumerate(np.ndindex(nz, ny, nx)):
        x0 = (np.array([i, j, k]) * h + rng.uniform(-0.2, 0.2, 3) * h).tolist()
        lines.append(f"  - {{name: m{q}, kind: port}}" if q == 0 else
                     f"  - {{name: m{q}, kind: mass, x0: {x0}, "
                     f"mass: {rng.uniform(0.002, 0.01)!r}}}")
    pairs = [(a, b) for sl in ((np.s_[:, :, :-1], np.s_[:, :, 1:]),
                               (np.s_[:, :-1, :], np.s_[:, 1:, :]),
                               (np.s_[:-1], np.s_[1:]))
             for a, b in zip(idx[sl[0]].ravel(), idx[sl[1]].ravel())
             if a == 0 or rng.uniform() > 0.2]
    n_grid = len(pairs)                 # Euclidean; then extra links of both kinds
    while len(pairs) < n * 3.5:
        a, b = sorted(rng.choice(n, 2, replace=False))
        if (a, b) not in pairs:
            pairs.append((a, b))
    lines.append("links:")
    links = []
    for q, (a, b) in enumerate(pairs):
        K, B = rng.uniform(50, 300), rng.uniform(0, 0.02)
        L = rng.uniform(0.5, 2) * h if q < n_grid or rng.uniform() < 0.5 else 0.0
        lines.append(f"  - {{kind: spring_damper, between: [m{a}, m{b}], stiffness: {K!r}, "
                     f"damping: {B!r}, length: {L!r}}}")
        links.append((a, b, K, B, L, L > 0))
    lines.append("planes:\n  - {name: floor, normal: [0, 0, 1], offset: 0.002, "
                 "stiffness: 500, damping: 0.05}")
    lines.append("device: {mass: 0.1}")
    scene = parse_scene_nd("\n".join(lines) + "\n")
    eng = Engine(scene, block=block)
    eng.set_port_position(np.zeros(3), at_rest=True)     # held at the origin
    fam = eng.dn_fam[eng.dn_fam[:, 2] > 0]
    assert np.any(fam[:, 0] == 0)                       # the port in one
    assert eng.eu_pieces.shape[0] + eng.lin_pieces.shape[0] > 0
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    planes = [(m, np.array([0.0, 0.0, 1.0]), 0.002, 500.0, 0.05) for m in range(n)]
    T = scene.period
    ref = reference_steps(X0, XP0, eng.t2m, links, T, 80, planes=planes)
    X79 = reference_steps(X0, XP0, eng.t2m, links, T, 79, planes=planes)
    X78 = reference_steps(X0, XP0, eng.t2m, links, T, 78, planes=planes)
    eng.step(80)
    scale = np.max(np.abs(ref - X0))
    assert scale > 0
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale
    F = sum((link_force(X79, X78, *lk, T) if lk[0] == 0 else -link_force(X79, X78, *lk, T))
            for lk in links if 0 in lk[:2])
    pen, pen_prev = 0.002 - X79[0, 2], 0.002 - X78[0, 2]     # the floor on the port
    F[2] += (500.0 * pen + 0.05 / T * (pen - pen_prev)) if pen > 0 else 0.0
    terms = sum(float(np.max(np.abs(link_force(X79, X78, *lk, T))))
                for lk in links if 0 in lk[:2])
    assert np.max(np.abs(eng.port_force - F)) <= KERNEL_VS_REFERENCE * terms


def test_schedule_pieces_stay_in_their_block():
    """Every piece's lower masses lie in one block, in block order, at most ``block``
    links long, and the pieces cover each stripe's links exactly once."""
    from hapsim.kernels.nd import schedule
    rng = np.random.default_rng(5)
    i1 = rng.integers(0, 300, 700)
    i2 = i1 + rng.choice([1, 2, 17, 40, 150], 700)
    keep = i2 < 300
    table, order = stripes(i1[keep], i2[keep])
    for block in (1, 7, 64, 256, 1000):
        pieces, ptr = schedule(table, 300, block)
        assert ptr[0] == 0 and ptr[-1] == len(pieces) and ptr.size == -(-300 // block) + 1
        covered = np.zeros(order.size, int)
        for q in range(ptr.size - 1):
            for a, s, c, j0 in pieces[ptr[q]:ptr[q + 1]]:
                assert 1 <= c <= block and s > 0
                assert q * block <= a and a + c <= (q + 1) * block
                covered[j0:j0 + c] += 1
        assert np.all(covered == 1)
    with pytest.raises(ValueError):
        schedule(np.array([[5, -1, 3, 0]]), 10, 4)


def test_stripes_cover_every_link_once():
    """Each link lands in exactly one slot of one stripe with its orientation; padding
    slots are -1 and inside gaps only; a 3-D grid's +x/+y/+z links make few stripes."""
    rng = np.random.default_rng(0)
    i1 = rng.integers(0, 200, 500)
    i2 = (i1 + rng.choice([-13, -1, 1, 2, 40], 500)) % 200
    keep = i1 != i2
    i1, i2 = i1[keep], i2[keep]
    table, order = stripes(i1, i2)
    seen = np.zeros(i1.size, int)
    for a, s, c, j0 in table:
        for i in range(c):
            j = order[j0 + i]
            if j >= 0:
                assert (i1[j], i2[j]) == (a + i, a + s + i)
                seen[j] += 1
    assert np.all(seen == 1)
    assert order.size == table[:, 2].sum()
    idx = np.arange(10 * 10 * 10).reshape(10, 10, 10)
    gi1 = np.concatenate([idx[:, :, :-1].ravel(), idx[:, :-1, :].ravel(), idx[:-1].ravel()])
    gi2 = np.concatenate([idx[:, :, 1:].ravel(), idx[:, 1:, :].ravel(), idx[1:].ravel()])
    gtable, gorder = stripes(gi1, gi2)
    assert len(gtable) <= 12 and (gorder < 0).mean() < 0.15


def test_linear_2d_scene_along_x_is_the_1d_engine():
    """A 1-D string laid along x in a 2-D scene (linear links): the x positions equal
    hapsim's 1-D engine on the 1-D scene (to round-off, ND_VS_1D), the y positions stay 0."""
    one = """\
rate_hz: 1000
masses:
  - {name: left, kind: ground, x0: 0.0}
  - {name: a, kind: mass, mass: 0.01, x0: 0.011, v0: 0.3}
  - {name: b, kind: mass, mass: 0.02, x0: 0.02}
  - {name: c, kind: mass, mass: 0.01, x0: 0.029, v0: -0.1}
  - {name: right, kind: ground, x0: 0.04}
links:
  - {kind: spring_damper, between: [left, a], stiffness: 200, damping: 0.01}
  - {kind: spring_damper, between: [a, b], stiffness: 300, damping: 0.02}
  - {kind: spring_damper, between: [b, c], stiffness: 300, damping: 0.0}
  - {kind: spring_damper, between: [c, right], stiffness: 200, damping: 0.01}
"""
    e1 = Engine(parse_scene(one))
    two = "dimension: 2\n" + one
    for v in ("0.0", "0.011", "0.02", "0.029", "0.04", "0.3", "-0.1"):
        two = two.replace(f"x0: {v}}}", f"x0: [{v}, 0.0]}}").replace(
            f"x0: {v},", f"x0: [{v}, 0.0],").replace(f"v0: {v}}}", f"v0: [{v}, 0.0]}}")
    e2 = Engine(parse_scene_nd(two))
    x0 = e1.positions.copy()
    for _ in range(5):
        e1.step(100)
        e2.step(100)
        scale = np.max(np.abs(e1.positions - x0)) + 1e-300
        assert np.max(np.abs(e2.positions[:, 0] - e1.positions[:, 0])) <= ND_VS_1D * scale
        assert np.all(e2.positions[:, 1] == 0.0)


def test_port_contacts_and_planes_follow_their_laws():
    """A port follows set_port_position and its force is -K d of its link; sphere
    contacts and planes (engaging and releasing on the way) match the plain reference
    over 400 samples of a falling, bouncing pair of beads."""
    base = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.0]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 300, damping: 0}
device: {mass: 0.1}
"""
    eng = Engine(parse_scene_nd(base))
    eng.set_port_position([0.01, -0.02])
    eng.step()
    # -K d: a difference of positions and one product (3 roundings)
    assert np.allclose(eng.port_force, [-3.0, 6.0], rtol=rel_tol(3), atol=0)
    text = """\
dimension: 2
rate_hz: 2000
masses:
  - {name: a, kind: mass, mass: 0.01, x0: [0.0, 0.01], v0: [0.05, -0.3]}
  - {name: b, kind: mass, mass: 0.02, x0: [0.006, 0.004], v0: [-0.1, 0.0]}
  - {name: g, kind: ground, x0: [0.02, 0.02]}
links:
  - {name: s, kind: spring_damper, between: [g, b], stiffness: 20, damping: 0.01,
     length: 0.01}
  - {name: c, kind: contact, between: [a, b], stiffness: 800, damping: 0.05,
     threshold: 0.006}
planes:
  - {name: floor, normal: [0.2, 1], offset: -0.002, stiffness: 1500, damping: 0.1}
"""
    scene = parse_scene_nd(text)
    eng = Engine(scene)
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    u = np.array([0.2, 1.0]) / np.hypot(0.2, 1.0)
    ref = reference_steps(X0, XP0, eng.t2m, [(2, 1, 20.0, 0.01, 0.01, True)], scene.period,
                          400, contacts=[(0, 1, 800.0, 0.05, 0.006)],
                          planes=[(0, u, -0.002, 1500.0, 0.1), (1, u, -0.002, 1500.0, 0.1)])
    # the reference engaged both: the contact and the floor
    eng.step(400)
    scale = np.max(np.abs(ref - X0))
    # bit for bit here on both targets; the kernels' class bound all the same
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale
    engaged = [False, False]
    eng2 = Engine(scene)
    for _ in range(400):
        eng2.step()
        d = np.linalg.norm(eng2.x[:, 0] - eng2.x[:, 1])
        engaged[0] |= d < 0.006
        engaged[1] |= bool(np.any(-0.002 - u @ eng2.x > 0))
    assert engaged == [True, True]


def test_simulate_cli_on_an_n_d_scene(tmp_path, capsys):
    """`hapsim simulate` on a 3-D scene writes time, position (N+1, R, 3) and names equal
    to Engine's own run; a diverging scene stops with exit 1 and the rows before it; a
    .csv output is refused (exit 2)."""
    import json

    from hapsim.cli import main
    text = """\
dimension: 3
rate_hz: 1000
masses:
  - {name: g, kind: ground, x0: [0, 0, 0]}
  - {name: a, kind: mass, mass: 0.01, x0: [0.01, 0.002, 0.0], v0: [0, 0.1, 0]}
links:
  - {name: s, kind: spring_damper, between: [g, a], stiffness: 40, damping: 0.001,
     length: 0.01}
"""
    f = tmp_path / "s.yaml"
    f.write_text(text)
    out = tmp_path / "o.npz"
    assert main(["simulate", str(f), "--steps", "50", "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dimension"] == 3
    d = np.load(out)
    assert d["position"].shape == (51, 2, 3) and list(d["names"]) == ["g", "a"]
    eng = Engine(parse_scene_nd(text))
    eng.step(50)
    assert np.array_equal(d["position"][-1], eng.positions)
    f.write_text(text.replace("stiffness: 40", "stiffness: 1.0e6"))
    assert main(["simulate", str(f), "--steps", "20000", "--out", str(out)]) == 1
    assert "diverged" in capsys.readouterr().err
    assert np.all(np.isfinite(np.load(out)["position"]))
    assert main(["simulate", str(f), "--steps", "5", "--out", str(tmp_path / "o.csv")]) == 2
