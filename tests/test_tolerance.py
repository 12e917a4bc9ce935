"""The derived tolerances (tests/tolerance.py) are bounds: on problems whose exact answer
is known in floating point (integer similarity transforms of triangular matrices, integer
systems), the computed answer's error stays within them; and they are not vacuous (far
below the errors the tests catch). And the tests marked ``numerical`` carry no bare literal
round-off tolerance: each is derived here or measured with its margin (issue 31)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tolerance import (EPS, companion, crossing_tol, dot_tol, eig_bounds, eig_tol,
                       gamma, measured, power_bound, recurrence_tol, rel_tol, roots_tol,
                       solve_tol, sum_tol)

pytestmark = pytest.mark.numerical

TESTS = Path(__file__).resolve().parent


def unimodular(rng, n):
    """An integer matrix of determinant 1 and its integer inverse (products of elementary
    integer row operations), so that V T V^-1 is exact in floating point for small
    integer T."""
    V, W = np.eye(n), np.eye(n)
    for _ in range(2 * n):
        i, j = rng.choice(n, 2, replace=False)
        c = int(rng.integers(-2, 3))
        E = np.eye(n)
        E[i, j] = c
        Einv = np.eye(n)
        Einv[i, j] = -c
        V, W = E @ V, W @ Einv
    assert np.array_equal(V @ W, np.eye(n))
    return V, W


@pytest.mark.parametrize("n", [3, 6, 10])
def test_eigenvalue_bound_holds_on_matrices_with_known_eigenvalues(n):
    """A = V T V^-1 with T upper triangular (integer, distinct diagonal) and V unimodular:
    A is exact in floating point and its eigenvalues are T's diagonal. numpy's eigvals
    (LAPACK dgeev, whatever the BLAS kernel) lands within eig_bounds of each one."""
    rng = np.random.default_rng(n)
    for _ in range(20):
        T = np.triu(rng.integers(-3, 4, (n, n))).astype(float)
        T[np.diag_indices(n)] = rng.choice(np.arange(-4 * n, 4 * n), n, replace=False)
        V, W = unimodular(rng, n)
        A = V @ T @ W
        assert np.max(np.abs(A)) < 2 ** 50          # exact integers
        exact = np.sort(np.diag(T))
        got = np.sort(np.linalg.eigvals(A).real)
        w, bound = eig_bounds(A)
        order = np.argsort(w.real)
        assert np.all(np.abs(got - exact) <= bound[order])
        assert np.all(bound < 1e-6 * np.max(np.abs(A)))    # not vacuous


def test_eigenvalue_bound_of_a_double_root_is_the_square_root_one():
    """A Jordan block J_2(1): eigenvalues of J + E move by ~sqrt(||E||); the bound switches
    to the Hoelder form and covers a perturbation of the backward error's size."""
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    _, b = eig_bounds(A)
    E = 2 * EPS * np.array([[0.0, 0.0], [1.0, 0.0]])
    moved = np.max(np.abs(np.linalg.eigvals(A + E) - 1.0))
    assert moved > 1e-9 and np.all(b >= moved)


def test_roots_and_solve_bounds_hold_on_exact_problems():
    """Roots of (z - 1)(z - 2)...(z - 6) (integer coefficients, exact), and an integer
    system with an integer solution: the computed answers are within the bounds."""
    c = np.poly(np.arange(1, 7))
    assert np.array_equal(c, np.round(c))
    assert np.max(np.abs(np.sort(np.roots(c).real) - np.arange(1, 7))) <= roots_tol(c)
    assert companion(c).shape == (6, 6)
    rng = np.random.default_rng(3)
    for n in (3, 8, 20):
        A = rng.integers(-9, 10, (n, n)).astype(float)
        x = rng.integers(-9, 10, n).astype(float)
        b = A @ x                                   # exact: small integers
        got = np.linalg.solve(A, b)
        assert np.linalg.norm(got - x, np.inf) <= solve_tol(A) * np.linalg.norm(x, np.inf)


