"""Where the n-D engine places the arrays its dense families stream
(hapsim.kernels.layout.family_offsets, placed) and the families' shared parameters: the
aliasing count's definition, the planner's guarantees, and that neither changes a single
bit of a trajectory (placement) or the physics (a live change of one family link)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapsim.engine import Engine
from hapsim.engine._space import _PLACED
from hapsim.kernels.layout import (ALIAS_WINDOW, PAGE, PLACED, _aliases, _family_streams,
                                   euclid_layout, family_offsets, placed)
from hapsim.kernels.nd import context
from hapsim.scene import parse_scene_nd
from test_engine_nd import KERNEL_VS_REFERENCE, grid_scene, reference_steps

pytestmark = pytest.mark.numerical


def test_aliases_count_stores_just_ahead_of_a_load_modulo_a_page():
    """Closed form of the count: a store 1 to ALIAS_WINDOW bytes ahead of a load modulo
    PAGE is one pair (a page or more apart too); the same address, a store behind the
    load, or one further ahead is none; loops are counted apart and summed."""
    one = [(0, 64), (0, PAGE + 64), (0, ALIAS_WINDOW), (PAGE - 64, 0), (8, 8 + 1)]
    none = [(0, 0), (64, 0), (0, ALIAS_WINDOW + 64), (0, PAGE), (0, 2 * PAGE - 64)]
    for ld, st_ in one:
        assert _aliases([([ld], [st_])]) == 1, (ld, st_)
    for ld, st_ in none:
        assert _aliases([([ld], [st_])]) == 0, (ld, st_)
    assert _aliases([([ld], [s]) for ld, s in one + none]) == len(one)
    assert _aliases([([0, None], [None, 64])]) == 1      # unplaced arrays not counted


def grid_families(nx, ny, nz):
    """A grid's +x, +y, +z links (lower index first) and its masses."""
    idx = np.arange(nx * ny * nz).reshape(nz, ny, nx)
    i1 = np.concatenate([idx[:, :, :-1].ravel(), idx[:, :-1, :].ravel(), idx[:-1].ravel()])
    i2 = np.concatenate([idx[:, :, 1:].ravel(), idx[:, 1:, :].ravel(), idx[1:].ravel()])
    return i1, i2, nx * ny * nz


@settings(max_examples=40, deadline=None, derandomize=True)
@given(dims=st.tuples(st.integers(2, 40), st.integers(2, 40), st.integers(2, 25)),
       itemsize=st.sampled_from([4, 8]), shared=st.booleans())
def test_family_offsets_are_cache_lines_in_a_page_and_alias_no_more_than_page_starts(
        dims, itemsize, shared):
    """Property over grid meshes of up to 40,000 masses, both precisions: every offset is
    a multiple of 64 bytes below a page, ``x`` at 0, the same on a second call, and the
    planned placement has no more aliasing pairs than every array at a page start (what
    a page-aligned allocator gives); at most 3 on these grids (measured: 0 to 3)."""
    i1, i2, n = grid_families(*dims)
    _, _, fam, _ = euclid_layout(i1, i2, n)
    if not len(fam):
        return
    P = int(fam[:, 1].max())
    off = family_offsets(n, fam, P, itemsize, shared)
    assert off == family_offsets(n, fam, P, itemsize, shared)
    assert set(off) == set(PLACED) and off["x"] == 0
    assert all(o % 64 == 0 and 0 <= o < PAGE for o in off.values())
    count = _aliases(_family_streams(n, fam.tolist(), P, itemsize, off, shared))
    starts = _aliases(_family_streams(n, fam.tolist(), P, itemsize,
                                      dict.fromkeys(PLACED, 0), shared))
    assert count <= starts and count <= 3


