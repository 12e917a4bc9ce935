"""List the tests' numerical tolerances that carry no justification (issue 31, item 1).

A tolerance is justified when it is derived (a call into ``tests/tolerance.py``: the value
is then no literal) or measured, with a comment on its own line, the line before or any
line of the assertion naming how (``# cond(A) * eps``, ``# Higham (3.4)``; a measurement
with both figures: ``# measured 3e-14 (generic 4e-14), margin 30``, the word "measured"
alone is no justification) or the literal written as ``measured(worst, margin)``.

What counts as a tolerance (found with :mod:`ast`, not a regular expression):

- ``pytest.approx(...)``: its ``rel=``/``abs=`` literals, or its default (rel 1e-6);
- ``np.testing.assert_allclose``/``np.allclose``/``np.isclose``/``math.isclose``: their
  ``rtol``/``atol``/``rel_tol``/``abs_tol`` literals, or the defaults when none is given;
- ``assert_array_almost_equal``/``assert_almost_equal``: ``decimal=``;
- a comparison ``<``/``<=`` (or ``>``/``>=`` mirrored) inside an ``assert`` whose one side
  takes the absolute value or the norm of a difference (``abs(a - b)``, ``np.abs``,
  ``np.linalg.norm``, ``np.max(np.abs(x - ref))``) and whose other side holds a float
  literal below 1.

A literal bound to a module-level name (``TOL = 1e-9``) used as the tolerance is reported
at the assignment. A literal 0 (``rel=0``: no relative part) is no tolerance.

Usage::

    python tools/tolerance_audit.py            # per-file counts and the total
    python tools/tolerance_audit.py -v         # every site, file:line: text
    python tools/tolerance_audit.py --check    # exit 1 when a converted file regresses

``--check`` reads ``tools/tolerance_converted.txt`` (one test file a line, ``#`` comments):
the files converted so far, each of which must stay at 0 unjustified tolerances.
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"
CONVERTED = Path(__file__).resolve().parent / "tolerance_converted.txt"

#: a comment that says how a tolerance was derived (a conditioning, a bound on the
#: round-off, a named source)
DERIVED = re.compile(
    r"\bcond\b|cond\(|\beps\b|\bulp|round-?off|derived|\bbound\b|Higham|"
    r"tolerance\.py|exact|\bgamma\b|first.order", re.I)
#: a comment that says how a tolerance was measured: the word, what was measured (a
#: number) and the margin over it (a number): ``measured 3e-14 (generic 4e-14), margin
#: 30``. The word alone ("measured on the rig", "as measured") says neither.
MEASURED = re.compile(r"\bmeasured\b.*?\d.*?\bmargin\b\W{0,3}(?:of\W{1,3})?[~x]?\d", re.I)


def says_how(comment: str) -> bool:
    """Whether ``comment`` (one comment, or a block joined) justifies a tolerance: a
    derivation (:data:`DERIVED`) or a measurement with its margin (:data:`MEASURED`)."""
    return bool(DERIVED.search(comment) or MEASURED.search(comment))

_TOL_KW = {"rel", "abs", "rtol", "atol", "rel_tol", "abs_tol", "decimal"}
_CLOSE = {"assert_allclose", "allclose", "isclose"}
_ALMOST = {"assert_array_almost_equal", "assert_almost_equal"}
_ABSLIKE = {"abs", "fabs", "absolute", "norm", "hypot"}


def _fname(node: ast.AST) -> str:
    """The last dotted part of a call's function (``np.testing.assert_allclose`` ->
    ``assert_allclose``), or ''."""
    f = node.func if isinstance(node, ast.Call) else node
    if isinstance(f, ast.Attribute):
        return f.attr
    if isinstance(f, ast.Name):
        return f.id
    return ""


def _literal(node: ast.AST) -> float | None:
    """The value of a numeric literal (``1e-9``, ``-1e-9``), else None."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        v = _literal(node.operand)
        return None if v is None else -v
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool):
        return float(node.value)
    return None


def _float_literals(node: ast.AST) -> list[ast.Constant]:
    """Float literals in ``(0, 1)`` inside ``node`` (the factors of a bound such as
    ``1e-9 * scale``), not inside a call other than ``max``/``min``/``float``."""
    out = []

    def walk(n):
        # a literal passed to a function (``measured(4e-13, 1000)``, a helper's argument)
        # is that function's parameter, not a factor of the bound
        if isinstance(n, ast.Call) and _fname(n) not in {"max", "min", "float"}:
            return
        if isinstance(n, ast.Constant) and isinstance(n.value, float) and 0 < n.value < 1:
            out.append(n)
        for c in ast.iter_child_nodes(n):
            walk(c)
    walk(node)
    return out


def _abslike(node: ast.AST) -> bool:
    """Whether ``node`` takes the absolute value or the norm of a difference somewhere
    (``abs(a - b)``, ``np.linalg.norm(x - ref)``; ``abs(x) < 0.01``, a size, is none)."""
    return any(isinstance(n, ast.Call) and _fname(n) in _ABSLIKE
               and any(isinstance(m, ast.BinOp) and isinstance(m.op, ast.Sub)
                       for a in n.args for m in ast.walk(a))
               for n in ast.walk(node))