def test_sum_dot_and_recurrence_bounds_hold():
    """A sum and a dot product against exact rational arithmetic (math.fsum is exactly
    rounded), and a rotation iterated 1000 times against its closed form."""
    import math
    rng = np.random.default_rng(4)
    x, y = rng.normal(size=1000), rng.normal(size=1000)
    assert abs(float(np.sum(x)) - math.fsum(x)) <= sum_tol(x)
    assert abs(float(x @ y) - math.fsum(x * y)) <= dot_tol(x, y) + sum_tol(x * y)
    th = 0.01
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    s = np.array([1.0, 0.0])
    for _ in range(1000):
        s = R @ s
    exact = np.array([math.cos(1000 * th), math.sin(1000 * th)])
    # the closed form carries R's own rounding (cos, sin: one rounding each) over 1000
    # steps: 1000 * rel_tol(1) on top of the iteration's round-off
    assert np.max(np.abs(s - exact)) <= recurrence_tol(R, 1000, 1.0) + 1000 * rel_tol(1)
    assert power_bound(R, 10) == pytest.approx(1.0, rel=0, abs=rel_tol(40))


def test_helpers_refuse_nonsense():
    assert gamma(0) == 0.0 and gamma(10) > 10 * EPS / 2
    with pytest.raises(ValueError):
        gamma(2 ** 60)
    with pytest.raises(ValueError):
        measured(1e-12, 0.5)
    assert crossing_tol(lambda v: 2 * v, 3.0, 1e-12) == pytest.approx(5e-13, rel=rel_tol(4))
    assert eig_tol(np.zeros((0, 0))) == 0.0


# a literal tolerance: pytest.approx/allclose keywords, or an assert's right-hand bound
_KEYWORD = re.compile(r"\b(?:rel|abs|atol|rtol)\s*=\s*(\d+(?:\.\d*)?(?:e-?\d+)?|\.\d+)")
_BOUND = re.compile(r"<=?\s*\\?\s*(\d+(?:\.\d*)?e-\d+)")


#: below this a literal is a round-off tolerance (a model's or a measurement's tolerance,
#: 1e-3 and above, is the physics' and is argued where it stands)
ROUNDOFF_SCALE = 1e-3


def bare_literals(path: Path) -> list[str]:
    """Lines of ``path`` with a literal round-off tolerance (0 < value < 1e-3) not inside
    ``measured(...)`` (a measured tolerance names its margin); a factor of a derivation
    (``atol=2 * dz``: two paths) is not one. The text is scanned whole, comments blanked,
    so a tolerance continued on the next line is found too."""
    lines = path.read_text().splitlines()
    code = "\n".join(line.split("#", 1)[0] for line in lines)
    out = []
    for rx in (_KEYWORD, _BOUND):
        for m in rx.finditer(code):
            if not 0.0 < float(m.group(1)) < ROUNDOFF_SCALE:
                continue
            before = code[:m.start()]
            if before.rfind("measured(") > before.rfind(")"):
                continue
            no = code.count("\n", 0, m.start(1)) + 1
            out.append(f"{path.name}:{no}: {lines[no - 1].strip()}")
    return sorted(set(out), key=lambda t: int(t.split(":")[1]))


def numerical_modules() -> list[Path]:
    """The test modules marked ``numerical`` (this checker and its fixtures aside)."""
    return sorted(p for p in TESTS.glob("test_*.py") if p.name != "test_tolerance.py"
                  and re.search(r"^pytestmark\s*=.*\bnumerical\b", p.read_text(), re.M))


def test_numerical_tests_have_no_bare_literal_tolerance():
    """Every tolerance of a module marked ``numerical`` is derived (tests/tolerance.py) or
    ``measured(worst, margin)`` with where it was measured written beside it."""
    mods = numerical_modules()
    assert len(mods) >= 3, mods
    bad = [b for p in mods for b in bare_literals(p)]
    assert not bad, "bare literal tolerances:\n" + "\n".join(bad)


def test_the_literal_finder_finds_literals():
    """The scan above can fail: it flags the forms the suite used."""
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "test_x.py"
        p.write_text("assert a == pytest.approx(b, rel=1e-9)\n"
                     "assert np.allclose(a, b, rtol=0, atol=1e-12)\n"
                     "assert err <= 1e-13\n"
                     "assert err <= measured(1e-13, 100)\n"
                     "assert err <= \\\n    1e-9 * scale\n"
                     "assert a == pytest.approx(b, rel=0, abs=tol)\n")
        assert [s.split(":")[1] for s in bare_literals(p)] == ["1", "2", "3", "6"]