@settings(max_examples=12, deadline=None, derandomize=True)
@given(values=st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=300),
       offset=st.integers(0, PAGE // 8 - 1), rows=st.integers(1, 3))
def test_placed_is_a_c_contiguous_copy_at_its_offset(values, offset, rows):
    """Property: ``placed`` keeps shape, type and values, is C-contiguous and writeable,
    and starts ``offset`` bytes after a page boundary."""
    a = np.array(values * rows).reshape(rows, -1)
    b = placed(a, 8 * offset)
    assert b.shape == a.shape and b.dtype == a.dtype and np.array_equal(a, b)
    assert b.flags.c_contiguous and b.flags.writeable
    assert b.ctypes.data % PAGE == 8 * offset


def replanted(eng):
    """The engine with its placed arrays copied to wherever numpy allocates them, and its
    context rebuilt on the copies (the layout before placement)."""
    for name in _PLACED:
        setattr(eng, name, np.array(getattr(eng, name)))
    eng._ctx = context(eng.dim, eng.block, *eng._arrays(), eng.port_index, eng.port_f,
                       dtype=eng.dtype)
    return eng


@settings(max_examples=8, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), dims=st.tuples(st.integers(3, 7),
                                                      st.integers(2, 5),
                                                      st.integers(2, 4)),
       odd=st.booleans(), precision=st.sampled_from(["double", "single"]))
def test_placement_changes_no_bit_of_the_trajectory(seed, dims, odd, precision):
    """Property over random grid meshes with dense families, both precisions, shared or
    per-link family parameters: the engine's streamed arrays start where
    ``family_offsets`` says, and 60 samples equal bit for bit those of the same engine
    on plainly allocated copies (placement moves arrays, never an operation)."""
    rng = np.random.default_rng(seed)
    text, _ = grid_scene(rng, *dims, odd)
    scene = parse_scene_nd(text)
    a, b = Engine(scene, precision=precision), Engine(scene, precision=precision)
    assert a.dn_fam.shape[0] == 3
    n = a._X.shape[1]
    fam = a.dn_fam[a.dn_fam[:, 2] > 0]
    shared = bool(a.eu_shared[0][a.eu_pieces.shape[0]:].all())
    assert shared != odd
    off = family_offsets(n, fam, a.dn_G.shape[1] - n, a._X.itemsize, shared)
    for name, key in _PLACED.items():
        assert getattr(a, name).ctypes.data % PAGE == off[key], name
        assert getattr(a, name).flags.c_contiguous
    replanted(b)
    a.step(60)
    b.step(60)
    assert np.array_equal(a._X, b._X) and np.array_equal(a._XP, b._XP)
    assert np.array_equal(a.eu_lprev, b.eu_lprev)


def test_a_live_change_of_one_family_link_is_felt_by_the_family():
    """A uniform grid's families read one (K, B, L) each; a live change of one link's
    stiffness through ``cells`` makes its family read per-link values (the others stay
    shared), and 40 samples then agree with the plain reference on the changed link
    to round-off (KERNEL_VS_REFERENCE)."""
    rng = np.random.default_rng(7)
    text, links = grid_scene(rng, 5, 4, 3, False)
    count = iter(range(len(links)))
    text = re.sub(r"\{kind: spring_damper", lambda _: f"{{name: l{next(count)}, "
                  "kind: spring_damper", text)
    scene = parse_scene_nd(text)
    eng = Engine(scene)
    nP = eng.eu_pieces.shape[0]
    assert eng.eu_shared[0][nP:].all() and eng.eu_shared[0][nP:].size == 3
    q = len(links) - 7                  # a +z link between moving masses
    assert min(links[q][:2]) >= 5 * 4
    cells = eng.cells(f"l{q}")
    arr, j = cells["stiffness"][0]
    arr[j] = links[q][2] * 2.0
    assert eng.eu_shared[0][nP:].tolist() == [True, True, False]
    links = [lk if i != q else (lk[0], lk[1], lk[2] * 2.0, *lk[3:])
             for i, lk in enumerate(links)]
    X0, XP0 = eng.x.T.copy(), eng.xp.T.copy()
    ref = reference_steps(X0, XP0, eng.t2m, links, scene.period, 40)
    same = reference_steps(X0, XP0, eng.t2m,
                           [lk if i != q else (lk[0], lk[1], lk[2] / 2.0, *lk[3:])
                            for i, lk in enumerate(links)], scene.period, 40)
    eng.step(40)
    scale = np.max(np.abs(ref - X0))
    assert np.max(np.abs(eng.x.T - ref)) <= KERNEL_VS_REFERENCE * scale
    # the change is felt: the unchanged mesh's trajectory is beyond round-off of it
    assert np.max(np.abs(eng.x.T - same)) > KERNEL_VS_REFERENCE * scale