class _Audit:
    def __init__(self, path: Path):
        self.path = path
        self.text = path.read_text()
        self.lines = self.text.splitlines()
        self.tree = ast.parse(self.text, str(path))
        self.comments: dict[int, str] = {}
        for tok in tokenize.generate_tokens(io.StringIO(self.text).readline):
            if tok.type == tokenize.COMMENT:
                self.comments[tok.start[0]] = tok.string
        # module-level NAME = <numeric literal>
        self.consts: dict[str, ast.AST] = {}
        for st in self.tree.body:
            if isinstance(st, ast.Assign) and _literal(st.value) is not None:
                for t in st.targets:
                    if isinstance(t, ast.Name):
                        self.consts[t.id] = st
        self.sites: dict[int, str] = {}

    def justified(self, first: int, last: int) -> bool:
        """A justifying comment on lines ``first .. last`` or in the block of comment-only
        lines directly above ``first`` (the line before at least)."""
        top = first - 1
        while top - 1 >= 1 and self.lines[top - 1].lstrip().startswith("#") \
                and self.lines[top - 2].lstrip().startswith("#"):
            top -= 1
        return says_how(" ".join(self.comments.get(n, "").lstrip("#").strip()
                                 for n in range(top, last + 1)))

    def flag(self, node: ast.AST, stmt: ast.AST, what: str) -> None:
        if self.justified(min(node.lineno, stmt.lineno), max(node.end_lineno,
                                                             stmt.end_lineno)):
            return
        self.sites.setdefault(node.lineno, what)

    def value(self, v: ast.AST, stmt: ast.AST, what: str) -> None:
        """A tolerance keyword's value: a literal, a named module literal, or an
        expression with literal factors."""
        if isinstance(v, ast.Name) and v.id in self.consts:
            a = self.consts[v.id]
            if _literal(a.value):
                self.flag(a, a, f"{what} via {v.id}")
            return
        lit = _literal(v)
        if lit is not None:
            if lit != 0:
                self.flag(v, stmt, what)
            return
        if _float_literals(v):
            self.flag(v, stmt, what)

    def call(self, c: ast.Call, stmt: ast.AST) -> None:
        name = _fname(c)
        kws = {k.arg: k.value for k in c.keywords if k.arg in _TOL_KW}
        if name == "approx":
            if not kws:
                self.flag(c, stmt, "approx default rel=1e-6")
        elif name in _CLOSE or name == "isclose":
            if not kws and len(c.args) <= 2:
                self.flag(c, stmt, f"{name} default tolerances")
            for a in c.args[2:4]:
                self.value(a, stmt, f"{name} positional tolerance")
        elif name in _ALMOST:
            if not kws and len(c.args) <= 2:
                self.flag(c, stmt, f"{name} default decimal")
            for a in c.args[2:3]:
                self.value(a, stmt, f"{name} positional decimal")
        else:
            return
        for k, v in kws.items():
            self.value(v, stmt, f"{name} {k}=")

    def compare(self, cmp: ast.Compare, stmt: ast.AST) -> None:
        sides = [cmp.left, *cmp.comparators]
        for op, a, b in zip(cmp.ops, sides, sides[1:]):
            if isinstance(op, (ast.Lt, ast.LtE)):
                small, big = a, b
            elif isinstance(op, (ast.Gt, ast.GtE)):
                small, big = b, a
            else:
                continue
            if _abslike(small) and not _abslike(big):
                if isinstance(big, ast.Name) and big.id in self.consts:
                    self.value(big, stmt, "abs-difference bound")
                elif _float_literals(big):
                    self.flag(big, stmt, "abs-difference bound")

    def run(self) -> list[tuple[int, str]]:
        for stmt in ast.walk(self.tree):
            if not isinstance(stmt, (ast.Assert, ast.Expr, ast.Assign, ast.Return)):
                continue
            for n in ast.walk(stmt):
                if isinstance(n, ast.Call):
                    self.call(n, stmt)
                elif isinstance(n, ast.Compare) and isinstance(stmt, ast.Assert):
                    self.compare(n, stmt)
        return sorted(self.sites.items())


def audit(path: Path) -> list[tuple[int, str]]:
    """Unjustified tolerance sites of one test file.

    Parameters
    ----------
    path : Path
        A Python file.

    Returns
    -------
    list of (int, str)
        ``(line, kind)`` for each site, sorted by line.
    """
    return _Audit(path).run()


def converted() -> list[str]:
    """The files listed in ``tools/tolerance_converted.txt`` (relative to tests/)."""
    if not CONVERTED.exists():
        return []
    out = []
    for line in CONVERTED.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(line)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-v", "--verbose", action="store_true", help="list every site")
    ap.add_argument("--check", action="store_true",
                    help="exit 1 when a file in tools/tolerance_converted.txt has a site")
    ap.add_argument("files", nargs="*", type=Path, help="files (default: tests/*.py)")
    args = ap.parse_args(argv)
    files = args.files or sorted(TESTS.rglob("*.py"))
    counts, audited = {}, {}
    for p in files:
        sites = audited[p] = audit(p)
        if sites:
            counts[p] = sites
    for p, sites in sorted(counts.items(), key=lambda kv: (-len(kv[1]), str(kv[0]))):
        rel = p.resolve().relative_to(TESTS) if p.resolve().is_relative_to(TESTS) else p
        print(f"{len(sites):5d}  {rel}")
        if args.verbose:
            lines = p.read_text().splitlines()
            for no, kind in sites:
                print(f"         {rel}:{no}: [{kind}] {lines[no - 1].strip()}")
    total = sum(len(s) for s in counts.values())
    print(f"{total:5d}  total in {len(counts)} files")
    if args.check:
        bad = []
        for name in converted():
            p = TESTS / name
            if not p.exists():
                bad.append(f"{name}: listed in {CONVERTED.name} but missing")
                continue
            n = len(audited[p] if p in audited else audit(p))     # each file audited once
            if n:
                bad.append(f"{name}: {n} unjustified tolerance(s)")
        if bad:
            print("tolerance_audit: converted files regressed:\n  " + "\n  ".join(bad),
                  file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
