"""tools/tolerance_audit.py finds the tolerances with no derivation or measurement beside
them, accepts the justified ones, and ``--check`` guards the converted files (issue 31)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from from_file import load_module  # same directory

ROOT = Path(__file__).resolve().parent.parent
TOOL = ROOT / "tools" / "tolerance_audit.py"
audit_mod = load_module(TOOL)

SRC = '''\
import numpy as np, pytest
TOL = 1e-9
def test_x(a, b, e):
    assert a == pytest.approx(b, rel=1e-9)
    assert a == pytest.approx(b)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert np.allclose(a, b)
    assert abs(a - b) < 1e-10
    assert np.max(np.abs(a - b)) <= 1e-9 * e
    assert a == pytest.approx(b, abs=TOL)
    # measured 3e-14 (generic 4e-14), margin 30
    assert a == pytest.approx(b, rel=1e-12)
    assert abs(a - b) < 1e-12  # cond(A) * eps
    assert a == pytest.approx(b, rel=0, abs=eig_tol(e))
    assert a == pytest.approx(b, rel=measured(1e-13, 100))
    assert 0 < abs(a) < 0.01
    x = 1e-3
'''


def test_finds_the_bare_literals_and_accepts_the_justified(tmp_path):
    p = tmp_path / "test_x.py"
    p.write_text(SRC)
    sites = audit_mod.audit(p)
    # TOL's assignment (line 2) for its use on line 10; lines 4-9 bare; 11-17 justified
    # or no tolerance
    assert [no for no, _ in sites] == [2, 4, 5, 6, 7, 8, 9]
    kinds = dict(sites)
    assert "default" in kinds[5] and "default" in kinds[7]


def test_a_comment_block_above_counts_a_code_line_between_does_not(tmp_path):
    p = tmp_path / "test_y.py"
    p.write_text("import pytest\n"
                 "# measured 1e-15 (generic 2e-15), margin 100,\n"
                 "# over the seeds below\n"
                 "assert a == pytest.approx(b, rel=1e-13)\n"
                 "assert c == pytest.approx(d, rel=1e-13)\n")
    assert [no for no, _ in audit_mod.audit(p)] == [5]


def test_check_passes_on_the_converted_files_and_fails_on_a_regression(tmp_path):
    names = audit_mod.converted()
    assert len(names) >= 10 and all((ROOT / "tests" / n).exists() for n in names)
    # exit 0 of --check: every one of these files audited to no unjustified site (the
    # tool audits each, as audit() here would: once, not twice)
    out = subprocess.run([sys.executable, str(TOOL), "--check"], capture_output=True,
                         text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1].endswith("files")
    # a converted file that gains a bare literal: exit 1, named on stderr
    fake = tmp_path / "tests"
    fake.mkdir()
    (fake / "test_a.py").write_text("assert x == pytest.approx(y, rel=1e-9)\n")
    (tmp_path / "tools").mkdir()
    tool = tmp_path / "tools" / "tolerance_audit.py"
    tool.write_text(TOOL.read_text())
    (tmp_path / "tools" / "tolerance_converted.txt").write_text("# c\ntest_a.py\n")
    bad = subprocess.run([sys.executable, str(tool), "--check"], capture_output=True,
                         text=True)
    assert bad.returncode == 1 and "test_a.py: 1 unjustified" in bad.stderr


def test_the_word_measured_alone_is_no_justification(tmp_path):
    """A comment must say what was measured and the margin over it (issue 31's
    leftover): the word "measured" (or "margin", "marginal") without both figures is
    flagged; the figures on two lines of one block, or a derivation, are accepted."""
    p = tmp_path / "test_z.py"
    p.write_text("import pytest\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # a free response, measured\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # measured 3e-14 (no margin said)\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # with a margin, as measured\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # b = 0: the marginal case\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # measured 3e-14, margin 3e4\n"
                 "# measured 2e-15 relative (generic 4e-15),\n"
                 "# margin of 250\n"
                 "assert a == pytest.approx(b, rel=1e-12)\n"
                 "assert a == pytest.approx(b, rel=1e-9)  # the bound: 8 roundings\n")
    assert [no for no, _ in audit_mod.audit(p)] == [2, 3, 4, 5]
    assert audit_mod.says_how("measured 0.023 %, margin 430")
    assert not audit_mod.says_how("measured (not NaN)")
